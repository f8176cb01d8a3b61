"""Chordal initialisation: exact on consistent graphs in any edge direction, a better start on bad ones."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph, reverse_constraints
from optimizer.graph_files import read_graph
from optimizer.gridworld import generate_grid_world
from optimizer.initialization import chordal_initialization, positions_given_headings, rotation_weights
from optimizer.planar_sync import ReducedRotationForm, planar_sync
from optimizer.polish import gauss_newton
from optimizer.sgd import sgd
from optimizer.sgd_tree import sgd_tree
from tests.conftest import shared_file


def pose_difference(poses: np.ndarray, truth: np.ndarray) -> float:
    difference = poses - truth
    difference[:, 2] = se2.wrap_angle(difference[:, 2])
    return float(np.abs(difference).max())


def gauss_newton_chi2(graph: PoseGraph, poses: np.ndarray) -> float:
    value = chi2(graph, poses)
    for step in gauss_newton(graph, poses, max_iterations=1000):
        value = step.chi2
    return value


def with_reversed_edges(graph: PoseGraph, reverse: np.ndarray, poses: np.ndarray) -> PoseGraph:
    """The same constraints, those in `reverse` stored b→a (inverse measurement, adjoint information)."""
    measurements = graph.measurements.copy()
    information = graph.information.copy()
    measurements[reverse], information[reverse] = reverse_constraints(measurements[reverse],
                                                                      information[reverse])
    edge_from = np.where(reverse, graph.edge_to, graph.edge_from)
    edge_to = np.where(reverse, graph.edge_from, graph.edge_to)
    return PoseGraph(poses.copy(), edge_from, edge_to, measurements, information, graph.vertex_ids.copy())


def test_noise_free_world_is_recovered_exactly_from_a_useless_estimate() -> None:
    world = generate_grid_world(3_000, seed=3, add_noise=False)
    # Only pose 0 (the anchor) is kept from the estimate: the others are scrambled.
    scrambled = np.random.default_rng(0).uniform(-50, 50, size=world.ground_truth.shape)
    scrambled[0] = world.ground_truth[0]
    graph = world.graph.with_poses(scrambled)
    assert pose_difference(chordal_initialization(graph), world.ground_truth) < 1e-9


def test_noise_free_world_with_reversed_edges_is_recovered_exactly() -> None:
    world = generate_grid_world(3_000, seed=4, add_noise=False)
    reverse = np.random.default_rng(1).random(world.graph.num_edges) < 0.4
    zeros = np.zeros_like(world.ground_truth)
    zeros[0] = world.ground_truth[0]
    graph = with_reversed_edges(world.graph, reverse, zeros)
    assert np.any(graph.edge_from > graph.edge_to)
    assert pose_difference(chordal_initialization(graph), world.ground_truth) < 1e-9


def test_reversing_edges_keeps_the_rotations_and_barely_moves_the_positions() -> None:
    # The chordal cost ‖r_b − R_z·r_a‖ = ‖r_a − R_zᵀ·r_b‖ and the marginal θ information are both unchanged
    # by reversing a constraint, so the rotations are the same; the positions minimise the χ² of the
    # reversed constraints, which equals the original χ² only to first order (adjoint information).
    world = generate_grid_world(1_500, seed=5, odometry_sigma=(0.02, 0.02, 0.1))
    reverse = np.random.default_rng(2).random(world.graph.num_edges) < 0.5
    reversed_graph = with_reversed_edges(world.graph, reverse, world.graph.poses)
    direct = chordal_initialization(world.graph)
    flipped = chordal_initialization(reversed_graph)
    np.testing.assert_allclose(se2.wrap_angle(flipped[:, 2] - direct[:, 2]), 0.0, atol=1e-9)
    assert pose_difference(flipped, direct) < 0.1
    assert chi2(reversed_graph, flipped) == pytest.approx(chi2(world.graph, direct), rel=0.05)


def test_duplicate_edges_count_twice() -> None:
    # A triangle whose loop edge disagrees with the odometry: duplicating the loop edge is the same as
    # doubling its information.
    poses = np.zeros((3, 3))
    edge_from, edge_to = np.array([0, 1, 0]), np.array([1, 2, 2])
    measurements = np.array([[1.0, 0.0, np.pi / 2], [1.0, 0.0, np.pi / 2], [1.2, 0.9, 2.9]])
    information = np.repeat(np.diag([10.0, 20.0, 30.0])[None], 3, axis=0)
    graph = PoseGraph(poses, edge_from, edge_to, measurements, information, np.arange(3))
    duplicated = PoseGraph(poses, np.r_[edge_from, 0], np.r_[edge_to, 2],
                           np.r_[measurements, measurements[2:]], np.r_[information, information[2:]],
                           np.arange(3))
    doubled_information = information.copy()
    doubled_information[2] *= 2.0
    doubled = PoseGraph(poses, edge_from, edge_to, measurements, doubled_information, np.arange(3))
    np.testing.assert_allclose(chordal_initialization(duplicated), chordal_initialization(doubled),
                               atol=1e-12)
    assert pose_difference(chordal_initialization(duplicated), chordal_initialization(graph)) > 1e-3


def test_positions_minimise_the_chi2_for_the_estimated_rotations() -> None:
    world = generate_grid_world(800, seed=6, odometry_sigma=(0.02, 0.02, 0.1))
    rng = np.random.default_rng(3)
    # Correlated information, so the θ–translation coupling matters.
    factors = rng.normal(size=(world.graph.num_edges, 3, 3))
    information = factors @ np.swapaxes(factors, 1, 2) + 3.0 * np.eye(3)
    graph = PoseGraph(world.graph.poses, world.graph.edge_from, world.graph.edge_to, world.graph.measurements,
                      information, world.graph.vertex_ids)
    poses = chordal_initialization(graph)
    best = chi2(graph, poses)
    for _ in range(5):
        moved = poses.copy()
        moved[1:, :2] += rng.normal(scale=1e-3, size=(graph.num_poses - 1, 2))
        assert chi2(graph, moved) > best


def test_positions_given_true_headings_recover_a_noise_free_world_from_any_positions() -> None:
    world = generate_grid_world(400, seed=2, add_noise=False)
    rng = np.random.default_rng(5)
    scrambled = np.array(world.ground_truth)
    scrambled[1:, :2] = rng.uniform(-50.0, 50.0, size=(world.graph.num_poses - 1, 2))
    solved = positions_given_headings(world.graph, scrambled)
    assert pose_difference(solved, world.ground_truth) < 1e-8


def test_positions_given_headings_keep_the_headings_and_minimise_the_chi2_over_positions() -> None:
    world = generate_grid_world(600, seed=4, odometry_sigma=(0.02, 0.02, 0.2))
    rng = np.random.default_rng(8)
    factors = rng.normal(size=(world.graph.num_edges, 3, 3))
    information = factors @ np.swapaxes(factors, 1, 2) + 3.0 * np.eye(3)  # θ–translation coupling
    graph = PoseGraph(world.graph.poses, world.graph.edge_from, world.graph.edge_to, world.graph.measurements,
                      information, world.graph.vertex_ids)
    headings = np.array(graph.poses)  # dead-reckoned headings: far from any minimum
    solved = positions_given_headings(graph, headings)
    np.testing.assert_allclose(solved[:, 2], se2.wrap_angle(headings[:, 2]), atol=1e-15)
    np.testing.assert_array_equal(solved[0], graph.poses[0])
    best = chi2(graph, solved)
    assert best < chi2(graph, headings)
    for _ in range(5):
        moved = solved.copy()
        moved[1:, :2] += rng.normal(scale=1e-3, size=(graph.num_poses - 1, 2))
        assert chi2(graph, moved) > best


def test_at_a_minimum_the_positions_given_its_headings_are_its_own() -> None:
    # The χ² is quadratic in the positions once the headings are fixed, so a minimum's positions are the
    # unique minimiser for its headings: the whole basin question is a question about headings.
    world = generate_grid_world(500, seed=1, odometry_sigma=(0.02, 0.02, 0.3))
    minimum = np.array(world.ground_truth)
    for step in gauss_newton(world.graph, minimum, relative_tolerance=1e-14):
        minimum = step.poses
    scrambled = minimum.copy()
    scrambled[1:, :2] += 3.0
    assert pose_difference(positions_given_headings(world.graph, scrambled), minimum) < 1e-6


def test_rotation_weights_are_the_marginal_theta_information_with_a_floor() -> None:
    covariance = np.array([[0.5, 0.1, 0.2], [0.1, 0.4, -0.1], [0.2, -0.1, 0.3]])
    information = np.stack([np.linalg.inv(covariance), np.diag([4.0, 4.0, 0.0]), np.diag([4.0, 4.0, 8.0])])
    weights = rotation_weights(information)
    assert weights[0] == pytest.approx(1.0 / covariance[2, 2])
    assert weights[2] == pytest.approx(8.0)
    assert 0.0 < weights[1] < 1e-4


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heavy_heading_noise_chordal_start_beats_odometry_and_reaches_the_truth_basin(seed: int) -> None:
    # Small worlds keep the test fast; on 3,500-pose worlds at σθ = 0.3 the chordal start does not always
    # reach the truth's basin (benchmarks/initialization_bench.py).
    world = generate_grid_world(500, seed=seed, odometry_sigma=(0.02, 0.02, 0.3))
    graph = world.graph
    from_chordal = gauss_newton_chi2(graph, chordal_initialization(graph))
    from_odometry = gauss_newton_chi2(graph, graph.poses)
    from_truth = gauss_newton_chi2(graph, world.ground_truth)
    assert from_chordal < 0.1 * from_odometry
    assert from_chordal <= 1.001 * from_truth


def test_single_pose_graph_returns_its_pose() -> None:
    graph = PoseGraph(np.array([[1.0, 2.0, 0.5]]), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                      np.zeros((0, 3)), np.zeros((0, 3, 3)), np.array([7]))
    np.testing.assert_array_equal(chordal_initialization(graph), graph.poses)


def test_pg1_singular_theta_information_gives_a_finite_start() -> None:
    graph = read_graph(shared_file("posegraphs/2d/pg1.g2o"), repair_information=True).graph
    poses = chordal_initialization(graph)
    assert np.all(np.isfinite(poses))
    assert gauss_newton_chi2(graph, poses) <= gauss_newton_chi2(graph, graph.poses) * 1.001 + 1e-9


@pytest.mark.parametrize(("name", "best_known"), [("CSAIL.g2o", 40.555), ("FR079.g2o", 37.598),
                                                 ("M3500.g2o", 137.913)])
def test_real_graphs_start_reaches_the_best_known_minimum(name: str, best_known: float) -> None:
    # Best known minima: the figures the optimizer benchmark checks (g2o/GTSAM agree on them).
    graph = read_graph(shared_file(f"posegraphs/2d/{name}")).graph
    assert gauss_newton_chi2(graph, chordal_initialization(graph)) == pytest.approx(best_known, rel=1e-3)


# ------------------------------------------------------------------------------- planar SE-Sync headings


def isotropic_cost_minimised_over_positions(graph: PoseGraph, headings: np.ndarray) -> float:
    """min over positions (pose 0 at the origin) of Σ τ|t_b − t_a − z·r_a|² + κ|r_b − e^{iθ}r_a|², by a
    dense least-squares solve: the cost `ReducedRotationForm` must equal without forming positions."""
    information = graph.information
    kappa = rotation_weights(information)
    tau = 0.5 * (information[:, 0, 0] + information[:, 1, 1])
    a, b = graph.edge_from, graph.edge_to
    r = np.exp(1j * headings)
    step = graph.measurements[:, 0] + 1j * graph.measurements[:, 1]
    incidence = np.zeros((graph.num_edges, graph.num_poses))
    incidence[np.arange(graph.num_edges), b] += 1.0
    incidence[np.arange(graph.num_edges), a] -= 1.0
    weights = np.sqrt(tau)[:, None]
    target = step * r[a]
    positions = np.linalg.lstsq(weights * incidence[:, 1:], np.sqrt(tau) * target, rcond=None)[0]
    translation = np.sum(tau * np.abs(incidence[:, 1:] @ positions - target) ** 2)
    rotation = np.sum(kappa * np.abs(r[b] - np.exp(1j * graph.measurements[:, 2]) * r[a]) ** 2)
    return float(translation + rotation)


def test_reduced_form_is_the_isotropic_cost_with_the_positions_eliminated() -> None:
    world = generate_grid_world(60, seed=3, odometry_sigma=(0.05, 0.05, 0.3))
    reverse = np.random.default_rng(4).random(world.graph.num_edges) < 0.4
    graph = with_reversed_edges(world.graph, reverse, world.graph.poses)
    form = ReducedRotationForm(graph)
    for seed in range(3):
        headings = np.random.default_rng(seed).uniform(-np.pi, np.pi, graph.num_poses)
        r = np.exp(1j * headings)
        reduced = float(np.real(np.vdot(r, form.apply(r[:, None])[:, 0])))
        assert reduced == pytest.approx(isotropic_cost_minimised_over_positions(graph, headings), rel=1e-9)


def test_sync_recovers_a_noise_free_world_with_reversed_edges_from_a_useless_estimate() -> None:
    world = generate_grid_world(1_500, seed=7, add_noise=False)
    reverse = np.random.default_rng(6).random(world.graph.num_edges) < 0.4
    scrambled = np.random.default_rng(0).uniform(-50, 50, size=world.ground_truth.shape)
    scrambled[0] = world.ground_truth[0]
    graph = with_reversed_edges(world.graph, reverse, scrambled)
    result = planar_sync(graph)
    assert pose_difference(result.poses, world.ground_truth) < 1e-6
    assert result.rounded_cost < 1e-8 * graph.num_edges


def test_sync_headings_reach_a_lower_minimum_than_every_rotation_only_start() -> None:
    # σθ = 0.3: the headings are known mainly through the odometry translations. Rotation-only estimates
    # (chordal; the paper's SGD then the tree SGD, which is the default's own path) lead the polish into
    # higher basins; the relaxation that sees the translations leads it to the truth's.
    world = generate_grid_world(600, seed=5, odometry_sigma=(0.02, 0.02, 0.3))
    graph = world.graph
    from_sync = gauss_newton_chi2(graph, planar_sync(graph).poses)
    descended = graph.poses
    for step in sgd_tree(graph, 100, sgd_final(graph)):
        descended = step.poses
    rotation_only = min(gauss_newton_chi2(graph, chordal_initialization(graph)),
                        gauss_newton_chi2(graph, descended))
    from_truth_headings = gauss_newton_chi2(graph, positions_given_headings(graph, world.ground_truth))
    assert from_sync < 0.97 * rotation_only
    assert from_sync <= 1.001 * from_truth_headings


def sgd_final(graph: PoseGraph) -> np.ndarray:
    poses = graph.poses
    for step in sgd(graph, 100):
        poses = step.poses
    return poses


def test_sync_of_a_single_pose_and_a_bad_rank() -> None:
    graph = PoseGraph(np.array([[1.0, 2.0, 7.0]]), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                      np.zeros((0, 3)), np.zeros((0, 3, 3)), np.array([7]))
    np.testing.assert_allclose(planar_sync(graph).poses, [[1.0, 2.0, se2.wrap_angle(7.0)]])
    with pytest.raises(OptimizerError):
        planar_sync(graph, rank=0)
