"""KISS-ICP odometry through our wrapper: configuration mapping, per-point times, poses at the stamp."""

from __future__ import annotations

import numpy as np
import pytest
from kiss_icp.preprocess import Preprocessor

from frontends.slam3d import se3
from frontends.slam3d.config import OdometryConfig
from frontends.slam3d.odometry import (
    KissOdometry,
    deskew,
    downsample,
    kiss_config,
    normalized_point_times,
)
from tests.lidar_world import Drive, Lidar, drive, mount_matrix, planar_to_matrix, town_loop


@pytest.fixture(scope="module")
def corner_drive() -> Drive:
    """Speeding up to 8 m/s, then into the loop's first turn (6.5° per sweep): motion distortion matters."""
    return drive(town_loop(), sweeps=32, step=0.8, start=4.0, lidar=Lidar(columns=720), mount=np.eye(4))


def test_every_setting_is_mapped_onto_kiss_icp() -> None:
    config = OdometryConfig(
        max_range=60.0,
        min_range=2.0,
        deskew=False,
        voxel_size=None,
        max_points_per_voxel=7,
        initial_threshold=1.5,
        min_motion_threshold=0.2,
        fixed_threshold=0.4,
        max_iterations=50,
        convergence_criterion=5e-3,
        max_threads=1,
    )
    kiss = kiss_config(config)
    assert (kiss.data.max_range, kiss.data.min_range, kiss.data.deskew) == (60.0, 2.0, False)
    assert kiss.mapping.voxel_size == pytest.approx(0.6)  # KISS-ICP's rule: max range / 100
    assert kiss.mapping.max_points_per_voxel == 7
    assert kiss.adaptive_threshold.initial_threshold == 1.5
    assert kiss.adaptive_threshold.min_motion_th == 0.2
    assert kiss.adaptive_threshold.fixed_threshold == 0.4
    assert kiss.registration.max_num_iterations == 50
    assert kiss.registration.convergence_criterion == 5e-3
    assert kiss.registration.max_num_threads == 1
    assert kiss_config(OdometryConfig(voxel_size=0.25)).mapping.voxel_size == 0.25


def test_point_times_are_normalised_over_the_sweep() -> None:
    times, at_stamp = normalized_point_times(np.array([0.0, 0.025, 0.05, 0.1]))
    np.testing.assert_allclose(times, [0.0, 0.25, 0.5, 1.0])
    assert at_stamp == 0.0
    times, at_stamp = normalized_point_times(np.array([-0.1, -0.05, 0.0]))  # stamped at the sweep's end
    np.testing.assert_allclose(times, [0.0, 0.5, 1.0])
    assert at_stamp == 1.0
    # KISS-ICP divides by the span: no span, no time or a NaN means no deskewing (it would abort)
    for unusable in (None, np.zeros(0), np.full(5, 0.03), np.array([0.0, np.nan, 0.1])):
        times, at_stamp = normalized_point_times(unusable)
        assert len(times) == 0 and at_stamp is None


@pytest.mark.parametrize("twist", [(0.8, -0.1, 0.02, 0.004, -0.003, 0.11), (0.5, 0.0, 0.0, 0.0, 0.0, 1e-12)])
def test_deskewing_moves_points_as_kiss_icp_does(twist: tuple[float, ...]) -> None:
    """Our deskewing against KISS-ICP's own (its C++ preprocessor, ranges wide open): a turning and a
    straight (first-order rotation) motion, times spread over the sweep."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-40.0, 40.0, (2000, 3))
    times = rng.uniform(0.0, 1.0, 2000)
    times[:2] = 0.0, 1.0
    motion = se3.exp(np.array(twist))
    theirs = Preprocessor(1e6, 0.0, True, 1).preprocess(points, times, motion)
    np.testing.assert_allclose(deskew(points, times, motion), theirs, rtol=0, atol=1e-9)


def _position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance between estimated and true positions, both taken relative to their first pose."""
    estimated = se3.relative(poses[0], poses)[:, :2, 3]
    expected = se3.relative(truth[0], truth)[:, :2, 3]
    return np.linalg.norm(estimated - expected, axis=1)


def _run(corner_drive: Drive, time_shift: float | None) -> np.ndarray:
    odometry = KissOdometry(OdometryConfig(azimuth_times=False))  # no times: not deskewed
    poses = []
    for points, times in zip(corner_drive.clouds, corner_drive.times, strict=True):
        step = odometry.register(
            points, None if time_shift is None else times.astype(np.float64) + time_shift
        )
        assert step is not None
        poses.append(step.pose)
    return np.array(poses)


def test_deskewed_poses_are_those_at_the_stamp(corner_drive: Drive) -> None:
    world = town_loop()
    truth_at_start = planar_to_matrix(corner_drive.base_poses)
    truth_at_end = planar_to_matrix(world.route.pose(corner_drive.distances + corner_drive.speeds))
    raw = _position_errors(_run(corner_drive, None), truth_at_start)
    stamped_at_start = _position_errors(_run(corner_drive, 0.0), truth_at_start)
    # The same sweeps stamped at their end (times in [−0.1, 0)): the poses must follow.
    stamped_at_end = _run(corner_drive, -0.1)
    # KISS-ICP drifts on this sparse synthetic sensor (about 2 % here, speeding up at 8 m/s²); deskewing
    # halves it, and the poses are those of the stamps: at the sweeps' starts or at their ends.
    assert stamped_at_start.max() < 0.6 * raw.max()
    assert stamped_at_start.max() < 0.6
    assert _position_errors(stamped_at_end, truth_at_end).max() < 0.6
    assert _position_errors(stamped_at_end, truth_at_end).max() < 0.5 * (
        _position_errors(stamped_at_end, truth_at_start).max()
    )


def test_a_cloud_with_too_few_points_is_not_registered(corner_drive: Drive) -> None:
    odometry = KissOdometry(OdometryConfig(min_points=50))
    first = odometry.register(corner_drive.clouds[0])
    assert first is not None
    assert odometry.register(corner_drive.clouds[1][:49]) is None
    np.testing.assert_array_equal(odometry.pose, first.pose)
    # As many points as a full cloud, every one at the same spot (a sensor fault): no geometry to register
    # (before: registered, the pose extrapolated and tilting a degree a cloud).
    one_spot = np.tile(corner_drive.clouds[1][:1], (len(corner_drive.clouds[1]), 1))
    assert odometry.register(one_spot) is None
    np.testing.assert_array_equal(odometry.pose, first.pose)


def test_the_mount_pitch_does_not_leak_into_the_base_trajectory() -> None:
    mount = mount_matrix((0.4, 0.0, 1.8), np.radians(5.0))
    pitched = drive(town_loop(), sweeps=12, step=0.8, ramp=1, lidar=Lidar(columns=720), mount=mount)
    odometry = KissOdometry()
    base = []
    for points, times in zip(pitched.clouds, pitched.times, strict=True):
        step = odometry.register(points, times.astype(np.float64))
        assert step is not None
        base.append(mount @ step.pose @ se3.inverse(mount))
    heights = np.array(base)[:, 2, 3]
    assert np.abs(heights).max() < 0.3  # a 5° pitch misread would climb 0.8 m over these 9 m


def test_downsample_keeps_one_point_per_voxel() -> None:
    points = np.array([[0.1, 0.1, 0.1], [0.2, 0.3, 0.4], [1.1, 0.1, 0.1], [1.2, 0.2, 0.2], [5.0, 5.0, 5.0]])
    kept = downsample(points, 1.0)
    assert len(kept) == 3
    assert downsample(np.zeros((0, 3)), 1.0).shape == (0, 3)
