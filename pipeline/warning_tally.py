"""The warnings of one replay, counted: what it reports instead of letting Python print them.

`tallied_warnings(tally)` catches every warning raised while its block runs. Our own and other libraries'
user warnings (a truncated log, messages dropped) are counted by message, the input's path taken off the
front; numpy's RuntimeWarnings and deprecation notices are developer noise and dropped. The tally goes
into the JSON summary (`[{message, count}]`); the API re-raises each message once as a `LogWarning`
(`reissue`), and the command line prints each as one line (`warning_lines`).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from frontends.errors import LogWarning, one_line

_NOISE: tuple[type[Warning], ...] = (RuntimeWarning, DeprecationWarning, PendingDeprecationWarning,
                                     FutureWarning, ImportWarning, ResourceWarning)
"""Categories never shown to a user: floating-point notices and library maintenance messages."""


class WarningTally:
    """Distinct warning messages of one input, in order of first appearance, with their counts."""

    def __init__(self, path: Path) -> None:
        self._prefix = f"{path}: "
        self._counts: dict[str, int] = {}

    def add(self, message: str) -> None:
        message = one_line(message).removeprefix(self._prefix)
        self._counts[message] = self._counts.get(message, 0) + 1

    def as_json(self) -> list[dict[str, Any]]:
        return [{"message": message, "count": count} for message, count in self._counts.items()]


@contextmanager
def tallied_warnings(tally: WarningTally) -> Iterator[WarningTally]:
    """Count the warnings raised in the block into `tally` as they come (see the module docstring); none
    escapes the block."""

    def count(message: Warning | str, category: type[Warning], *_: Any, **__: Any) -> None:
        if not issubclass(category, _NOISE):
            tally.add(str(message))

    with warnings.catch_warnings():
        warnings.simplefilter("always")  # every occurrence reaches the tally, which merges repeats
        warnings.showwarning = count
        yield tally


WHILE_READING = "while reading: "
"""How a replay that failed notes the warnings before its error (`BaseException.add_note`)."""


def with_notes(error: BaseException) -> str:
    """The error on one line, with the warnings its replay noted before it (`WHILE_READING`)."""
    notes = [note for note in getattr(error, "__notes__", ()) if note.startswith(WHILE_READING)]
    return one_line("; ".join([str(error), *notes]))


def with_count(message: str, count: int) -> str:
    return message if count == 1 else f"{message} ({count} times)"


def reissue(path: Path, tally: Sequence[Mapping[str, Any]]) -> None:
    """Raise each tallied warning once more, as a `LogWarning` naming the input (for API callers)."""
    for item in tally:
        warnings.warn(f"{path}: {with_count(item['message'], item['count'])}", LogWarning, stacklevel=3)


def warning_lines(program: str, path: Path, tally: Sequence[Mapping[str, Any]]) -> list[str]:
    """`program: warning: FILE: message (N times)`, one line per distinct warning."""
    return [f"{program}: warning: {path}: {with_count(item['message'], item['count'])}" for item in tally]
