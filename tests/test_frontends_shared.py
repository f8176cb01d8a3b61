"""The real logs of ../shared/data (skipped when absent): the same recording in four containers decodes
identically, and each log agrees with an independent decoder (mcap_ros2, rosbags) on what it holds."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.logs import Scan2D, open_log
from tests.conftest import shared_file

CSAIL = (
    "logs/csail/csail.mcap",
    "logs/csail/csail.bag",
    "logs/csail/csail_ros2",
    "logs/csail/csail_foxglove.mcap",
)
CSAIL_RANGE_MAX = 81.9  # PROVENANCE: range_max 81.90, no-return marker 81.91 (Foxglove scans carry no limits)


@pytest.fixture(scope="module")
def csail_scans() -> dict[str, list[Scan2D]]:
    return {
        name: list(open_log(shared_file(name)).scans(range_limits=(0.0, CSAIL_RANGE_MAX))) for name in CSAIL
    }


def test_csail_info_from_each_container() -> None:
    for name in CSAIL:
        info = open_log(shared_file(name)).info()
        counts = {t.name: t.count for t in info.topics}
        assert counts["/scan"] == 1988 and counts["/tf"] == 1988 and counts["/tf_static"] == 1
        assert counts.get("/odom", 1988) == 1988  # the Foxglove file has no /odom
        assert (info.start_ns, info.end_ns) == (1134864629895182000, 1134865053892206000)
    containers = [open_log(shared_file(name)).info().container for name in CSAIL]
    assert containers == ["mcap", "rosbag1", "rosbag2-sqlite3", "mcap"]


def test_csail_containers_decode_to_identical_scans(csail_scans: dict[str, list[Scan2D]]) -> None:
    reference = csail_scans[CSAIL[0]]
    assert len(reference) == 1988
    assert all(s.beam_count == 361 and s.frame_id == "laser" for s in reference)
    stamps = [s.stamp_ns for s in reference]
    assert stamps == sorted(stamps)
    for name in CSAIL[1:]:
        scans = csail_scans[name]
        assert [s.stamp_ns for s in scans] == stamps, name
        for scan, ref in zip(scans, reference, strict=True):
            # ROS ranges are float32 of the logged decimals, Foxglove's float64 of the same decimals.
            np.testing.assert_array_equal(scan.ranges.astype(np.float32), ref.ranges.astype(np.float32))
            if name.endswith("foxglove.mcap"):
                np.testing.assert_allclose(scan.points, ref.points, rtol=0, atol=1e-5)
            else:
                np.testing.assert_array_equal(scan.points, ref.points)


def test_csail_no_return_beams_are_dropped(csail_scans: dict[str, list[Scan2D]]) -> None:
    ranges = np.concatenate([s.ranges for s in csail_scans[CSAIL[0]]])
    assert ranges.max() <= np.float32(CSAIL_RANGE_MAX)
    assert 1988 * 361 - ranges.size == 23711  # readings of 81.91 in the log (counted with mcap_ros2 below)


def test_csail_no_return_count_with_an_independent_decoder() -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with shared_file("logs/csail/csail.mcap").open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        markers = sum(
            int((np.asarray(m.decoded_message.ranges) > m.decoded_message.range_max).sum())
            for m in reader.iter_decoded_messages(topics=["/scan"])
        )
    assert markers == 23711


def test_csail_odometry_is_identical_in_every_container() -> None:
    poses = {name: list(open_log(shared_file(name)).odometry()) for name in CSAIL}
    reference = poses[CSAIL[0]]
    assert len(reference) == 1988
    for name in CSAIL[1:]:  # the Foxglove file's odometry comes from its odom → base_link transforms
        assert [(p.stamp_ns, p.frame_id, p.child_frame_id) for p in poses[name]] == [
            (p.stamp_ns, p.frame_id, p.child_frame_id) for p in reference
        ]
        np.testing.assert_array_equal(
            [p.translation for p in poses[name]], [p.translation for p in reference]
        )
        np.testing.assert_array_equal([p.rotation for p in poses[name]], [p.rotation for p in reference])


@pytest.mark.parametrize("after_tree", [False, True], ids=["own-pass", "kept-by-transform-tree"])
def test_csail_odometry_arrays_are_the_odometry_stream_stacked(after_tree: bool) -> None:
    for name in CSAIL:  # odometry topics, and the Foxglove file's odometry on tf
        with open_log(shared_file(name)) as log:
            if after_tree:
                log.transform_tree()
            arrays = log.odometry_arrays()
        with open_log(shared_file(name)) as log:
            poses = list(log.odometry())
        assert arrays is not None
        assert arrays.stamps_ns.tolist() == [p.stamp_ns for p in poses]
        assert (arrays.frame_id, arrays.child_frame_id) == (poses[-1].frame_id, poses[-1].child_frame_id)
        for stacked, single in ((arrays.translations, [p.translation for p in poses]),
                                (arrays.rotations, [p.rotation for p in poses])):
            assert stacked.flags.c_contiguous
            assert stacked.tobytes() == np.array(single, dtype=np.float64).tobytes()


def test_tf_example_bag_and_ros2_bag_hold_identical_transforms() -> None:
    ros1 = list(open_log(shared_file("bags/tf_example.bag")).transforms())
    ros2 = list(open_log(shared_file("bags/tf_example")).transforms())
    assert len(ros1) == len(ros2) == 518
    assert [(t.parent_frame, t.child_frame, t.stamp_ns, t.is_static) for t in ros1] == [
        (t.parent_frame, t.child_frame, t.stamp_ns, t.is_static) for t in ros2
    ]
    np.testing.assert_array_equal([t.translation for t in ros1], [t.translation for t in ros2])
    np.testing.assert_array_equal([t.rotation for t in ros1], [t.rotation for t in ros2])
    assert sum(t.is_static for t in ros1) == 1


def test_nav2_turtlebot_odometry_matches_mcap_ros2() -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = shared_file("bags/nav2_turtlebot.mcap")
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        expected = []
        for message in reader.iter_decoded_messages(topics=["/odom"]):
            odometry = message.decoded_message
            stamp = odometry.header.stamp.sec * 10**9 + odometry.header.stamp.nanosec
            p, q = odometry.pose.pose.position, odometry.pose.pose.orientation
            expected.append(
                (stamp, odometry.header.frame_id, odometry.child_frame_id, p.x, p.y, p.z, q.x, q.y, q.z, q.w)
            )
    expected.sort(key=lambda row: row[0])
    poses = list(open_log(path).odometry())
    assert len(poses) == len(expected) == 2639
    assert [(p.stamp_ns, p.frame_id, p.child_frame_id) for p in poses] == [row[:3] for row in expected]
    np.testing.assert_allclose(
        [[*p.translation, *p.rotation] for p in poses], [row[3:] for row in expected], atol=1e-12
    )


def test_nav2_turtlebot_transform_tree_places_the_lidar() -> None:
    log = open_log(shared_file("bags/nav2_turtlebot.mcap"))
    tree = log.transform_tree()
    stamp = next(iter(log.odometry())).stamp_ns
    lidar_in_odom = tree.lookup("odom", "rplidar_link", stamp, tolerance_ns=50_000_000)
    chain = (
        tree.lookup("odom", "base_link", stamp, tolerance_ns=50_000_000).matrix()
        @ tree.lookup("base_link", "rplidar_link", stamp).matrix()
    )
    np.testing.assert_allclose(lidar_in_odom.matrix(), chain, atol=1e-12)


@pytest.mark.parametrize(
    ("name", "count"), [("logs/mumble/straight", 147), ("logs/mumble/hallway_room_loop", 896)]
)
def test_mumble_rplidar_scans(name: str, count: int) -> None:
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    path = shared_file(name)
    store = get_typestore(Stores.ROS2_HUMBLE)  # the bags store no message definitions
    with Reader(path) as reader:
        connections = [c for c in reader.connections if c.topic == "/scan"]
        expected = [
            store.deserialize_cdr(data, "sensor_msgs/msg/LaserScan")
            for _, _, data in reader.messages(connections)
        ]
    log = open_log(path)
    assert log.odometry_topic() is None and log.transform_topics == ()
    scans = list(log.scans())
    assert len(scans) == len(expected) == count
    expected.sort(key=lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)
    for scan, message in zip(scans, expected, strict=True):
        assert scan.stamp_ns == message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
        assert scan.beam_count == 360 and scan.frame_id == "laser_frame"
        valid = (
            np.isfinite(message.ranges)
            & (message.ranges >= message.range_min)
            & (message.ranges <= message.range_max)
        )
        np.testing.assert_array_equal(scan.ranges, message.ranges[valid])
        bearings = message.angle_min + np.flatnonzero(valid) * np.float64(message.angle_increment)
        np.testing.assert_allclose(scan.bearings, bearings, atol=1e-9)


def test_kitti_point_clouds() -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = shared_file("logs/kitti/kitti_city.mcap")  # read in place: CC BY-NC-SA test data, never copied
    clouds = list(open_log(path).clouds())
    assert len(clouds) == 154
    start = 1316995200 * 10**9  # 2011-09-26T00:00:00Z, frames 0.1 s apart (synthetic stamps)
    assert [c.stamp_ns for c in clouds] == [start + k * 100_000_000 for k in range(154)]
    assert all(c.frame_id == "velodyne" and c.point_times is None for c in clouds)
    sizes = [c.points.shape[0] for c in clouds]
    assert min(sizes) == 32845 and max(sizes) == 41375
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        first = next(iter(reader.iter_decoded_messages(topics=["/velodyne_points"]))).decoded_message
    xyz = np.frombuffer(bytes(first.data), np.float32).reshape(-1, 4)[:, :3]
    np.testing.assert_array_equal(clouds[0].points, xyz)


def test_aces_scans() -> None:
    log = open_log(shared_file("logs/aces/aces.mcap"))
    assert {t.name: t.count for t in log.info().topics}["/scan"] == 7374
    first = next(log.scans())
    assert first.beam_count == 180 and first.ranges.max() <= np.float32(49.99)
