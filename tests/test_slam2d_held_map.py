"""The new run's keyframe graph solved with the saved map held (`frontends.slam2d.held_map`), on small graphs
whose exact solutions are known independently."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.errors import FrontendError
from frontends.slam2d.held_map import HeldOdometry, held_map_problem, solve_held_map, solve_with_map_held
from frontends.slam2d.localization import LocalizedScan
from frontends.slam2d.resume import MapPlacementError, SavedConstraints
from frontends.slam2d.slam import LaserSlam2D
from optimizer import se2
from optimizer.graph import PoseGraph
from optimizer.solve import optimize

SAVED = 6
NEW = 8
INFORMATION = np.diag([400.0, 400.0, 2500.0])


def truth(seed: int = 0) -> np.ndarray:
    """A saved run of SAVED keyframes, then a new run of NEW, wandering over a few metres."""
    rng = np.random.default_rng(seed)
    count = SAVED + NEW - 1
    steps = np.column_stack([rng.uniform(0.5, 1.0, count), rng.normal(0, 0.2, count),
                             rng.normal(0, 0.3, count)])
    return se2.compose_chain(steps, start=np.array([1.0, -2.0, 0.4]))


def edges(new_to_saved: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Consecutive keyframes, every saved keyframe to the new one two later than its mirror, new keyframes
    to the one three on (loops within the new run); and one new→saved edge when asked."""
    count = SAVED + NEW
    pairs = [(k, k + 1) for k in range(count - 1)]
    pairs += [(k, SAVED + (k + 2) % NEW) for k in range(SAVED)]
    pairs += [(k, k + 3) for k in range(SAVED, count - 3)]
    if new_to_saved:
        pairs.append((SAVED + 4, 2))
    array = np.array(pairs, dtype=np.int64)
    return array[:, 0], array[:, 1]


def graph_of(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, measurements: np.ndarray,
             start: np.ndarray | None = None) -> PoseGraph:
    information = np.repeat(INFORMATION[None], len(edge_from), axis=0)
    return PoseGraph.build(np.arange(len(poses)), poses if start is None else start, edge_from, edge_to,
                           measurements, information)


def test_exact_constraints_give_the_true_new_poses_from_a_start_far_off() -> None:
    """Every constraint measured from the truth and the saved keyframes held at theirs: the only optimum
    is the truth, whatever the start (the new run's online estimate here: 1 m and 0.3 rad off, and the
    saved keyframes moved rigidly, as a resumed SLAM's online optimizations move them)."""
    poses = truth()
    edge_from, edge_to = edges()
    measurements = se2.relative(poses[edge_from], poses[edge_to])
    start = poses.copy()
    start[SAVED:] = se2.compose(np.array([1.0, -0.5, 0.3]), poses[SAVED:])
    start = se2.compose(np.array([2.0, 3.0, -0.7]), start)
    solution = solve_with_map_held(graph_of(poses, edge_from, edge_to, measurements, start), poses[:SAVED])
    assert solution.converged
    np.testing.assert_allclose(solution.poses, poses[SAVED:], atol=1e-6)


def test_the_saved_map_stays_where_it_was_saved_when_the_new_run_disagrees_with_it() -> None:
    """The new run sees the saved keyframes bent away from the saved map (up to 0.25 m): optimized freely,
    the saved keyframes move; held, they cannot, and the new run's poses are those of the free optimization
    with the saved keyframes tied by near-rigid priors (an independent formulation of holding them)."""
    poses = truth(seed=1)
    edge_from, edge_to = edges()
    bent = poses.copy()
    bent[:SAVED, 1] += 0.05 * np.arange(SAVED)
    measurements = se2.relative(bent[edge_from], bent[edge_to])
    measurements[: SAVED - 1] = se2.relative(poses[: SAVED - 1], poses[1:SAVED])  # the saved run's own
    held = solve_with_map_held(graph_of(poses, edge_from, edge_to, measurements), poses[:SAVED]).poses

    free = optimize(graph_of(poses, edge_from, edge_to, measurements), method="gn")
    for _ in free:
        pass
    assert np.abs(free.result.poses[1:SAVED, :2] - poses[1:SAVED, :2]).max() > 0.01, "free, the map moves"

    # Pose 0 of this graph is the origin; each saved keyframe is tied to it at its saved pose, 10⁸ times
    # firmer than any constraint.
    prior_from = np.zeros(SAVED, dtype=np.int64)
    prior_to = np.arange(1, SAVED + 1)
    tied = PoseGraph.build(
        np.arange(SAVED + NEW + 1), np.vstack([np.zeros((1, 3)), poses]),
        np.concatenate([prior_from, edge_from + 1]), np.concatenate([prior_to, edge_to + 1]),
        np.concatenate([poses[:SAVED], measurements]),
        np.concatenate([np.repeat(1e8 * INFORMATION[None], SAVED, axis=0),
                        np.repeat(INFORMATION[None], len(edge_from), axis=0)]))
    tied_run = optimize(tied, method="gn")
    for _ in tied_run:
        pass
    np.testing.assert_allclose(held, tied_run.result.poses[SAVED + 1:], atol=1e-5)
    assert np.abs(held[:, :2] - free.result.poses[SAVED:, :2]).max() > 0.01, "not the free solution"


def test_the_odometry_start_chains_the_new_keyframes_from_the_first_ones_online_pose() -> None:
    """The held-map problem's poor start: each new keyframe reached from the one before by the constraint
    between them (the first of two, as the SLAM adds its odometry first), from the first new keyframe's
    online pose; the loop closures and the map play no part in it."""
    poses = truth(seed=3)
    edge_from, edge_to = edges()
    first_new = np.flatnonzero(edge_from == SAVED)[0]
    edge_from = np.insert(edge_from, first_new + 1, SAVED)
    edge_to = np.insert(edge_to, first_new + 1, SAVED + 1)
    measurements = se2.relative(poses[edge_from], poses[edge_to])
    measurements[first_new + 1] += np.array([0.3, 0.2, 0.1])  # a second one between the two: not chained
    online = poses.copy()
    online[SAVED:] = se2.compose(np.array([0.4, -0.2, 0.15]), poses[SAVED:])  # the saved map as saved
    problem = held_map_problem(graph_of(poses, edge_from, edge_to, measurements, online), poses[:SAVED])

    np.testing.assert_array_equal(problem.odometry_start[0], np.zeros(3))
    np.testing.assert_allclose(problem.odometry_start[1], online[SAVED], atol=1e-12)
    chained = se2.compose(online[SAVED], se2.relative(poses[SAVED], poses[SAVED:]))
    np.testing.assert_allclose(problem.odometry_start[1:], chained, atol=1e-9)
    assert problem.graph.num_poses == NEW + 1 and len(problem.keyframe_scans) == NEW + 1
    assert solve_held_map(problem).converged


def test_constraints_between_saved_keyframes_do_not_matter() -> None:
    poses = truth(seed=2)
    edge_from, edge_to = edges()
    measurements = se2.relative(poses[edge_from], poses[edge_to])
    changed = measurements.copy()
    changed[: SAVED - 1] += np.array([0.5, -0.3, 0.2])  # the saved run's consecutive constraints
    first = solve_with_map_held(graph_of(poses, edge_from, edge_to, measurements), poses[:SAVED]).poses
    second = solve_with_map_held(graph_of(poses, edge_from, edge_to, changed), poses[:SAVED]).poses
    np.testing.assert_array_equal(first, second)


def test_a_constraint_from_a_new_keyframe_to_a_saved_one_is_refused() -> None:
    poses = truth()
    edge_from, edge_to = edges(new_to_saved=True)
    measurements = se2.relative(poses[edge_from], poses[edge_to])
    with pytest.raises(FrontendError, match="from a new keyframe to a saved one"):
        solve_with_map_held(graph_of(poses, edge_from, edge_to, measurements), poses[:SAVED])


def test_a_graph_with_nothing_new_tied_to_the_saved_map_is_refused() -> None:
    poses = truth()
    edge_from, edge_to = edges()
    measurements = se2.relative(poses[edge_from], poses[edge_to])
    with pytest.raises(FrontendError, match="no constraint ties"):
        solve_with_map_held(graph_of(poses, edge_from, edge_to, measurements), poses)  # every keyframe saved


def test_a_run_placed_by_its_caller_needs_the_callers_localization() -> None:
    poses = truth()[:SAVED]
    scans = [np.column_stack([np.linspace(-2, 2, 50), np.full(50, 1.5)]) for _ in range(SAVED)]
    edge_from, edge_to = np.arange(SAVED - 1), np.arange(1, SAVED)
    constraints = SavedConstraints(edge_from, edge_to, se2.relative(poses[:-1], poses[1:]),
                                   np.repeat(INFORMATION[None], SAVED - 1, axis=0))
    resumed = LaserSlam2D.resume(scans, poses, constraints, placed_by_caller=True)
    with pytest.raises(MapPlacementError, match="without its localization"):
        resumed.add_scan(1, scans[0])


def _found(index: int, pose: tuple[float, float, float], *, localized: bool = True,
           matched: bool = True) -> LocalizedScan:
    return LocalizedScan(index, index, np.array(pose), localized, matched, 0.9, 1.0, 0.01, np.eye(3))


def test_the_run_s_own_slam_takes_the_map_matches_as_odometry_where_the_wheels_measured_nothing() -> None:
    """`HeldOdometry`: the wheels' odometry as it is; without it, once the localizer has placed the run,
    each scan it matched to the saved map at its map pose (the map measured the motion), nothing for a scan
    it did not match; the SLAM's odometry restarts wherever the source changes (two frames)."""
    held = HeldOdometry()
    wheels = np.array([5.0, 1.0, 0.2])
    # Before the run is placed: no map pose to give, whatever the localizer says of the scan.
    assert held.of(None, 0.0, _found(0, (np.nan, np.nan, np.nan), localized=False, matched=False)) == (
        None, 0.0, False)
    odometry, interval, restart = held.of(wheels, 0.1, _found(1, (1.0, 2.0, 0.3)))
    assert odometry is wheels and interval == 0.1 and not restart
    # The wheels stop: a matched scan's map pose, exactly, the odometry restarted first.
    odometry, interval, restart = held.of(None, 0.0, _found(2, (1.5, 2.0, 0.3)))
    assert odometry is not None and restart and interval == 0.0
    np.testing.assert_array_equal(odometry, [1.5, 2.0, 0.3])
    # Still no wheels: the next map pose, no restart (one frame); a scan not matched gets none.
    assert not held.of(None, 0.0, _found(3, (2.0, 2.0, 0.3)))[2]
    assert held.of(None, 0.0, _found(4, (2.5, 2.0, 0.3), matched=False)) == (None, 0.0, False)
    # The wheels again: restart back into their frame.
    odometry, _, restart = held.of(wheels, 0.1, _found(5, (3.0, 2.0, 0.3)))
    assert odometry is wheels and restart
