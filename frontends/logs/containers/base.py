"""The common form every container reader produces: channels and raw messages, in log-time order.

Containers only find and unpack messages; decoding the payloads is the dispatch layer's job, so each
container stays small and the message converters are written once.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, Set
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, NamedTuple, Protocol

from frontends.logs.types import LogInfo, TopicInfo


@dataclass(frozen=True, slots=True)
class Channel:
    """One stream of messages of one type on one topic.

    `id` is unique within one opened log. `type` is the ROS 2 form (`sensor_msgs/msg/LaserScan`) or the
    schema name as written (`foxglove.LaserScan`); `encoding` is the message encoding ("cdr", "ros1",
    "protobuf", "json", ...). The schema fields are what the file carries (empty when it carries none).
    """

    id: int
    topic: str
    type: str
    encoding: str
    schema_name: str = ""
    schema_encoding: str = ""
    schema_data: bytes = b""


class RawMessage(NamedTuple):
    """One undecoded message: its channel, the time the recorder logged it, and its payload."""

    channel: Channel
    log_time_ns: int
    data: bytes | memoryview


class Container(Protocol):
    """What every container reader offers. Reading is streaming: each call of `messages` is one pass."""

    path: Path

    def info(self) -> LogInfo:
        """Topics, counts and time span from the summary / index (not from the messages)."""
        ...

    def channels(self) -> tuple[Channel, ...]:
        """Every channel of the log."""
        ...

    def messages(self, channel_ids: Set[int]) -> Iterator[RawMessage]:
        """The messages of these channels in log-time order; intact messages of a damaged file are read,
        then a `LogWarning` says how many were lost."""
        ...

    def close(self) -> None:
        """Free what the reader holds between passes (temporary files); passes close their own files."""
        ...


def ros2_type_name(name: str) -> str:
    """`sensor_msgs/LaserScan` → `sensor_msgs/msg/LaserScan`; ROS 2 names and Foxglove names unchanged."""
    parts = name.split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def topic_table(channels: Mapping[int, Channel], counts: Mapping[int, int]) -> tuple[TopicInfo, ...]:
    """One row per (topic, type), channels of the same topic and type summed, sorted by topic."""
    rows: dict[tuple[str, str], TopicInfo] = {}
    for channel in channels.values():
        key = (channel.topic, channel.type)
        count = counts.get(channel.id, 0) + (rows[key].count if key in rows else 0)
        rows[key] = TopicInfo(channel.topic, channel.type, count, channel.encoding)
    return tuple(rows[key] for key in sorted(rows))


def read_at_most(stream: BinaryIO, length: int) -> bytes:
    """`length` bytes from the stream's position, or fewer when the file ends first. Length fields of a
    damaged file may claim up to 2⁶⁴ bytes; Python allocates what `read` is asked for before reading, so
    the request is cut to what the file holds."""
    remaining = os.fstat(stream.fileno()).st_size - stream.tell()
    return stream.read(max(0, min(length, remaining)))


MAX_CHUNK_BYTES = 512 << 20
"""Largest uncompressed chunk we accept (recorders write chunks of a few MB): a damaged size field must
not make us allocate gigabytes. The chunk is refused as damaged instead."""
