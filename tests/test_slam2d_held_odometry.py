"""Wheel odometry that stops updating while the robot turns, then jumps by the whole turn (CSAIL's log
does it three times: 4 scans of a turn in place, then +1.49 rad at once)."""

from __future__ import annotations

import numpy as np

from frontends.slam2d.localization import MapLocalizer
from frontends.slam2d.slam import LaserSlam2D
from tests.laser_world import between, compose, simulate_run, simulate_scan, square_loop

TURN_PER_SCAN = 0.25
"""Radians the robot turns in place between two scans (CSAIL turns about this fast)."""


def turn_in_place_drive() -> tuple[np.ndarray, list[np.ndarray]]:
    """True poses: 15 scans east along the south corridor, then 12 turning in place (left, 3 rad)."""
    straight = np.array([[3.0 + 0.2 * k, 1.0, 0.0] for k in range(15)])
    turning = np.array([[straight[-1, 0], 1.0, TURN_PER_SCAN * (k + 1)] for k in range(12)])
    truth = np.concatenate([straight, turning])
    rng = np.random.default_rng(3)
    scans = [simulate_scan(square_loop().segments, pose, range_noise=0.01, rng=rng) for pose in truth]
    return truth, scans


def held_odometry(truth: np.ndarray, held: range) -> np.ndarray:
    """Exact odometry, except that the scans of `held` repeat the value before them (the turn goes on);
    the next scan's value then holds the whole motion since."""
    odometry = truth.copy()
    odometry[list(held)] = odometry[held.start - 1]
    return odometry


def slam_poses(truth: np.ndarray, scans: list[np.ndarray], odometry: np.ndarray) -> np.ndarray:
    slam = LaserSlam2D()
    estimates = [slam.add_scan(1_700_000_000_000_000_000 + k * 200_000_000, scan, odo)
                 for k, (scan, odo) in enumerate(zip(scans, odometry, strict=True))]
    return compose(np.broadcast_to(truth[0], truth.shape), np.array([e.pose for e in estimates]))


def heading_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.abs(between(truth, poses)[:, 2])


def test_a_turn_the_odometry_held_back_is_not_counted_twice() -> None:
    """The odometry holds still for 4 scans of the turn (1 rad), which the scans track; its next value
    holds that 1 rad again. Predicted from the last pose, the scan would be sought a whole radian off;
    every scan stays on the true pose."""
    truth, scans = turn_in_place_drive()
    held = range(17, 21)
    odometry = held_odometry(truth, held)
    assert abs(between(odometry[held.stop - 1], odometry[held.stop])[2]) > 4.5 * TURN_PER_SCAN
    poses = slam_poses(truth, scans, odometry)
    assert heading_errors(poses, truth).max() < np.radians(1.0)
    assert np.hypot(*(poses[:, :2] - truth[:, :2]).T).max() < 0.05


def test_odometry_that_holds_while_the_robot_stands_still_changes_nothing() -> None:
    """Held odometry while the robot does not move (a slow odometry stream): nothing to correct."""
    truth, scans = turn_in_place_drive()
    still = np.concatenate([truth[:10], np.repeat(truth[9:10], 4, axis=0), truth[10:]])
    still_scans = scans[:10] + [scans[9]] * 4 + scans[10:]
    odometry = held_odometry(still, range(10, 14))
    poses = slam_poses(still, still_scans, odometry)
    assert heading_errors(poses, still).max() < np.radians(1.0)
    assert np.hypot(*(poses[:, :2] - still[:, :2]).T).max() < 0.05


def test_the_localizer_does_not_count_a_held_turn_twice() -> None:
    """The same held odometry, localized in a saved map of the building (scans at true poses): the turn
    the scans tracked while the odometry held still is not sought again when its jump arrives."""
    truth, scans = turn_in_place_drive()
    held = range(17, 21)
    odometry = held_odometry(truth, held)
    run = simulate_run(square_loop(), seed=1)
    keyframes = np.arange(0, len(run.truth), 3)
    localizer = MapLocalizer([run.scans[k] for k in keyframes], run.truth[keyframes], initial_pose=truth[0])
    results = [localizer.localize(1_700_000_000_000_000_000 + k * 200_000_000, scan, odo)
               for k, (scan, odo) in enumerate(zip(scans, odometry, strict=True))]
    assert all(r.localized and r.matched for r in results)
    poses = np.array([r.pose for r in results])
    assert heading_errors(poses, truth).max() < np.radians(1.0)
    assert np.hypot(*(poses[:, :2] - truth[:, :2]).T).max() < 0.05
