"""The session file (`<stem>.session`): everything needed to localize in a map or continue mapping later.

It is an MCAP file (profile `sgdslam.session`), so any MCAP tool lists and dumps it:
- `/session/header`: one JSON message (schema `sgdslam.session.Header`, a JSON Schema): the format name and
  version, the software version, and whatever the writer describes (sensor kind, mounts, settings, the
  source log's path and SHA-256, the units of every array).
- `/session/arrays/<name>`: one message per named array, as a NumPy `.npy` payload (message encoding
  `npy`: dtype and shape in its own header), e.g. keyframe poses, constraints, information matrices.
- `/session/keyframe_points`: one `.npy` message per keyframe (in keyframe order, `sequence` = its index):
  the keyframe's scan or downsampled cloud in its own frame.
Reading goes through our own bounded, CRC-checked MCAP reader; any damage is an error, never a partial
session. A file written by a newer format version is refused with a one-line error.
"""

from __future__ import annotations

import hashlib
import io
import json
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError, LogWarning
from pipeline.errors import PipelineError
from pipeline.outputs import writing

if TYPE_CHECKING:
    from frontends.slam2d.session_frontends import SavedMap2D
    from frontends.slam3d.session_frontends import SavedMap3D

SESSION_FORMAT = "sgdslam.session"
SESSION_VERSION = 1
HEADER_TOPIC = "/session/header"
ARRAY_TOPIC_PREFIX = "/session/arrays/"
KEYFRAME_POINTS_TOPIC = "/session/keyframe_points"
ARRAY_ENCODING = "npy"
HEADER_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "sgdslam.session.Header",
    "type": "object",
    "required": ["format", "version", "software_version"],
    "properties": {
        "format": {"const": SESSION_FORMAT},
        "version": {"type": "integer", "minimum": 1},
        "software_version": {"type": "string"},
    },
}
MCAP_MAGIC = b"\x89MCAP0\r\n"
"""An MCAP file starts and ends with it; a session without its end was cut short (its summary lost)."""


class SessionError(PipelineError):
    """A session file that cannot be read: not a session, damaged, or from a newer format version."""


@dataclass(frozen=True, eq=False)
class SessionContent:
    """What a session file holds, before any meaning is given to it."""

    header: Mapping[str, Any]
    arrays: Mapping[str, NDArray[Any]]
    keyframe_points: tuple[NDArray[Any], ...]


def software_version() -> str:
    try:
        return metadata.version("sgdslam")
    except metadata.PackageNotFoundError:
        return "unknown"


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file, read in chunks (logs are gigabytes)."""
    with path.open("rb") as stream:
        return hashlib.file_digest(stream, "sha256").hexdigest()


def source_description(files: Sequence[Path]) -> dict[str, Any]:
    """The source log's files (several for split bags or a ROS 2 bag folder): path, size and SHA-256, so
    a later run can tell whether it is given the same log."""
    return {"files": [{"path": str(Path(path).resolve()), "bytes": Path(path).stat().st_size,
                       "sha256": file_sha256(Path(path))} for path in files]}


def write_session_file(path: Path, header: Mapping[str, Any], arrays: Mapping[str, NDArray[Any]],
                       keyframe_points: Sequence[NDArray[Any]]) -> None:
    """`write_session` into a new file at `path` (a staged output); OS errors become `OutputError`."""
    with writing(path, "the session"), path.open("wb") as stream:
        write_session(stream, header, arrays, keyframe_points)


def write_session(stream: BinaryIO, header: Mapping[str, Any], arrays: Mapping[str, NDArray[Any]],
                  keyframe_points: Sequence[NDArray[Any]]) -> None:
    """Write a session to an open binary stream (the caller stages and publishes the file)."""
    from mcap.writer import CompressionType, Writer

    full_header = {"format": SESSION_FORMAT, "version": SESSION_VERSION,
                   "software_version": software_version(), **header}
    writer = Writer(stream, compression=CompressionType.ZSTD)
    writer.start(profile=SESSION_FORMAT, library=f"sgdslam {software_version()}")
    header_schema = writer.register_schema("sgdslam.session.Header", "jsonschema",
                                           json.dumps(HEADER_SCHEMA).encode())
    header_channel = writer.register_channel(HEADER_TOPIC, "json", header_schema)
    writer.add_message(header_channel, 0, json.dumps(full_header, default=_json_value).encode(), 0, 0)
    for name, array in arrays.items():
        channel = writer.register_channel(ARRAY_TOPIC_PREFIX + name, ARRAY_ENCODING, 0)
        writer.add_message(channel, 0, _npy(array), 0, 0)
    points_channel = writer.register_channel(KEYFRAME_POINTS_TOPIC, ARRAY_ENCODING, 0)
    for index, points in enumerate(keyframe_points):
        writer.add_message(points_channel, index, _npy(points), index, index)
    writer.finish()


def read_session(path: str | Path) -> SessionContent:
    """Read a whole session file; `SessionError` names the file and what is wrong with it."""
    from frontends.logs.containers.mcap_file import McapContainer

    path = Path(path)
    try:
        with path.open("rb") as stream:
            stream.seek(max(path.stat().st_size - len(MCAP_MAGIC), 0))
            if stream.read() != MCAP_MAGIC:
                raise SessionError(f"{path}: not a session file, or cut short (no MCAP end magic)")
        with warnings.catch_warnings():
            warnings.simplefilter("error", LogWarning)  # a damaged session is refused, not half read
            container = McapContainer(path)
            messages = [(m.channel.topic, m.log_time_ns, bytes(m.data))
                        for m in container.messages({channel.id for channel in container.channels()})]
    except (FrontendError, LogWarning) as error:
        raise SessionError(f"{path}: not a readable session file: {_reason(error, path)}") from error
    except OSError as error:
        raise SessionError(f"{path}: {error.strerror or error}") from error
    headers = [data for topic, _, data in messages if topic == HEADER_TOPIC]
    if len(headers) != 1:
        raise SessionError(f"{path}: not a session file (no {HEADER_TOPIC} message)")
    header = _header(path, headers[0])
    arrays = {topic[len(ARRAY_TOPIC_PREFIX):]: _array(path, topic, data)
              for topic, _, data in messages if topic.startswith(ARRAY_TOPIC_PREFIX)}
    points = sorted((index, _array(path, KEYFRAME_POINTS_TOPIC, data))
                    for topic, index, data in messages if topic == KEYFRAME_POINTS_TOPIC)
    if [index for index, _ in points] != list(range(len(points))):
        raise SessionError(f"{path}: damaged session file (keyframe points missing or repeated)")
    return SessionContent(header, arrays, tuple(array for _, array in points))


load_session = read_session
"""`pipeline.load_session(path)`: the public name of `read_session`."""


def _reason(error: Exception, path: Path) -> str:
    """The error's message without the file name our readers put in front of it."""
    return str(error).removeprefix(f"{path}: ")


def _header(path: Path, data: bytes) -> dict[str, Any]:
    try:
        header = json.loads(data)
    except ValueError as error:
        raise SessionError(f"{path}: damaged session header: {error}") from error
    if not isinstance(header, dict) or header.get("format") != SESSION_FORMAT:
        raise SessionError(f"{path}: not a session file (format {header.get('format')!r})"
                           if isinstance(header, dict) else f"{path}: damaged session header")
    version = header.get("version")
    if not isinstance(version, int) or version < 1:
        raise SessionError(f"{path}: damaged session header (version {version!r})")
    if version > SESSION_VERSION:
        raise SessionError(f"{path}: written by a newer sgdslam ({header.get('software_version', '?')}, "
                           f"session format {version}); this version ({software_version()}) reads format "
                           f"{SESSION_VERSION}: upgrade sgdslam")
    return header


def _json_value(value: Any) -> Any:
    """Settings hold numpy scalars and tuples of them: plain JSON numbers and lists."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot store {type(value).__name__} in a session header")


def _npy(array: NDArray[Any]) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def _array(path: Path, topic: str, data: bytes) -> NDArray[Any]:
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError, EOFError) as error:
        raise SessionError(f"{path}: damaged session file ({topic}: {error})") from error


SENSOR_WORDS = {"scan": "2D laser scans", "cloud": "3D point clouds"}


def is_session_file(path: Path) -> bool:
    """Whether `path` is an MCAP file of the session profile: its header record (opcode 1, after the magic)
    names the profile first, as a 4-byte length and the string."""
    profile = SESSION_FORMAT.encode()
    expected = MCAP_MAGIC + b"\x01"  # the magic, then the header record's opcode
    profile_at = len(expected) + 8  # after the record's 8-byte length
    try:
        with path.open("rb") as stream:
            start = stream.read(profile_at + 4 + len(profile))
    except OSError:  # a folder (a ROS 2 bag), or unreadable: the log reader says what it is
        return False
    return (start.startswith(expected)
            and start[profile_at:] == len(profile).to_bytes(4, "little") + profile)


def describe_session(path: str | Path) -> dict[str, Any]:
    """What `replay info` tells of a session file: what wrote it, what its map was made of and from which
    logs, and its size (keyframes, scans or clouds placed, constraints, loop closures)."""
    path = Path(path)
    content = read_session(path)
    kind = session_sensor_kind(path, content)
    header, arrays = content.header, content.arrays
    stamps = arrays.get(f"{kind}_stamps_ns", np.empty(0))
    is_loop = arrays.get("is_loop", np.empty(0, dtype=bool))
    named = ("format", "version", "software_version", "topic", "sensor_frame", "base_frame", "source",
             "continued_from")
    return {"path": str(path), "container": "session", **{key: header.get(key) for key in named},
            "sensor_kind": kind, "keyframes": len(content.keyframe_points), "measurements": len(stamps),
            "constraints": len(is_loop), "loop_closures": int(np.count_nonzero(is_loop))}


def session_sensor_kind(path: Path, content: SessionContent) -> str:
    """"scan" or "cloud": what the session's map was made of."""
    kind = content.header.get("sensor_kind")
    if kind not in SENSOR_WORDS:
        raise SessionError(f"{path}: damaged session header (sensor_kind {kind!r})")
    return str(kind)


def saved_map_2d(path: Path, content: SessionContent) -> SavedMap2D:
    """The keyframe map of a 2D laser session (`SavedMap2D.from_arrays`): `SessionError` naming the file
    and the array when one is missing or does not fit the others."""
    from frontends.slam2d.session_frontends import SavedMap2D

    with _naming(path):
        return SavedMap2D.from_arrays(content.arrays, content.keyframe_points)


def saved_map_3d(path: Path, content: SessionContent) -> SavedMap3D:
    """The keyframe map of a 3D point-cloud session (`SavedMap3D.from_arrays`): `SessionError` naming the
    file and the array when one is missing or does not fit the others."""
    from frontends.slam3d.session_frontends import SavedMap3D

    with _naming(path):
        return SavedMap3D.from_arrays(content.arrays, content.keyframe_points)


@contextmanager
def _naming(path: Path) -> Iterator[None]:
    """The frontends' `SavedArraysError` as the session reader's `SessionError`, with the file's name."""
    from frontends.saved_arrays import SavedArraysError

    try:
        yield
    except SavedArraysError as error:
        raise SessionError(f"{path}: {error}") from error
