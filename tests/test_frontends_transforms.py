"""The transform tree, quaternion helpers and sensor-time ordering, against hand-computed geometry."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from frontends.errors import LogWarning, TransformLookupError
from frontends.logs import Cloud3D, OdometryPose, Scan2D, Transform, TransformTree, open_log, rotations
from frontends.logs.ordering import by_stamp
from tests._frontends_fixtures import ScanListLog, ros2_mcap


def planar(
    parent: str, child: str, stamp: int, x: float, y: float, yaw: float, static: bool = False
) -> Transform:
    return Transform(parent, child, stamp, stamp, np.array([x, y, 0.0]), rotations.from_yaw(yaw), static)


def se2_compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    x, y, t = a
    return (
        x + math.cos(t) * b[0] - math.sin(t) * b[1],
        y + math.sin(t) * b[0] + math.cos(t) * b[1],
        t + b[2],
    )


@pytest.fixture
def tree() -> TransformTree:
    tree = TransformTree()
    tree.add(planar("map", "odom", 0, 10.0, -5.0, 0.3, static=True))
    tree.add(planar("base_link", "laser", 0, 0.2, 0.05, math.pi, static=True))
    tree.add(planar("odom", "base_link", 100, 0.0, 0.0, 0.0))
    tree.add(planar("odom", "base_link", 200, 2.0, 1.0, math.pi / 2))
    return tree


def test_chain_through_static_and_dynamic_edges(tree: TransformTree) -> None:
    laser_in_map = tree.lookup("map", "laser", 200)
    expected = se2_compose(se2_compose((10.0, -5.0, 0.3), (2.0, 1.0, math.pi / 2)), (0.2, 0.05, math.pi))
    np.testing.assert_allclose(laser_in_map.translation, [expected[0], expected[1], 0.0], atol=1e-12)
    assert math.remainder(laser_in_map.yaw - expected[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    assert (laser_in_map.parent_frame, laser_in_map.child_frame, laser_in_map.is_static) == (
        "map",
        "laser",
        False,
    )
    assert tree.lookup("base_link", "laser", 12345).is_static


def test_opposite_lookups_are_inverses(tree: TransformTree) -> None:
    forward = tree.lookup("map", "laser", 150).matrix()
    backward = tree.lookup("laser", "map", 150).matrix()
    np.testing.assert_allclose(forward @ backward, np.eye(4), atol=1e-12)
    sibling = tree.lookup("laser", "odom", 150).matrix()  # common ancestor odom, not the root
    np.testing.assert_allclose(sibling, np.linalg.inv(tree.lookup("odom", "laser", 150).matrix()), atol=1e-12)


def test_interpolation_is_linear_in_translation_and_spherical_in_rotation(tree: TransformTree) -> None:
    halfway = tree.lookup("odom", "base_link", 150)
    np.testing.assert_allclose(halfway.translation, [1.0, 0.5, 0.0], atol=1e-12)
    assert halfway.yaw == pytest.approx(math.pi / 4, abs=1e-12)
    quarter = tree.lookup("odom", "base_link", 125)
    assert quarter.yaw == pytest.approx(math.pi / 8, abs=1e-12)
    exact = tree.lookup("odom", "base_link", 200)
    assert exact.yaw == pytest.approx(math.pi / 2, abs=1e-12)


def test_extrapolation_is_an_error_unless_within_tolerance(tree: TransformTree) -> None:
    with pytest.raises(
        TransformLookupError, match=r"no transform odom → base_link at 250 ns: its data spans 100 … 200 ns"
    ):
        tree.lookup("map", "laser", 250)
    assert not tree.can_transform("odom", "base_link", 99)
    near = tree.lookup("odom", "base_link", 210, tolerance_ns=20)
    np.testing.assert_allclose(near.translation, [2.0, 1.0, 0.0])


def test_unknown_and_disconnected_frames(tree: TransformTree) -> None:
    with pytest.raises(TransformLookupError, match=r"unknown frame 'camera'"):
        tree.lookup("map", "camera", 150)
    tree.add(planar("world", "gps", 0, 0.0, 0.0, 0.0, static=True))
    with pytest.raises(TransformLookupError, match=r"not connected"):
        tree.lookup("map", "gps", 150)


def test_lookup_many_matches_single_lookups(tree: TransformTree) -> None:
    stamps = np.array([100, 133, 150, 199, 200])
    translations, rotations_ = tree.lookup_many("map", "laser", stamps)
    for i, stamp in enumerate(stamps):
        single = tree.lookup("map", "laser", int(stamp))
        np.testing.assert_allclose(translations[i], single.translation, atol=1e-12)
        np.testing.assert_allclose(rotations_[i], single.rotation, atol=1e-12)


def test_unsorted_samples_are_sorted_before_lookup() -> None:
    tree = TransformTree()
    for stamp in (300, 100, 200):
        tree.add(planar("odom", "base", stamp, stamp / 100, 0.0, 0.0))
    assert tree.lookup("odom", "base", 150).translation[0] == pytest.approx(1.5)


def test_cache_keeps_only_recent_samples() -> None:
    tree = TransformTree(cache_ns=1000)
    for stamp in range(0, 100_000, 10):
        tree.add(planar("odom", "base", stamp, stamp * 1e-3, 0.0, 0.0))
    assert tree.lookup("odom", "base", 99_500).translation[0] == pytest.approx(99.5)
    with pytest.raises(TransformLookupError):
        tree.lookup("odom", "base", 50_000)


def test_scan_transformed_into_the_base_frame(tree: TransformTree) -> None:
    points = np.array([[1.0, 0.0], [0.0, 2.0]])
    scan = Scan2D(7, 7, "laser", points, np.array([1.0, 2.0]), np.array([0.0, math.pi / 2]), 2)
    in_base = scan.transformed(tree.lookup("base_link", "laser", 7))
    assert in_base.frame_id == "base_link"
    # laser at (0.2, 0.05) turned by π: its x axis points backwards.
    np.testing.assert_allclose(in_base.points, [[-0.8, 0.05], [0.2, -1.95]], atol=1e-12)
    np.testing.assert_array_equal(in_base.ranges, scan.ranges)
    with pytest.raises(ValueError, match="transform is for frame"):
        scan.transformed(tree.lookup("map", "odom", 0))


def test_types_are_read_only_and_validated() -> None:
    scan = Scan2D(1, 1, "laser", np.zeros((2, 2)), np.zeros(2), np.zeros(2), 3)
    with pytest.raises(ValueError):
        scan.points[0, 0] = 1.0
    with pytest.raises(ValueError, match="disagree"):
        Scan2D(1, 1, "laser", np.zeros((3, 2)), np.zeros(2), np.zeros(2), 3)
    pose = OdometryPose(1, 1, "odom", "base", np.array([1.0, 2.0, 0.0]), rotations.from_yaw(-2.0))
    np.testing.assert_allclose(pose.se2, [1.0, 2.0, -2.0])
    np.testing.assert_allclose(pose.matrix()[:2, 3], [1.0, 2.0])


angles = st.floats(-math.pi + 1e-6, math.pi - 1e-6)


@settings(max_examples=60, deadline=None)
@given(angles, angles, st.floats(0.0, 1.0))
def test_slerp_of_planar_rotations_moves_along_the_shorter_arc(a: float, b: float, fraction: float) -> None:
    q = rotations.slerp(rotations.from_yaw(a), rotations.from_yaw(b), fraction)
    difference = math.remainder(b - a, 2 * math.pi)
    expected = a + fraction * difference
    assert math.remainder(rotations.yaw(q) - expected, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert np.linalg.norm(q) == pytest.approx(1.0)


@settings(max_examples=60, deadline=None)
@given(angles, angles)
def test_quaternion_products_add_planar_angles(a: float, b: float) -> None:
    product = rotations.multiply(rotations.from_yaw(a), rotations.from_yaw(b))
    assert math.remainder(rotations.yaw(product) - (a + b), 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    identity = rotations.multiply(rotations.from_yaw(a), rotations.conjugate(rotations.from_yaw(a)))
    np.testing.assert_allclose(np.abs(identity), [0.0, 0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(
        rotations.rotate(rotations.from_yaw(a), [1.0, 0.0, 0.0]), [math.cos(a), math.sin(a), 0.0], atol=1e-12
    )


def _pose(stamp: int, log_time: int, frame: str = "odom") -> OdometryPose:
    return OdometryPose(stamp, log_time, frame, "base", np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))


def test_ordering_sorts_within_the_window_and_drops_later_arrivals() -> None:
    second = 10**9
    stamps = [0, 3 * second, 1 * second, 2 * second, 6 * second, 9 * second, 4 * second, 10 * second]
    items = [_pose(s, i * second) for i, s in enumerate(stamps)]
    with pytest.warns(LogWarning, match=r"1 messages dropped: their stamps were more than 2 s older"):
        out = list(by_stamp(items, Path("log.mcap"), window_ns=2 * second))
    # 4 s arrives after 6 s and 9 s: 9 − 2 = 7 s had already released 6 s.
    assert [p.stamp_ns // second for p in out] == [0, 1, 2, 3, 6, 9, 10]


def test_ordering_keeps_each_sources_own_pace() -> None:
    second = 10**9
    items = []
    for k in range(20):
        # A tf edge post-dated by 1.5 s (like AMCL's map → odom) beside odometry stamped on time.
        items.append(
            Transform(
                "map",
                "odom",
                k * second // 2 + 3 * second // 2,
                k * second // 2,
                np.zeros(3),
                np.array([0.0, 0.0, 0.0, 1.0]),
                False,
            )
        )
        items.append(_pose(k * second // 2 - second // 10, k * second // 2))
    items.append(Transform("base", "laser", 0, 0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), True))
    out = list(by_stamp(items, Path("log.mcap"), window_ns=second))
    assert len(out) == len(items)  # nothing late: each source is judged against its own newest stamp
    moving = [item for item in out if not getattr(item, "is_static", False)]
    assert [item.stamp_ns for item in moving] == sorted(item.stamp_ns for item in moving)
    # The static transform, stamped 0, passed straight through instead of counting as late.
    assert sum(getattr(item, "is_static", False) for item in out) == 1


def test_laser_scans_default_to_the_frame_that_moves_as_clouds_do() -> None:
    """One rule for both sensors (`frontends.protocol.default_base_frame`): up the laser's static tf chain to
    the frame whose edge moves, here base_footprint under odom, not the laser's parent base_link."""
    from frontends.slam2d.log_input import scans_in_base_frame

    identity = np.array([0.0, 0.0, 0.0, 1.0])
    tree = TransformTree().extend([
        Transform("odom", "base_footprint", 0, 0, np.zeros(3), identity, False),
        Transform("base_footprint", "base_link", 0, 0, np.array([0.0, 0.0, 0.1]), identity, True),
        Transform("base_link", "laser", 0, 0, np.array([0.2, 0.0, 0.3]), identity, True),
    ])
    points = np.array([[1.0, 0.0], [0.0, 2.0]])
    scan = Scan2D(0, 0, "laser", points, np.array([1.0, 2.0]), np.array([0.0, math.pi / 2]), 2)
    [(moved, mount)] = list(scans_in_base_frame(ScanListLog([scan]), "/scan", tree, None,  # type: ignore[arg-type]
                                                 min_points=1))
    assert mount is not None and mount.parent_frame == "base_footprint"
    assert moved.frame_id == "base_footprint"
    np.testing.assert_allclose(moved.points, points + np.array([0.2, 0.0]))


def test_frames_are_named_as_tf2_names_them_without_a_leading_slash() -> None:
    """tf1 named frames "/odom"; tf2 drops one leading slash on every lookup (`stripSlash`). A log mixing
    both (old bags, tf1-era drivers) is one tree."""
    from frontends.protocol import FrontendOptions
    from frontends.slam2d.log_input import scans_in_base_frame

    identity = np.array([0.0, 0.0, 0.0, 1.0])
    tree = TransformTree().extend([
        Transform("/odom", "/base_link", 0, 0, np.zeros(3), identity, False),
        Transform("base_link", "/laser", 0, 0, np.array([0.2, 0.0, 0.3]), identity, True),
    ])
    points = np.array([[1.0, 0.0], [0.0, 2.0]])
    scan = Scan2D(0, 0, "/laser", points, np.array([1.0, 2.0]), np.array([0.0, math.pi / 2]), 2)
    assert scan.frame_id == "laser"
    [(moved, mount)] = list(scans_in_base_frame(ScanListLog([scan]), "/scan", tree, None,  # type: ignore[arg-type]
                                                 min_points=1))
    assert mount is not None and (mount.parent_frame, mount.child_frame) == ("base_link", "laser")
    np.testing.assert_allclose(moved.points, points + np.array([0.2, 0.0]))
    odometry = OdometryPose(0, 0, "/odom", "/base_link", np.zeros(3), identity)
    assert (odometry.frame_id, odometry.child_frame_id) == ("odom", "base_link")
    assert Cloud3D(0, 0, "/velodyne", np.zeros((0, 3), np.float32), None).frame_id == "velodyne"
    assert FrontendOptions(base_frame="/base_link").base_frame == "base_link"
    # One slash, as tf2: "//x" is "/x"; a frame without one is left as it is.
    assert Transform("//map", "a/b", 0, 0, np.zeros(3), identity, True).parent_frame == "/map"
    assert Transform("//map", "a/b", 0, 0, np.zeros(3), identity, True).child_frame == "a/b"


def _tf_odometry_log(path: Path) -> Path:
    """Odometry only on tf: odom → base_link at 20 Hz with one message stored late (out of stamp order), a
    static odom → dock and, later, a second moving child odom → cart (not the odometry: the first child
    seen is), with map → odom beside them."""
    with ros2_mcap(path) as (messages, add):
        tf = "tf2_msgs/msg/TFMessage"
        add("/tf_static", tf, 0, messages.tf_message([messages.transform_stamped(0, "odom", "dock",
                                                                               (1.0, 0.0, 0.0), 0.0)]))
        stamps = [k * 50_000_000 for k in range(40)]
        stamps[10], stamps[11] = stamps[11], stamps[10]  # stored late: sorted by the reader
        for stamp in stamps:
            moving = [messages.transform_stamped(stamp, "odom", "base_link", (stamp * 1e-9, 0.2, 0.0), 0.1),
                      messages.transform_stamped(stamp, "map", "odom", (0.5, 0.0, 0.0), 0.0)]
            if stamp >= 1_000_000_000:
                cart = (0.0, stamp * 1e-9, 0.0)
                moving.append(messages.transform_stamped(stamp, "odom", "cart", cart, 0.0))
            add("/tf", tf, stamp, messages.tf_message(moving))
    return path


def test_the_odometry_on_tf_is_kept_from_the_tree_pass(tmp_path: Path) -> None:
    path = _tf_odometry_log(tmp_path / "tf_odometry.mcap")
    with open_log(path) as log:
        second_pass = [(p.stamp_ns, p.frame_id, p.child_frame_id, *p.translation, *p.rotation)
                       for p in log.odometry()]
    with open_log(path) as log:
        tree = log.transform_tree()
        log.transforms = None  # type: ignore[method-assign]  # another pass over tf would fail
        kept = [(p.stamp_ns, p.frame_id, p.child_frame_id, *p.translation, *p.rotation)
                for p in log.odometry()]
    assert kept == second_pass
    assert len(kept) == 40 and {pose[2] for pose in kept} == {"base_link"}
    assert tree.lookup("map", "cart", 1_500_000_000).translation[1] == pytest.approx(1.5)
