"""Exceptions and warnings of the frontends package; callers (the CLI) turn errors into one-line messages."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path


def one_line(text: str) -> str:
    """Text from a library or a file (sqlite messages, names inside a log) on one line, so an error is
    always one line whatever the log holds."""
    return " ".join(text.split())


class FrontendError(Exception):
    """Base class of every error the frontends raise on purpose."""


class MapPlacementError(FrontendError):
    """The continued run never matched the saved map: its keyframes cannot join the old graph."""


class EmptySavedMapError(FrontendError):
    """A saved map to localize in or continue holds nothing to match against."""


class LogFileError(FrontendError):
    """A log could not be read: names the file, and the message index when one message is at fault.

    `str()` is ``"path: message"`` or ``"path: message #index"`` (the index counts the messages of one
    topic from 0, in the order they are stored).
    """

    def __init__(self, path: str | Path, message: str, message_index: int | None = None) -> None:
        self.path = Path(path)
        message = one_line(message)
        self.reason = message
        self.message_index = message_index
        text = f"{self.path}: {message}"
        if message_index is not None:
            text += f" #{message_index}"
        super().__init__(text)


class UnusableLogError(LogFileError):
    """The log was read, but too little of it is usable data (e.g. most scans have no valid return)."""


class MapExtentError(FrontendError):
    """A grid would cover more cells than memory allows: the poses or points it was asked for span an
    implausible area."""


class TopicSelectionError(FrontendError):
    """No topic, or more than one, fits what was asked for; lists the candidates and the option to use."""

    def __init__(
        self,
        path: str | Path,
        message: str,
        candidates: Sequence[str] = (),
        option: str | None = None,
    ) -> None:
        self.path = Path(path)
        self.reason = one_line(message)
        self.candidates = tuple(one_line(c) for c in candidates)
        self.option = option
        text = f"{self.path}: {self.reason}"
        if self.candidates:
            text += ": " + ", ".join(self.candidates)
        if option is not None:
            text += f"; choose one with {option}"
        super().__init__(text)


class TransformLookupError(FrontendError):
    """The transform tree cannot answer a query (unknown frame, no path, or a time outside its data)."""


class LogWarning(UserWarning):
    """Something in a log was skipped or lost while reading (truncation, late messages); reading went on."""
