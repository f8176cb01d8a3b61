"""Gauss–Seidel relaxation: the per-pose step, monotone decrease, and convergence to the exact optimum."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import GraphError, OptimizerError
from optimizer.gauss_seidel import gauss_seidel
from optimizer.graph import PoseGraph
from optimizer.graph_files import read_graph
from optimizer.polish import edge_jacobians, gauss_newton
from tests.conftest import shared_file


def random_information(rng: np.random.Generator, count: int) -> np.ndarray:
    factors = rng.normal(size=(count, 3, 3))
    return factors @ np.swapaxes(factors, 1, 2) + 0.5 * np.eye(3)


def ring(rng: np.random.Generator, count: int, noise: float) -> tuple[PoseGraph, np.ndarray]:
    """Poses on a circle, odometry + closure + chords, measurements from the truth plus `noise`."""
    angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
    truth = np.stack([5 * np.cos(angles), 5 * np.sin(angles), se2.wrap_angle(angles + np.pi / 2)], axis=1)
    edge_from = np.concatenate([np.arange(count), np.arange(0, count - 3, 3)])
    edge_to = np.concatenate([(np.arange(count) + 1) % count, np.arange(0, count - 3, 3) + 3])
    measurements = se2.relative(truth[edge_from], truth[edge_to])
    measurements += noise * rng.normal(size=measurements.shape)
    initial = truth + rng.normal(scale=[0.3, 0.3, 0.1], size=truth.shape)
    graph = PoseGraph.build(np.arange(count), initial, edge_from, edge_to, measurements,
                            random_information(rng, len(edge_from)))
    return graph, truth


def test_one_sweep_on_a_single_free_pose_is_one_gauss_newton_step() -> None:
    rng = np.random.default_rng(1)
    graph = PoseGraph.build(np.arange(2), [[0.5, -1.0, 0.7], [2.0, 1.0, -2.5]], [0, 0], [1, 1],
                            [[1.0, 2.0, 3.0], [1.5, 1.8, 2.8]], random_information(rng, 2))
    errors, _, jac_b = edge_jacobians(graph)
    hessian = np.einsum("mji,mjk,mkl->il", jac_b, graph.information, jac_b)
    gradient = np.einsum("mji,mjk,mk->i", jac_b, graph.information, errors)
    expected = graph.poses[1] - np.linalg.solve(hessian, gradient)
    swept = next(gauss_seidel(graph, iterations=1)).poses
    np.testing.assert_allclose(swept[1, :2], expected[:2], atol=1e-12)
    assert se2.wrap_angle(swept[1, 2] - expected[2]) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_array_equal(swept[0], graph.poses[0])


def test_sweeps_decrease_chi2_and_keep_the_anchor() -> None:
    graph, _ = ring(np.random.default_rng(2), 24, noise=0.02)
    iterations = list(gauss_seidel(graph, iterations=50))
    assert [it.index for it in iterations] == list(range(1, 51))
    assert all(it.stage == "gauss-seidel" for it in iterations)
    values = np.array([chi2(graph)] + [it.chi2 for it in iterations])
    assert np.all(np.diff(values) <= 1e-9 * np.abs(values[:-1]))
    assert values[-1] < 0.1 * values[0]
    for it in iterations:
        assert it.chi2 == pytest.approx(chi2(graph, it.poses), rel=1e-12)
        np.testing.assert_array_equal(it.poses[0], graph.poses[0])
        assert np.all((it.poses[:, 2] >= -np.pi) & (it.poses[:, 2] < np.pi))


def test_consistent_ring_converges_to_the_truth_relative_to_the_anchor() -> None:
    graph, truth = ring(np.random.default_rng(3), 8, noise=0.0)
    final = list(gauss_seidel(graph, iterations=1000))[-1]
    assert final.chi2 < 1e-10
    expected = se2.compose(graph.poses[0], se2.relative(truth[0], truth))
    np.testing.assert_allclose(final.poses[:, :2], expected[:, :2], atol=1e-6)
    np.testing.assert_allclose(se2.wrap_angle(final.poses[:, 2] - expected[:, 2]), 0.0, atol=1e-6)


def test_noisy_ring_converges_to_the_gauss_newton_optimum() -> None:
    graph, _ = ring(np.random.default_rng(4), 8, noise=0.05)
    optimum = list(gauss_newton(graph))[-1]
    final = list(gauss_seidel(graph, iterations=1000))[-1]
    assert final.chi2 == pytest.approx(optimum.chi2, rel=1e-6)
    np.testing.assert_allclose(final.poses, optimum.poses, atol=1e-4)


def test_singular_pose_is_left_in_place_without_nan() -> None:
    # Pose 1's heading is unconstrained (zero θθ information on its only edge): its 3×3 system is singular.
    information = np.array([np.diag([100.0, 100.0, 0.0]), np.diag([100.0, 100.0, 100.0])])
    graph = PoseGraph.build(np.arange(3), [[0, 0, 0], [1.2, 0.3, 0.4], [0.2, 1.1, 1.0]], [0, 0], [1, 2],
                            [[1, 0, 0], [0, 1, 1.5]], information, check_information=False)
    final = list(gauss_seidel(graph, iterations=3))[-1]
    assert np.all(np.isfinite(final.poses))
    np.testing.assert_array_equal(final.poses[1], graph.poses[1])
    np.testing.assert_allclose(final.poses[2], [0, 1, 1.5], atol=1e-12)


def test_rejects_bad_arguments() -> None:
    graph, _ = ring(np.random.default_rng(5), 6, noise=0.0)
    with pytest.raises(GraphError):
        next(gauss_seidel(graph, np.zeros((2, 3))))
    with pytest.raises(OptimizerError):
        next(gauss_seidel(graph, iterations=-1))
    assert list(gauss_seidel(graph, iterations=0)) == []


def test_pose2example_converges_to_the_exact_optimum() -> None:
    graph = read_graph(shared_file("posegraphs/2d/pose2example.txt")).graph
    final = list(gauss_seidel(graph, iterations=3000))[-1]
    assert final.chi2 == pytest.approx(1.0989, rel=1e-3)
