"""MCAP files: topics and counts from the summary, messages chunk by chunk in log-time order.

The `mcap` package reads the summary (schemas, channels, chunk indexes, statistics). Messages are unpacked
here with one `struct` call per record instead of the package's record objects: that is most of the time
spent per message, and it lets a truncated file be read up to its last intact message (including the
intact part of a cut-off chunk), which the package cannot do.
"""

from __future__ import annotations

import io
import struct
import warnings
import zlib
from collections.abc import Callable, Iterator, Set
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import IO, Any, BinaryIO, cast

import lz4.frame
import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.summary import Summary

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

MAGIC = b"\x89MCAP0\r\n"

_OP_HEADER = 0x01
_OP_FOOTER = 0x02
_OP_SCHEMA = 0x03
_OP_CHANNEL = 0x04
_OP_MESSAGE = 0x05
_OP_CHUNK = 0x06
_OP_DATA_END = 0x0F
_OP_NAMES = {
    0x01: "header",
    0x02: "footer",
    0x03: "schema",
    0x04: "channel",
    0x05: "message",
    0x06: "chunk",
    0x07: "message index",
    0x08: "chunk index",
    0x09: "attachment",
    0x0A: "attachment index",
    0x0B: "statistics",
    0x0C: "metadata",
    0x0D: "metadata index",
    0x0E: "summary offset",
    0x0F: "data end",
}

_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel id, sequence, log time, publish time
_MESSAGE_HEAD_SIZE = _MESSAGE_HEAD.size
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHUNK_FIXED = struct.Struct("<QQQI")  # message start, message end, uncompressed size, uncompressed crc


class _CorruptError(ValueError):
    """A record cannot be parsed (internal; becomes a warning or a LogFileError)."""


class ChecksumError(_CorruptError):
    """A chunk decompressed, but its CRC says the data is not what was written: never read on past it."""


@dataclass(slots=True)
class _Definitions:
    """Schemas and channels met while reading a file without (usable) summary."""

    schemas: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)

    def add(self, opcode: int, body: memoryview) -> None:
        if opcode == _OP_SCHEMA:
            schema_id, name, encoding, data = _parse_schema(body)
            self.schemas[schema_id] = (name, encoding, data)
        elif opcode == _OP_CHANNEL:
            channel_id, schema_id, topic, message_encoding = _parse_channel(body)
            if channel_id not in self.channels:
                name, encoding, data = self.schemas.get(schema_id, ("", "", b""))
                self.channels[channel_id] = Channel(
                    channel_id, topic, ros2_type_name(name), message_encoding, name, encoding, data
                )


@dataclass(slots=True)
class _LinearScan:
    """What one pass over the records found: definitions, counts, time span and where the file ended."""

    definitions: _Definitions
    counts: dict[int, int]
    start_ns: int
    end_ns: int
    truncation: str | None  # why the data ended early, None when the file is whole


class McapContainer:
    """One MCAP file (any profile: ros2, ros1, protobuf/Foxglove, json)."""

    container_name = "mcap"

    def __init__(self, path: Path) -> None:
        self.path = path
        self._summary = self._read_summary()
        self._linear: _LinearScan | None = None
        self._warned: set[str] = set()
        """The truncation notes already given (a replay reads the log several times)."""

    def close(self) -> None:
        """Nothing to free: every pass opens and closes its own file handle."""

    # --- summary -------------------------------------------------------------------------------

    def _read_summary(self) -> Summary | None:
        """The summary section, or None when the file has none or it is damaged (e.g. truncated)."""
        try:
            with self.path.open("rb") as stream:
                stream.seek(0, io.SEEK_END)
                size = stream.tell()
                if size < 2 * len(MAGIC) + 9:
                    return None
                stream.seek(size - len(MAGIC))
                if stream.read(len(MAGIC)) != MAGIC:
                    return None  # no closing magic: cut off before the footer
                stream.seek(0)
                cut_to_file = cast(IO[bytes], _ReadsCutToFile(stream))  # a BufferedIOBase, typed as one
                summary = SeekingReader(cut_to_file, record_size_limit=size).get_summary()
        except (McapError, struct.error, ValueError, EOFError):
            return None
        if summary is None or not summary.channels:
            return None
        return summary

    def _summary_channels(self, summary: Summary) -> dict[int, Channel]:
        channels: dict[int, Channel] = {}
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            name = schema.name if schema is not None else ""
            channels[channel.id] = Channel(
                channel.id,
                channel.topic,
                ros2_type_name(name),
                channel.message_encoding,
                name,
                schema.encoding if schema is not None else "",
                bytes(schema.data) if schema is not None else b"",
            )
        return channels

    def _linear_scan(self) -> _LinearScan:
        if self._linear is None:
            definitions = _Definitions()
            counts: dict[int, int] = {}
            start, end = 2**64, 0
            reader = _LinearReader(self.path, definitions)
            for log_time, channel_id, _ in reader.records(None):
                counts[channel_id] = counts.get(channel_id, 0) + 1
                start = min(start, log_time)
                end = max(end, log_time)
            self._linear = _LinearScan(
                definitions, counts, start if counts else 0, end, reader.truncation_note()
            )
            if self._linear.truncation is not None and self._linear.truncation not in self._warned:
                self._warned.add(self._linear.truncation)
                warnings.warn(f"{self.path}: {self._linear.truncation}", LogWarning, stacklevel=4)
        return self._linear

    def channels(self) -> tuple[Channel, ...]:
        if self._summary is not None:
            return tuple(self._summary_channels(self._summary).values())
        return tuple(self._linear_scan().definitions.channels.values())

    def info(self) -> LogInfo:
        summary = self._summary
        if summary is not None and summary.statistics is not None:
            channels = self._summary_channels(summary)
            counts = dict(summary.statistics.channel_message_counts)
            stats = summary.statistics
            start, end = (stats.message_start_time, stats.message_end_time) if stats.message_count else (0, 0)
        else:
            scan = self._linear_scan()
            channels = scan.definitions.channels
            counts = scan.counts
            start, end = scan.start_ns, scan.end_ns
        return LogInfo(
            self.path, self.container_name, start, end, topic_table(channels, counts), (self.path,)
        )

    # --- messages ------------------------------------------------------------------------------

    def messages(self, channel_ids: Set[int]) -> Iterator[RawMessage]:
        summary = self._summary
        if summary is not None and summary.chunk_indexes:
            yield from self._indexed_messages(summary, channel_ids)
            return
        channels = self._summary_channels(summary) if summary is not None else None
        reader = _LinearReader(self.path, _Definitions())
        for log_time, channel_id, data in reader.records(channel_ids):
            channel = (
                channels[channel_id] if channels is not None else reader.definitions.channels[channel_id]
            )
            yield RawMessage(channel, log_time, data)
        note = reader.truncation_note()
        if note is not None and note not in self._warned:  # once, not once per pass over the log
            self._warned.add(note)
            warnings.warn(f"{self.path}: {note}", LogWarning, stacklevel=2)

    def _indexed_messages(self, summary: Summary, channel_ids: Set[int]) -> Iterator[RawMessage]:
        channels = self._summary_channels(summary)
        wanted = frozenset(channel_ids)
        damaged: list[str] = []
        with self.path.open("rb") as stream:
            refs = []
            for order, index in enumerate(summary.chunk_indexes):
                offsets = index.message_index_offsets
                if offsets and wanted.isdisjoint(offsets):
                    continue  # the chunk's message index says none of our channels is in it
                refs.append(
                    ChunkRef(
                        index.message_start_time,
                        index.message_end_time,
                        order,
                        _indexed_chunk_loader(
                            self.path, stream, index.chunk_start_offset, index.chunk_length, wanted, damaged
                        ),
                    )
                )
            read = 0
            for log_time, channel_id, data in merge_chunks(refs):
                read += 1
                yield RawMessage(channels[channel_id], log_time, data)
        if summary.statistics is not None:
            expected = sum(summary.statistics.channel_message_counts.get(i, 0) for i in wanted)
            if read < expected:
                where = f" (damaged chunks at byte {', '.join(damaged)})" if damaged else ""
                warnings.warn(
                    f"{self.path}: {expected - read} of {expected} messages lost{where}",
                    LogWarning,
                    stacklevel=2,
                )


class _ReadsCutToFile(io.BufferedIOBase):
    """A file whose reads never ask for more than it holds: the `mcap` package reads a string by its
    length field, and Python allocates the whole request before reading. Buffered, not raw: the `mcap`
    package wraps a raw stream in a `BufferedReader`, whose `read(n)` allocates n bytes before asking
    this file (a damaged length field then cost 1.6 GB)."""

    def __init__(self, stream: BinaryIO) -> None:
        super().__init__()
        self._stream = stream

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def close(self) -> None:
        """Left open: the caller's `with` closes the real file (a reader of the `mcap` package closing this
        when collected once made every summary read fail and every MCAP fall back to linear passes)."""

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._stream.seek(offset, whence)

    def tell(self) -> int:
        return self._stream.tell()

    def read(self, size: int | None = -1) -> bytes:
        if size is None or size < 0:
            return self._stream.read()
        return read_at_most(self._stream, size)

    def readinto(self, buffer: Any) -> int:
        data = self.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)


def _indexed_chunk_loader(
    path: Path, stream: BinaryIO, offset: int, length: int, wanted: frozenset[int], damaged: list[str]
) -> Callable[[], list[ChunkMessage]]:
    def load() -> list[ChunkMessage]:
        stream.seek(offset)
        record = read_at_most(stream, length)
        try:
            if len(record) < length or record[0] != _OP_CHUNK:
                raise _CorruptError("chunk record missing")
            data, _ = _chunk_records(memoryview(record)[9:], partial=False)
            messages = _unpack_records(data, wanted, None).messages
        except ChecksumError as err:
            raise LogFileError(path, f"damaged chunk at byte {offset}: {err}") from None
        except _CorruptError:
            damaged.append(str(offset))
            return []
        messages.sort(key=itemgetter(0))
        return messages

    return load


# --- record parsing -------------------------------------------------------------------------------


def _read_string(body: memoryview, pos: int) -> tuple[str, int]:
    (length,) = _U32.unpack_from(body, pos)
    end = pos + 4 + length
    if end > len(body):
        raise _CorruptError("string runs past its record")
    return str(body[pos + 4 : end], "utf-8"), end


def _parse_schema(body: memoryview) -> tuple[int, str, str, bytes]:
    try:
        (schema_id,) = _U16.unpack_from(body, 0)
        name, pos = _read_string(body, 2)
        encoding, pos = _read_string(body, pos)
        (length,) = _U32.unpack_from(body, pos)
        return schema_id, name, encoding, bytes(body[pos + 4 : pos + 4 + length])
    except (struct.error, UnicodeDecodeError) as err:
        raise _CorruptError(f"bad schema record: {err}") from None


def _parse_channel(body: memoryview) -> tuple[int, int, str, str]:
    try:
        channel_id, schema_id = struct.unpack_from("<HH", body, 0)
        topic, pos = _read_string(body, 4)
        message_encoding, _ = _read_string(body, pos)
        return channel_id, schema_id, topic, message_encoding
    except (struct.error, UnicodeDecodeError) as err:
        raise _CorruptError(f"bad channel record: {err}") from None


def _chunk_records(body: memoryview, partial: bool) -> tuple[bytes | memoryview, int]:
    """The (decompressed) records of a chunk record body, and its declared uncompressed size.

    With `partial`, the body may be cut off: what decompresses of it is returned.
    """
    try:
        _, _, uncompressed_size, uncompressed_crc = _CHUNK_FIXED.unpack_from(body, 0)
        compression, pos = _read_string(body, _CHUNK_FIXED.size)
        (records_length,) = _U64.unpack_from(body, pos)
    except struct.error:
        raise _CorruptError("chunk header cut off") from None
    if uncompressed_size > MAX_CHUNK_BYTES:
        raise _CorruptError(f"chunk claims {uncompressed_size} bytes uncompressed")
    compressed = body[pos + 8 : pos + 8 + records_length]
    if not partial and len(compressed) < records_length:
        raise _CorruptError("chunk data cut off")
    try:
        # Never more than the declared size is decompressed, whatever the compressed frame claims.
        if compression == "":
            records: bytes | memoryview = compressed[:uncompressed_size]
        elif compression == "zstd" and partial:
            records = _zstd_at_most(compressed, uncompressed_size)
        elif compression == "zstd":
            declared = zstandard.get_frame_parameters(compressed).content_size
            if declared not in (uncompressed_size, zstandard.CONTENTSIZE_UNKNOWN):
                raise _CorruptError(f"zstd frame claims {declared} bytes, the chunk {uncompressed_size}")
            records = zstandard.decompress(compressed, uncompressed_size)
        elif compression == "lz4":
            records = lz4.frame.LZ4FrameDecompressor().decompress(compressed, max_length=uncompressed_size)
        else:
            raise _CorruptError(f"unsupported chunk compression {compression!r}")
    except (zstandard.ZstdError, RuntimeError, ValueError, EOFError) as err:
        if isinstance(err, _CorruptError):
            raise
        raise _CorruptError(f"{compression} data does not decompress: {err}") from None
    if not partial:
        if len(records) != uncompressed_size:
            raise _CorruptError(f"chunk holds {len(records)} bytes, its header says {uncompressed_size}")
        if uncompressed_crc and zlib.crc32(records) != uncompressed_crc:
            raise ChecksumError("chunk CRC does not match its data")
    return records, uncompressed_size


def _zstd_at_most(compressed: bytes | memoryview, limit: int) -> bytes:
    """What the (possibly cut-off) zstd data decompresses to, stopping once past `limit` bytes: fed in
    small pieces, so neither a frame header's content size nor a damaged stream allocates more."""
    decompressor = zstandard.ZstdDecompressor().decompressobj()
    out = bytearray()
    piece = 4096
    for start in range(0, len(compressed), piece):
        out += decompressor.decompress(compressed[start : start + piece])
        if len(out) > limit:
            break
    return bytes(out)


def _unpack_records(
    data: bytes | memoryview,
    wanted: Set[int] | None,
    on_definition: Callable[[int, memoryview], None] | None,
) -> Unpacked:
    """Messages of `wanted` channels (all when None) in a run of records.

    Stops at the first record that does not fit (a cut-off record). Schema and channel records go to
    `on_definition`.
    """
    view = memoryview(data)
    end = len(view)
    pos = 0
    out: list[ChunkMessage] = []
    message_count = message_bytes = 0
    unpack_message = _MESSAGE_HEAD.unpack_from
    unpack_record = _RECORD_HEAD.unpack_from
    while pos + 9 <= end:
        opcode = view[pos]
        if opcode == _OP_MESSAGE and pos + _MESSAGE_HEAD_SIZE <= end:
            _, length, channel_id, _, log_time, _ = unpack_message(view, pos)
            following = pos + 9 + length
            if following > end:
                break
            message_count += 1
            message_bytes += 9 + length
            if wanted is None or channel_id in wanted:
                out.append((log_time, channel_id, view[pos + _MESSAGE_HEAD_SIZE : following]))
        else:
            _, length = unpack_record(view, pos)
            following = pos + 9 + length
            if following > end:
                break
            if on_definition is not None and opcode in (_OP_SCHEMA, _OP_CHANNEL):
                on_definition(opcode, view[pos + 9 : following])
        pos = following
    return Unpacked(out, pos, message_count, message_bytes)


_OP_ATTACHMENT = 0x09
_FIRST_USER_OPCODE = 0x80  # opcodes from here on are the user's (the spec's extension range)


def _implausible_record(opcode: int, length: int, offset: int) -> bool:
    """Whether a record head cannot be a real one: the first record is not the header, an opcode the
    spec does not define (outside the user range), or a length no writer produces (attachments, which
    may be large, are skipped without reading)."""
    if offset == len(MAGIC):
        return opcode != _OP_HEADER or length > 1 << 20
    if opcode == 0 or (opcode not in _OP_NAMES and opcode < _FIRST_USER_OPCODE):
        return True
    return opcode != _OP_ATTACHMENT and length > MAX_CHUNK_BYTES


class _LinearReader:
    """Reads the data section record by record from the start: for files without a usable summary."""

    def __init__(self, path: Path, definitions: _Definitions) -> None:
        self.path = path
        self.definitions = definitions
        self._truncation: str | None = None
        self._lost_estimate = 0
        self._cut_chunk = False

    def truncation_note(self) -> str | None:
        if self._truncation is None:
            return None
        if self._lost_estimate:
            lost = f"about {self._lost_estimate} messages of that record are lost, and any recorded after it"
        elif self._cut_chunk:
            lost = "the messages in it are lost, and any recorded after it"
        else:
            lost = "any messages recorded after it are lost"
        return f"file is truncated: it {self._truncation}; {lost}"

    def records(self, wanted: Set[int] | None) -> Iterator[ChunkMessage]:
        """(log time, channel id, payload) of the wanted channels (all when None) in file order, sorted
        by log time within each chunk."""
        definitions = self.definitions
        with self.path.open("rb") as stream:
            size = stream.seek(0, io.SEEK_END)
            stream.seek(len(MAGIC))
            offset = len(MAGIC)
            while True:
                head = stream.read(9)
                if len(head) < 9:
                    self._truncation = f"stops after byte {offset} without an end-of-data record"
                    return
                opcode, length = _RECORD_HEAD.unpack(head)
                if opcode in (_OP_DATA_END, _OP_FOOTER):
                    return
                name = _OP_NAMES.get(opcode, f"opcode {opcode:#x}")
                if _implausible_record(opcode, length, offset):
                    # A cut-off file ends inside a real record; this one is not one (random bytes, or a
                    # length field damaged): reading on would only invent records.
                    raise LogFileError(
                        self.path, f"damaged record at byte {offset}: {name} record claiming {length} bytes"
                    )
                if opcode not in (_OP_CHUNK, _OP_MESSAGE, _OP_SCHEMA, _OP_CHANNEL):
                    if offset + 9 + length >= size:
                        self._truncation = f"ends inside a {name} record at byte {offset}"
                        return
                    stream.seek(length, io.SEEK_CUR)
                    offset += 9 + length
                    continue
                body = memoryview(read_at_most(stream, length))
                cut = len(body) < length
                if opcode == _OP_CHUNK:
                    try:
                        data, uncompressed_size = _chunk_records(body, partial=cut)
                        unpacked = _unpack_records(data, wanted, definitions.add)
                    except _CorruptError as err:
                        if not cut:
                            raise LogFileError(self.path, f"damaged chunk at byte {offset}: {err}") from None
                        uncompressed_size, unpacked = 0, Unpacked([], 0, 0, 0)
                    if cut:
                        self._cut_chunk = True
                        self._lost_estimate = lost_in_cut_chunk(uncompressed_size, unpacked)
                    messages = unpacked.messages
                    messages.sort(key=itemgetter(0))
                    yield from messages
                elif cut:
                    self._lost_estimate = 1 if opcode == _OP_MESSAGE else 0
                elif opcode == _OP_MESSAGE:
                    if len(body) < _MESSAGE_HEAD_SIZE - 9:
                        raise LogFileError(self.path, f"damaged message record at byte {offset}: too short")
                    channel_id, _, log_time, _ = struct.unpack_from("<HIQQ", body, 0)
                    if wanted is None or channel_id in wanted:
                        yield log_time, channel_id, body[22:]
                else:
                    try:
                        definitions.add(opcode, body)
                    except _CorruptError as err:
                        raise LogFileError(
                            self.path, f"damaged {name} record at byte {offset}: {err}"
                        ) from None
                if cut:
                    self._truncation = f"ends inside a {name} record at byte {offset}"
                    return
                offset += 9 + length
