"""SE(2) algebra, the PoseGraph model's normalisation rules, and the χ² cost."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from optimizer import se2
from optimizer.cost import chi2, edge_chi2, edge_errors
from optimizer.errors import GraphError
from optimizer.graph import PoseGraph, reverse_constraints

poses_strategy = arrays(np.float64, (5, 3), elements=st.floats(-10, 10))


def _close(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    d = np.abs(a - b)
    d[..., 2] = np.abs(se2.wrap_angle(a[..., 2] - b[..., 2]))
    return bool(d.max() < tol)


@given(poses_strategy, poses_strategy)
def test_relative_is_inverse_then_compose(a: np.ndarray, b: np.ndarray) -> None:
    assert _close(se2.relative(a, b), se2.compose(se2.inverse(a), b))
    assert _close(se2.compose(a, se2.relative(a, b)), b, 1e-8)
    assert _close(se2.compose(a, se2.inverse(a)), np.zeros_like(a))


def test_compose_by_hand() -> None:
    a = np.array([1.0, 2.0, np.pi / 2])
    b = np.array([3.0, 0.0, np.pi / 2])
    # Three metres ahead of a robot facing +y is (1, 5); two quarter turns face -x.
    assert _close(se2.compose(a, b), np.array([1.0, 5.0, np.pi]))


@given(arrays(np.float64, (3,), elements=st.floats(-5, 5)),
       arrays(np.float64, (3,), elements=st.floats(-0.5, 0.5)))
def test_adjoint_moves_a_small_local_motion_into_the_parent_frame(pose: np.ndarray, xi: np.ndarray) -> None:
    # a·exp(ε ξ)·a⁻¹ ≈ exp(ε Ad(a) ξ): compare first-order motions with a tiny ε.
    eps = 1e-6
    moved = se2.compose(se2.compose(pose, eps * xi), se2.inverse(pose))
    assert np.allclose(moved / eps, se2.adjoint(pose) @ xi, atol=1e-4)


def test_compose_chain_matches_repeated_compose() -> None:
    rng = np.random.default_rng(0)
    steps = rng.normal(size=(20, 3))
    start = np.array([1.0, -2.0, 0.3])
    chain = se2.compose_chain(steps, start)
    pose = start.copy()
    for i, step in enumerate(steps):
        pose = se2.compose(pose, step)
        assert _close(chain[i + 1], pose, 1e-9)


def _information(n: int) -> np.ndarray:
    return np.tile(np.diag([4.0, 9.0, 16.0]), (n, 1, 1))


def test_ids_are_remapped_in_increasing_order() -> None:
    graph = PoseGraph.build([30, 10, 20], [[3, 0, 0], [1, 0, 0], [2, 0, 0]], [10, 20], [20, 30],
                            [[1, 0, 0], [1, 0, 0]], _information(2))
    np.testing.assert_array_equal(graph.vertex_ids, [10, 20, 30])
    np.testing.assert_array_equal(graph.poses[:, 0], [1, 2, 3])
    np.testing.assert_array_equal(graph.edge_from, [0, 1])
    np.testing.assert_array_equal(graph.edge_to, [1, 2])


@pytest.mark.parametrize(("vertex_ids", "edge_to"), [([0, 1.7], [1.7]), ([0, 0.5], [0.5]), ([0, 1], [1.2])])
def test_ids_that_are_not_whole_numbers_are_errors(vertex_ids: list[float], edge_to: list[float]) -> None:
    # 1.7 became id 1 (a graph that matched by accident), 0.5 a "duplicate" of 0.
    with pytest.raises(GraphError, match="must be integers"):
        PoseGraph.build(vertex_ids, np.zeros((2, 3)), [0], edge_to, [[1.0, 0.0, 0.0]], _information(1))


def test_reversing_a_constraint_twice_gives_it_back() -> None:
    z = np.array([[1.0, -0.5, 0.7]])
    info = np.array([[[5.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 2.0]]])
    twice = reverse_constraints(*reverse_constraints(z, info))
    np.testing.assert_allclose(twice[0], z, atol=1e-12)
    np.testing.assert_allclose(twice[1], info, atol=1e-12)


def test_reversed_edge_is_kept_as_stored_with_the_files_exact_cost() -> None:
    rng = np.random.default_rng(1)
    poses = rng.normal(size=(2, 3))
    info = np.array([[5.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 2.0]])
    # The file says: pose 0 seen from pose 1 is z_10 (slightly wrong), θ given outside [-π, π).
    z_10 = se2.relative(poses[1], poses[0]) + np.array([0.01, -0.02, 0.015 + 2 * np.pi])
    graph = PoseGraph.build([0, 1], poses, [1], [0], [z_10], info[None])
    assert (graph.edge_from[0], graph.edge_to[0]) == (1, 0)
    assert graph.is_reversed.tolist() == [True] and graph.is_odometry.tolist() == [True]
    assert (graph.edge_low[0], graph.edge_high[0]) == (0, 1)
    np.testing.assert_array_equal(graph.measurements[0], z_10)  # number for number, not wrapped
    np.testing.assert_array_equal(graph.information[0], info)
    # The cost of the relation exactly as the file wrote it, computed by hand in the 1 → 0 direction.
    e_10 = se2.relative(z_10, se2.relative(poses[1], poses[0]))
    assert chi2(graph) == pytest.approx(float(e_10 @ info @ e_10), rel=1e-12)


def test_flipping_an_edge_changes_the_problem_with_anisotropic_information() -> None:
    # Why edges are never flipped: the adjoint-moved information only matches to first order.
    poses = np.array([[0.0, 0.0, 0.0], [2.0, 0.5, 0.3]])
    info = np.diag([1e4, 1.0, 1e2])
    z_10 = se2.relative(poses[1], poses[0]) + np.array([0.3, -0.2, 0.25])
    stored = PoseGraph.build([0, 1], poses, [1], [0], [z_10], info[None])
    z_01, info_01 = reverse_constraints(np.array([z_10]), info[None])
    flipped = PoseGraph.build([0, 1], poses, [0], [1], z_01, info_01)
    assert abs(chi2(flipped) - chi2(stored)) > 0.01 * chi2(stored)


@pytest.mark.parametrize("matrix", [np.diag([1.0, 1.0, 0.0]), np.diag([1.0, -2.0, 3.0]),
                                    np.array([[1.0, 5.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])])
def test_information_that_is_not_positive_definite_is_rejected(matrix: np.ndarray) -> None:
    with pytest.raises(GraphError, match=r"constraint 0 \(7 → 9\).*not symmetric positive definite"):
        PoseGraph.build([7, 9], np.zeros((2, 3)), [7], [9], [[1, 0, 0]], matrix[None])


def test_duplicate_edges_are_kept() -> None:
    graph = PoseGraph.build([0, 1], np.zeros((2, 3)), [0, 0], [1, 1], [[1, 0, 0], [1, 0, 0]], _information(2))
    assert graph.num_edges == 2
    assert chi2(graph) == pytest.approx(2 * 4.0)


@pytest.mark.parametrize(
    ("ids", "edges", "message"),
    [
        ([0, 1, 2, 3, 4], [(0, 1), (2, 3)], "not connected: 3 components of sizes 2, 2, 1"),
        ([0, 1], [(0, 0), (0, 1)], "to itself"),
        ([0, 1], [(0, 7)], "unknown pose id 7"),
        ([0, 0], [(0, 1)], "duplicate vertex ids"),
    ],
)
def test_invalid_graphs_are_rejected(ids: list[int], edges: list[tuple[int, int]], message: str) -> None:
    with pytest.raises(GraphError, match=message):
        PoseGraph.build(ids, np.zeros((len(ids), 3)), [e[0] for e in edges], [e[1] for e in edges],
                        np.ones((len(edges), 3)), _information(len(edges)))


def test_non_finite_input_is_rejected() -> None:
    with pytest.raises(GraphError, match="non-finite"):
        PoseGraph.build([0, 1], [[0, 0, 0], [np.nan, 0, 0]], [0], [1], [[1, 0, 0]], _information(1))


def test_graph_arrays_are_read_only() -> None:
    graph = PoseGraph.build([0, 1], np.zeros((2, 3)), [0], [1], [[1, 0, 0]], _information(1))
    with pytest.raises(ValueError):
        graph.poses[0, 0] = 1.0


def test_chi2_by_hand_and_theta_wrapping() -> None:
    # Pose 1 sits 1 m ahead and turned by almost +π; the measurement says almost -π: nearly no error.
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi - 0.01]])
    graph = PoseGraph.build([0, 1], poses, [0], [1], [[1.0, 0.0, -np.pi + 0.01]], _information(1))
    assert _close(edge_errors(graph)[0], np.array([0.0, 0.0, -0.02]), 1e-12)
    assert chi2(graph) == pytest.approx(16.0 * 0.02**2)
    # 0.5 m short in x and 0.2 m off in y, in the frame of pose 0 rotated by 90°.
    poses = np.array([[0.0, 0.0, np.pi / 2], [-0.2, 0.5, np.pi / 2]])
    graph = PoseGraph.build([0, 1], poses, [0], [1], [[1.0, 0.0, 0.0]], _information(1))
    assert _close(edge_errors(graph)[0], np.array([-0.5, 0.2, 0.0]), 1e-12)
    assert edge_chi2(graph)[0] == pytest.approx(4 * 0.25 + 9 * 0.04)


@pytest.mark.parametrize("shape", [(1, 3), (3, 3), (2, 2), (6,)])
def test_chi2_of_poses_that_do_not_fit_the_graph_is_an_error(shape: tuple[int, ...]) -> None:
    # The kernels index the poses by the constraints' ends: fewer rows were read out of bounds (nan or
    # another graph's number, no error).
    graph = PoseGraph.build([0, 1], np.zeros((2, 3)), [0], [1], [[1.0, 0.0, 0.0]], _information(1))
    with pytest.raises(GraphError, match=r"poses must be \(2, 3\)"):
        chi2(graph, np.zeros(shape))


@settings(max_examples=30)
@given(st.integers(0, 10_000))
def test_chunked_chi2_equals_the_sum_over_edges(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 50
    graph = PoseGraph.build(np.arange(n), rng.normal(size=(n, 3)), np.arange(n - 1), np.arange(1, n),
                            rng.normal(size=(n - 1, 3)), _information(n - 1))
    assert chi2(graph) == pytest.approx(float(edge_chi2(graph).sum()), rel=1e-12)
