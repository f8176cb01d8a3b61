"""The LiDAR's mount from tf, the vehicle's odometry as a registration prior, deskewing from azimuths."""

from __future__ import annotations

import math

import numpy as np
import pytest

from frontends.errors import LogWarning
from frontends.logs import Cloud3D, OdometryPose, Transform, TransformTree
from frontends.protocol import default_base_frame
from frontends.slam3d import LidarFrontend, LidarSlam3D, se3
from frontends.slam3d.config import OdometryConfig
from frontends.slam3d.odometry import KissOdometry, azimuth_point_times, normalized_point_times
from frontends.slam3d.vehicle import OdometryPrior, lidar_mount
from tests.lidar_world import (
    Drive,
    Lidar,
    drive,
    homogeneous,
    planar_to_matrix,
    rotation_z,
    town_loop,
)

IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])


def _q_yaw(theta: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)])


def _edge(parent: str, child: str, xyz: tuple[float, float, float], q: np.ndarray, static: bool) -> Transform:
    return Transform(parent, child, 0, 0, np.array(xyz, dtype=np.float64), q, static)


def _tree(*edges: Transform) -> TransformTree:
    return TransformTree().extend(edges)


# ------------------------------------------------------------------------------------------ the mount


def test_the_base_is_the_frame_that_moves() -> None:
    tree = _tree(
        _edge("odom", "base_footprint", (5.0, 0.0, 0.0), IDENTITY_Q, static=False),
        _edge("base_footprint", "base_link", (0.0, 0.0, 0.3), IDENTITY_Q, static=True),
        _edge("base_link", "velodyne", (0.5, 0.0, 1.5), _q_yaw(math.pi / 2), static=True),
    )
    assert default_base_frame(tree, "velodyne") == "base_footprint"
    mount = lidar_mount(tree, "velodyne", 0)
    assert mount.base_frame == "base_footprint" and mount.from_tf
    # the sensor's origin is 0.5 m ahead and 0.3 + 1.5 m up; its x axis points along the base's y
    np.testing.assert_allclose(mount.sensor_to_base[:3, 3], [0.5, 0.0, 1.8], atol=1e-12)
    np.testing.assert_allclose(mount.sensor_to_base[:3, 0], [0.0, 1.0, 0.0], atol=1e-12)
    # overridden: the mount on base_link leaves out the footprint's 0.3 m
    override = lidar_mount(tree, "velodyne", 0, base_frame="base_link")
    np.testing.assert_allclose(override.sensor_to_base[:3, 3], [0.5, 0.0, 1.5], atol=1e-12)


def test_a_static_only_tree_ends_at_base_link_or_its_root() -> None:
    with_base_link = _tree(
        _edge("map", "base_link", (0.0, 0.0, 0.0), IDENTITY_Q, static=True),
        _edge("base_link", "lidar", (0.0, 0.0, 2.0), IDENTITY_Q, static=True),
    )
    assert default_base_frame(with_base_link, "lidar") == "base_link"
    rig = _tree(
        _edge("vehicle", "rig", (1.0, 0.0, 0.0), IDENTITY_Q, static=True),
        _edge("rig", "lidar", (0.0, 0.0, 2.0), IDENTITY_Q, static=True),
    )
    mount = lidar_mount(rig, "lidar", 0)
    assert mount.base_frame == "vehicle"
    np.testing.assert_allclose(mount.sensor_to_base[:3, 3], [1.0, 0.0, 2.0])


def test_a_sensor_frame_tf_does_not_know_is_its_own_base() -> None:
    tree = _tree(_edge("base_link", "camera", (0.0, 0.0, 1.0), IDENTITY_Q, static=True))
    mount = lidar_mount(tree, "velodyne", 0)
    assert mount.base_frame == "velodyne" and not mount.from_tf
    np.testing.assert_array_equal(mount.sensor_to_base, np.eye(4))
    assert default_base_frame(TransformTree(), "velodyne") == "velodyne"


def test_a_base_frame_tf_does_not_link_has_no_mount() -> None:
    """(The frontend turns it into an error naming the log: `test_pipeline_log`, `test_pipeline_cloud`.)"""
    tree = _tree(_edge("base_link", "lidar", (0.0, 0.0, 1.0), IDENTITY_Q, static=True))
    assert lidar_mount(tree, "lidar", 0, base_frame="base_footprint") is None
    assert lidar_mount(tree, "lidar", 0, base_frame="base_link") is not None


# ------------------------------------------------------------------------------------ odometry prior


def test_the_odometry_prior_interpolates_between_poses() -> None:
    poses = [
        OdometryPose(1_000, 1_000, "odom", "base_link", np.array([0.0, 0.0, 0.0]), IDENTITY_Q),
        OdometryPose(3_000, 3_000, "odom", "base_link", np.array([2.0, 4.0, 0.0]), _q_yaw(math.pi / 2)),
        OdometryPose(10_000, 10_000, "odom", "base_link", np.array([9.0, 4.0, 0.0]), _q_yaw(math.pi / 2)),
    ]
    prior = OdometryPrior.from_poses(poses, max_gap_ns=5_000)
    assert prior is not None and len(prior) == 3
    halfway = prior.at(2_000)
    assert halfway is not None
    np.testing.assert_allclose(halfway[:3, 3], [1.0, 2.0, 0.0])
    np.testing.assert_allclose(halfway[:3, :3], rotation_z(math.pi / 4), atol=1e-12)
    np.testing.assert_allclose(prior.at(3_000)[:3, 3], [2.0, 4.0, 0.0])  # type: ignore[index]
    assert prior.at(999) is None and prior.at(10_001) is None  # outside the odometry's span
    assert prior.at(5_000) is None  # inside a 7 µs gap, longer than the 5 µs allowed
    assert OdometryPrior.from_poses([]) is None
    assert prior.child_frame == "base_link"
    # the same odometry for a frame 1 m ahead of base_link: at 90° yaw it sits 1 m along odom's y
    ahead = prior.rebase(homogeneous(np.eye(3), np.array([1.0, 0.0, 0.0])))
    np.testing.assert_allclose(ahead.at(3_000)[:3, 3], [2.0, 5.0, 0.0], atol=1e-12)  # type: ignore[index]


def test_wheel_odometry_guides_the_registration_through_a_jump_in_speed() -> None:
    # 8 m/s, then only every 4th sweep arrives (a dropped-message burst): 3.2 m between clouds, which
    # KISS-ICP's constant-velocity prediction (0.8 m) does not expect
    run = drive(town_loop(), sweeps=40, step=0.8, ramp=5, lidar=Lidar(columns=360))
    kept = [*range(12), *range(15, 40, 4)]
    truth = planar_to_matrix(run.base_poses)[kept]
    wheel = truth.copy()
    wheel[:, :3, 3] *= 1.03  # wheel odometry 3 % long: a prior, not the truth
    expected = se3.relative(truth[0], truth)[:, :2, 3]

    def errors(with_prior: bool) -> np.ndarray:
        slam = LidarSlam3D(sensor_to_base=run.mount)
        poses = []
        for n, k in enumerate(kept):
            cloud = Cloud3D(k, k, "lidar", run.clouds[k], run.times[k].astype(np.float64))
            poses.append(slam.add_cloud(cloud, wheel[n] if with_prior else None).pose)
        estimated = se3.relative(poses[0], np.array(poses))[:, :2, 3]
        return np.linalg.norm(estimated - expected, axis=1)

    guided, unguided = errors(True), errors(False)
    assert guided.max() < 0.5 * unguided.max()
    assert guided[-1] < 0.1 * np.linalg.norm(expected[-1])


@pytest.mark.parametrize("jump", [
    homogeneous(np.eye(3), np.array([5.0, 0.0, 0.0])),  # a 5 m jump (a reset, a glitch)
    homogeneous(rotation_z(math.radians(30.0)), np.zeros(3)),  # a 30° jump in heading
], ids=["5 m", "30 deg"])
def test_a_jump_in_the_wheel_odometry_is_not_taken_as_motion(jump: np.ndarray) -> None:
    # the odometry is right but for one jump halfway: every pose after it is moved by `jump`, so one
    # guessed motion is metres (or 30°) off, which ICP cannot undo from there
    run = drive(town_loop(), sweeps=30, step=0.8, ramp=5, lidar=Lidar(columns=360))
    truth = planar_to_matrix(run.base_poses)
    wheel = truth.copy()
    wheel[15:] = jump @ wheel[15:]
    expected = se3.relative(truth[0], truth)[:, :2, 3]

    def errors(odometry: np.ndarray) -> tuple[np.ndarray, int]:
        slam = LidarSlam3D(sensor_to_base=run.mount)
        poses = [slam.add_cloud(Cloud3D(k, k, "lidar", run.clouds[k], run.times[k].astype(np.float64)),
                                odometry[k]).pose for k in range(len(truth))]
        estimated = se3.relative(poses[0], np.array(poses))[:, :2, 3]
        return np.linalg.norm(estimated - expected, axis=1), slam.finish().odometry_guesses_overruled

    clean, clean_overruled = errors(truth)
    jumped, overruled = errors(wheel)
    assert (clean_overruled, overruled) == (0, 1)
    assert jumped.max() < clean.max() + 0.05


# ------------------------------------------------------------------------------------------ deskewing


def test_azimuth_times_follow_the_sweep() -> None:
    # clockwise seen from above, from behind (Velodyne): behind … left … front … right … behind
    behind_left, left, front, right, behind_right = (
        [-1.0, 1e-6, 0],
        [0, 1.0, 0],
        [1.0, 0, 0],
        [0, -1.0, 0],
        [-1.0, -1e-6, 0],
    )
    points = np.array([behind_left, left, front, right, behind_right], dtype=np.float64)
    np.testing.assert_allclose(azimuth_point_times(points), [0.0, 0.25, 0.5, 0.75, 1.0], atol=1e-6)
    counter = azimuth_point_times(points, clockwise=False, start_azimuth=0.0)
    np.testing.assert_allclose(counter, [0.5, 0.25, 0.0, 0.75, 0.5], atol=1e-6)


@pytest.fixture(scope="module")
def corner_drive() -> Drive:
    """Into the loop's first turn at 8 m/s (6.5° per sweep): the motion distorts each sweep."""
    return drive(town_loop(), sweeps=32, step=0.8, start=4.0, lidar=Lidar(columns=720), mount=np.eye(4))


def test_azimuths_give_the_sweep_times_a_spinning_sensor_has(corner_drive: Drive) -> None:
    # the simulated sensor spins counter-clockwise from +x and fires its columns at a constant rate
    for points, recorded in zip(corner_drive.clouds[:3], corner_drive.times[:3], strict=True):
        swept = azimuth_point_times(points, clockwise=False, start_azimuth=0.0)
        from_azimuth, _ = normalized_point_times(swept)
        from_field, _ = normalized_point_times(recorded.astype(np.float64))
        assert np.abs(from_azimuth - from_field).max() < 2.0 / 720


def _odometry_errors(corner_drive: Drive, config: OdometryConfig, with_times: bool) -> np.ndarray:
    odometry = KissOdometry(config)
    poses = []
    for points, times in zip(corner_drive.clouds, corner_drive.times, strict=True):
        step = odometry.register(points, times.astype(np.float64) if with_times else None)
        assert step is not None
        poses.append(step.pose)
    truth = planar_to_matrix(corner_drive.base_poses)
    estimated = se3.relative(poses[0], np.array(poses))[:, :2, 3]
    return np.linalg.norm(estimated - se3.relative(truth[0], truth)[:, :2, 3], axis=1)


def test_clouds_without_times_are_deskewed_from_their_azimuths(corner_drive: Drive) -> None:
    # the simulated sensor spins counter-clockwise from +x, stamped at the sweep's start
    spin = {"spin_clockwise": False, "sweep_start_angle": 0.0, "stamp_at_sweep_end": False}
    per_point, auto = OdometryConfig(azimuth_times=False), OdometryConfig(**spin)
    not_deskewed = _odometry_errors(corner_drive, per_point, with_times=False)
    from_azimuth = _odometry_errors(corner_drive, auto, with_times=False)
    from_field = _odometry_errors(corner_drive, per_point, with_times=True)
    assert from_azimuth.max() < 0.6 * not_deskewed.max()
    assert from_azimuth.max() < from_field.max() + 0.1
    # the spin the wrong way round deskews the wrong way: worse than not deskewing
    wrong = OdometryConfig(stamp_at_sweep_end=False)
    wrong_way = _odometry_errors(corner_drive, wrong, with_times=False)
    assert wrong_way.max() > from_azimuth.max()


def test_a_narrow_field_of_view_is_not_deskewed_from_azimuths(corner_drive: Drive) -> None:
    odometry = KissOdometry(OdometryConfig())
    points = corner_drive.clouds[5]
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    front = points[np.abs(azimuth) < 35.0]  # a 70° solid-state sensor's view
    step = odometry.register(front)
    assert step is not None and not step.deskewed
    full = KissOdometry(OdometryConfig()).register(points)
    assert full is not None and full.deskewed


class _TfOnlyLog:
    """What `LidarFrontend` reads of a log before the clouds, for a log with these transforms and no
    odometry topic; counts how often the log is read for odometry."""

    path = "tf_only.mcap"

    def __init__(self, *transforms: Transform) -> None:
        self.transforms = transforms
        self.odometry_reads = 0

    def odometry_topic(self, topic: str | None = None) -> str | None:
        return topic

    def transform_tree(self) -> TransformTree:
        return _tree(*self.transforms)

    def odometry(self, topic: str | None = None) -> list[OdometryPose]:
        self.odometry_reads += 1
        return [OdometryPose(t.stamp_ns, 0, t.parent_frame, t.child_frame, t.translation, t.rotation)
                for t in self.transforms if not t.is_static and t.parent_frame == "odom"]


def test_odometry_comes_from_tf_only_when_tf_has_a_moving_edge() -> None:
    mount = _edge("base_link", "lidar", (1.0, 0.0, 1.8), IDENTITY_Q, True)
    static_only = _TfOnlyLog(mount)
    assert LidarFrontend(static_only, "/points")._prior is None  # type: ignore[arg-type]
    assert static_only.odometry_reads == 0  # the tf already read has no moving edge: not read again
    assert LidarFrontend(static_only, "/points").odometry_topic is None  # type: ignore[arg-type]
    moving = [Transform("odom", "base_link", stamp, 0, np.array([0.5 * k, 0.0, 0.0]), IDENTITY_Q, False)
              for k, stamp in enumerate((0, 100, 200))]
    with_odometry = _TfOnlyLog(mount, *moving)
    frontend = LidarFrontend(with_odometry, "/points")  # type: ignore[arg-type]
    prior = frontend._prior
    assert with_odometry.odometry_reads == 1 and prior is not None and len(prior) == 3
    assert frontend.odometry_topic == "tf odom -> base_link"  # what the summary names
    np.testing.assert_allclose(prior.at(150)[:3, 3], [0.75, 0.0, 0.0])


def test_odometry_of_a_frame_tf_does_not_link_to_the_lidar_is_left_out_with_a_warning() -> None:
    """The LiDAR sits on a rig tf does not attach to base_link, whose odometry tf holds: the poses are the
    rig's, which no odometry describes; the odometry is not used, and a warning says so."""
    moving = [Transform("odom", "base_link", stamp, 0, np.array([0.5 * k, 0.0, 0.0]), IDENTITY_Q, False)
              for k, stamp in enumerate((0, 100, 200))]
    log = _TfOnlyLog(_edge("rig", "lidar", (0.0, 0.0, 1.0), IDENTITY_Q, True), *moving)
    frontend = LidarFrontend(log, "/points")  # type: ignore[arg-type]
    mount = lidar_mount(frontend._tree, "lidar", 0)
    assert frontend._prior is not None and mount is not None and mount.base_frame == "rig"
    with pytest.warns(LogWarning, match="tf gives no path from the poses' frame rig .* to the odometry's "
                                        "base_link: the odometry was not used"):
        assert frontend._prior_of_base(mount, 0) is None
    linked = _TfOnlyLog(_edge("base_link", "lidar", (0.0, 0.0, 1.0), IDENTITY_Q, True), *moving)
    linked_frontend = LidarFrontend(linked, "/points")  # type: ignore[arg-type]
    linked_mount = lidar_mount(linked_frontend._tree, "lidar", 0)
    assert linked_mount is not None and linked_frontend._prior_of_base(linked_mount, 0) is not None


def test_odometry_that_covers_none_of_the_clouds_is_a_warning(corner_drive: Drive) -> None:
    """Odometry on another clock than the LiDAR (seconds since boot beside epoch time) never gives a prior:
    the clouds are registered without it, and a warning says why (before: silently)."""
    moving = [Transform("odom", "base_link", stamp, 0, np.array([0.5 * k, 0.0, 0.0]), IDENTITY_Q, False)
              for k, stamp in enumerate((0, 100, 200))]
    log = _TfOnlyLog(_edge("base_link", "lidar", (0.0, 0.0, 1.0), IDENTITY_Q, True), *moving)
    frontend = LidarFrontend(log, "/points")  # type: ignore[arg-type]
    stamps = [10**18 + k * 10**8 for k in range(6)]
    for stamp, points in zip(stamps, corner_drive.clouds, strict=False):
        frontend.add(Cloud3D(stamp, stamp, "lidar", points.astype(np.float32), None))
    with pytest.warns(LogWarning, match=r"the odometry covers none of the 6 clouds' stamps \(it runs from "
                                        r"0\.000 to 0\.000 s, the clouds from 1000000000\.000"):
        frontend.finish()
