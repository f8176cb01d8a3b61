"""ROS 1 bags (format 2.0), one file or a split set: topics and counts from the index, messages chunk by
chunk in log-time order.

Read here rather than with `rosbags.rosbag1`, which loads the index entry of every message into memory
when the bag is opened (memory grows with the log) and cannot read a bag whose index is missing. This
reader keeps one chunk (or the few that overlap in time) in memory, and reads an unindexed or truncated
bag front to back up to its last intact message.
"""

from __future__ import annotations

import bz2
import io
import struct
import warnings
from collections.abc import Callable, Iterator, Set
from dataclasses import dataclass
from operator import itemgetter
from pathlib import Path
from typing import BinaryIO

import lz4.frame

from frontends.errors import LogFileError, LogWarning
from frontends.logs.containers.base import (
    MAX_CHUNK_BYTES,
    Channel,
    RawMessage,
    read_at_most,
    ros2_type_name,
    topic_table,
)
from frontends.logs.containers.chunk_merge import (
    ChunkMessage,
    ChunkRef,
    Unpacked,
    lost_in_cut_chunk,
    merge_chunks,
)
from frontends.logs.types import LogInfo

MAGIC = b"#ROSBAG V2.0\n"

_OP_MESSAGE = 0x02
_OP_BAG_HEADER = 0x03
_OP_INDEX = 0x04
_OP_CHUNK = 0x05
_OP_CHUNK_INFO = 0x06
_OP_CONNECTION = 0x07

_U32 = struct.Struct("<I")
_TIME = struct.Struct("<II")
_CHUNK_COUNT = struct.Struct("<II")

# A connection id is unique within one file; a split set gets ids file_index * _FILE_STRIDE + conn.
_FILE_STRIDE = 1 << 32


class _CorruptError(ValueError):
    """A record cannot be parsed (internal; becomes a warning or a LogFileError)."""


def _fields(header: bytes | memoryview) -> dict[str, bytes]:
    """The `name=value` fields of a record header."""
    header = bytes(header)
    fields: dict[str, bytes] = {}
    pos = 0
    end = len(header)
    while pos + 4 <= end:
        (length,) = _U32.unpack_from(header, pos)
        field = header[pos + 4 : pos + 4 + length]
        if len(field) < length:
            raise _CorruptError("record header field runs past the header")
        name, sep, value = field.partition(b"=")
        if not sep:
            raise _CorruptError("record header field without '='")
        fields[name.decode("ascii", "replace")] = value
        pos += 4 + length
    return fields


def _time(value: bytes) -> int:
    secs, nsecs = _TIME.unpack(value)
    return secs * 1_000_000_000 + nsecs


def _u32(fields: dict[str, bytes], name: str) -> int:
    try:
        return int(_U32.unpack(fields[name])[0])
    except (KeyError, struct.error):
        raise _CorruptError(f"record header lacks a valid {name!r}") from None


def _read_record(stream: BinaryIO) -> tuple[dict[str, bytes], bytes, bool] | None:
    """(header fields, data, cut off?) of the record at the stream position; None at the end of file."""
    size = stream.read(4)
    if not size:
        return None
    if len(size) < 4:
        return {}, b"", True
    (header_length,) = _U32.unpack(size)
    header = read_at_most(stream, header_length)
    if len(header) < header_length:
        return {}, b"", True
    fields = _fields(header)
    size = stream.read(4)
    if len(size) < 4:
        return fields, b"", True
    (data_length,) = _U32.unpack(size)
    data = read_at_most(stream, data_length)
    return fields, data, len(data) < data_length


@dataclass(frozen=True, slots=True)
class _ChunkInfo:
    position: int
    start_ns: int
    end_ns: int
    counts: dict[int, int]  # connection id (within its file) → messages in this chunk


@dataclass(slots=True)
class _BagIndex:
    channels: dict[int, Channel]
    chunks: list[_ChunkInfo]


class _BagFile:
    """One bag file: its index when it has one, and reading its chunks."""

    def __init__(self, path: Path, file_index: int) -> None:
        self.path = path
        self.base_id = file_index * _FILE_STRIDE
        self.index = self._read_index()

    def _channel(self, fields: dict[str, bytes], data: bytes) -> Channel:
        conn = _u32(fields, "conn")
        details = _fields(data)
        topic = details.get("topic", fields.get("topic", b"")).decode("utf-8", "replace")
        msg_type = details.get("type", b"").decode("utf-8", "replace")
        definition = details.get("message_definition", b"")
        return Channel(
            self.base_id + conn, topic, ros2_type_name(msg_type), "ros1", msg_type, "ros1msg", definition
        )

    def _read_index(self) -> _BagIndex | None:
        """The index section, or None when the bag has none (unindexed, or truncated before it)."""
        with self.path.open("rb") as stream:
            if stream.read(len(MAGIC)) != MAGIC:
                raise LogFileError(self.path, "not a ROS 1 bag (format 2.0)")
            try:
                record = _read_record(stream)
                if record is None or record[2]:
                    raise LogFileError(
                        self.path, "ROS 1 bag is cut off inside its header record: no messages"
                    )
                if record[0].get("op") != bytes([_OP_BAG_HEADER]):
                    raise _CorruptError("bag header record missing")
                fields = record[0]
                (index_position,) = struct.unpack("<Q", fields["index_pos"])
                connection_count = _u32(fields, "conn_count")
                chunk_count = _u32(fields, "chunk_count")
            except (_CorruptError, KeyError, struct.error) as err:
                raise LogFileError(self.path, f"damaged ROS 1 bag header: {err}") from None
            self.data_start = stream.tell()
            self.index_position = index_position
            size = stream.seek(0, io.SEEK_END)
            if index_position == 0 or index_position >= size:
                return None
            stream.seek(index_position)
            try:
                channels: dict[int, Channel] = {}
                for _ in range(connection_count):
                    record = _read_record(stream)
                    if record is None or record[2] or record[0].get("op") != bytes([_OP_CONNECTION]):
                        return None
                    channel = self._channel(record[0], record[1])
                    channels[channel.id] = channel
                chunks: list[_ChunkInfo] = []
                for _ in range(chunk_count):
                    record = _read_record(stream)
                    if record is None or record[2] or record[0].get("op") != bytes([_OP_CHUNK_INFO]):
                        return None
                    fields, data = record[0], record[1]
                    counts = {
                        conn: count
                        for conn, count in (
                            _CHUNK_COUNT.unpack_from(data, 8 * i) for i in range(len(data) // 8)
                        )
                    }
                    (position,) = struct.unpack("<Q", fields["chunk_pos"])
                    chunks.append(
                        _ChunkInfo(position, _time(fields["start_time"]), _time(fields["end_time"]), counts)
                    )
            except (_CorruptError, KeyError, struct.error):
                return None
            return _BagIndex(channels, chunks)

    def chunk_loader(
        self, stream: BinaryIO, position: int, wanted: frozenset[int], damaged: list[str]
    ) -> Callable[[], list[ChunkMessage]]:
        def load() -> list[ChunkMessage]:
            stream.seek(position)
            try:
                record = _read_record(stream)
                if record is None or record[2] or record[0].get("op") != bytes([_OP_CHUNK]):
                    raise _CorruptError("chunk record missing")
                records = _decompress(record[0], record[1], partial=False)
                messages = self.unpack_chunk(records, wanted, None).messages
            except _CorruptError:
                damaged.append(f"{self.path.name}:{position}")
                return []
            messages.sort(key=itemgetter(0))
            return messages

        return load

    def unpack_chunk(
        self,
        records: bytes,
        wanted: Set[int] | None,
        on_connection: Callable[[Channel], object] | None,
    ) -> Unpacked:
        """Messages of the wanted channels (all when None) in a chunk's records (stops at a cut-off
        record)."""
        view = memoryview(records)
        end = len(records)
        pos = 0
        out: list[ChunkMessage] = []
        message_count = message_bytes = 0
        base_id = self.base_id
        unpack_u32 = _U32.unpack_from
        while pos + 4 <= end:
            (header_length,) = unpack_u32(records, pos)
            data_size_at = pos + 4 + header_length
            if data_size_at + 4 > end:
                break
            (data_length,) = unpack_u32(records, data_size_at)
            following = data_size_at + 4 + data_length
            if following > end:
                break
            fields = _fields(records[pos + 4 : data_size_at])
            opcode = fields.get("op", b"\0")[0]
            if opcode == _OP_MESSAGE:
                message_count += 1
                message_bytes += following - pos
                channel_id = base_id + _u32(fields, "conn")
                if wanted is None or channel_id in wanted:
                    out.append((_time(fields["time"]), channel_id, view[data_size_at + 4 : following]))
            elif opcode == _OP_CONNECTION and on_connection is not None:
                on_connection(self._channel(fields, records[data_size_at + 4 : following]))
            pos = following
        return Unpacked(out, pos, message_count, message_bytes)


def _decompress(fields: dict[str, bytes], data: bytes, partial: bool) -> bytes:
    compression = fields.get("compression", b"none").decode("ascii", "replace")
    size = _u32(fields, "size")  # u32: at most 4 GiB, still refused beyond MAX_CHUNK_BYTES
    if size > MAX_CHUNK_BYTES:
        raise _CorruptError(f"chunk claims {size} bytes uncompressed")
    try:
        # Never more than the declared size is decompressed, whatever the compressed stream holds.
        if compression == "none":
            records = data[:size]
        elif compression == "bz2":
            records = bz2.BZ2Decompressor().decompress(data, max_length=size)
        elif compression == "lz4":
            records = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size)
        else:
            raise _CorruptError(f"unsupported chunk compression {compression!r}")
    except (OSError, RuntimeError, EOFError) as err:
        raise _CorruptError(f"{compression} data does not decompress: {err}") from None
    except ValueError as err:
        if isinstance(err, _CorruptError):
            raise
        raise _CorruptError(f"{compression} data does not decompress: {err}") from None
    if not partial and len(records) != size:
        raise _CorruptError(f"chunk holds {len(records)} bytes, its header says {size}")
    return records


class Rosbag1Container:
    """A ROS 1 bag, or the files of one split recording read as one log."""

    container_name = "rosbag1"

    def __init__(self, path: Path, files: tuple[Path, ...]) -> None:
        self.path = path
        self.files = files
        self._bags = [_BagFile(file, i) for i, file in enumerate(files)]
        self._linear: tuple[dict[int, Channel], dict[int, int], int, int] | None = None
        self._warned: set[tuple[Path, str]] = set()
        """The truncation notes already given (a replay reads the log several times)."""

    def close(self) -> None:
        """Nothing to free: every pass opens and closes its own file handle."""

    def channels(self) -> tuple[Channel, ...]:
        return tuple(self._survey()[0].values())

    def info(self) -> LogInfo:
        channels, counts, start, end = self._survey()
        if not counts:
            start, end = 0, 0
        return LogInfo(self.path, self.container_name, start, end, topic_table(channels, counts), self.files)

    def _survey(self) -> tuple[dict[int, Channel], dict[int, int], int, int]:
        """Channels, counts and time span of every file: from its index, or (unindexed or truncated)
        by reading it front to back."""
        if self._linear is None:
            channels: dict[int, Channel] = {}
            counts: dict[int, int] = {}
            start, end = 2**64, 0
            for bag in self._bags:
                if bag.index is not None:
                    channels.update(bag.index.channels)
                    for chunk in bag.index.chunks:
                        if chunk.counts:
                            start = min(start, chunk.start_ns)
                            end = max(end, chunk.end_ns)
                        for conn, count in chunk.counts.items():
                            counts[bag.base_id + conn] = counts.get(bag.base_id + conn, 0) + count
                    continue
                reader = _LinearBagReader(bag)
                for log_time, channel_id, _ in reader.records(None, channels):
                    counts[channel_id] = counts.get(channel_id, 0) + 1
                    start = min(start, log_time)
                    end = max(end, log_time)
                if reader.note is not None:
                    warnings.warn(f"{bag.path}: {reader.note}", LogWarning, stacklevel=4)
            self._linear = (channels, counts, start, end)
        return self._linear

    def messages(self, channel_ids: Set[int]) -> Iterator[RawMessage]:
        wanted = frozenset(channel_ids)
        channels = self._survey()[0]
        indexed = [bag for bag in self._bags if bag.index is not None]
        damaged: list[str] = []
        read = 0
        expected = 0
        with_streams = [(bag, bag.path.open("rb")) for bag in indexed]
        try:
            refs: list[ChunkRef] = []
            for bag, stream in with_streams:
                assert bag.index is not None
                for chunk in bag.index.chunks:
                    in_chunk = sum(n for conn, n in chunk.counts.items() if bag.base_id + conn in wanted)
                    if in_chunk == 0:
                        continue
                    expected += in_chunk
                    refs.append(
                        ChunkRef(
                            chunk.start_ns,
                            chunk.end_ns,
                            len(refs),
                            bag.chunk_loader(stream, chunk.position, wanted, damaged),
                        )
                    )
            for log_time, channel_id, data in merge_chunks(refs):
                read += 1
                yield RawMessage(channels[channel_id], log_time, data)
        finally:
            for _, stream in with_streams:
                stream.close()
        if read < expected:
            warnings.warn(
                f"{self.path}: {expected - read} of {expected} messages lost (damaged chunks at "
                f"{', '.join(damaged)})",
                LogWarning,
                stacklevel=2,
            )
        # Files without an index (a recording that was cut off) are read front to back, after the rest.
        for bag in self._bags:
            if bag.index is not None:
                continue
            reader = _LinearBagReader(bag)
            found: dict[int, Channel] = {}
            for log_time, channel_id, data in reader.records(wanted, found):
                yield RawMessage(found[channel_id], log_time, data)
            if reader.note is not None and (bag.path, reader.note) not in self._warned:  # once, not per pass
                self._warned.add((bag.path, reader.note))
                warnings.warn(f"{bag.path}: {reader.note}", LogWarning, stacklevel=2)


class _LinearBagReader:
    """Reads a bag without a usable index front to back."""

    def __init__(self, bag: _BagFile) -> None:
        self.bag = bag
        self.note: str | None = None

    def records(self, wanted: Set[int] | None, channels: dict[int, Channel]) -> Iterator[ChunkMessage]:
        bag = self.bag
        lost = 0
        with bag.path.open("rb") as stream:
            stream.seek(bag.data_start)
            while True:
                offset = stream.tell()
                try:
                    record = _read_record(stream)
                except _CorruptError as err:
                    raise LogFileError(bag.path, f"damaged record at byte {offset}: {err}") from None
                if record is None:
                    break
                fields, data, cut = record
                if cut and 0 < bag.index_position <= offset:
                    break  # cut inside the index section: every message was before it
                opcode = fields.get("op", b"\0")[0] if fields else 0
                if opcode == _OP_CHUNK:
                    try:
                        records = _decompress(fields, data, partial=cut)
                        unpacked = bag.unpack_chunk(
                            records, wanted, lambda channel: channels.setdefault(channel.id, channel)
                        )
                    except _CorruptError as err:
                        if not cut:
                            raise LogFileError(bag.path, f"damaged chunk at byte {offset}: {err}") from None
                        unpacked = Unpacked([], 0, 0, 0)
                    if cut:
                        lost = lost_in_cut_chunk(_u32(fields, "size"), unpacked)
                    messages = unpacked.messages
                    messages.sort(key=itemgetter(0))
                    yield from messages
                elif opcode == _OP_CONNECTION and not cut:
                    channel = bag._channel(fields, data)
                    channels.setdefault(channel.id, channel)
                elif opcode == _OP_MESSAGE and not cut:
                    channel_id = bag.base_id + _u32(fields, "conn")
                    if wanted is None or channel_id in wanted:
                        yield _time(fields["time"]), channel_id, data
                elif cut and opcode == _OP_MESSAGE:
                    lost = 1
                if cut:
                    if lost:
                        estimate = f"about {lost} messages of that record are lost, and any recorded after it"
                    elif opcode == _OP_CHUNK:
                        estimate = "the messages in it are lost, and any recorded after it"
                    else:
                        estimate = "any messages recorded after it are lost"
                    self.note = f"bag is truncated: it ends inside a record at byte {offset}; {estimate}"
                    return
        # Read to the end without a cut: the bag was only missing its index (e.g. never closed).
        self.note = None
