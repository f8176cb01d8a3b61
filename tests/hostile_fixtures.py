"""Generators of hostile inputs, shared by the bad-input battery (tests/test_frontends_hostile.py) and the
per-family case table (benchmarks/hostile_cases.py): logs written with the mcap / rosbags writers and then
damaged, logs with absurd values in intact messages, clouds with absurd layouts."""

from __future__ import annotations

import contextlib
import math
import os
import random
import sqlite3
import struct
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from tests._frontends_fixtures import PoseTruth, RosMessages, write_mcap_ros, write_rosbag1, write_rosbag2

# --- damaged containers -------------------------------------------------------------------------------

def mcap_records(data: bytes, start: int = 8) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level records from `start` until the footer."""
    out = []
    pos = start
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, opcode, length))
        if opcode == 0x02:
            break
        pos += 9 + length
    return out


def first_record(data: bytes, opcode: int, start: int = 8) -> int:
    return next(pos for pos, op, _ in mcap_records(data, start) if op == opcode)


def summary_start(data: bytes) -> int:
    return int(struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)[0])


def patched(data: bytes, offset: int, fmt: str, value: int) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    return bytes(out)


def unchunked_mcap(path: Path) -> Path:
    messages = RosMessages(ros1=False)
    with path.open("wb") as stream:
        writer = McapWriter(stream, use_chunking=False)
        writer.start("ros2", "hostile tests")
        channels: dict[str, int] = {}
        for topic, msgtype, log_time, message in messages.recording():
            if topic not in channels:
                definition, _ = messages.store.generate_msgdef(msgtype, ros_version=2)
                schema = writer.register_schema(msgtype, "ros2msg", definition.encode())
                channels[topic] = writer.register_channel(topic, "cdr", schema)
            writer.add_message(channels[topic], log_time, messages.serialize(message, msgtype), log_time)
        writer.finish()
    return path


Damage = Callable[[Path], Path]


def _mcap_random_records(seed: int) -> Damage:
    def make(tmp: Path) -> Path:
        rng = random.Random(seed)
        path = tmp / f"random{seed}.mcap"
        path.write_bytes(b"\x89MCAP0\r\n" + bytes(rng.randrange(256) for _ in range(4000)))
        return path

    return make


def _mcap_random_after_header(tmp: Path) -> Path:
    data = write_mcap_ros(tmp / "source.mcap").read_bytes()
    header_end = mcap_records(data)[0]
    end = header_end[0] + 9 + header_end[2]
    rng = random.Random(7)
    path = tmp / "random_body.mcap"
    path.write_bytes(data[:end] + bytes(rng.randrange(256) for _ in range(3000)) + data[-8:])
    return path


def _mcap_message_length(claim: int) -> Damage:
    def make(tmp: Path) -> Path:
        data = unchunked_mcap(tmp / "source.mcap").read_bytes()
        path = tmp / f"message_length_{claim}.mcap"
        path.write_bytes(patched(data, first_record(data, 0x05) + 1, "<Q", claim))
        return path

    return make


def _mcap_chunk_length(claim: int) -> Damage:
    def make(tmp: Path) -> Path:
        data = write_mcap_ros(tmp / "source.mcap").read_bytes()
        path = tmp / f"chunk_length_{claim}.mcap"
        path.write_bytes(patched(data, first_record(data, 0x06) + 1, "<Q", claim))
        return path

    return make


def _mcap_chunk_index_length(claim: int) -> Damage:
    def make(tmp: Path) -> Path:
        data = write_mcap_ros(tmp / "source.mcap").read_bytes()
        index = first_record(data, 0x08, summary_start(data))
        # chunk index body: message start/end time, chunk start offset, then chunk length
        path = tmp / f"chunk_index_length_{claim}.mcap"
        path.write_bytes(patched(data, index + 9 + 24, "<Q", claim))
        return path

    return make


def _mcap_chunk_uncompressed_size(claim: int) -> Damage:
    def make(tmp: Path) -> Path:
        data = write_mcap_ros(tmp / "source.mcap").read_bytes()
        path = tmp / f"uncompressed_{claim}.mcap"
        path.write_bytes(patched(data, first_record(data, 0x06) + 9 + 16, "<Q", claim))
        return path

    return make


def _mcap_schema_string_length(tmp: Path) -> Path:
    data = unchunked_mcap(tmp / "source.mcap").read_bytes()
    path = tmp / "schema_name.mcap"
    path.write_bytes(patched(data, first_record(data, 0x03) + 9 + 2, "<I", 0xFFFFFFF0))
    return path


def _mcap_truncated(fraction: float) -> Damage:
    def make(tmp: Path) -> Path:
        data = write_mcap_ros(tmp / "source.mcap").read_bytes()
        path = tmp / f"truncated_{fraction}.mcap"
        path.write_bytes(data[: int(len(data) * fraction)])
        return path

    return make


def _rosbag1_patched(name: str, change: Callable[[bytes], bytes]) -> Damage:
    def make(tmp: Path) -> Path:
        (source,) = write_rosbag1(tmp / "source.bag")
        path = tmp / f"{name}.bag"
        path.write_bytes(change(source.read_bytes()))
        return path

    return make


def _bag_header_length(data: bytes) -> bytes:
    return patched(data, 13, "<I", 0xFFFFFFFF)


def _bag_first_chunk(data: bytes) -> int:
    """Offset of the first chunk record (its header length field)."""
    return data.index(b"op=\x05") - 8  # 4-byte record header length, 4-byte field length


def _bag_chunk_data_length(data: bytes) -> bytes:
    start = _bag_first_chunk(data)
    (header_length,) = struct.unpack_from("<I", data, start)
    return patched(data, start + 4 + header_length, "<I", 0xFFFFFFF0)


def _bag_chunk_size_field(data: bytes) -> bytes:
    at = data.index(b"size=", _bag_first_chunk(data)) + 5
    return patched(data, at, "<I", 0xFFFFFFF0)


def _bag_index_position(data: bytes) -> bytes:
    at = data.index(b"index_pos=") + len(b"index_pos=")
    return patched(data, at, "<Q", 2**63 - 1)


def _bag_random_body(data: bytes) -> bytes:
    rng = random.Random(3)
    return data[:13] + bytes(rng.randrange(256) for _ in range(len(data) - 13))


def _bag_chunk_bytes_flipped(data: bytes) -> bytes:
    start = _bag_first_chunk(data)
    out = bytearray(data)
    for offset in range(start + 60, min(start + 400, len(out)), 7):
        out[offset] ^= 0xA5
    return bytes(out)


def _rosbag2_garbage_db3(tmp: Path) -> Path:
    bag = write_rosbag2(tmp / "bag2")
    db3 = bag / "bag2.db3"
    data = bytearray(db3.read_bytes())
    rng = random.Random(5)
    for offset in range(100, len(data), 3):
        data[offset] = rng.randrange(256)
    db3.write_bytes(bytes(data))
    return bag


def _rosbag2_row_values(column: str, value: object) -> Damage:
    """A well-formed .db3 whose every 7th message row holds `value` in `column` (SQLite keeps any type in any
    column: a damaged or hand-edited bag can hold NULL, text or a real where an integer belongs)."""

    def damage(tmp: Path) -> Path:
        bag = write_rosbag2(tmp / f"bag-{column}")
        db3 = bag / f"bag-{column}.db3"
        with contextlib.closing(sqlite3.connect(db3)) as connection, connection:
            # The writer's NOT NULL constraints do not hold in a damaged file either.
            connection.execute("PRAGMA writable_schema = ON")
            connection.execute("UPDATE sqlite_master SET sql = replace(sql, 'NOT NULL', '') "
                               "WHERE name = 'messages'")
        with contextlib.closing(sqlite3.connect(db3)) as connection, connection:
            connection.execute(f"UPDATE messages SET {column} = ? WHERE id % 7 = 3",
                               (value,))
        return bag

    return damage


def _rosbag2_metadata_wrong_types(tmp: Path) -> Path:
    bag = write_rosbag2(tmp / "bag3")
    text = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(text.replace("relative_file_paths:", "relative_file_paths: 7\n  x:"))
    return bag


def fifo(tmp: Path) -> Path:
    path = tmp / "pipe.mcap"
    os.mkfifo(path)
    return path


def mcap_crc_mismatch(tmp: Path) -> Path:
    """An uncompressed chunk with one payload byte changed: it still parses, only the CRC can tell."""
    data = bytearray(write_mcap_ros(tmp / "source.mcap", compression=CompressionType.NONE).read_bytes())
    chunk = first_record(bytes(data), 0x06)
    data[chunk + 9 + 200] ^= 0x01
    path = tmp / "crc.mcap"
    path.write_bytes(bytes(data))
    return path


DAMAGED: dict[str, Damage] = {
    **{f"mcap-random-records-{seed}": _mcap_random_records(seed) for seed in range(3)},
    "mcap-random-after-header": _mcap_random_after_header,
    **{f"mcap-message-length-2^{int(math.log2(c))}": _mcap_message_length(c) for c in (2**33, 2**40, 2**63)},
    "mcap-message-length-2^64-1": _mcap_message_length(2**64 - 1),
    **{f"mcap-chunk-length-2^{int(math.log2(c))}": _mcap_chunk_length(c) for c in (2**33, 2**48)},
    "mcap-chunk-length-2^64-1": _mcap_chunk_length(2**64 - 1),
    **{f"mcap-chunk-index-length-2^{int(math.log2(c))}": _mcap_chunk_index_length(c) for c in (2**33, 2**62)},
    **{f"mcap-uncompressed-2^{int(math.log2(c))}": _mcap_chunk_uncompressed_size(c) for c in (2**40, 2**63)},
    "mcap-schema-name-length": _mcap_schema_string_length,
    **{f"mcap-truncated-{f}": _mcap_truncated(f) for f in (0.1, 0.5, 0.97)},
    "mcap-crc-mismatch": mcap_crc_mismatch,
    "rosbag1-header-length": _rosbag1_patched("header_length", _bag_header_length),
    "rosbag1-chunk-data-length": _rosbag1_patched("chunk_data_length", _bag_chunk_data_length),
    "rosbag1-chunk-size-field": _rosbag1_patched("chunk_size_field", _bag_chunk_size_field),
    "rosbag1-index-position": _rosbag1_patched("index_position", _bag_index_position),
    "rosbag1-random-body": _rosbag1_patched("random_body", _bag_random_body),
    "rosbag1-chunk-bytes-flipped": _rosbag1_patched("chunk_flipped", _bag_chunk_bytes_flipped),
    "rosbag2-garbage-db3": _rosbag2_garbage_db3,
    "rosbag2-metadata-wrong-types": _rosbag2_metadata_wrong_types,
    "rosbag2-null-timestamp": _rosbag2_row_values("timestamp", None),
    "rosbag2-text-timestamp": _rosbag2_row_values("timestamp", "soon"),
    "rosbag2-real-timestamp": _rosbag2_row_values("timestamp", 0.5),
    "rosbag2-null-data": _rosbag2_row_values("data", None),
    "rosbag2-text-data": _rosbag2_row_values("data", "not a message"),
    "fifo": fifo,
}


# --- absurd values in intact files ---------------------------------------------------------------------


def scan_log(
    path: Path,
    ranges: Callable[[int], np.ndarray],
    *,
    angle_increment: float = 0.01,
    count: int = 40,
    beams: int = 360,
    odometry: Callable[[int], tuple[float, float, float]] | None = None,
    stamp: Callable[[int], int] = lambda i: 10**18 + i * 100_000_000,
    tf_static: Sequence[tuple[str, str]] = (),
    time_increment: float = 0.0,
) -> Path:
    """An MCAP of `count` LaserScans (ranges(i) for scan i, in frame base_link, `time_increment` between
    beams) and, optionally, odometry poses odometry(i) and static tf edges (parent, child), identities."""
    messages = RosMessages(ros1=False)
    types = messages.types
    with path.open("wb") as stream:
        writer = McapWriter(stream, compression=CompressionType.ZSTD)
        writer.start("ros2", "hostile tests")
        schemas: dict[str, int] = {}

        def channel(topic: str, msgtype: str) -> int:
            if topic not in schemas:
                definition, _ = messages.store.generate_msgdef(msgtype, ros_version=2)
                schema = writer.register_schema(msgtype, "ros2msg", definition.encode())
                schemas[topic] = writer.register_channel(topic, "cdr", schema)
            return schemas[topic]

        if tf_static:
            edges = [messages.transform_stamped(stamp(0), parent, child, (0.0, 0.0, 0.0), 0.0)
                     for parent, child in tf_static]
            data = messages.serialize(messages.tf_message(edges), "tf2_msgs/msg/TFMessage")
            writer.add_message(channel("/tf_static", "tf2_msgs/msg/TFMessage"), stamp(0), data, stamp(0))
        for i in range(count):
            values = np.asarray(ranges(i), dtype=np.float32)
            scan = types["sensor_msgs/msg/LaserScan"](
                header=messages.header(stamp(i), "base_link"),
                angle_min=-1.5,
                angle_max=-1.5 + angle_increment * max(len(values) - 1, 0),
                angle_increment=angle_increment,
                time_increment=time_increment,
                scan_time=0.1,
                range_min=0.1,
                range_max=30.0,
                ranges=values,
                intensities=np.zeros(0, dtype=np.float32),
            )
            topic_id = channel("/scan", "sensor_msgs/msg/LaserScan")
            data = messages.serialize(scan, "sensor_msgs/msg/LaserScan")
            log_time = 10**18 + i * 100_000_000  # the recorder's clock runs on whatever the stamps do
            writer.add_message(topic_id, log_time, data, log_time)
            if odometry is not None:
                x, y, yaw = odometry(i)
                message = messages.odometry(PoseTruth(stamp(i), stamp(i), x, y, yaw))
                writer.add_message(
                    channel("/odom", "nav_msgs/msg/Odometry"),
                    log_time,
                    messages.serialize(message, "nav_msgs/msg/Odometry"),
                    log_time,
                )
        writer.finish()
    return path


def walls(i: int, beams: int = 360) -> np.ndarray:
    return 3.0 + 0.5 * np.sin(np.arange(beams) * 0.05 + i * 0.01)


GARBAGE_RANGES: dict[str, Callable[[int], np.ndarray]] = {
    "all-nan": lambda i: np.full(360, np.nan),
    "all-inf": lambda i: np.full(360, np.inf),
    "all-negative": lambda i: np.full(360, -2.0),
    "empty": lambda i: np.zeros(0),
    "all-beyond-range-max": lambda i: np.full(360, 1e9),
    "mostly-nan": lambda i: walls(i) if i % 4 == 0 else np.full(360, np.nan),
}


# --- 3D clouds with absurd layouts ---------------------------------------------------------------------


def cloud_log(path: Path, **overrides: Any) -> Path:
    messages = RosMessages(ros1=False)
    types = messages.types
    field = types["sensor_msgs/msg/PointField"]
    layout = {
        "height": 1,
        "width": 4,
        "point_step": 12,
        "row_step": 48,
        "fields": [field(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")],
        "data": np.arange(48, dtype=np.uint8),
        **overrides,
    }
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start("ros2", "hostile tests")
        definition, _ = messages.store.generate_msgdef("sensor_msgs/msg/PointCloud2", ros_version=2)
        schema = writer.register_schema("sensor_msgs/msg/PointCloud2", "ros2msg", definition.encode())
        channel = writer.register_channel("/points", "cdr", schema)
        cloud = types["sensor_msgs/msg/PointCloud2"](
            header=messages.header(10**18, "lidar"),
            is_bigendian=False,
            is_dense=True,
            **layout,
        )
        writer.add_message(channel, 10**18, messages.serialize(cloud, "sensor_msgs/msg/PointCloud2"), 10**18)
        writer.finish()
    return path


CLOUD_LAYOUTS: dict[str, dict[str, Any]] = {
    "point-step-0": {"point_step": 0},
    "width-2^32-1": {"width": 2**32 - 1},
    "height-2^32-1": {"height": 2**32 - 1},
    "row-step-too-small": {"height": 2, "row_step": 4},
    "field-offset-beyond-step": {"point_step": 4},
    "point-step-2^32-1": {"point_step": 2**32 - 1},
}
