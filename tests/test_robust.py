"""Robust kernels: the kernels by hand, the wrappers' bookkeeping, and false loops on a grid world."""

from __future__ import annotations

import math
from collections.abc import Generator

import numpy as np
import pytest

from optimizer.cost import chi2, edge_chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.graph_files import read_graph
from optimizer.gridworld import generate_grid_world
from optimizer.initialization import chordal_initialization
from optimizer.iteration import Iteration
from optimizer.polish import PolishStatus, gauss_newton
from optimizer.robust import (
    KERNELS,
    adaptive_scale,
    kernel_cost,
    kernel_weight,
    robust_cost,
    robust_polish,
    robust_sgd,
    robust_weights,
    weighted_graph,
)
from optimizer.robust_gnc import graduated_chordal, robust_optimize
from optimizer.sgd import sgd
from optimizer.sgd_tree import sgd_tree
from optimizer.solve import optimize
from tests.conftest import shared_file


def finish(stages: Generator[Iteration, None, PolishStatus]) -> tuple[list[Iteration], PolishStatus]:
    seen: list[Iteration] = []
    while True:
        try:
            seen.append(next(stages))
        except StopIteration as stop:
            return seen, stop.value


# ------------------------------------------------------------------------------------------- the kernels

def test_cauchy_by_hand() -> None:
    u = np.array([0.0, 2.0, 6.0])
    np.testing.assert_allclose(kernel_cost("cauchy", u, 2.0), [0.0, 2.0 * math.log(2.0), 2.0 * math.log(4.0)])
    np.testing.assert_allclose(kernel_weight("cauchy", u, 2.0), [1.0, 0.5, 0.25])


def test_dcs_by_hand() -> None:
    u = np.array([0.0, 0.5, 1.0, 3.0, 7.0])
    # Beyond Φ = 1: ρ = (3u − 1)/(1 + u), s = 2/(1 + u), weight s².
    np.testing.assert_allclose(kernel_cost("dcs", u, 1.0), [0.0, 0.5, 1.0, 2.0, 2.5])
    np.testing.assert_allclose(kernel_weight("dcs", u, 1.0), [1.0, 1.0, 1.0, 0.25, 0.0625])
    assert kernel_cost("dcs", np.array([1e12]), 1.0)[0] == pytest.approx(3.0)  # bounded by 3Φ


@pytest.mark.parametrize("kernel", KERNELS)
def test_weight_is_the_derivative_of_the_cost(kernel: str) -> None:
    u = np.array([0.1, 0.7, 1.3, 4.0, 50.0, 3e3])
    h = 1e-6 * u
    numeric = (kernel_cost(kernel, u + h, 0.8) - kernel_cost(kernel, u - h, 0.8)) / (2.0 * h)
    np.testing.assert_allclose(kernel_weight(kernel, u, 0.8), numeric, rtol=1e-6)


def test_adaptive_scale_follows_the_median_up_to_honest_information() -> None:
    # Factor × median of the χ² terms (Cauchy 10, DCS 40), capped for honest information (10 and 4 times
    # 2.366, the median of a 3-dof χ²); DCS's Φ ≥ 1.
    assert adaptive_scale("cauchy", np.array([0.01, 0.02, 0.03, 500.0, 900.0])) == pytest.approx(10.0 * 0.03)
    assert adaptive_scale("dcs", np.array([0.01, 0.02, 0.03, 500.0, 900.0])) == pytest.approx(40.0 * 0.03)
    assert adaptive_scale("dcs", np.array([0.001, 0.002, 0.003])) == pytest.approx(1.0)
    assert adaptive_scale("dcs", np.array([0.5, 0.6, 0.7])) == pytest.approx(4.0 * 2.366)
    assert adaptive_scale("cauchy", np.array([100.0, 200.0])) == pytest.approx(10.0 * 2.366)
    assert adaptive_scale("dcs", np.array([])) == pytest.approx(4.0 * 2.366)


def test_unknown_kernel_and_bad_scale_are_errors() -> None:
    graph = generate_grid_world(20, seed=0).graph
    with pytest.raises(OptimizerError, match="unknown robust kernel"):
        robust_cost(graph, None, "huber")
    with pytest.raises(OptimizerError, match="scale"):
        robust_cost(graph, None, "cauchy", -1.0)


# ----------------------------------------------------------------------------------- costs on a tiny graph

def triangle(loop_error_x: float) -> PoseGraph:
    """Three poses on the x axis, exact odometry, and a loop 2 → 0 (reversed) whose x is off by the error."""
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    edge_from = np.array([0, 1, 2])
    edge_to = np.array([1, 2, 0])
    measurements = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-2.0 + loop_error_x, 0.0, 0.0]])
    information = np.repeat(np.eye(3)[None], 3, axis=0)
    return PoseGraph(poses, edge_from, edge_to, measurements, information, np.arange(3))


def test_robust_cost_and_weights_on_a_triangle() -> None:
    graph = triangle(2.0)  # the loop's χ² term is 2² = 4, the odometry's 0
    assert robust_cost(graph, None, "cauchy", 2.0) == pytest.approx(2.0 * math.log(3.0))
    np.testing.assert_allclose(robust_weights(graph, None, "cauchy", 2.0), [1.0, 1.0, 1.0 / 3.0])
    assert robust_cost(graph, None, "dcs", 1.0) == pytest.approx(11.0 / 5.0)
    np.testing.assert_allclose(robust_weights(graph, None, "dcs", 1.0), [1.0, 1.0, 0.16])


def test_odometry_is_protected_unless_asked() -> None:
    graph = triangle(0.0)
    moved = graph.poses.copy()
    moved[1, 0] += 1.0  # odometry terms 1 each (0→1 long, 1→2 short), the loop exact
    assert robust_cost(graph, moved, "cauchy", 1.0) == pytest.approx(2.0)
    everything = robust_cost(graph, moved, "cauchy", 1.0, protect_odometry=False)
    assert everything == pytest.approx(2.0 * math.log(2.0))
    np.testing.assert_allclose(robust_weights(graph, moved, "cauchy", 1.0, protect_odometry=False),
                               [0.5, 0.5, 1.0])


def test_weighted_graph_scales_only_the_information() -> None:
    graph = triangle(1.0)
    weighted = weighted_graph(graph, np.array([1.0, 0.5, 0.25]))
    np.testing.assert_array_equal(weighted.information[2], 0.25 * np.eye(3))
    np.testing.assert_array_equal(weighted.measurements, graph.measurements)
    np.testing.assert_array_equal(weighted.edge_from, graph.edge_from)


# ------------------------------------------------------------------------------------------ the wrappers

def test_robust_sgd_with_unit_weights_is_the_paper_sgd() -> None:
    # With every weight 1 the learning rate is untouched; the paper's SGD recomputes M at iterations 1
    # and 2, as the robust SGD does at every iteration, so the first two iterations agree exactly.
    graph = generate_grid_world(300, seed=3).graph
    plain = [step.poses for step in sgd(graph, 2)]
    robust = list(robust_sgd(graph, 2, kernel="cauchy", scale=1e300))
    for expected, step in zip(plain, robust, strict=True):
        np.testing.assert_allclose(step.poses, expected, rtol=0.0, atol=1e-12)
    assert robust[-1].stage == "sgd" and robust[-1].index == 2
    assert robust[-1].chi2 == pytest.approx(chi2(graph, plain[-1]), rel=1e-9)


def test_robust_polish_counts_on_and_reports_honestly() -> None:
    world = generate_grid_world(300, seed=4)
    graph = world.graph
    steps, status = finish(robust_polish(graph, world.ground_truth, kernel="cauchy", scale=5.0))
    assert status.converged
    assert [step.index for step in steps] == list(range(1, len(steps) + 1))
    assert status.iterations == len(steps)
    assert all(step.stage == "gauss-newton" for step in steps)
    costs = [step.chi2 for step in steps]
    assert costs[-1] == pytest.approx(robust_cost(graph, steps[-1].poses, "cauchy", 5.0))
    # Majorize–minimize: at a fixed scale each round ends below where it started (the majorizer is tight
    # only at a round's start, so single steps within a round may rise).
    assert costs[-1] < robust_cost(graph, world.ground_truth, "cauchy", 5.0)

    _, capped = finish(robust_polish(graph, graph.poses, kernel="cauchy", max_iterations=1))
    assert not capped.converged
    assert capped.iterations == 1


# ------------------------------------------------------------------------------- false loops, grid world

def with_gross_false_loops(graph: PoseGraph, count: int, seed: int) -> PoseGraph:
    """Random non-consecutive pairs measured anywhere in the map, with a true loop's information."""
    rng = np.random.default_rng(seed)
    pairs = rng.choice(graph.num_poses, size=(4 * count, 2))
    pairs = pairs[np.abs(pairs[:, 0] - pairs[:, 1]) > 1][:count]
    extent = np.ptp(graph.poses[:, :2], axis=0)
    measurements = np.column_stack([rng.uniform(-extent[0], extent[0], count),
                                    rng.uniform(-extent[1], extent[1], count),
                                    rng.uniform(-np.pi, np.pi, count)])
    loop_information = graph.information[np.flatnonzero(~graph.is_odometry)[0]]
    return PoseGraph(graph.poses, np.concatenate([graph.edge_from, pairs[:, 0]]),
                     np.concatenate([graph.edge_to, pairs[:, 1]]),
                     np.concatenate([graph.measurements, measurements]),
                     np.concatenate([graph.information, np.repeat(loop_information[None], count, axis=0)]),
                     graph.vertex_ids)


PollutedWorld = tuple[PoseGraph, PoseGraph, float]


@pytest.fixture(scope="module")
def polluted_world() -> PollutedWorld:
    """A 500-pose grid world, the same with 6 false loops, and the clean graph's optimum χ²."""
    clean = generate_grid_world(500, seed=11).graph
    polluted = with_gross_false_loops(clean, 6, seed=5)
    steps = list(gauss_newton(clean, generate_grid_world(500, seed=11).ground_truth, max_iterations=100))
    return clean, polluted, steps[-1].chi2


def default_method(graph: PoseGraph) -> np.ndarray:
    poses = graph.poses
    for step in sgd(graph, 100):
        poses = step.poses
    for step in gauss_newton(graph, poses, max_iterations=300):
        poses = step.poses
    return poses


@pytest.mark.parametrize("kernel", KERNELS)
def test_robust_chain_ignores_false_loops(kernel: str, polluted_world: PollutedWorld) -> None:
    clean, polluted, optimum = polluted_world
    steps, status = finish(robust_optimize(polluted, kernel))
    assert status.converged
    assert chi2(clean, steps[-1].poses) <= 1.01 * optimum
    weights = robust_weights(polluted, steps[-1].poses, kernel)
    assert np.all(weights[clean.num_edges:] < 0.1)
    assert np.all(weights[:clean.num_edges] > 0.1)
    rounds = [step for step in steps if step.stage == "gnc"]
    assert rounds and steps[:len(rounds)] == rounds  # graduated non-convexity first, then the polish
    assert {step.stage for step in steps[len(rounds):]} == {"gauss-newton"}


def test_default_method_is_pulled_off_by_false_loops(polluted_world: PollutedWorld) -> None:
    clean, polluted, optimum = polluted_world
    assert chi2(clean, default_method(polluted)) > 1.5 * optimum


def test_robust_tree_sgd_reweights_the_tree_sgd() -> None:
    # With every weight 1 the reweighted tree SGD is the tree SGD itself (its first iteration).
    graph = generate_grid_world(300, seed=3).graph
    plain = next(iter(sgd_tree(graph, 1)))
    robust = next(iter(robust_sgd(graph, 1, kernel="dcs", scale=1e30, descent=sgd_tree)))
    assert robust.stage == "sgd-tree"
    np.testing.assert_allclose(robust.poses, plain.poses, rtol=0.0, atol=1e-12)


# ------------------------------------------------------ many false loops: a fifth of the loop closures

@pytest.fixture(scope="module")
def heavily_polluted_world() -> PollutedWorld:
    """A 300-pose grid world with a quarter as many gross false loops as it has true ones."""
    world = generate_grid_world(300, seed=21)
    clean = world.graph
    false_count = int(np.count_nonzero(~clean.is_odometry)) // 4
    polluted = with_gross_false_loops(clean, false_count, seed=8)
    steps = list(gauss_newton(clean, world.ground_truth, max_iterations=100))
    return clean, polluted, steps[-1].chi2


@pytest.mark.parametrize(("kernel", "bound"), [("dcs", 1.01), ("cauchy", 1.03)])
def test_robust_default_reaches_the_clean_optimum_through_many_false_loops(
        kernel: str, bound: float, heavily_polluted_world: PollutedWorld) -> None:
    # Cauchy's cost grows without bound (log), so every rejected false loop keeps a pull ∝ c²/‖e‖: its
    # minimum lies a little off the clean one. DCS's cost is bounded (3Φ) and its pull falls as 1/‖e‖³.
    clean, polluted, optimum = heavily_polluted_world
    run = optimize(polluted, robust=kernel)
    iterations = list(run)
    assert run.result.converged
    assert chi2(clean, run.result.poses) <= bound * optimum
    assert "gnc" in {iteration.stage for iteration in iterations}
    weights = robust_weights(polluted, run.result.poses, kernel)
    assert np.all(weights[clean.num_edges:] < 0.1)
    assert np.all(weights[:clean.num_edges] > 0.1)


def test_non_robust_default_is_pulled_off_by_many_false_loops(heavily_polluted_world: PollutedWorld) -> None:
    clean, polluted, optimum = heavily_polluted_world
    run = optimize(polluted)
    list(run)
    assert chi2(clean, run.result.poses) > 1.5 * optimum


# ---------------------------------------------------------------------- graduated non-convexity itself

def test_graduated_chordal_starts_unweighted_and_shrinks_to_the_target(
        polluted_world: PollutedWorld) -> None:
    _, polluted, _ = polluted_world
    gnc = graduated_chordal(polluted, "dcs", scale=2.0)
    rounds: list[Iteration] = []
    while True:
        try:
            rounds.append(next(gnc))
        except StopIteration as stop:
            result = stop.value
            break
    np.testing.assert_allclose(rounds[0].poses, chordal_initialization(polluted), atol=1e-12)
    assert [step.index for step in rounds] == list(range(1, len(rounds) + 1))
    np.testing.assert_array_equal(result, rounds[-1].poses)
    # The first round's scale is the largest χ² term: halving down to 2 takes ⌈log2(largest/2)⌉ rounds.
    largest = float(edge_chi2(polluted, rounds[0].poses)[~polluted.is_odometry].max())
    assert len(rounds) == 1 + math.ceil(math.log2(largest / 2.0))
    assert rounds[-1].chi2 == pytest.approx(robust_cost(polluted, result, "dcs", 2.0))


def test_graduated_chordal_never_cuts_a_pose_off() -> None:
    # Pose 3 hangs on two constraints that disagree by 47 m: both fit badly at every scale, yet leaving
    # both out of a solve would cut pose 3 off (without odometry protection nothing else holds it).
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    graph = PoseGraph(poses, np.array([0, 1, 0, 2, 0]), np.array([1, 2, 2, 3, 3]),
                      np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.0, 0.0],
                                [50.0, 0.0, 0.0]]),
                      np.repeat(np.eye(3)[None], 5, axis=0), np.arange(4))
    rounds = list(graduated_chordal(graph, "dcs", scale=1e-3, protect_odometry=False))
    assert len(rounds) > 10
    final = rounds[-1].poses
    assert np.all(np.isfinite(final))
    assert 3.0 - 1e-6 <= final[3, 0] <= 50.0 + 1e-6
    np.testing.assert_allclose(final[:3], poses[:3], atol=1e-3)  # the triangle agrees with itself


def test_the_robust_default_does_not_depend_on_the_estimate(polluted_world: PollutedWorld) -> None:
    # Its rounds are chordal solves, which read pose 0 only: a scrambled estimate ends at the same poses.
    _, polluted, _ = polluted_world
    scrambled = np.random.default_rng(0).uniform(-100.0, 100.0, polluted.poses.shape)
    scrambled[0] = polluted.poses[0]
    first, second = optimize(polluted, robust="dcs"), optimize(polluted.with_poses(scrambled), robust="dcs")
    list(first)
    list(second)
    np.testing.assert_allclose(second.result.poses, first.result.poses, atol=1e-9)


# -------------------------------------------------------------------------------- clean real graphs

@pytest.mark.parametrize("name", ["CSAIL.g2o", "FR079.g2o"])
def test_dcs_keeps_every_true_loop_of_a_clean_real_graph(name: str) -> None:
    # Their information is pessimistic (loop closures' median χ² term 0.09 / 0.04 at the optimum) and a
    # few true loops reach 2.3 / 0.9: DCS's Φ (40 × the median, at least 1) leaves all of them weight 1,
    # so the robust default ends at the plain optimum.
    graph = read_graph(shared_file(f"posegraphs/2d/{name}")).graph
    plain, robust = optimize(graph), optimize(graph, robust="dcs")
    list(plain)
    list(robust)
    assert robust.result.converged
    assert chi2(graph, robust.result.poses) == pytest.approx(plain.result.chi2, rel=1e-6)
    assert np.all(robust_weights(graph, robust.result.poses, "dcs") == 1.0)
