"""The synthetic grid world: a walk on city streets, noisy odometry, loop closures on revisits."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.cost import chi2, edge_errors
from optimizer.errors import OptimizerError
from optimizer.gridworld import generate_grid_world

ODOMETRY_SIGMA = (0.03, 0.02, 0.01)
LOOP_SIGMA = (0.1, 0.07, 0.04)


@pytest.fixture(scope="module")
def world():
    return generate_grid_world(30_000, seed=7, odometry_sigma=ODOMETRY_SIGMA, loop_sigma=LOOP_SIGMA)


def test_same_seed_same_world_other_seed_other_world() -> None:
    first = generate_grid_world(2_000, seed=11)
    again = generate_grid_world(2_000, seed=11)
    other = generate_grid_world(2_000, seed=12)
    np.testing.assert_array_equal(first.ground_truth, again.ground_truth)
    np.testing.assert_array_equal(first.graph.poses, again.graph.poses)
    np.testing.assert_array_equal(first.graph.edge_from, again.graph.edge_from)
    np.testing.assert_array_equal(first.graph.edge_to, again.graph.edge_to)
    np.testing.assert_array_equal(first.graph.measurements, again.graph.measurements)
    assert not np.array_equal(first.ground_truth, other.ground_truth)


def test_walk_follows_the_streets_one_step_at_a_time_without_reversing() -> None:
    block, step = 5, 2.5
    truth = generate_grid_world(5_000, seed=3, step=step, block_steps=block, world_blocks=4).ground_truth
    lattice = truth[:, :2] / step
    np.testing.assert_allclose(lattice, np.round(lattice), atol=1e-9)
    lattice = np.round(lattice).astype(int)
    on_street = (lattice[:, 0] % block == 0) | (lattice[:, 1] % block == 0)
    assert on_street.all()
    assert lattice.min() >= 0 and lattice.max() <= 4 * block
    moves = np.diff(lattice, axis=0)
    assert (np.abs(moves).sum(axis=1) == 1).all()
    # The heading is the direction of the last move, and the robot never turns back on itself.
    headings = np.round(np.arctan2(moves[:, 1], moves[:, 0]) / (np.pi / 2)) % 4
    np.testing.assert_allclose(np.round(truth[1:, 2] / (np.pi / 2)) % 4, headings)
    assert not np.any((moves[1:] == -moves[:-1]).all(axis=1))
    # Turns happen only at intersections.
    turned = (moves[1:] != moves[:-1]).any(axis=1)
    at_intersection = (lattice[1:-1] % block == 0).all(axis=1)
    assert np.all(at_intersection[turned])


def test_odometry_chain_and_dead_reckoning_initial_estimate(world) -> None:
    graph = world.graph
    odometry = graph.is_odometry
    assert np.count_nonzero(odometry) == graph.num_poses - 1
    np.testing.assert_array_equal(np.sort(graph.edge_from[odometry]), np.arange(graph.num_poses - 1))
    np.testing.assert_array_equal(graph.poses[0], world.ground_truth[0])
    # Composing the odometry measurements in order reproduces the initial estimate.
    order = np.argsort(graph.edge_from[odometry])
    steps = graph.measurements[odometry][order]
    pose = graph.poses[0].copy()
    for index in (1, 2, 3):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        dx, dy, dtheta = steps[index - 1]
        pose = np.array([pose[0] + c * dx - s * dy, pose[1] + s * dx + c * dy, pose[2] + dtheta])
        np.testing.assert_allclose(graph.poses[index, :2], pose[:2], atol=1e-12)
    # The dead reckoning drifts away from the truth: a poor initial estimate.
    drift = np.linalg.norm(graph.poses[-1, :2] - world.ground_truth[-1, :2])
    assert drift > 1.0


@pytest.mark.parametrize(("kind", "sigma"), [("odometry", ODOMETRY_SIGMA), ("loop", LOOP_SIGMA)])
def test_measurement_noise_matches_the_declared_sigmas(world, kind: str, sigma: tuple) -> None:
    graph = world.graph
    mask = graph.is_odometry if kind == "odometry" else ~graph.is_odometry
    errors = edge_errors(graph, world.ground_truth)[mask]
    assert len(errors) > 10_000
    np.testing.assert_allclose(errors.std(axis=0), sigma, rtol=0.03)
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * np.array(sigma) / np.sqrt(len(errors)))
    expected_information = np.diag(1.0 / np.square(sigma))
    np.testing.assert_allclose(graph.information[mask][0], expected_information)
    np.testing.assert_allclose(graph.information[mask][-1], expected_information)


def test_chi2_of_the_truth_is_chi_square_distributed(world) -> None:
    degrees = 3 * world.graph.num_edges
    assert abs(chi2(world.graph, world.ground_truth) - degrees) < 5 * np.sqrt(2 * degrees)


def test_loop_closures_join_poses_at_the_same_place(world) -> None:
    graph = world.graph
    loops = ~graph.is_odometry
    assert world.num_loop_closures == np.count_nonzero(loops) > 0
    earlier, later = graph.edge_from[loops], graph.edge_to[loops]
    truth = world.ground_truth
    np.testing.assert_allclose(truth[earlier, :2], truth[later, :2], atol=1e-9)
    # Returning to a point without reversing takes at least one lap around a block.
    assert np.all(later - earlier >= 4 * 10)
    pairs = set(zip(earlier.tolist(), later.tolist(), strict=True))
    assert len(pairs) == len(earlier)


def test_every_revisit_closes_one_loop_when_asked_to() -> None:
    world = generate_grid_world(3_000, seed=5, loop_probability=1.0, max_loops_per_revisit=1)
    points = [tuple(p) for p in np.round(world.ground_truth[:, :2]).astype(int).tolist()]
    seen: set[tuple[int, int]] = set()
    revisits = []
    for index, point in enumerate(points):
        if point in seen:
            revisits.append(index)
        seen.add(point)
    loops = ~world.graph.is_odometry
    np.testing.assert_array_equal(np.sort(world.graph.edge_to[loops]), revisits)


def test_no_loop_closures_when_none_are_wanted() -> None:
    world = generate_grid_world(3_000, seed=5, loop_probability=0.0)
    assert world.num_loop_closures == 0
    assert world.graph.num_edges == 2_999


def test_without_noise_the_truth_has_zero_chi2() -> None:
    world = generate_grid_world(4_000, seed=2, add_noise=False)
    assert world.num_loop_closures > 0
    assert chi2(world.graph, world.ground_truth) < 1e-12
    difference = world.graph.poses - world.ground_truth
    difference[:, 2] = np.angle(np.exp(1j * difference[:, 2]))
    np.testing.assert_allclose(difference, 0.0, atol=1e-9)


def test_default_density_is_about_two_constraints_per_pose() -> None:
    graph = generate_grid_world(100_000, seed=1).graph
    assert 1.7 < graph.num_edges / graph.num_poses < 2.2


@pytest.mark.parametrize(
    "arguments",
    [
        {"num_poses": 1},
        {"step": 0.0},
        {"block_steps": 0},
        {"world_blocks": 0},
        {"turn_probability": 1.5},
        {"loop_probability": -0.1},
        {"max_loops_per_revisit": -1},
        {"odometry_sigma": (0.1, 0.0, 0.1)},
        {"loop_sigma": (0.1, 0.1)},
    ],
)
def test_bad_arguments_are_rejected(arguments: dict) -> None:
    arguments = {"num_poses": 100, **arguments}
    with pytest.raises(OptimizerError):
        generate_grid_world(seed=0, **arguments)
