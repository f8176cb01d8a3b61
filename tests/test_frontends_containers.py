"""Every container, every message kind: the same tiny recording written with the mcap / rosbags writers
decodes to what the plain-Python truth in `_frontends_fixtures` says (expectations computed here)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from frontends.errors import TopicSelectionError
from frontends.logs import LogInfo, open_log
from frontends.logs.containers import mcap_file
from tests._frontends_fixtures import (
    ANGLE_INCREMENT,
    ANGLE_MIN,
    BASE_FRAME,
    CLOUDS,
    LASER_MOUNT,
    MS,
    ODOM_FRAME,
    POSES,
    RANGE_MAX,
    RANGE_MIN,
    SCAN_FRAME,
    SCANS,
    STATIC_STAMP_NS,
    T0,
    write_mcap_foxglove,
    write_mcap_ros,
    write_rosbag1,
    write_rosbag2,
)

ROS_CONTAINERS = {
    "mcap-ros2": ("mcap", lambda d: write_mcap_ros(d / "log.mcap")),
    "mcap-ros1": ("mcap", lambda d: write_mcap_ros(d / "log.mcap", ros1=True)),
    "rosbag1": ("rosbag1", lambda d: write_rosbag1(d / "log.bag")[0]),
    "rosbag1-lz4": ("rosbag1", lambda d: write_rosbag1(d / "log.bag", compression="lz4")[0]),
    "rosbag1-split-bz2": ("rosbag1", lambda d: write_rosbag1(d / "log.bag", compression="bz2", split=7)[1]),
    "rosbag2-sqlite3": ("rosbag2-sqlite3", lambda d: write_rosbag2(d / "bag")),
    "rosbag2-mcap": ("rosbag2-mcap", lambda d: write_rosbag2(d / "bag", storage="mcap")),
    "rosbag2-sqlite3-zstd-messages": (
        "rosbag2-sqlite3",
        lambda d: write_rosbag2(d / "bag", compression="message"),
    ),
    "rosbag2-mcap-zstd-file": (
        "rosbag2-mcap",
        lambda d: write_rosbag2(d / "bag", "mcap", compression="file"),
    ),
}
FOXGLOVE_CONTAINERS = {
    "foxglove-protobuf": ("mcap", lambda d: write_mcap_foxglove(d / "log.mcap")),
    "foxglove-json": ("mcap", lambda d: write_mcap_foxglove(d / "log.mcap", encoding="json")),
}
ALL_CONTAINERS = {**ROS_CONTAINERS, **FOXGLOVE_CONTAINERS}


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = {}
    for name, (_, write) in ALL_CONTAINERS.items():
        out[name] = write(tmp_path_factory.mktemp(name))
    return out


def expected_scan(ranges: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, ranges, bearings) of the valid beams, by the LaserScan rules, in plain Python."""
    points, kept, bearings = [], [], []
    for i, value in enumerate(ranges):
        r = float(np.float32(value))  # ROS stores ranges as float32 (the fixture's values are exact in it)
        if math.isfinite(r) and RANGE_MIN <= r <= RANGE_MAX:
            angle = ANGLE_MIN + i * ANGLE_INCREMENT
            points.append((r * math.cos(angle), r * math.sin(angle)))
            kept.append(r)
            bearings.append(angle)
    return np.array(points).reshape(-1, 2), np.array(kept), np.array(bearings)


@pytest.mark.parametrize("name", list(ALL_CONTAINERS))
def test_info_comes_from_the_index(logs: dict[str, Path], name: str) -> None:
    log = open_log(logs[name])
    info = log.info()
    assert info.container == ALL_CONTAINERS[name][0]
    log_times = [STATIC_STAMP_NS] + [s.log_time_ns for s in SCANS] + [p.log_time_ns for p in POSES]
    log_times += [c.log_time_ns for c in CLOUDS]
    assert (info.start_ns, info.end_ns) == (min(log_times), max(log_times))
    counts = {t.name: (t.type, t.count) for t in info.topics}
    if name.startswith("foxglove"):
        assert counts == {
            "/points": ("foxglove.PointCloud", 2),
            "/pose": ("foxglove.PoseInFrame", 5),
            "/scan": ("foxglove.LaserScan", 5),
            "/tf": ("foxglove.FrameTransforms", 5),
            "/tf_static": ("foxglove.FrameTransform", 1),
        }
    else:
        assert counts == {
            "/odom": ("nav_msgs/msg/Odometry", 5),
            "/points": ("sensor_msgs/msg/PointCloud2", 2),
            "/scan": ("sensor_msgs/msg/LaserScan", 5),
            "/tf": ("tf2_msgs/msg/TFMessage", 5),
            "/tf_static": ("tf2_msgs/msg/TFMessage", 1),
        }
    assert [t.name for t in info.topics] == sorted(counts)


@pytest.mark.parametrize("name", ["mcap-ros2", "mcap-ros1", "foxglove-protobuf", "foxglove-json"])
def test_a_whole_mcap_is_read_through_its_summary_and_index_without_a_linear_pass(
    logs: dict[str, Path], name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the mcap writer ends these files with a summary and chunk indexes: opening, the info and every
    # message must come from them, never from a pass decompressing the whole file (issue 12: KITTI was
    # read twice because the summary read failed silently)
    def no_linear_pass(*_: object) -> None:
        raise AssertionError("a linear pass over an indexed MCAP")

    monkeypatch.setattr(mcap_file._LinearReader, "records", no_linear_pass)
    with open_log(logs[name]) as log:
        assert log.info().end_ns == max(c.log_time_ns for c in CLOUDS + SCANS + POSES)
        assert len(list(log.clouds())) == len(CLOUDS)
        assert len(list(log.scans())) == len(SCANS)


def test_info_json_shape(logs: dict[str, Path]) -> None:
    info = open_log(logs["mcap-ros2"]).info()
    document = json.loads(json.dumps(info.to_json_dict()))
    assert set(document) == {"path", "container", "start_ns", "end_ns", "topics"}
    assert document["path"] == str(logs["mcap-ros2"])
    assert {"name": "/scan", "type": "sensor_msgs/msg/LaserScan", "count": 5} in document["topics"]
    assert all(set(topic) == {"name", "type", "count"} for topic in document["topics"])


def test_split_bag_is_one_log_from_any_part_or_its_directory(logs: dict[str, Path]) -> None:
    part = logs["rosbag1-split-bz2"]
    for path in (part, part.with_name("log_0.bag"), part.parent):
        info = open_log(path).info()
        assert [f.name for f in info.files] == ["log_0.bag", "log_1.bag"]
        assert info.message_count == 18


@pytest.mark.parametrize("name", list(ALL_CONTAINERS))
def test_scans_are_valid_beams_in_stamp_order(logs: dict[str, Path], name: str) -> None:
    log = open_log(logs[name])
    # Foxglove scans carry no range limits: give the same ones the ROS messages carry.
    scans = list(log.scans(range_limits=(RANGE_MIN, RANGE_MAX)))
    truths = sorted(SCANS, key=lambda s: s.stamp_ns)
    assert [s.stamp_ns for s in scans] == [t.stamp_ns for t in truths]
    assert [s.stamp_ns - T0 for s in scans] == [0, 100 * MS, 200 * MS, 250 * MS, 300 * MS]
    for scan, truth in zip(scans, truths, strict=True):
        points, ranges, bearings = expected_scan(truth.ranges)
        assert scan.frame_id == SCAN_FRAME
        assert scan.log_time_ns == truth.log_time_ns
        assert scan.beam_count == len(truth.ranges)
        np.testing.assert_array_equal(scan.ranges, ranges)
        np.testing.assert_allclose(scan.bearings, bearings, rtol=0, atol=1e-15)
        np.testing.assert_allclose(scan.points, points, rtol=0, atol=1e-12)
        assert not scan.points.flags.writeable


@pytest.mark.parametrize("name", list(ROS_CONTAINERS))
def test_ros_scans_use_their_own_range_limits(logs: dict[str, Path], name: str) -> None:
    first = next(open_log(logs[name]).scans())
    assert first.stamp_ns == T0
    np.testing.assert_array_equal(first.ranges, expected_scan(SCANS[0].ranges)[1])
    narrower = next(open_log(logs[name]).scans(range_limits=(0.0, 2.0)))
    np.testing.assert_array_equal(narrower.ranges, [1.0, 0.5])


def test_foxglove_scans_keep_every_finite_beam_without_limits(logs: dict[str, Path]) -> None:
    first = next(open_log(logs["foxglove-protobuf"]).scans())
    assert first.ranges.tolist() == [1.0, 0.25, 12.0, 2.5, 10.0, 0.5, 3.75]


@pytest.mark.parametrize("name", list(ALL_CONTAINERS))
def test_odometry(logs: dict[str, Path], name: str) -> None:
    poses = list(open_log(logs[name]).odometry())
    assert [p.stamp_ns for p in poses] == [t.stamp_ns for t in POSES]
    for pose, truth in zip(poses, POSES, strict=True):
        assert pose.frame_id == ODOM_FRAME
        # Foxglove's PoseInFrame does not name the moving frame.
        assert pose.child_frame_id == ("" if name.startswith("foxglove") else BASE_FRAME)
        np.testing.assert_allclose(pose.se2, [truth.x, truth.y, truth.yaw], rtol=0, atol=1e-12)
        np.testing.assert_allclose(pose.translation[2], 0.0)


@pytest.mark.parametrize("name", list(ALL_CONTAINERS))
def test_transforms_and_tree(logs: dict[str, Path], name: str) -> None:
    log = open_log(logs[name])
    transforms = list(log.transforms())
    static = [t for t in transforms if t.is_static]
    dynamic = [t for t in transforms if not t.is_static]
    assert [(t.parent_frame, t.child_frame, t.stamp_ns) for t in static] == [
        (BASE_FRAME, SCAN_FRAME, STATIC_STAMP_NS)
    ]
    assert [(t.parent_frame, t.child_frame) for t in dynamic] == [(ODOM_FRAME, BASE_FRAME)] * 5
    assert [t.stamp_ns for t in dynamic] == [p.stamp_ns for p in POSES]

    tree = log.transform_tree()
    (mx, my, mz), mount_yaw = LASER_MOUNT
    truth = POSES[2]
    laser_in_odom = tree.lookup(ODOM_FRAME, SCAN_FRAME, truth.stamp_ns)
    c, s = math.cos(truth.yaw), math.sin(truth.yaw)
    np.testing.assert_allclose(
        laser_in_odom.translation, [truth.x + c * mx - s * my, truth.y + s * mx + c * my, mz], atol=1e-12
    )
    assert laser_in_odom.yaw == pytest.approx(truth.yaw + mount_yaw, abs=1e-12)


@pytest.mark.parametrize("name", list(ALL_CONTAINERS))
def test_clouds_drop_nan_points_with_their_times(logs: dict[str, Path], name: str) -> None:
    clouds = list(open_log(logs[name]).clouds())
    assert [c.stamp_ns for c in clouds] == [t.stamp_ns for t in CLOUDS]
    for cloud, truth in zip(clouds, CLOUDS, strict=True):
        finite = [i for i, p in enumerate(truth.points) if all(math.isfinite(v) for v in p)]
        assert cloud.points.dtype == np.float32
        np.testing.assert_array_equal(cloud.points, np.array([truth.points[i] for i in finite], np.float32))
        assert cloud.point_times is not None
        np.testing.assert_allclose(cloud.point_times, [truth.times[i] for i in finite], atol=1e-7)


def test_merged_stream_holds_every_kind_in_stamp_order(logs: dict[str, Path]) -> None:
    log = open_log(logs["rosbag1"])
    items = list(log.messages(["/scan", "/odom", "/tf", "/tf_static", "/points"]))
    assert len(items) == 5 + 5 + 5 + 1 + 2
    stamps = [item.stamp_ns for item in items if not getattr(item, "is_static", False)]
    assert stamps == sorted(stamps)


def test_several_scan_topics_need_a_choice(tmp_path: Path) -> None:
    path = write_mcap_ros(tmp_path / "two.mcap", extra_scan_topic="/scan_rear")
    log = open_log(path)
    with pytest.raises(TopicSelectionError) as raised:
        log.scans()
    message = str(raised.value)
    assert "/scan (sensor_msgs/msg/LaserScan)" in message and "/scan_rear" in message
    assert "--scan-topic" in message and str(path) in message
    assert len(list(log.scans("/scan_rear"))) == 5
    assert log.sensor_topic("/scan_rear") == ("/scan_rear", "scan")


def test_topic_selection_errors_name_the_log_and_candidates(logs: dict[str, Path]) -> None:
    log = open_log(logs["mcap-ros2"])
    with pytest.raises(TopicSelectionError, match=r"topic /odom carries nav_msgs/msg/Odometry"):
        log.scans("/odom")
    with pytest.raises(TopicSelectionError, match=r"no topic /nope.*/scan"):
        log.scans("/nope")
    with pytest.raises(
        TopicSelectionError, match=r"several LaserScan or PointCloud topics: /points .*, /scan "
    ):
        log.sensor_topic()
    assert log.sensor_topic("/points") == ("/points", "cloud")
    assert log.odometry_topic() == "/odom"
    with pytest.raises(TopicSelectionError, match=r"carries sensor_msgs/msg/LaserScan, not an odometry type"):
        log.odometry_topic("/scan")


def test_no_scan_topic_lists_what_the_log_has(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "imu_only.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start("ros2", "test")
        schema = writer.register_schema("sensor_msgs/msg/Imu", "ros2msg", b"")
        channel = writer.register_channel("/imu", "cdr", schema)
        writer.add_message(channel, 1, b"\x00\x01\x00\x00", 1)
        writer.finish()
    log = open_log(path)
    with pytest.raises(
        TopicSelectionError, match=r"no LaserScan topic; the log has: /imu \(sensor_msgs/msg/Imu\)"
    ):
        log.scans()
    # A topic asked for by name that is not there either: said so, and what the log has instead.
    with pytest.raises(TopicSelectionError) as caught:
        log.scans("/scan")
    assert str(caught.value) == (f"{path}: no topic /scan (--scan-topic), and no LaserScan topic; "
                                 "the log has: /imu (sensor_msgs/msg/Imu)")
    assert log.odometry_topic() is None
    assert list(log.odometry()) == []  # optional when absent


def test_log_info_is_a_value(logs: dict[str, Path]) -> None:
    info = open_log(logs["rosbag2-sqlite3"]).info()
    assert isinstance(info, LogInfo)
    assert info.duration_s == pytest.approx((info.end_ns - info.start_ns) / 1e9)
    assert info.message_count == 18
