"""Choose the container reader from the path and the file's first bytes, never from a flag.

The ROS bag readers (and sqlite3, yaml behind them) are imported only for a file that is not an MCAP.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from frontends.errors import FrontendError, LogFileError, LogWarning
from frontends.logs.containers.base import Container
from frontends.logs.containers.mcap_file import MAGIC as MCAP_MAGIC
from frontends.logs.containers.mcap_file import McapContainer
from frontends.logs.guard import READ_ERRORS, check_is_regular, check_readable_file, guarded_call

if TYPE_CHECKING:
    from frontends.logs.containers.rosbag1 import Rosbag1Container
    from frontends.logs.containers.rosbag2 import Rosbag2Container

_SPLIT_BAG = re.compile(r"^(?P<prefix>.*)_(?P<number>\d+)\.bag$")
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_EXPECTED = "expected an MCAP file, a ROS 1 bag or a ROS 2 bag"


_INDEX_ERRORS: tuple[type[BaseException], ...] = (FrontendError, *READ_ERRORS)
"""What reading a bag's index may raise: a bag that cannot be read is skipped, not a failure."""


def open_container(path: str | Path) -> Container:
    """The container reader for a log file or ROS 2 bag directory. Anything else, and a file whose
    structure is damaged beyond reading, is a one-line `LogFileError` naming the path."""
    path = Path(path)
    return guarded_call(path, lambda: _open(path))


def _open(path: Path) -> Container:
    if not path.exists():
        raise LogFileError(path, "no such file or directory")
    if path.is_dir():
        try:
            return _open_directory(path)
        except PermissionError as err:
            raise LogFileError(path, f"cannot read: {err.strerror}") from None
    check_readable_file(path)
    if path.name == "metadata.yaml":
        return _checked_rosbag2(path.parent)
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError as err:
        raise LogFileError(path, f"cannot read: {err.strerror}") from None
    if not head:
        raise LogFileError(path, "empty file")
    if head.startswith(MCAP_MAGIC):
        return McapContainer(path)
    from frontends.logs.containers.rosbag1 import MAGIC as ROSBAG1_MAGIC
    from frontends.logs.containers.rosbag2 import SQLITE_MAGIC, Rosbag2Container

    if head.startswith(ROSBAG1_MAGIC):
        return _rosbag1(path, split_bag_files(path))
    if head.startswith(b"#ROSBAG V"):
        version = head[len(b"#ROSBAG V") :].split(b"\n")[0].decode("ascii", "replace")
        raise LogFileError(
            path, f"ROS 1 bag format {version} is not supported (only 2.0; `rosbag fix` converts)"
        )
    if head.startswith(SQLITE_MAGIC):
        if (path.parent / "metadata.yaml").exists():
            return _checked_rosbag2(path.parent)
        return Rosbag2Container(path)
    if head.startswith(_ZSTD_MAGIC):
        raise LogFileError(path, f"zstd-compressed file: decompress it first ({_EXPECTED})")
    raise LogFileError(path, f"not a log ({_EXPECTED})")


def _rosbag1(path: Path, parts: tuple[Path, ...]) -> Rosbag1Container:
    from frontends.logs.containers.rosbag1 import Rosbag1Container

    return Rosbag1Container(path, parts)


def _checked_rosbag2(directory: Path) -> Rosbag2Container:
    """A ROS 2 bag directory, once its metadata and every regular file in it are known to be regular."""
    from frontends.logs.containers.rosbag2 import Rosbag2Container

    check_readable_file(directory / "metadata.yaml")
    for entry in directory.iterdir():
        if entry.suffix in (".db3", ".mcap", ".zstd"):
            check_readable_file(entry)
    return Rosbag2Container(directory)


def _open_directory(path: Path) -> Container:
    if (path / "metadata.yaml").exists():
        return _checked_rosbag2(path)
    kinds = [pattern for pattern in ("*.bag", "*.db3", "*.mcap") if any(path.glob(pattern))]
    if len(kinds) > 1:  # which one was meant is not ours to guess
        names = ", ".join(sorted(f.name for pattern in kinds for f in path.glob(pattern)))
        raise LogFileError(path, f"logs of more than one kind and no metadata.yaml: {names}; name one")
    bags = sorted(path.glob("*.bag"), key=_split_order)
    if bags:
        for bag in bags:
            check_readable_file(bag)
        parts = split_bag_files(bags[0])
        if len(parts) != len(bags):
            names = ", ".join(b.name for b in bags)
            raise LogFileError(
                path, f"several .bag files that are not one split recording: {names}; name one"
            )
        return _rosbag1(path, parts)
    for pattern in ("*.db3", "*.mcap"):
        found = sorted(path.glob(pattern))
        if len(found) == 1:
            return open_container(found[0])
        if found:
            names = ", ".join(f.name for f in found)
            raise LogFileError(path, f"several {pattern[1:]} files and no metadata.yaml: {names}; name one")
    raise LogFileError(path, f"no log in this directory ({_EXPECTED}; a ROS 2 bag needs metadata.yaml)")


def _split_order(path: Path) -> tuple[str, int]:
    match = _SPLIT_BAG.match(path.name)
    if match is None:
        return (path.name, -1)
    return (match["prefix"], int(match["number"]))


def split_bag_files(path: Path) -> tuple[Path, ...]:
    """The files of a split ROS 1 recording (`name_0.bag`, `name_1.bag`, …) that `path` belongs to, in
    order; just `path` when it is not part of one.

    A name alone does not make a split set (`trial_1.bag` and `trial_2.bag` are often two runs): the parts
    must be numbered consecutively, carry the same topics with the same types, and follow each other in
    time (each starts within `SPLIT_OVERLAP_NS` before to `MAX_SPLIT_GAP_NS` after the previous one's end).
    """
    match = _SPLIT_BAG.match(path.name)
    if match is None:
        return (path,)
    prefix = match["prefix"]
    numbered = {
        int(m["number"]): sibling
        for sibling in path.parent.glob("*.bag")
        if (m := _SPLIT_BAG.match(sibling.name)) is not None and m["prefix"] == prefix
    }
    number = int(match["number"])
    numbered[number] = path
    if len(numbered) == 1:
        return (path,)
    spans: dict[int, _BagSpan | None] = {number: _bag_span(path)}
    if spans[number] is None:
        return (path,)  # the named file is read, and reports its own damage, alone
    first = last = number
    while first - 1 in numbered and _follows(spans, numbered, first - 1, first):
        first -= 1
    while last + 1 in numbered and _follows(spans, numbered, last, last + 1):
        last += 1
    return tuple(numbered[n] for n in range(first, last + 1))


MAX_SPLIT_GAP_NS = 10_000_000_000
"""`rosbag record --split` starts the next file with the next message: a longer pause is another run."""
SPLIT_OVERLAP_NS = 1_000_000_000
"""Messages are written as they arrive, so a part may begin slightly before the previous one's last
message (a late topic); a part beginning earlier than that is another recording of the same time."""


@dataclass(frozen=True, slots=True)
class _BagSpan:
    start_ns: int
    end_ns: int
    types: dict[str, str]  # topic → type


def _bag_span(path: Path) -> _BagSpan | None:
    """Time span and topics of one bag from its index, None when it cannot be read or is empty."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LogWarning)  # the named file's damage is reported when read
            info = _rosbag1(path, (path,)).info()
    except _INDEX_ERRORS:
        return None
    counted = {t.name: t.type for t in info.topics if t.count}
    if not counted:
        return None
    return _BagSpan(info.start_ns, info.end_ns, counted)


def _follows(spans: dict[int, _BagSpan | None], files: dict[int, Path], before: int, after: int) -> bool:
    """Whether part `after` continues part `before` of the same recording."""
    for n in (before, after):
        if n not in spans:
            spans[n] = _bag_span(files[n]) if check_is_regular(files[n]) else None
    earlier, later = spans[before], spans[after]
    if earlier is None or later is None:
        return False
    shared = earlier.types.keys() & later.types.keys()
    if not shared or any(earlier.types[t] != later.types[t] for t in shared):
        return False
    return -SPLIT_OVERLAP_NS <= later.start_ns - earlier.end_ns <= MAX_SPLIT_GAP_NS
