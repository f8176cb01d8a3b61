"""Choose the container reader from the path and the file's first bytes, never from a flag."""

from __future__ import annotations

import re
from pathlib import Path

from frontends.containers.base import Container
from frontends.containers.mcap_file import MAGIC as MCAP_MAGIC
from frontends.containers.mcap_file import McapContainer
from frontends.containers.rosbag1 import MAGIC as ROSBAG1_MAGIC
from frontends.containers.rosbag1 import Rosbag1Container
from frontends.containers.rosbag2 import SQLITE_MAGIC, Rosbag2Container
from frontends.errors import LogFileError

_SPLIT_BAG = re.compile(r"^(?P<prefix>.*)_(?P<number>\d+)\.bag$")
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_EXPECTED = "expected an MCAP file, a ROS 1 bag or a ROS 2 bag"


def open_container(path: str | Path) -> Container:
    """The container reader for a log file or ROS 2 bag directory."""
    path = Path(path)
    if not path.exists():
        raise LogFileError(path, "no such file or directory")
    if path.is_dir():
        return _open_directory(path)
    if path.name == "metadata.yaml":
        return Rosbag2Container(path.parent)
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError as err:
        raise LogFileError(path, f"cannot read: {err.strerror}") from None
    if not head:
        raise LogFileError(path, "empty file")
    if head.startswith(MCAP_MAGIC):
        return McapContainer(path)
    if head.startswith(ROSBAG1_MAGIC):
        return Rosbag1Container(path, split_bag_files(path))
    if head.startswith(b"#ROSBAG V"):
        version = head[len(b"#ROSBAG V") :].split(b"\n")[0].decode("ascii", "replace")
        raise LogFileError(
            path, f"ROS 1 bag format {version} is not supported (only 2.0; `rosbag fix` converts)"
        )
    if head.startswith(SQLITE_MAGIC):
        if (path.parent / "metadata.yaml").exists():
            return Rosbag2Container(path.parent)
        return Rosbag2Container(path)
    if head.startswith(_ZSTD_MAGIC):
        raise LogFileError(path, f"zstd-compressed file: decompress it first ({_EXPECTED})")
    raise LogFileError(path, f"not a log ({_EXPECTED})")


def _open_directory(path: Path) -> Container:
    if (path / "metadata.yaml").exists():
        return Rosbag2Container(path)
    bags = sorted(path.glob("*.bag"), key=_split_order)
    if bags:
        return Rosbag1Container(path, tuple(bags))
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
    order; just `path` when it is not part of one."""
    match = _SPLIT_BAG.match(path.name)
    if match is None:
        return (path,)
    prefix = match["prefix"]
    parts = [
        sibling
        for sibling in path.parent.glob("*.bag")
        if (m := _SPLIT_BAG.match(sibling.name)) is not None and m["prefix"] == prefix
    ]
    return tuple(sorted(parts, key=_split_order))
