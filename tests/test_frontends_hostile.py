"""Hostile inputs, each written here with the mcap / rosbags writers and then damaged: every path ends in a
complete result or one of our exceptions, on one line, naming the file; memory stays bounded whatever a
length field or a value claims; garbage is counted or refused, never mapped as if it were data."""

from __future__ import annotations

import math
import os
import re
import tracemalloc
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from frontends.errors import FrontendError, LogFileError, LogWarning, MapExtentError, UnusableLogError
from frontends.logs import TransformTree, open_log
from frontends.logs.containers.detect import split_bag_files
from frontends.slam2d.config import DataChecksConfig
from frontends.slam2d.grid import MAX_LIKELIHOOD_CELLS, build_likelihood_grid
from frontends.slam2d.log_input import read_odometry, scans_in_base_frame
from frontends.slam2d.occupancy import MAX_MAP_CELLS, occupancy_grid
from tests._frontends_fixtures import ros2_mcap, write_mcap_ros, write_rosbag1
from tests.hostile_fixtures import (
    CLOUD_LAYOUTS,
    DAMAGED,
    GARBAGE_RANGES,
    cloud_log,
    fifo,
    mcap_crc_mismatch,
    scan_log,
    walls,
)

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
        "rosbag2-null-timestamp",
        "rosbag2-text-timestamp",
        "rosbag2-real-timestamp",
        "rosbag2-null-data",
        "rosbag2-text-data",
        "fifo",
    ],
)
def test_damage_that_leaves_nothing_readable_is_an_error(name: str, tmp_path: Path) -> None:
    path = DAMAGED[name](tmp_path)
    assert_one_line_naming(outcome(path), path)


def test_chunk_crc_mismatch_is_named(tmp_path: Path) -> None:
    path = mcap_crc_mismatch(tmp_path)
    text = assert_one_line_naming(outcome(path), path)
    assert "CRC" in text and "chunk at byte" in text


def test_character_device_is_refused_up_front(tmp_path: Path) -> None:
    error = outcome(Path("/dev/zero"))
    assert isinstance(error, LogFileError)
    assert str(error).startswith("/dev/zero: is a character device, not a regular file")


def test_fifo_is_refused_without_opening_it(tmp_path: Path) -> None:
    # Opening a FIFO for reading blocks until a writer appears: the check must come first.
    error = outcome(fifo(tmp_path))
    assert isinstance(error, LogFileError) and "is a FIFO" in str(error)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root reads any file")
def test_unreadable_file_is_one_line(tmp_path: Path) -> None:
    path = write_mcap_ros(tmp_path / "secret.mcap")
    path.chmod(0)
    assert "cannot read" in assert_one_line_naming(outcome(path), path)


# --- absurd values in intact files ---------------------------------------------------------------------


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


def test_odometry_with_jittering_stamps_is_kept(tmp_path: Path) -> None:
    # A logger stamping messages when it gets round to them (the Intel Research Lab log: stamps up to 0.6 s
    # out of order): sorted by stamp, poses taken 0.3 s apart may be stamped 1 ms apart. Not glitches.
    jitter = np.random.default_rng(5).uniform(-0.3, 0.3, 40)
    path = scan_log(tmp_path / "jitter.mcap", walls, odometry=lambda i: (0.05 * i, 0.0, 0.02 * i),
                    stamp=lambda i: 10**18 + round((0.1 * i + jitter[i]) * 1e9))
    counts: dict[str, int] = {}
    with open_log(path) as log:
        track = read_odometry(log, counts=counts)
    assert track is not None and len(track.stamps_ns) == 40
    assert counts.get("odometry_dropped_jumps", 0) == 0


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


def test_of_scans_stamped_alike_the_first_is_read_and_the_rest_counted_and_warned_of(tmp_path: Path) -> None:
    # Scans 2k and 2k + 1 share a stamp; each scan's ranges tell which one it was.
    path = scan_log(tmp_path / "twice.mcap", lambda i: np.full(360, 1.0 + 0.01 * i), count=40,
                    stamp=lambda i: 10**18 + (i // 2) * 100_000_000)
    with open_log(path) as log, pytest.warns(LogWarning, match=r"twice\.mcap: 20 scans skipped: each was "
                                                               r"stamped the same as the one before it"):
        scans = list(log.scans())
        counts = dict(log.counts)
    assert [scan.stamp_ns for scan in scans] == [10**18 + k * 100_000_000 for k in range(20)]
    first_ranges = [float(np.median(np.hypot(*scan.points.T))) for scan in scans]
    np.testing.assert_allclose(first_ranges, 1.0 + 0.02 * np.arange(20), atol=1e-5)
    assert counts == {"scans_repeated_stamp": 20}


def test_of_clouds_stamped_alike_the_first_is_read(tmp_path: Path) -> None:
    path = tmp_path / "clouds.mcap"
    stamps = [10**18, 10**18, 10**18 + 10**8, 10**18 + 2 * 10**8, 10**18 + 2 * 10**8, 10**18 + 2 * 10**8]
    with ros2_mcap(path) as (messages, add):
        types = messages.types
        fields = [types["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=7, count=1)
                  for k, n in enumerate("xyz")]
        for index, stamp in enumerate(stamps):
            points = np.full((4, 3), 1.0 + index, dtype=np.float32)  # each cloud tells which one it was
            add("/points", "sensor_msgs/msg/PointCloud2", stamp, types["sensor_msgs/msg/PointCloud2"](
                header=messages.header(stamp, "lidar"), height=1, width=4, fields=fields, is_bigendian=False,
                point_step=12, row_step=48, data=np.frombuffer(points.tobytes(), dtype=np.uint8),
                is_dense=True))
    with open_log(path) as log, pytest.warns(LogWarning, match="3 clouds skipped"):
        clouds = list(log.clouds())
        counts = dict(log.counts)
    assert [cloud.stamp_ns for cloud in clouds] == sorted(set(stamps))
    assert [float(cloud.points[0, 0]) for cloud in clouds] == [1.0, 3.0, 4.0]
    assert counts == {"clouds_repeated_stamp": 3}


def test_unstamped_scans_and_odometry_take_their_log_times(tmp_path: Path) -> None:
    # A driver that never fills the header: every stamp 0. The fixture's log times are 10^18 + i * 0.1 s.
    path = scan_log(tmp_path / "unstamped.mcap", walls, count=30, stamp=lambda i: 0,
                    odometry=lambda i: (0.01 * i, 0.0, 0.0))
    log_times = [10**18 + i * 100_000_000 for i in range(30)]
    with open_log(path) as log, pytest.warns(LogWarning) as warned:
        scans = list(log.scans())
        odometry = list(log.odometry())
        counts = dict(log.counts)
    # One warning for each kind of message, both naming the file (the odometry's was left to leak out of
    # the test before: `pytest.warns` re-emits the warnings its `match` does not take).
    messages = sorted(str(warning.message) for warning in warned)
    assert len(messages) == 2
    assert re.search(r"unstamped\.mcap: 30 odometry poses in frame 'odom' had no stamp \(0\)", messages[0])
    assert re.search(r"unstamped\.mcap: 30 scans in frame 'base_link' had no stamp \(0\)", messages[1])
    assert [scan.stamp_ns for scan in scans] == log_times
    assert [pose.stamp_ns for pose in odometry] == log_times
    assert counts == {"messages_stamped_by_log_time": 60}


def test_a_clock_starting_at_zero_is_a_clock_not_unset_stamps(tmp_path: Path) -> None:
    # A simulator's first scan is stamped 0, the next ones 0.1 s, 0.2 s, ...: the stamps are kept.
    path = scan_log(tmp_path / "sim.mcap", walls, count=10, stamp=lambda i: i * 100_000_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        with open_log(path) as log:
            stamps = [scan.stamp_ns for scan in log.scans()]
            counts = dict(log.counts)
    assert stamps == [i * 100_000_000 for i in range(10)]
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
