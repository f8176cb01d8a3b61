"""ROS 2 bags: a directory with `metadata.yaml` and sqlite3 (`.db3`) or MCAP storage files, or a bare `.db3`.

Topics and counts come from `metadata.yaml`. sqlite3 storage is queried directly (`sqlite3` of the standard
library, ordered by the bag's timestamp index); MCAP storage files are read by the MCAP container. A
truncated `.db3` cannot be opened by sqlite as it is (its header claims pages that are gone), so it is read
from a temporary copy whose header states the pages that remain, in stored order up to the first lost
page, and the messages lost are counted against `metadata.yaml`.
"""

from __future__ import annotations

import shutil
import sqlite3
import struct
import tempfile
import warnings
from collections.abc import Iterable, Iterator, Set
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
import zstandard

from frontends.errors import LogFileError, LogWarning
from frontends.logs.containers.base import Channel, RawMessage, topic_table
from frontends.logs.containers.mcap_file import McapContainer
from frontends.logs.types import LogInfo

SQLITE_MAGIC = b"SQLite format 3\x00"


@dataclass(frozen=True, slots=True)
class _TopicMetadata:
    name: str
    type: str
    encoding: str
    count: int


@dataclass(frozen=True, slots=True)
class _BagMetadata:
    storage: str  # "sqlite3" or "mcap"
    files: tuple[Path, ...]
    topics: tuple[_TopicMetadata, ...]
    start_ns: int
    duration_ns: int
    message_count: int
    compression_mode: str  # "", "file" or "message"


def _read_metadata(directory: Path) -> _BagMetadata:
    metadata_path = directory / "metadata.yaml"
    try:
        document = yaml.safe_load(metadata_path.read_text(encoding="utf-8"))
        info = document["rosbag2_bagfile_information"]
        storage = str(info["storage_identifier"])
        files = tuple(directory / Path(name).name for name in info["relative_file_paths"])
        topics = tuple(
            _TopicMetadata(
                str(entry["topic_metadata"]["name"]),
                str(entry["topic_metadata"]["type"]),
                str(entry["topic_metadata"].get("serialization_format", "cdr")),
                int(entry["message_count"]),
            )
            for entry in info["topics_with_message_count"] or []
        )
        start_ns = int(info["starting_time"]["nanoseconds_since_epoch"])
        duration_ns = int(info["duration"]["nanoseconds"])
        message_count = int(info["message_count"])
        compression_mode = str(info.get("compression_mode") or "").lower()
        compression_format = str(info.get("compression_format") or "").lower()
    except OSError as err:
        raise LogFileError(metadata_path, f"cannot read ROS 2 bag metadata: {err.strerror}") from None
    except yaml.YAMLError as err:
        raise LogFileError(metadata_path, f"not valid YAML: {str(err).splitlines()[0]}") from None
    except (KeyError, TypeError, ValueError) as err:
        raise LogFileError(metadata_path, f"not ROS 2 bag metadata (missing or bad {err})") from None
    if storage not in ("sqlite3", "mcap"):
        raise LogFileError(
            metadata_path, f"unsupported ROS 2 bag storage {storage!r} (expected sqlite3 or mcap)"
        )
    if compression_mode == "none":
        compression_mode = ""
    if compression_mode and compression_format != "zstd":
        raise LogFileError(metadata_path, f"unsupported ROS 2 bag compression {compression_format!r}")
    missing = [file.name for file in files if not file.exists()]
    if missing:
        raise LogFileError(directory, f"ROS 2 bag is missing its storage file {', '.join(missing)}")
    return _BagMetadata(storage, files, topics, start_ns, duration_ns, message_count, compression_mode)


class Rosbag2Container:
    """A ROS 2 bag directory (sqlite3 or MCAP storage, split files read in order), or a bare `.db3`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._stack = ExitStack()
        if path.is_file():  # a bare .db3 without metadata.yaml
            self.metadata = None
            self.container_name = "rosbag2-sqlite3"
            self._storage_files: tuple[Path, ...] = (path,)
        else:
            self.metadata = _read_metadata(path)
            self.container_name = f"rosbag2-{self.metadata.storage}"
            self._storage_files = self._decompressed_files(self.metadata)
        self._mcaps = (
            [McapContainer(file) for file in self._storage_files]
            if self.metadata is not None and self.metadata.storage == "mcap"
            else []
        )
        self._channels = self._read_channels()

    def close(self) -> None:
        self._stack.close()

    def _decompressed_files(self, metadata: _BagMetadata) -> tuple[Path, ...]:
        """Storage files to read: file-compressed bags are decompressed to a temporary directory once."""
        if metadata.compression_mode != "file":
            return metadata.files
        directory = Path(self._stack.enter_context(tempfile.TemporaryDirectory(prefix="rosbag2-")))
        out = []
        for file in metadata.files:
            target = directory / file.stem  # x.db3.zstd → x.db3
            try:
                with file.open("rb") as source, target.open("wb") as sink:
                    zstandard.ZstdDecompressor().copy_stream(source, sink)
            except zstandard.ZstdError as err:
                raise LogFileError(file, f"does not decompress: {err}") from None
            out.append(target)
        return tuple(out)

    # --- channels and info -----------------------------------------------------------------------

    def _read_channels(self) -> dict[int, Channel]:
        """Channels of all storage files, one per (topic, type), numbered from 1."""
        by_key: dict[tuple[str, str], Channel] = {}
        for file in self._storage_files:
            if self._mcaps:
                found = self._mcaps[self._storage_files.index(file)].channels()
            else:
                with _open_sqlite(file) as (connection, _):
                    found = tuple(_sqlite_channels(file, connection).values())
            for channel in found:
                key = (channel.topic, channel.type)
                if key not in by_key:
                    by_key[key] = Channel(
                        len(by_key) + 1,
                        channel.topic,
                        channel.type,
                        channel.encoding,
                        channel.schema_name,
                        channel.schema_encoding,
                        channel.schema_data,
                    )
        return {channel.id: channel for channel in by_key.values()}

    def channels(self) -> tuple[Channel, ...]:
        return tuple(self._channels.values())

    def info(self) -> LogInfo:
        files = self.metadata.files if self.metadata is not None else self._storage_files
        if self.metadata is not None:
            by_topic = {(t.name, t.type): t.count for t in self.metadata.topics}
            counts = {c.id: by_topic.get((c.topic, c.type), 0) for c in self._channels.values()}
            # Topics listed in the metadata but absent from the storage still belong in the table.
            known = {(c.topic, c.type) for c in self._channels.values()}
            channels = dict(self._channels)
            for topic in self.metadata.topics:
                if (topic.name, topic.type) not in known:
                    channel_id = -1 - len(channels)
                    channels[channel_id] = Channel(channel_id, topic.name, topic.type, topic.encoding)
                    counts[channel_id] = topic.count
            start = self.metadata.start_ns if self.metadata.message_count else 0
            end = start + self.metadata.duration_ns if self.metadata.message_count else 0
            return LogInfo(self.path, self.container_name, start, end, topic_table(channels, counts), files)
        with _open_sqlite(self._storage_files[0]) as (connection, _):
            rows = connection.execute(
                "SELECT topic_id, COUNT(*), MIN(timestamp), MAX(timestamp) FROM messages GROUP BY topic_id"
            ).fetchall()
        counts = {row[0]: row[1] for row in rows}
        start = min((row[2] for row in rows), default=0)
        end = max((row[3] for row in rows), default=0)
        return LogInfo(self.path, self.container_name, start, end, topic_table(self._channels, counts), files)

    # --- messages --------------------------------------------------------------------------------

    def messages(self, channel_ids: Set[int]) -> Iterator[RawMessage]:
        wanted = {i: self._channels[i] for i in channel_ids if i in self._channels}
        if not wanted:
            return
        decompress = (
            zstandard.ZstdDecompressor().decompress
            if self.metadata is not None and self.metadata.compression_mode == "message"
            else None
        )
        if self._mcaps:
            yield from self._mcap_messages(wanted, decompress)
            return
        expected = self._expected_count(wanted.values())
        read = 0
        truncated: list[str] = []
        for file in self._storage_files:
            with _open_sqlite(file) as (connection, recovered):
                ids = _local_ids(_sqlite_channels(file, connection).values(), wanted)
                if not ids:
                    continue
                order = "id" if recovered else "timestamp"  # a cut-off file's timestamp index may be gone
                query = (
                    f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN "
                    f"({','.join('?' * len(ids))}) ORDER BY {order}"
                )
                try:
                    for topic_id, timestamp, data in connection.execute(query, tuple(ids)):
                        if type(timestamp) is not int or not isinstance(data, bytes):
                            # SQLite stores any type in any column: a damaged file can hold NULL or text.
                            raise LogFileError(file, "damaged message table: a message's timestamp is "
                                                     f"{_sql_type(timestamp)} and its data {_sql_type(data)}"
                                                     " (an integer and a blob expected)")
                        read += 1
                        payload = data if decompress is None else decompress(data)
                        yield RawMessage(ids[topic_id], timestamp, payload)
                except sqlite3.DatabaseError:
                    truncated.append(file.name)
                if recovered and file.name not in truncated:
                    truncated.append(file.name)
        if truncated:
            lost = (
                f"{expected - read} of {expected} messages lost" if expected is not None else "messages lost"
            )
            warnings.warn(
                f"{self.path}: storage file {', '.join(truncated)} is truncated or damaged: {lost}",
                LogWarning,
                stacklevel=2,
            )

    def _expected_count(self, channels: Any) -> int | None:
        if self.metadata is None:
            return None
        counts = {(t.name, t.type): t.count for t in self.metadata.topics}
        return sum(counts.get((c.topic, c.type), 0) for c in channels)

    def _mcap_messages(self, wanted: dict[int, Channel], decompress: Any) -> Iterator[RawMessage]:
        for mcap in self._mcaps:
            mapping = _local_ids(mcap.channels(), wanted)
            for message in mcap.messages(set(mapping)):
                payload = message.data if decompress is None else decompress(message.data)
                yield RawMessage(mapping[message.channel.id], message.log_time_ns, payload)


def _local_ids(local: Iterable[Channel], wanted: dict[int, Channel]) -> dict[int, Channel]:
    """Channel ids of one storage file → the bag-wide channels they carry (matched by topic and type)."""
    by_key = {(c.topic, c.type): c for c in wanted.values()}
    return {c.id: by_key[(c.topic, c.type)] for c in local if (c.topic, c.type) in by_key}


class _open_sqlite:  # noqa: N801 - used like a function in `with` statements
    """A read-only connection to a `.db3`; a truncated file is opened through a repaired temporary copy.

    Yields (connection, recovered).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._temporary: tempfile.TemporaryDirectory[str] | None = None
        self._connection: sqlite3.Connection | None = None

    def __enter__(self) -> tuple[sqlite3.Connection, bool]:
        recovered = False
        target = self.path
        try:
            with self.path.open("rb") as stream:
                header = stream.read(100)
            size = self.path.stat().st_size
        except OSError as err:
            raise LogFileError(self.path, f"cannot read: {err.strerror}") from None
        if len(header) < 100 or not header.startswith(SQLITE_MAGIC):
            raise LogFileError(self.path, "not an sqlite3 database")
        (page_size,) = struct.unpack_from(">H", header, 16)
        page_size = 65536 if page_size == 1 else page_size
        (page_count,) = struct.unpack_from(">I", header, 28)
        if page_count * page_size > size:
            # Cut off: sqlite refuses a file shorter than its header says. Repair a copy's page count.
            self._temporary = tempfile.TemporaryDirectory(prefix="db3-recovery-")
            target = Path(self._temporary.name) / self.path.name
            shutil.copyfile(self.path, target)
            with target.open("r+b") as stream:
                stream.truncate(size - size % page_size)
                stream.seek(28)
                stream.write(struct.pack(">I", size // page_size))
            recovered = True
        try:
            self._connection = sqlite3.connect(f"file:{target}?immutable=1", uri=True)
            self._connection.execute("SELECT name FROM sqlite_master").fetchall()
        except sqlite3.DatabaseError as err:
            self.__exit__(None, None, None)
            raise LogFileError(self.path, f"damaged sqlite3 storage: {err}") from None
        return self._connection, recovered

    def __exit__(self, *_: object) -> None:
        if self._connection is not None:
            self._connection.close()
            self._connection = None
        if self._temporary is not None:
            self._temporary.cleanup()
            self._temporary = None


def _sqlite_channels(path: Path, connection: sqlite3.Connection) -> dict[int, Channel]:
    try:
        columns = {row[1] for row in connection.execute("PRAGMA table_info(topics)")}
        if not {"id", "name", "type"} <= columns:
            raise LogFileError(path, "not a ROS 2 bag database (no topics table)")
        encoding = "serialization_format" if "serialization_format" in columns else "'cdr'"
        rows = connection.execute(f"SELECT id, name, type, {encoding} FROM topics").fetchall()
        definitions: dict[str, tuple[str, bytes]] = {}
        tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if "message_definitions" in tables:
            for topic_type, schema_encoding, text in connection.execute(
                "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"
            ):
                definitions[topic_type] = (schema_encoding, str(text).encode())
    except sqlite3.DatabaseError as err:
        raise LogFileError(path, f"damaged sqlite3 storage: {err}") from None
    channels = {}
    for topic_id, name, topic_type, serialization in rows:
        schema_encoding, data = definitions.get(topic_type, ("", b""))
        channels[topic_id] = Channel(
            topic_id, name, topic_type, serialization, topic_type, schema_encoding, data
        )
    return channels


def _sql_type(value: object) -> str:
    """How SQLite stored `value`, in its own words."""
    if value is None:
        return "NULL"
    return {int: "integer", float: "real", str: "text", bytes: "blob"}.get(type(value), type(value).__name__)
