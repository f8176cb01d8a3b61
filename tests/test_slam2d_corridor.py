"""Along-corridor ambiguity in the 2D SLAM's keyframe constraints (issue 13, the continued ACES figure).

In a featureless corridor the scans pin the robot across the corridor and in heading, never along it: there
the keyframe step is what the wheels measured. Its constraint must say so, neither as certain as a scan
match (the optimizer would trust a slip) nor looser than the wheels (the optimizer would fold such a
stretch by metres to absorb the misfit of loop closures elsewhere, which is what bent ACES' continued run).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from frontends.slam2d.config import OdometryConfig, Slam2DConfig
from frontends.slam2d.icp import refine_point_to_line, scan_normals
from frontends.slam2d.local_map import Keyframe, Submap
from frontends.slam2d.match_covariance import PLATEAU_SIGMA, score_plateau
from frontends.slam2d.slam import LaserSlam2D, Slam2DGraph
from tests.laser_world import Run, box, long_corridor, simulate_run, simulate_scan


@pytest.fixture(scope="module")
def corridor_run() -> Run:
    """20 m down two parallel walls 2 m apart (the corridor runs along x), scans every 0.1 m."""
    return simulate_run(long_corridor(), step=0.1, seed=4)


def mapped(run: Run, *, with_odometry: bool) -> Slam2DGraph:
    slam = LaserSlam2D()
    for stamp, scan, odometry in zip(run.stamps_ns, run.scans, run.odometry, strict=True):
        slam.add_scan(int(stamp), scan, odometry if with_odometry else None)
    return slam.finish()


def keyframe_steps(result: Slam2DGraph, at_least: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """The odometry constraints' measurements (K, 3) and covariances (K, 3, 3), in the earlier keyframe's
    frame (the robot heads along the corridor: x is along it, y across); `at_least` of them."""
    graph = result.graph
    odometry = graph.edge_to - graph.edge_from == 1
    assert odometry.sum() >= at_least  # the drive made keyframes all along the corridor
    return graph.measurements[odometry], np.linalg.inv(graph.information[odometry])


def test_a_step_along_a_featureless_corridor_is_as_uncertain_as_the_wheels_say(corridor_run: Run) -> None:
    steps, covariances = keyframe_steps(mapped(corridor_run, with_odometry=True))
    settings = OdometryConfig()
    # The wheel-odometry model over each step, written out from the settings' documented meaning
    # (σ = constant + per-metre × distance, here of the matched step; the wheels' own distance differs by
    # their scale error and noise, a few per cent): the step's σ along the corridor may not exceed it …
    wheels = settings.odometry_sigma_linear + settings.odometry_sigma_per_metre * np.hypot(steps[:, 0],
                                                                                             steps[:, 1])
    along = np.sqrt(covariances[:, 0, 0])
    assert np.all(along <= 1.1 * wheels)
    # … nor be claimed much better: nothing along the corridor is measured but the wheels.
    assert np.all(along >= 0.5 * wheels)
    # Across the corridor and in heading the walls measure the step far better than the wheels would.
    across = np.sqrt(covariances[:, 1, 1])
    assert np.all(across < 0.25 * wheels)
    assert np.all(np.sqrt(covariances[:, 2, 2]) < settings.odometry_sigma_angular)


def test_without_wheel_odometry_a_corridor_step_stays_loosely_known(corridor_run: Run) -> None:
    """No wheels, nothing to fuse: along the corridor the step stays at least twice looser than wheels
    would have made it (only the constant-velocity guess and the score's plateau speak there), across it
    the walls pin it."""
    # Without wheels nothing measures the motion along the corridor: the estimate barely moves along it
    # and makes few keyframes.
    steps, covariances = keyframe_steps(mapped(corridor_run, with_odometry=False), at_least=10)
    settings = OdometryConfig()
    wheels = settings.odometry_sigma_linear + settings.odometry_sigma_per_metre * np.hypot(steps[:, 0],
                                                                                             steps[:, 1])
    assert np.all(np.sqrt(covariances[:, 0, 0]) > 2.0 * wheels)
    assert np.all(np.sqrt(covariances[:, 1, 1]) < 0.05)


# ------------------------------------------------------------------------- a match that would slide

PILLAR_SHIFT = 0.25
"""The one feature along the corridor sits this much farther (m) in the scanned world than in the map: a
local map bent by an optimization, as on ACES' continued run at 1082 s."""


def corridor_with_pillar(pillar_x: float) -> np.ndarray:
    return np.concatenate([long_corridor().segments, box(pillar_x, 0.7, pillar_x + 0.04, 1.0)])


def local_map_and_scan(true_x: float) -> tuple[Submap, np.ndarray]:
    matching = Slam2DConfig().matching
    rng = np.random.default_rng(8)
    reference = simulate_scan(corridor_with_pillar(3.0), np.zeros(3), range_noise=0.01, rng=rng)
    submap = Submap.of([Keyframe(reference, scan_normals(reference))], [np.zeros(3)],
                       resolution=matching.resolution, likelihood_sigma=matching.likelihood_sigma, margin=2.0,
                       pairing_distance=matching.icp_max_distance)
    # Other bearings than the map's: in a uniform corridor a scan with the same ones, placed where the map's
    # was taken, would repeat the map's points exactly wherever it was taken.
    scan = simulate_scan(corridor_with_pillar(3.0 + PILLAR_SHIFT), np.array([true_x, 0.0, 0.0]), beams=347,
                         range_noise=0.01, rng=rng)
    return submap, scan


def test_the_score_plateau_of_a_corridor_runs_along_it_and_a_room_has_none() -> None:
    submap, scan = local_map_and_scan(0.5)
    sigma, axis = score_plateau(scan, submap.grid, np.array([0.5, 0.0, 0.0])).long_axis
    assert sigma > 2 * PLATEAU_SIGMA
    assert abs(axis[0]) > 0.95  # along the corridor (x)
    # A closed room 4 m × 3 m: every translation moves some wall off its returns.
    room = box(-2.0, -1.5, 2.0, 1.5)
    matching = Slam2DConfig().matching
    seen = simulate_scan(room, np.zeros(3), range_noise=0.01, rng=np.random.default_rng(2))
    room_map = Submap.of([Keyframe(seen, scan_normals(seen))], [np.zeros(3)], resolution=matching.resolution,
                         likelihood_sigma=matching.likelihood_sigma, margin=2.0,
                         pairing_distance=matching.icp_max_distance)
    assert not score_plateau(seen, room_map.grid, np.zeros(3)).is_slide


def test_a_scan_does_not_slide_along_a_corridor_to_a_misplaced_feature() -> None:
    """The scan fits the corridor's walls anywhere along it; only a pillar, misplaced in the map by
    `PILLAR_SHIFT`, says where along it. ICP pulls the scan onto the pillar; the score barely prefers it,
    so the wheel odometry (here exact) decides the position along the corridor."""
    true_x = 0.5
    submap, scan = local_map_and_scan(true_x)
    slam = LaserSlam2D()
    slam._local_map = submap
    slam._last_odometry = np.zeros(3)  # a wheel-odometry prediction: the narrow window
    prior = np.array([true_x, 0.0, 0.0])
    sigma = OdometryConfig().odometry_sigma_linear
    prior_information = np.diag([sigma**-2, sigma**-2, math.radians(2.0) ** -2])
    pose, matched, information = slam._match(0, scan, prior, prior_information, 1.0)
    assert matched
    assert abs(pose[0] - true_x) < 0.05  # without the plateau: 0.2 m short, the pillar matched
    assert abs(pose[1]) < 0.02
    covariance = np.linalg.inv(information)
    # The match's σ along the corridor says it measured nothing there; across, the walls pin it.
    assert math.sqrt(covariance[0, 0]) > PLATEAU_SIGMA
    assert math.sqrt(covariance[1, 1]) < 0.05


def lidar_only_match(pillar_shift: float) -> tuple[np.ndarray, bool]:
    """The scan at x = 0.5 matched without odometry (window ±0.5 m) on a map whose pillar sits
    `pillar_shift` farther along the corridor than the scanned one."""
    matching = Slam2DConfig().matching
    rng = np.random.default_rng(8)
    reference = simulate_scan(corridor_with_pillar(3.0), np.zeros(3), range_noise=0.01, rng=rng)
    slam = LaserSlam2D()
    slam._local_map = Submap.of([Keyframe(reference, scan_normals(reference))], [np.zeros(3)],
                                resolution=matching.resolution, likelihood_sigma=matching.likelihood_sigma,
                                margin=2.0, pairing_distance=matching.icp_max_distance)
    scan = simulate_scan(corridor_with_pillar(3.0 + pillar_shift), np.array([0.5, 0.0, 0.0]), beams=347,
                         range_noise=0.01, rng=rng)
    assert OdometryConfig().window_linear_without_odometry == 0.5
    # The last scan 0.1 m back: a match failing around the prediction is tried around it as well (a motion
    # reversing), whose window (±0.5 m of x = 0.4) does not reach the slid pose either.
    slam._last_pose = np.array([0.4, 0.0, 0.0])
    pose, matched, _ = slam._match(0, scan, np.array([0.5, 0.0, 0.0]), np.diag([4.0, 4.0, 10.0]), 1.0)
    return pose, matched


def test_without_odometry_a_match_that_slid_beyond_the_search_window_is_not_taken() -> None:
    """ICP follows the pillar along the corridor past the window the correlative search scored (the
    pillar 0.8 m off: ICP ends 0.8 m back, outside ±0.5 m): the scan keeps its prediction, unmatched,
    instead of a pose the search never judged (taken before: 0.8 m off)."""
    pose, matched = lidar_only_match(0.8)
    assert not matched
    np.testing.assert_allclose(pose, [0.5, 0.0, 0.0])
    # Within the window the match is taken (the plateau then hands the along-corridor position to the
    # prediction, as with odometry).
    pose, matched = lidar_only_match(0.3)
    assert matched and abs(pose[1]) < 0.02


def test_a_loop_closure_along_a_corridor_is_weak_along_it_only() -> None:
    """A loop closure's match on the same look-alike stretch: its information along the corridor is the
    plateau's (it cannot say where along the corridor the two keyframes are), across it the walls'."""
    submap, scan = local_map_and_scan(0.5)
    matching = Slam2DConfig().matching
    refined = refine_point_to_line(scan, submap.grid, submap.points, submap.normals,
                                   np.array([0.5, 0.0, 0.0]), max_distance=matching.icp_max_distance,
                                   sigma=matching.point_sigma)
    along_icp = math.sqrt(np.linalg.inv(matching.information_scale * refined.information)[0, 0])
    covariance = np.linalg.inv(LaserSlam2D()._loop_information(scan, submap, refined))
    assert along_icp < PLATEAU_SIGMA  # the fin alone makes ICP sure of itself along the corridor …
    assert math.sqrt(covariance[0, 0]) > 2 * PLATEAU_SIGMA  # … the score is not
    assert math.sqrt(covariance[1, 1]) < 0.05
