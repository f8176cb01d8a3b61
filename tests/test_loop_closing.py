"""Pruning the keyframe graph's loop closures (`frontends.loop_closing.optimize_and_prune`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from frontends.loop_closing import Constraints, HypothesisPool, optimize_and_prune
from optimizer import se2
from optimizer.graph import PoseGraph

CHAIN_INFORMATION = np.diag([2500.0, 2500.0, 1e4])
"""A scan-matching step: σ 2 cm, 0.6°."""
LOOP_INFORMATION = np.diag([1e4, 1e4, 1e5])
"""A loop closure verified on a whole submap: far surer than one step."""
CHI2_THRESHOLD = 30.0
LAP = 40


def two_laps() -> np.ndarray:
    """(80, 3) a robot driving a 10 m square twice, a pose a metre, turning 90° at the corners."""
    poses, pose = [], np.zeros(3)
    for k in range(2 * LAP):
        poses.append(pose)
        turn = np.pi / 2 if k % 10 == 9 else 0.0
        pose = se2.compose(pose, np.array([1.0, 0.0, turn]) if turn == 0.0 else np.array([0.0, 0.0, turn]))
    return np.array(poses)


def graph_with(truth: np.ndarray, loops: list[tuple[int, int, np.ndarray]]) -> Constraints:
    """The true chain, then `loops` (a, b, measurement) in order."""
    edges = Constraints(measurement_shape=(3,), information_size=3)
    for k in range(len(truth) - 1):
        edges.add(k, k + 1, se2.relative(truth[k], truth[k + 1]), CHAIN_INFORMATION, is_loop=False)
    for a, b, measurement in loops:
        edges.add(a, b, measurement, LOOP_INFORMATION, is_loop=True)
    return edges


def graph_at(edges: Constraints) -> Callable[[np.ndarray], PoseGraph]:
    def build(poses: np.ndarray) -> PoseGraph:
        first, second, measurements, informations, _ = edges.arrays()
        return PoseGraph.build(np.arange(len(poses)), poses, first, second, measurements, informations)

    return build


def look_alike_case() -> tuple[np.ndarray, Constraints, list[tuple[int, int]]]:
    """Two laps closed by old true loop closures; the newest three are one more true closure and two that
    matched a look-alike room 3 m from the true place (they agree with each other, as a repeated false
    match does)."""
    truth = two_laps()
    true_loops = [(k, k + LAP, se2.relative(truth[k], truth[k + LAP])) for k in (0, 10, 20, 30)]
    offset = np.array([3.0, 0.0, 0.0])
    false_loops = [(5, b, se2.compose(se2.relative(truth[5], truth[b]), offset)) for b in (62, 64)]
    newest_true = (15, 55, se2.relative(truth[15], truth[55]))
    loops = [*true_loops, newest_true, *false_loops]
    return truth, graph_with(truth, loops), [(a, b) for a, b, _ in loops]


def loop_pairs(edges: Constraints) -> list[tuple[int, int]]:
    return [(a, b) for a, b, loop in zip(edges.first, edges.second, edges.is_loop, strict=True) if loop]


def test_the_new_loop_closures_that_strain_the_chain_are_removed_and_the_true_ones_kept() -> None:
    truth, edges, loops = look_alike_case()
    start = truth + np.random.default_rng(0).normal(0.0, 0.02, truth.shape)
    poses, removed = optimize_and_prune(edges, graph_at(edges), start, CHI2_THRESHOLD, 15, new_loops=3)
    assert removed == 2
    assert loop_pairs(edges) == loops[:5]  # both look-alike matches gone, every true closure kept
    aligned = se2.compose(se2.relative(poses[0], truth[0]), poses)
    assert np.max(np.hypot(*(aligned[:, :2] - truth[:, :2]).T)) < 1e-6


def test_without_new_loop_closures_to_suspect_nothing_is_removed_for_strain() -> None:
    # The false closures bend the chain between the true ones without a large error of their own: the loop
    # closures' χ² alone keeps them (what the check is for).
    truth, edges, loops = look_alike_case()
    poses, removed = optimize_and_prune(edges, graph_at(edges), truth.copy(), CHI2_THRESHOLD, 15)
    assert removed == 0 and loop_pairs(edges) == loops
    aligned = se2.compose(se2.relative(poses[0], truth[0]), poses)
    assert np.max(np.hypot(*(aligned[:, :2] - truth[:, :2]).T)) > 0.5


def test_strain_the_new_closures_did_not_cause_removes_none_of_them() -> None:
    # The chain strained by an old false closure: the newest, true, closures do not relieve it and stay.
    truth, edges, loops = look_alike_case()
    order = [0, 1, 5, 6, 2, 3, 4]  # the false pair among the old closures, the true ones newest
    reordered = graph_with(truth, [(a, b, edges.measurement[len(truth) - 1 + k])
                                   for k, (a, b) in ((k, loops[k]) for k in order)])
    _, removed = optimize_and_prune(reordered, graph_at(reordered), truth.copy(), CHI2_THRESHOLD, 15,
                                    new_loops=3)
    assert removed == 0 and len(loop_pairs(reordered)) == 7


@dataclass(frozen=True)
class _Hypothesis:
    current: int
    correction: np.ndarray


def pool() -> HypothesisPool[_Hypothesis]:
    return HypothesisPool(small_linear=0.3, small_angular=np.radians(3.0))


def test_a_loop_closure_barely_moving_the_map_is_accepted_at_once() -> None:
    small = _Hypothesis(50, np.array([0.1, -0.1, np.radians(1.0)]))
    hypotheses = pool()
    assert hypotheses.confirm(small) == [small]
    assert hypotheses.pending == []


def test_a_large_correction_waits_for_an_agreeing_one() -> None:
    hypotheses = pool()
    first = _Hypothesis(50, np.array([2.3, 0.0, 0.0]))
    assert hypotheses.confirm(first) == []  # waits
    # A different correction confirms nothing.
    other = _Hypothesis(52, np.array([-1.0, 0.5, 0.0]))
    assert hypotheses.confirm(other) == []
    assert hypotheses.pending == [first, other]
    # One that agrees (within the small correction's bounds) confirms those it agrees with; they leave the
    # pool.
    agreeing = _Hypothesis(54, np.array([2.3, 0.1, np.radians(1.0)]))
    assert hypotheses.confirm(agreeing) == [first, agreeing]
    assert hypotheses.pending == [other]


def test_hypotheses_older_than_their_age_are_forgotten_and_counted() -> None:
    hypotheses = pool()
    for current in (10, 20, 30):
        hypotheses.confirm(_Hypothesis(current, np.array([5.0 + current, 0.0, 0.0])))
    assert hypotheses.expire(32, max_age=12) == 1
    assert [h.current for h in hypotheses.pending] == [20, 30]
    assert hypotheses.clear() == 2
    assert hypotheses.dropped == 3


def test_path_columns_follow_the_constraints_through_additions_removals_and_restores() -> None:
    """The arrays a loop search reads are the constraint lists, whatever was added, removed or put back
    (the buffer behind them grows past its first size here), and a view taken earlier keeps its rows."""
    rng = np.random.default_rng(3)
    edges = Constraints(measurement_shape=(3,), information_size=3)
    for k in range(40):
        edges.add(k, k + 1 + int(rng.integers(0, 3)), rng.normal(size=3), np.eye(3), is_loop=bool(k % 5 == 0))
    before, lengths_before = edges.path_columns(), list(edges.planar_length)
    removed = edges.remove(7)
    edges.add(2, 30, np.array([3.0, 4.0, 0.1]), np.eye(3), is_loop=True)
    first, second, lengths = edges.path_columns()
    np.testing.assert_array_equal(first, edges.first)
    np.testing.assert_array_equal(second, edges.second)
    np.testing.assert_array_equal(lengths, edges.planar_length)
    assert lengths[-1] == 5.0
    edges.restore(7, removed)
    first, second, lengths = edges.path_columns()
    np.testing.assert_array_equal(first, edges.first)
    np.testing.assert_array_equal(lengths, edges.planar_length)
    np.testing.assert_array_equal(before[2], lengths_before)  # the earlier view is as it was
