"""Hostile inputs, each written here with the mcap / rosbags writers and then damaged: every path ends in a
complete result or one of our exceptions, on one line, naming the file; memory stays bounded whatever a
length field or a value claims; garbage is counted or refused, never mapped as if it were data."""

from __future__ import annotations

import math
import os
import random
import struct
import tracemalloc
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from frontends.errors import FrontendError, LogFileError, LogWarning, MapExtentError, UnusableLogError
from frontends.logs import TransformTree, open_log
from frontends.logs.containers.detect import split_bag_files
from frontends.slam2d.config import DataChecksConfig
from frontends.slam2d.grid import MAX_LIKELIHOOD_CELLS, build_likelihood_grid
from frontends.slam2d.log_input import read_odometry, scans_in_base_frame
from frontends.slam2d.occupancy import MAX_MAP_CELLS, occupancy_grid
from tests._frontends_fixtures import PoseTruth, RosMessages, write_mcap_ros, write_rosbag1, write_rosbag2

MEMORY_BOUND = 64 << 20
"""tracemalloc peak allowed for reading one tiny damaged log (bytes): the logs are a few kB, so anything
near this means a length field was believed."""

# --- helpers ------------------------------------------------------------------------------------------


def read_everything(path: Path) -> None:
    """What the pipeline does with a log: info, every message of every topic, the 2D SLAM input."""
    with open_log(path) as log:
        log.info()
        list(log.messages({c.topic for c in log.channels}))
        if log.topics_of_kind("scan"):
            topic = log.select_topic(("scan",))
            read_odometry(log)
            list(scans_in_base_frame(log, topic, TransformTree(), "base_link"))


def outcome(path: Path, action: Callable[[], Any] | None = None) -> FrontendError | None:
    """Run `action` (reading `path` through by default) under tracemalloc; the error it raised, if any.
    Fails the test when anything but our exceptions escapes, or memory is not bounded."""
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # numpy warnings are bugs, not messages
            warnings.simplefilter("ignore", LogWarning)
            (action or (lambda: read_everything(path)))()
    except FrontendError as err:
        return err
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < MEMORY_BOUND, f"peak {peak} bytes"
    return None


def assert_one_line_naming(error: FrontendError | None, path: Path) -> str:
    assert error is not None, "damaged input was read as if it were whole"
    text = str(error)
    assert "\n" not in text and "\r" not in text
    assert path.name in text
    return text


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


# --- damaged containers -------------------------------------------------------------------------------

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


def _rosbag2_metadata_wrong_types(tmp: Path) -> Path:
    bag = write_rosbag2(tmp / "bag3")
    text = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(text.replace("relative_file_paths:", "relative_file_paths: 7\n  x:"))
    return bag


def _fifo(tmp: Path) -> Path:
    path = tmp / "pipe.mcap"
    os.mkfifo(path)
    return path


def _mcap_crc_mismatch(tmp: Path) -> Path:
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
    "mcap-crc-mismatch": _mcap_crc_mismatch,
    "rosbag1-header-length": _rosbag1_patched("header_length", _bag_header_length),
    "rosbag1-chunk-data-length": _rosbag1_patched("chunk_data_length", _bag_chunk_data_length),
    "rosbag1-chunk-size-field": _rosbag1_patched("chunk_size_field", _bag_chunk_size_field),
    "rosbag1-index-position": _rosbag1_patched("index_position", _bag_index_position),
    "rosbag1-random-body": _rosbag1_patched("random_body", _bag_random_body),
    "rosbag1-chunk-bytes-flipped": _rosbag1_patched("chunk_flipped", _bag_chunk_bytes_flipped),
    "rosbag2-garbage-db3": _rosbag2_garbage_db3,
    "rosbag2-metadata-wrong-types": _rosbag2_metadata_wrong_types,
    "fifo": _fifo,
}


@pytest.mark.parametrize("name", DAMAGED)
def test_damaged_container_ends_in_our_error_or_a_result(name: str, tmp_path: Path) -> None:
    path = DAMAGED[name](tmp_path)
    error = outcome(path)
    if error is not None:
        assert_one_line_naming(error, path)


@pytest.mark.parametrize(
    "name",
    [
        "mcap-random-records-0",
        "mcap-random-after-header",
        "mcap-message-length-2^64-1",
        "mcap-chunk-length-2^64-1",
        "mcap-crc-mismatch",
        "rosbag1-header-length",
        "rosbag1-random-body",
        "fifo",
    ],
)
def test_damage_that_leaves_nothing_readable_is_an_error(name: str, tmp_path: Path) -> None:
    path = DAMAGED[name](tmp_path)
    assert_one_line_naming(outcome(path), path)


def test_chunk_crc_mismatch_is_named(tmp_path: Path) -> None:
    path = _mcap_crc_mismatch(tmp_path)
    text = assert_one_line_naming(outcome(path), path)
    assert "CRC" in text and "chunk at byte" in text


def test_character_device_is_refused_up_front(tmp_path: Path) -> None:
    error = outcome(Path("/dev/zero"))
    assert isinstance(error, LogFileError)
    assert str(error).startswith("/dev/zero: is a character device, not a regular file")


def test_fifo_is_refused_without_opening_it(tmp_path: Path) -> None:
    # Opening a FIFO for reading blocks until a writer appears: the check must come first.
    error = outcome(_fifo(tmp_path))
    assert isinstance(error, LogFileError) and "is a FIFO" in str(error)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root reads any file")
def test_unreadable_file_is_one_line(tmp_path: Path) -> None:
    path = write_mcap_ros(tmp_path / "secret.mcap")
    path.chmod(0)
    assert "cannot read" in assert_one_line_naming(outcome(path), path)


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
) -> Path:
    """An MCAP of `count` LaserScans (ranges(i) for scan i) and, optionally, odometry poses odometry(i)."""
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

        for i in range(count):
            values = np.asarray(ranges(i), dtype=np.float32)
            scan = types["sensor_msgs/msg/LaserScan"](
                header=messages.header(stamp(i), "base_link"),
                angle_min=-1.5,
                angle_max=-1.5 + angle_increment * max(len(values) - 1, 0),
                angle_increment=angle_increment,
                time_increment=0.0,
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


def slam_input(path: Path, counts: dict[str, int], checks: DataChecksConfig | None = None) -> int:
    with open_log(path) as log:
        return len(list(scans_in_base_frame(log, "/scan", TransformTree(), "base_link", checks=checks,
                                            counts=counts)))


@pytest.mark.parametrize("kind", GARBAGE_RANGES)
def test_garbage_scans_are_refused_not_mapped(kind: str, tmp_path: Path) -> None:
    path = scan_log(tmp_path / f"{kind}.mcap", GARBAGE_RANGES[kind])
    counts: dict[str, int] = {}
    error = outcome(path, lambda: slam_input(path, counts))
    assert isinstance(error, UnusableLogError)
    assert_one_line_naming(error, path)
    assert "of the 40 scans" in str(error)


@pytest.mark.parametrize("increment", [math.nan, math.inf, -math.inf, 0.0, 1.0])
def test_scans_whose_angles_are_not_a_sweep_are_refused(increment: float, tmp_path: Path) -> None:
    # 1.0 rad × 359 beams is 57 turns: not a laser either.
    path = scan_log(tmp_path / "angles.mcap", walls, angle_increment=increment)
    counts: dict[str, int] = {}
    error = outcome(path, lambda: slam_input(path, counts))
    assert isinstance(error, UnusableLogError)
    assert counts["scans_without_returns"] == 40


def test_negative_increment_is_a_clockwise_laser(tmp_path: Path) -> None:
    path = scan_log(tmp_path / "clockwise.mcap", walls, angle_increment=-0.01)
    counts: dict[str, int] = {}
    assert slam_input(path, counts) == 40
    assert counts == {}


def test_empty_scans_are_skipped_and_counted_when_enough_remain(tmp_path: Path) -> None:
    path = scan_log(tmp_path / "some.mcap", lambda i: np.full(360, np.nan) if i % 5 == 0 else walls(i))
    counts: dict[str, int] = {}
    assert slam_input(path, counts) == 32
    assert counts == {"scans_without_returns": 8}


def test_usable_share_is_configurable(tmp_path: Path) -> None:
    path = scan_log(tmp_path / "quarter.mcap", GARBAGE_RANGES["mostly-nan"])
    counts: dict[str, int] = {}
    assert slam_input(path, counts, DataChecksConfig(min_usable_scan_share=0.2)) == 10
    assert counts == {"scans_without_returns": 30}


def test_two_million_beams_is_one_line_error(tmp_path: Path) -> None:
    path = scan_log(tmp_path / "huge.mcap", lambda i: np.full(2_000_000, 5.0), count=1, angle_increment=1e-6)
    error = outcome(path, lambda: slam_input(path, {}))
    text = assert_one_line_naming(error, path)
    assert "2000000 beams" in text and "#0" in text


@pytest.mark.parametrize("distance", [1e4, 1e5, 1e7])
def test_one_odometry_glitch_far_away_is_dropped_and_counted(distance: float, tmp_path: Path) -> None:
    path = scan_log(
        tmp_path / "glitch.mcap",
        walls,
        odometry=lambda i: (distance, -distance, 0.0) if i == 17 else (0.05 * i, 0.0, 0.0),
    )
    counts: dict[str, int] = {}
    with open_log(path) as log:
        track = read_odometry(log, counts=counts)
    assert track is not None
    assert len(track.stamps_ns) == 39
    assert np.abs(track.poses[:, :2]).max() < 2.0
    assert sum(counts.values()) == 1
    assert counts.get("odometry_dropped_jumps", 0) + counts.get("odometry_dropped_out_of_world", 0) == 1


def test_glitch_in_the_first_odometry_message_is_the_one_dropped(tmp_path: Path) -> None:
    path = scan_log(
        tmp_path / "first.mcap", walls, odometry=lambda i: (5e3, 0.0, 0.0) if i == 0 else (0.05 * i, 0.0, 0.0)
    )
    counts: dict[str, int] = {}
    with open_log(path) as log:
        track = read_odometry(log, counts=counts)
    assert track is not None and len(track.stamps_ns) == 39 and track.poses[0, 0] == pytest.approx(0.05)
    assert counts == {"odometry_dropped_jumps": 1}


def test_nan_odometry_is_dropped_and_counted(tmp_path: Path) -> None:
    path = scan_log(
        tmp_path / "nan.mcap",
        walls,
        odometry=lambda i: (math.nan, 0.0, 0.0) if i % 10 == 3 else (0.05 * i, 0.0, 0.0),
    )
    counts: dict[str, int] = {}
    with open_log(path) as log:
        track = read_odometry(log, counts=counts)
    assert track is not None and len(track.stamps_ns) == 36 and np.isfinite(track.poses).all()
    assert counts == {"odometry_dropped_nonfinite": 4}


def test_odometry_reset_starts_the_track_over(tmp_path: Path) -> None:
    # An odometry reset (back to the origin after 20 messages) is not a glitch: both halves are kept.
    path = scan_log(
        tmp_path / "reset.mcap", walls, odometry=lambda i: (0.05 * (i % 20) + 100.0 * (i < 20), 0.0, 0.0)
    )
    counts: dict[str, int] = {}
    with open_log(path) as log:
        track = read_odometry(log, counts=counts)
    assert track is not None
    assert len(track.stamps_ns) + counts.get("odometry_dropped_jumps", 0) == 40
    assert len(track.stamps_ns) >= 31  # at most the few messages before the reset was confirmed are lost


def test_time_going_backwards_is_handled_without_numpy_warnings(tmp_path: Path) -> None:
    # Stamps jump back by 20 s after 4 s: those scans are too late to be placed, and are dropped and counted
    # by the reader; the odometry going back in time is sorted and counted.
    path = scan_log(
        tmp_path / "back.mcap",
        walls,
        count=60,
        stamp=lambda i: 10**18 + i * 100_000_000 - (20 * 10**9 if i >= 40 else 0),
        odometry=lambda i: (0.05 * i, 0.0, 0.0),
    )
    counts: dict[str, int] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        warnings.simplefilter("ignore", LogWarning)
        with open_log(path) as log:
            read_odometry(log, counts=counts)
            kept = len(list(scans_in_base_frame(log, "/scan", TransformTree(), "base_link", counts=counts)))
            late = dict(log.counts)
    assert kept == 40 and late == {"messages_late": 40}  # 20 scans, 20 odometry messages
    assert counts == {}


# --- bounded grids --------------------------------------------------------------------------------------


def test_occupancy_grid_of_a_huge_extent_is_drawn_coarser() -> None:
    scans = [np.array([[1.0, 0.0], [0.0, 1.0]])] * 2
    grid = occupancy_grid(scans, np.array([[0.0, 0.0, 0.0], [1e5, 1e5, 0.0]]))
    assert grid.log_odds.size <= MAX_MAP_CELLS
    assert grid.resolution > 0.05


def test_occupancy_grid_of_a_small_extent_keeps_its_resolution() -> None:
    grid = occupancy_grid([np.array([[1.0, 0.0]])], np.zeros((1, 3)))
    assert grid.resolution == 0.05


def test_likelihood_grid_beyond_its_bound_is_our_error() -> None:
    with pytest.raises(MapExtentError, match="cells"):
        build_likelihood_grid(np.array([[0.0, 0.0], [1e6, 1e6]]), 0.05, 0.06, 1.0)
    assert MAX_LIKELIHOOD_CELLS * 12 < 1 << 30


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


@pytest.mark.parametrize("name", CLOUD_LAYOUTS)
def test_cloud_with_absurd_layout_is_one_line_error(name: str, tmp_path: Path) -> None:
    path = cloud_log(tmp_path / f"{name}.mcap", **CLOUD_LAYOUTS[name])

    def clouds() -> None:
        with open_log(path) as log:
            list(log.clouds())

    text = assert_one_line_naming(outcome(path, clouds), path)
    assert "#0" in text


def test_cloud_points_far_beyond_any_lidar_are_dropped(tmp_path: Path) -> None:
    path = cloud_log(tmp_path / "far.mcap", data=np.frombuffer(
        np.array([[1, 2, 3], [1e30, 0, 0], [0, -1e5, 0], [4, 5, 6]], np.float32).tobytes(), np.uint8
    ))
    with open_log(path) as log:
        (cloud,) = list(log.clouds())
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, 6]])


# --- split bags -------------------------------------------------------------------------------------------


def test_numbered_bags_of_two_runs_are_not_merged(tmp_path: Path) -> None:
    # Two runs of the same experiment, numbered by the user: same topics, but the second covers the same
    # span of time again instead of continuing the first.
    (first,) = write_rosbag1(tmp_path / "trial_1.bag")
    (tmp_path / "other").mkdir()
    (second,) = write_rosbag1(tmp_path / "other" / "trial_2.bag")
    second.rename(tmp_path / "trial_2.bag")
    assert split_bag_files(first) == (first,)
    assert split_bag_files(tmp_path / "trial_2.bag") == (tmp_path / "trial_2.bag",)
    with open_log(first) as log:
        assert log.info().files == (first,)
    with pytest.raises(LogFileError, match=r"not one split recording: trial_1\.bag, trial_2\.bag; name one"):
        open_log(tmp_path)


def test_split_parts_are_merged(tmp_path: Path) -> None:
    parts = write_rosbag1(tmp_path / "log.bag", split=7)
    assert split_bag_files(parts[1]) == tuple(parts)
