"""The rigid realignment of the free poses to the anchor's constraints (`optimizer.anchor_alignment`)."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer import se2
from optimizer.anchor_alignment import aligned_to_anchor
from optimizer.cost import chi2
from optimizer.graph import PoseGraph
from optimizer.gridworld import generate_grid_world
from optimizer.polish import gauss_newton
from tests.conftest import MULTIGRID_STACK
from tests.optimizer_fixtures import run

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


def moved_rigidly(poses: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """`poses` with every pose but the anchor moved by the world-frame rigid motion `motion`."""
    moved = poses.copy()
    moved[1:] = se2.compose(motion, poses[1:])
    return moved


def test_an_optimum_moved_rigidly_off_its_anchor_is_moved_back() -> None:
    graph = generate_grid_world(500, seed=5).graph
    iterations, status = run(gauss_newton(graph, linear_solver="direct"))
    assert status.converged, status
    optimum = iterations[-1]
    shifted = moved_rigidly(optimum.poses, np.array([4.0, -3.0, 0.3]))
    assert chi2(graph, shifted) > 2.0 * optimum.chi2
    aligned = aligned_to_anchor(graph, shifted)
    assert chi2(graph, aligned) == pytest.approx(optimum.chi2, rel=1e-9)
    np.testing.assert_allclose(aligned, optimum.poses, atol=1e-6)


def test_only_the_constraints_at_the_anchor_change() -> None:
    graph = generate_grid_world(500, seed=5).graph
    aligned = aligned_to_anchor(graph, graph.poses)
    assert chi2(graph, aligned) < chi2(graph, graph.poses)
    away = (graph.edge_from != 0) & (graph.edge_to != 0)
    before = se2.relative(graph.poses[graph.edge_from[away]], graph.poses[graph.edge_to[away]])
    after = se2.relative(aligned[graph.edge_from[away]], aligned[graph.edge_to[away]])
    np.testing.assert_allclose(after, before, atol=1e-9)
    assert np.array_equal(aligned[0], graph.poses[0])


def test_a_singular_information_at_the_anchor_is_handled() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [1.2, 0.3, 0.4], [0.2, 1.1, 1.0]])
    # Pose 1's heading is unconstrained: the anchor's edge to it has zero θθ information.
    information = np.array([np.diag([100.0, 100.0, 0.0]), np.diag([100.0, 100.0, 100.0])])
    singular = PoseGraph.build(np.arange(3), poses, [0, 0], [1, 2], [[1, 0, 0], [0, 1, 1.5]], information,
                               check_information=False)
    aligned = aligned_to_anchor(singular, poses)
    assert np.all(np.isfinite(aligned))
    assert chi2(singular, aligned) < chi2(singular, poses)


def test_the_inexact_polish_moves_a_graph_held_weakly_by_its_anchor_in_a_few_steps() -> None:
    # The anchor's constraints are a millionth as informative as the rest: moving all other poses rigidly
    # is then a mode far softer than λ's floor, which the damped CG steps alone take a dozen steps over.
    base = generate_grid_world(2000, seed=3).graph
    information = base.information.copy()
    information[(base.edge_from == 0) | (base.edge_to == 0)] *= 1e-6
    graph = PoseGraph.build(np.arange(base.num_poses), base.poses, base.edge_from, base.edge_to,
                            base.measurements, information)
    iterations, status = run(gauss_newton(graph, linear_solver="direct"))
    assert status.converged, status
    optimum = iterations[-1]
    start = moved_rigidly(optimum.poses, np.array([3.0, -2.0, 0.2]))
    iterations, status = run(gauss_newton(graph, start, linear_solver="multigrid"))
    assert status.converged, status
    assert iterations[-1].chi2 == pytest.approx(optimum.chi2, rel=1e-9)
    assert status.iterations <= 4
