"""The SGD of Olson et al. (2006): behaviour of the algorithm, and the O(log N) tree against Algorithm 1."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer import se2
from optimizer.cost import chi2, edge_errors
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.sgd import recomputes_stiffness, sgd
from tests.conftest import shared_file
from tests.optimizer_fixtures import square_loop_graph


def _angle_aware_max_difference(a: np.ndarray, b: np.ndarray) -> float:
    difference = np.abs(a - b)
    difference[:, 2] = np.abs(se2.wrap_angle(a[:, 2] - b[:, 2]))
    return float(difference.max())


def test_stiffness_schedule_is_powers_of_two() -> None:
    assert [t for t in range(1, 40) if recomputes_stiffness(t)] == [1, 2, 4, 8, 16, 32]


def test_consistent_graph_at_its_solution_does_not_move() -> None:
    graph, truth = square_loop_graph(noise=0.0)
    graph = graph.with_poses(truth)
    for step in sgd(graph, 5):
        assert _angle_aware_max_difference(step.poses, truth) < 1e-12
        assert step.chi2 < 1e-20


def test_chain_is_rebuilt_from_its_measurements_in_one_iteration() -> None:
    # With α = 1/γ at t = 1 every step is clamped to the full residual, so visiting the odometry
    # edges in order rebuilds dead reckoning exactly, whatever the starting estimate (isotropic x/y
    # information keeps diag(W) = γ in every heading, so every step is clamped).
    rng = np.random.default_rng(3)
    z = rng.normal([1.0, 0.1, 0.05], [0.2, 0.2, 0.3], (40, 3))
    info = np.tile(np.diag([10.0, 10.0, 50.0]), (40, 1, 1))  # isotropic: W does not rotate
    graph = PoseGraph.build(np.arange(41), rng.normal(size=(41, 3)), np.arange(40), np.arange(1, 41), z, info)
    first = next(sgd(graph, 1))
    expected = se2.compose_chain(z, start=graph.poses[0])
    assert _angle_aware_max_difference(first.poses, expected) < 1e-9


def test_last_visited_constraint_is_satisfied_after_the_first_iteration() -> None:
    graph, _ = square_loop_graph(noise=0.05)
    first = next(sgd(graph, 1))
    assert np.abs(edge_errors(graph, first.poses)[-1]).max() < 1e-9


def test_sgd_recovers_the_loop_from_a_poor_initial_estimate() -> None:
    graph, truth = square_loop_graph(noise=0.03, seed=1)
    steps = list(sgd(graph, 100))
    assert [s.index for s in steps] == list(range(1, 101))
    assert all(s.stage == "sgd" for s in steps)
    assert steps[-1].chi2 < 0.05 * chi2(graph)
    # The shape, not only the cost: relative to pose 0 the result is close to the ground truth.
    aligned = se2.relative(steps[-1].poses[0], steps[-1].poses)
    assert np.abs(aligned[:, :2] - truth[:, :2]).max() < 0.5
    assert np.all(np.abs(steps[-1].poses[:, 2]) <= np.pi)


def test_first_pose_is_the_anchor() -> None:
    graph, _ = square_loop_graph(noise=0.05, seed=2)
    for step in sgd(graph, 10):
        np.testing.assert_array_equal(step.poses[0], graph.poses[0])


@pytest.mark.parametrize("reverse_every", [2, 3])
def test_sgd_solves_reversed_edges_as_stored(reverse_every: int) -> None:
    # Edges measured from the later pose: a wrong sign on their steps would drive χ² up, not down.
    graph, truth = square_loop_graph(noise=0.03, seed=1, reverse_every=reverse_every)
    assert graph.is_reversed.sum() > graph.num_edges // 4
    final = list(sgd(graph, 100))[-1]
    assert final.chi2 < 0.05 * chi2(graph)
    aligned = se2.relative(final.poses[0], final.poses)
    assert np.abs(aligned[:, :2] - truth[:, :2]).max() < 0.5


@pytest.mark.parametrize(("seed", "reverse_every"), [(0, 0), (1, 0), (2, 0), (0, 2), (1, 3)])
@pytest.mark.parametrize("tree_block", [1, 3, 8, 128])
def test_tree_equals_algorithm_1_on_generated_loops(seed: int, reverse_every: int, tree_block: int) -> None:
    # Blocks of 1 are a plain segment tree over the increments; 128 > N puts the whole loop in one block.
    graph, _ = square_loop_graph(noise=0.1, seed=seed, laps=4, reverse_every=reverse_every)
    tree = list(sgd(graph, 40, tree_block=tree_block))
    linear = list(sgd(graph, 40, implementation="linear"))
    for a, b in zip(tree, linear, strict=True):
        assert _angle_aware_max_difference(a.poses, b.poses) < 1e-9


@pytest.mark.parametrize("tree_block", [1, 3, 8])
def test_tree_equals_algorithm_1_with_constraints_in_random_order(tree_block: int) -> None:
    # The tree pass defers re-summing the ancestors of one block while constraints keep ending in it; in a
    # random order, with half the constraints reversed, nearly every constraint ends elsewhere or reads
    # that block's ancestors, so a missed re-sum would show here.
    from optimizer.gridworld import generate_grid_world

    graph = generate_grid_world(400, seed=5).graph
    rng = np.random.default_rng(3)
    order = rng.permutation(graph.num_edges)
    flip = rng.random(graph.num_edges) < 0.5
    edge_from = np.where(flip, graph.edge_to, graph.edge_from)[order]
    edge_to = np.where(flip, graph.edge_from, graph.edge_to)[order]
    shuffled = PoseGraph.build(np.arange(graph.num_poses), graph.poses, edge_from, edge_to,
                               graph.measurements[order], graph.information[order])
    tree = list(sgd(shuffled, 20, tree_block=tree_block))
    linear = list(sgd(shuffled, 20, implementation="linear"))
    for a, b in zip(tree, linear, strict=True):
        assert _angle_aware_max_difference(a.poses, b.poses) < 1e-9


@pytest.mark.parametrize(("relative", "iterations"), [("posegraphs/2d/M3500.g2o", 30),
                                                       ("posegraphs/2d/INTEL.g2o", 30),
                                                       ("posegraphs/2d/FR079.g2o", 30)])
def test_tree_equals_algorithm_1_on_real_graphs(relative: str, iterations: int) -> None:
    from optimizer.graph_files import read_graph

    graph = read_graph(shared_file(relative)).graph
    tree = list(sgd(graph, iterations))
    linear = list(sgd(graph, iterations, implementation="linear"))
    for a, b in zip(tree, linear, strict=True):
        assert _angle_aware_max_difference(a.poses, b.poses) < 1e-9


@pytest.mark.parametrize("iterations", [0, 1, 2, 9])
def test_each_iteration_reports_the_chi2_of_its_own_poses(iterations: int) -> None:
    # Pass t + 1 sums the χ² of iteration t's poses while it reads the constraints (the last iteration's
    # is computed on its own): each must be `chi2` of the yielded poses to the bit, with reversed edges and
    # full (correlated) information, every one of the nine terms nonzero.
    from optimizer.gridworld import generate_grid_world

    graph = generate_grid_world(400, seed=7).graph
    rng = np.random.default_rng(2)
    flip = rng.random(graph.num_edges) < 0.3
    root = rng.normal(size=(graph.num_edges, 3, 3))
    information = graph.information + 0.3 * root @ root.transpose(0, 2, 1) * graph.information[:, :1, :1]
    graph = PoseGraph.build(np.arange(graph.num_poses), graph.poses,
                            np.where(flip, graph.edge_to, graph.edge_from),
                            np.where(flip, graph.edge_from, graph.edge_to), graph.measurements, information)
    steps = list(sgd(graph, iterations))
    assert [step.index for step in steps] == list(range(1, iterations + 1))
    for step in steps:
        assert step.chi2 == chi2(graph, step.poses)


def test_continuing_the_schedule_matches_one_long_run() -> None:
    graph, _ = square_loop_graph(noise=0.1, seed=5)
    whole = list(sgd(graph, 6))
    head = list(sgd(graph, 3))
    tail = list(sgd(graph, 3, head[-1].poses, first_iteration=4))
    # Iteration 4 recomputes M from the current poses, as in the single run; 5 and 6 reuse it.
    assert _angle_aware_max_difference(tail[-1].poses, whole[-1].poses) < 1e-9


def test_bad_arguments_raise_our_error() -> None:
    graph, _ = square_loop_graph(noise=0.0)
    with pytest.raises(OptimizerError):
        list(sgd(graph, -1))
    with pytest.raises(OptimizerError):
        list(sgd(graph, 1, implementation="quadratic"))  # type: ignore[arg-type]
    with pytest.raises(OptimizerError):
        list(sgd(graph, 1, np.zeros((2, 3))))
    with pytest.raises(OptimizerError):
        list(sgd(graph, 1, tree_block=0))


def test_later_iterations_leave_earlier_poses_and_the_graph_untouched() -> None:
    # The tree starts each iteration from the poses it yielded last and writes a new array.
    graph, _ = square_loop_graph(noise=0.1, seed=4)
    initial = graph.poses.copy()
    iterations = []
    copies = []
    for iteration in sgd(graph, 5):
        iterations.append(iteration)
        copies.append(iteration.poses.copy())
    np.testing.assert_array_equal(graph.poses, initial)
    for iteration, copy in zip(iterations, copies, strict=True):
        np.testing.assert_array_equal(iteration.poses, copy)
    assert len({id(iteration.poses) for iteration in iterations}) == len(iterations)


def test_the_tree_pass_residual_has_the_same_bits_as_the_shared_one() -> None:
    # The tree pass computes cos, sin of θ_a once and keeps W in registers; Algorithm 1 and the TORO-tree
    # SGD use the shared helper. Same operations in the same order: the results must be equal bit for bit,
    # including angles past ±π, anisotropic and asymmetric-looking (rounded) information.
    from optimizer.sgd_kernels import _weighted_residual, _weighted_residual_one_rotation

    rng = np.random.default_rng(11)
    for _ in range(500):
        pa = rng.normal(0.0, [50.0, 50.0, 6.0])
        pb = rng.normal(0.0, [50.0, 50.0, 6.0])
        z = rng.normal(0.0, [2.0, 2.0, 3.0])
        root = rng.normal(size=(3, 3)) * rng.uniform(0.01, 100.0, 3)
        info = root @ root.T + np.diag(rng.uniform(1e-3, 1e3, 3))
        r_shared, d_shared, w_shared = np.empty(3), np.empty(3), np.empty((3, 3))
        _weighted_residual(pa, pb, z, info, w_shared, r_shared, d_shared)
        r_and_d = _weighted_residual_one_rotation(*pa, *pb, z, info)
        np.testing.assert_array_equal(np.array(r_and_d[:3]), r_shared)
        np.testing.assert_array_equal(np.array(r_and_d[3:]), d_shared)
