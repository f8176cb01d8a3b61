"""The Levenberg–Marquardt polish: Jacobians against finite differences, exact optima, real χ² targets."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer import se2
from optimizer.cost import chi2, edge_errors
from optimizer.errors import GraphError, OptimizerError
from optimizer.graph import PoseGraph
from optimizer.graph_files import read_graph
from optimizer.gridworld import generate_grid_world
from optimizer.polish import PolishStatus, _gradient, edge_jacobians, gauss_newton, moved_by
from optimizer.sgd import sgd
from tests.conftest import MULTIGRID_STACK, shared_file
from tests.optimizer_fixtures import random_information, run

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


def square_loop(rng: np.random.Generator, noise: float = 0.0) -> tuple[PoseGraph, np.ndarray]:
    """Eight poses around a 4 m square, odometry + loop closure + two chords; measurements from the truth
    (plus `noise`), initial estimate perturbed. Returns the graph and the true poses."""
    corners = np.array([[0, 0, 0], [2, 0, 0], [4, 0, np.pi / 2], [4, 2, np.pi / 2], [4, 4, np.pi],
                        [2, 4, np.pi], [0, 4, -np.pi / 2], [0, 2, -np.pi / 2]], dtype=float)
    truth = corners + np.array([1.5, -0.5, 0.3])  # not at the origin, to exercise the anchoring
    truth[:, 2] = se2.wrap_angle(truth[:, 2])
    edge_from = np.array([0, 1, 2, 3, 4, 5, 6, 7, 1, 2])
    edge_to = np.array([1, 2, 3, 4, 5, 6, 7, 0, 5, 6])
    measurements = se2.relative(truth[edge_from], truth[edge_to])
    measurements += noise * rng.normal(size=measurements.shape)
    initial = truth + rng.normal(scale=[0.3, 0.3, 0.2], size=truth.shape)
    graph = PoseGraph.build(np.arange(8) * 10, initial, edge_from * 10, edge_to * 10, measurements,
                            random_information(rng, len(edge_from)))
    return graph, truth


def test_jacobians_match_central_differences() -> None:
    rng = np.random.default_rng(1)
    poses = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], size=(6, 3))
    edge_from = np.array([0, 0, 1, 2, 3, 4, 1])
    edge_to = np.array([1, 2, 3, 5, 4, 5, 4])
    measurements = rng.uniform([-3, -3, -np.pi], [3, 3, np.pi], size=(7, 3))
    graph = PoseGraph.build(np.arange(6), poses, edge_from, edge_to, measurements, random_information(rng, 7))
    _, jac_a, jac_b = edge_jacobians(graph)

    step = 1e-6
    for endpoint, jac in ((graph.edge_from, jac_a), (graph.edge_to, jac_b)):
        for k in range(3):
            numeric = np.empty((graph.num_edges, 3))
            for m in range(graph.num_edges):
                plus, minus = graph.poses.copy(), graph.poses.copy()
                plus[endpoint[m], k] += step
                minus[endpoint[m], k] -= step
                difference = edge_errors(graph, plus)[m] - edge_errors(graph, minus)[m]
                difference[2] = se2.wrap_angle(difference[2])
                numeric[m] = difference / (2 * step)
            np.testing.assert_allclose(jac[:, :, k], numeric, atol=1e-7)


def test_gradient_is_half_the_derivative_of_chi2_over_free_poses() -> None:
    graph, _ = square_loop(np.random.default_rng(2), noise=0.1)
    errors, jac_a, jac_b = edge_jacobians(graph)
    gradient = _gradient(graph, errors, jac_a, jac_b)
    step = 1e-6
    numeric = np.empty(3 * (graph.num_poses - 1))
    for v in range(len(numeric)):
        plus, minus = graph.poses.copy(), graph.poses.copy()
        plus[1 + v // 3, v % 3] += step
        minus[1 + v // 3, v % 3] -= step
        numeric[v] = (chi2(graph, plus) - chi2(graph, minus)) / (2 * step)
    np.testing.assert_allclose(2 * gradient, numeric, rtol=1e-6, atol=1e-6)


def test_consistent_square_loop_reaches_zero_and_the_truth_relative_to_the_anchor() -> None:
    graph, truth = square_loop(np.random.default_rng(3))
    iterations = list(gauss_newton(graph))
    final = iterations[-1]
    assert final.chi2 < 1e-12
    # Pose 0 keeps its (perturbed) estimate; the others sit where the truth puts them relative to pose 0.
    expected = se2.compose(graph.poses[0], se2.relative(truth[0], truth))
    np.testing.assert_allclose(final.poses[:, :2], expected[:, :2], atol=1e-7)
    np.testing.assert_allclose(se2.wrap_angle(final.poses[:, 2] - expected[:, 2]), 0.0, atol=1e-7)


def test_yields_accepted_steps_with_decreasing_chi2_and_fixed_anchor() -> None:
    graph, _ = square_loop(np.random.default_rng(4), noise=0.05)
    iterations = list(gauss_newton(graph, max_iterations=100))
    assert [it.index for it in iterations] == list(range(1, len(iterations) + 1))
    assert all(it.stage == "gauss-newton" for it in iterations)
    values = np.array([chi2(graph)] + [it.chi2 for it in iterations])
    assert np.all(np.diff(values) < 0)
    for it in iterations:
        assert it.chi2 == pytest.approx(chi2(graph, it.poses), rel=1e-12)
        np.testing.assert_array_equal(it.poses[0], graph.poses[0])
        assert np.all((it.poses[:, 2] >= -np.pi) & (it.poses[:, 2] < np.pi))
    assert values[-1] > 0.0  # noisy measurements: the optimum is not zero
    # At the optimum the gradient vanishes (relative to its size at the start).
    errors, jac_a, jac_b = edge_jacobians(graph, iterations[-1].poses)
    start_errors, start_a, start_b = edge_jacobians(graph)
    final_gradient = np.abs(_gradient(graph, errors, jac_a, jac_b)).max()
    assert final_gradient < 1e-5 * np.abs(_gradient(graph, start_errors, start_a, start_b)).max()


def test_max_iterations_limits_the_accepted_steps_and_is_reported_as_not_converged() -> None:
    graph, _ = square_loop(np.random.default_rng(5), noise=0.05)
    iterations, status = run(gauss_newton(graph, max_iterations=2))
    assert len(iterations) == 2
    assert status == PolishStatus(False, status.reason, 2)
    assert "iteration cap 2 reached" in status.reason
    iterations, status = run(gauss_newton(graph, max_iterations=0))
    assert iterations == [] and not status.converged and status.iterations == 0


def test_converges_with_a_status_that_counts_the_yielded_steps() -> None:
    graph, _ = square_loop(np.random.default_rng(5), noise=0.05)
    iterations, status = run(gauss_newton(graph))
    assert status.converged and status.iterations == len(iterations) > 0
    # Converged means the last step barely changed χ², or the gradient vanished.
    before_last = iterations[-2].chi2 if len(iterations) > 1 else chi2(graph)
    assert (before_last - iterations[-1].chi2) / before_last < 1e-9 or "gradient" in status.reason


def test_never_claims_convergence_while_chi2_is_still_dropping() -> None:
    world = generate_grid_world(300, seed=3)  # dead reckoning: a poor start, far from the optimum
    graph = world.graph
    iterations, status = run(gauss_newton(graph))
    assert status.converged
    values = np.array([chi2(graph)] + [it.chi2 for it in iterations])
    drops = -np.diff(values) / values[:-1]
    assert len(iterations) >= 3 and drops[0] > 0.5
    # Stopped earlier, at any step where χ² still fell by more than the tolerance, it must say so.
    for cap in range(1, len(iterations)):
        capped, capped_status = run(gauss_newton(graph, max_iterations=cap))
        assert len(capped) == cap
        assert not capped_status.converged, (cap, drops[cap - 1], capped_status)


def test_a_stall_away_from_the_optimum_is_not_convergence(monkeypatch: pytest.MonkeyPatch) -> None:
    # A linear solver that only ever returns uphill steps: λ runs away with the gradient far from zero.
    from optimizer import damped_solvers

    graph, _ = square_loop(np.random.default_rng(9), noise=0.05)
    monkeypatch.setattr(damped_solvers.DirectSolver, "step",
                        lambda self, linearisation, damping: linearisation.scale * linearisation.gradient)
    iterations, status = run(gauss_newton(graph))
    assert iterations == []
    assert not status.converged and status.reason.startswith("no decreasing step")


def test_starts_from_given_poses_and_leaves_the_graph_alone() -> None:
    graph, truth = square_loop(np.random.default_rng(6))
    before = graph.poses.copy()
    first = next(gauss_newton(graph, truth + 0.01))
    assert first.chi2 < chi2(graph, truth + 0.01)
    np.testing.assert_allclose(first.poses[0], truth[0] + 0.01, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(graph.poses, before)


def test_stops_at_once_at_the_optimum() -> None:
    graph, truth = square_loop(np.random.default_rng(7))
    # χ² at the truth is zero up to rounding: at most a rounding-sized step is found before λ runs away.
    iterations, status = run(gauss_newton(graph, truth))
    assert len(iterations) <= 2 and status.converged
    for it in iterations:
        np.testing.assert_allclose(it.poses, truth, rtol=0, atol=1e-12)


def test_unconstrained_direction_stays_finite() -> None:
    # Pose 1's heading is unconstrained: its only edge has zero θθ information.
    information = np.array([np.diag([100.0, 100.0, 0.0]), np.diag([100.0, 100.0, 100.0])])
    graph = PoseGraph.build(np.arange(3), [[0, 0, 0], [1.2, 0.3, 0.4], [0.2, 1.1, 1.0]], [0, 0], [1, 2],
                            [[1, 0, 0], [0, 1, 1.5]], information, check_information=False)
    iterations = list(gauss_newton(graph))
    assert iterations and np.all(np.isfinite(iterations[-1].poses))
    assert iterations[-1].chi2 < 1e-12
    assert iterations[-1].poses[1, 2] == pytest.approx(0.4)


def test_rejects_bad_arguments() -> None:
    graph, _ = square_loop(np.random.default_rng(8))
    with pytest.raises(GraphError):
        next(gauss_newton(graph, np.zeros((3, 3))))
    with pytest.raises(GraphError):
        next(gauss_newton(graph, np.full(graph.poses.shape, np.nan)))
    with pytest.raises(OptimizerError):
        next(gauss_newton(graph, max_iterations=-1))


def shared_graph(name: str) -> PoseGraph:
    # CSAIL.g2o has no vertex lines: the reader composes its odometry edges i → i+1.
    return read_graph(shared_file(f"posegraphs/2d/{name}")).graph


@pytest.mark.parametrize(
    ("name", "optimum"),
    [("pose2example.txt", 1.0989), ("FR079.g2o", 37.5985), ("CSAIL.g2o", 40.5551), ("M3500.g2o", 137.913)],
)
def test_real_graphs_converge_to_their_optimum_from_the_file_estimate(name: str, optimum: float) -> None:
    # Optima: g2o's published figures for these files (FR079, CSAIL, M3500); pose2example from GTSAM.
    graph = shared_graph(name)
    iterations, status = run(gauss_newton(graph))
    assert status.converged, status
    assert iterations[-1].chi2 == pytest.approx(optimum, rel=1e-4)


def test_intel_converges_to_its_optimum_after_30_sgd_iterations() -> None:
    graph = shared_graph("INTEL.g2o")
    start = list(sgd(graph, 30))[-1].poses
    iterations, status = run(gauss_newton(graph, start))
    assert status.converged, status
    assert iterations[-1].chi2 == pytest.approx(215.83, rel=1e-4)


def test_badly_conditioned_intel_stays_finite_and_decreasing() -> None:
    graph = shared_graph("INTEL.g2o")
    iterations = list(gauss_newton(graph, max_iterations=40))
    assert len(iterations) == 40
    values = np.array([it.chi2 for it in iterations])
    assert np.all(np.isfinite(values)) and all(np.all(np.isfinite(it.poses)) for it in iterations)
    assert np.all(np.diff(values) < 0)
    assert values[-1] < 0.05 * chi2(graph)


def turned_about_the_anchor(poses: np.ndarray, angle: float) -> np.ndarray:
    """`poses` with every pose but the anchor turned rigidly by `angle` about pose 0."""
    turned = poses.copy()
    relative = poses[1:, :2] - poses[0, :2]
    c, s = np.cos(angle), np.sin(angle)
    turned[1:, 0] = poses[0, 0] + c * relative[:, 0] - s * relative[:, 1]
    turned[1:, 1] = poses[0, 1] + s * relative[:, 0] + c * relative[:, 1]
    turned[1:, 2] = se2.wrap_angle(poses[1:, 2] + angle)
    return turned


def test_a_step_that_turns_the_graph_about_the_anchor_keeps_every_relative_pose() -> None:
    graph = generate_grid_world(300, seed=4).graph
    poses = graph.poses
    angle = 0.3
    relative = poses[1:, :2] - poses[0, :2]
    # The linear step of a rotation by `angle` about pose 0: δθ = angle, δt = angle·R(π/2)·(t − t₀).
    step = angle * np.column_stack([-relative[:, 1], relative[:, 0], np.ones(len(relative))]).reshape(-1)
    moved = moved_by(poses, step)
    np.testing.assert_allclose(moved, turned_about_the_anchor(poses, angle), atol=1e-9)
    unchanged = edge_errors(graph, poses)[(graph.edge_from != 0) & (graph.edge_to != 0)]
    np.testing.assert_allclose(edge_errors(graph, moved)[(graph.edge_from != 0) & (graph.edge_to != 0)],
                               unchanged, atol=1e-9)


def test_moving_by_a_step_is_the_additive_update_to_first_order() -> None:
    graph = generate_grid_world(300, seed=4).graph
    step = np.random.default_rng(2).normal(size=3 * (graph.num_poses - 1))
    deviations = []
    for size in (1e-3, 1e-4):
        additive = graph.poses.copy()
        additive[1:] += size * step.reshape(-1, 3)
        deviations.append(np.abs(moved_by(graph.poses, size * step) - additive).max())
    assert deviations[1] < deviations[0] / 50.0  # second order: ÷100 for a tenth of the step


@pytest.mark.parametrize("linear_solver", ["direct", "multigrid"])
def test_an_optimum_turned_about_a_weakly_held_anchor_is_reached_in_a_few_steps(linear_solver: str) -> None:
    # The anchor has one or two edges, so turning the rest of the graph rigidly about it is the softest
    # mode; a large such turn is a pure rotation that the additive update would turn into a stretch.
    graph = generate_grid_world(2000, seed=3).graph
    optimum_iterations, status = run(gauss_newton(graph, linear_solver=linear_solver))
    assert status.converged, status
    optimum = optimum_iterations[-1]
    start = turned_about_the_anchor(optimum.poses, 0.4)
    iterations, status = run(gauss_newton(graph, start, linear_solver=linear_solver))
    assert status.converged, status
    assert iterations[-1].chi2 == pytest.approx(optimum.chi2, rel=1e-9)
    assert status.iterations <= 6
