"""The benchmark's hard graphs: reversed anisotropic loop closures, false loops, poor-start worlds."""

from __future__ import annotations

import importlib.machinery
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from optimizer import benchmark_graphs, se2
from optimizer.benchmark_graphs import (
    ANISOTROPY_RANGE,
    loop_closures,
    noisy_manhattan,
    odometry_chain,
    reversed_anisotropic_variant,
    true_edges_chi2,
    with_false_loops,
)
from optimizer.cost import chi2, edge_errors
from optimizer.errors import GraphError
from optimizer.graph import PoseGraph
from optimizer.gridworld import generate_grid_world
from tests.conftest import shared_file


@pytest.fixture(scope="module")
def exact_world():
    return generate_grid_world(600, seed=3, add_noise=False)


@pytest.fixture(scope="module")
def noisy_world():
    return generate_grid_world(600, seed=4)


def _rotation_matrix(theta: float) -> np.ndarray:
    return np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])


def test_variant_reverses_every_loop_closure_and_keeps_odometry(noisy_world):
    graph = noisy_world.graph
    variant = reversed_anisotropic_variant(graph, seed=1)
    loops = loop_closures(graph)
    assert loops.sum() > 50
    np.testing.assert_array_equal(variant.edge_from[loops], graph.edge_to[loops])
    np.testing.assert_array_equal(variant.edge_to[loops], graph.edge_from[loops])
    assert np.all(variant.edge_from[loops] > variant.edge_to[loops])
    for array in ("edge_from", "edge_to", "measurements", "information"):
        np.testing.assert_array_equal(getattr(variant, array)[~loops], getattr(graph, array)[~loops])
    np.testing.assert_array_equal(variant.poses, graph.poses)


def test_reversed_measurement_of_a_noise_free_world_has_zero_error_at_the_truth(exact_world):
    variant = reversed_anisotropic_variant(exact_world.graph, seed=2)
    truth = exact_world.ground_truth
    loops = loop_closures(variant)
    # The pose of a in the frame of b, straight from the ground truth (a = the stored edge_to).
    expected = se2.relative(truth[variant.edge_from[loops]], truth[variant.edge_to[loops]])
    np.testing.assert_allclose(variant.measurements[loops][:, :2], expected[:, :2], atol=1e-9)
    np.testing.assert_allclose(se2.wrap_angle(variant.measurements[loops][:, 2] - expected[:, 2]), 0.0,
                               atol=1e-12)
    assert chi2(variant, truth) < 1e-12


def test_variant_information_is_anisotropic_and_first_order_equivalent(exact_world):
    graph = exact_world.graph
    variant = reversed_anisotropic_variant(graph, seed=5)
    loops = np.flatnonzero(loop_closures(graph))
    reversed_information = variant.information[loops]
    assert np.all(np.linalg.eigvalsh(reversed_information) > 0.0)
    np.testing.assert_allclose(reversed_information, np.swapaxes(reversed_information, 1, 2))

    # Carry the stored information back to a's frame: Ad(z)ᵀ Ω' Ad(z) with z the original measurement.
    forward_adjoint = se2.adjoint(graph.measurements[loops])
    forward = np.einsum("mji,mjk,mkl->mil", forward_adjoint, reversed_information, forward_adjoint)
    translation_eigenvalues = np.linalg.eigvalsh(forward[:, :2, :2])
    ratio = translation_eigenvalues[:, 1] / translation_eigenvalues[:, 0]
    assert np.all(ratio >= ANISOTROPY_RANGE[0] * (1 - 1e-6))
    assert np.all(ratio <= ANISOTROPY_RANGE[1] * (1 + 1e-6))
    np.testing.assert_allclose(forward[:, 2, 2], graph.information[loops, 2, 2], rtol=1e-9)

    # Near the truth (errors small enough that second-order terms vanish even along the 10⁴ times stiffer
    # direction), each reversed edge costs what its forward twin with that information costs.
    rng = np.random.default_rng(0)
    truth = exact_world.ground_truth
    poses = truth + rng.normal(scale=1e-7, size=truth.shape)
    forward_graph = PoseGraph(graph.poses, graph.edge_from[loops], graph.edge_to[loops],
                              graph.measurements[loops], forward, graph.vertex_ids)
    reversed_graph = PoseGraph(graph.poses, variant.edge_from[loops], variant.edge_to[loops],
                               variant.measurements[loops], reversed_information, graph.vertex_ids)
    forward_errors = edge_errors(forward_graph, poses)
    reversed_errors = edge_errors(reversed_graph, poses)
    forward_cost = np.einsum("mi,mij,mj->m", forward_errors, forward, forward_errors)
    reversed_cost = np.einsum("mi,mij,mj->m", reversed_errors, reversed_information, reversed_errors)
    np.testing.assert_allclose(reversed_cost, forward_cost, rtol=1e-3)


def test_variant_is_reproducible_per_seed(noisy_world):
    first = reversed_anisotropic_variant(noisy_world.graph, seed=7)
    again = reversed_anisotropic_variant(noisy_world.graph, seed=7)
    other = reversed_anisotropic_variant(noisy_world.graph, seed=8)
    np.testing.assert_array_equal(first.information, again.information)
    np.testing.assert_array_equal(first.measurements, again.measurements)
    assert not np.allclose(first.information, other.information)


def test_variant_of_a_real_graph_reverses_its_loops():
    from optimizer.graph_files import read_graph

    graph = read_graph(shared_file("posegraphs/2d/FR079.g2o")).graph
    variant = reversed_anisotropic_variant(graph, seed=0)
    loops = loop_closures(graph)
    assert np.all(variant.edge_from[loops] > variant.edge_to[loops])
    # z'·z is the identity for every reversed loop closure.
    product = se2.compose(variant.measurements[loops], graph.measurements[loops])
    np.testing.assert_allclose(product, 0.0, atol=1e-9)
    # FR079's loop closures span metres, so a wrong adjoint would couple translation and heading: carried
    # back to a's frame, the information must be the documented one (no cross terms, θθ unchanged).
    forward_adjoint = se2.adjoint(graph.measurements[loops])
    forward = np.einsum("mji,mjk,mkl->mil", forward_adjoint, variant.information[loops], forward_adjoint)
    scale = np.abs(forward).max(axis=(1, 2))
    np.testing.assert_allclose(forward[:, :2, 2] / scale[:, None], 0.0, atol=1e-9)
    np.testing.assert_allclose(forward[:, 2, 2], graph.information[loops, 2, 2], rtol=1e-9)
    translation_eigenvalues = np.linalg.eigvalsh(forward[:, :2, :2])
    ratio = translation_eigenvalues[:, 1] / translation_eigenvalues[:, 0]
    assert np.all((ratio > 0.99 * ANISOTROPY_RANGE[0]) & (ratio < 1.01 * ANISOTROPY_RANGE[1]))


def test_variant_needs_loop_closures():
    chain = generate_grid_world(30, seed=0, loop_probability=0.0)
    with pytest.raises(GraphError):
        reversed_anisotropic_variant(chain.graph, seed=0)


def test_false_loops_are_appended_non_consecutive_distinct_with_true_loop_information(noisy_world):
    graph = noisy_world.graph
    noisy = with_false_loops(graph, 200, seed=3)
    assert noisy.num_edges == graph.num_edges + 200
    for array in ("edge_from", "edge_to", "measurements", "information"):
        np.testing.assert_array_equal(getattr(noisy, array)[: graph.num_edges], getattr(graph, array))
    a = noisy.edge_from[graph.num_edges:]
    b = noisy.edge_to[graph.num_edges:]
    assert np.all(np.abs(b - a) > 1)
    assert np.all((a >= 0) & (b < graph.num_poses))
    assert len({(int(x), int(y)) for x, y in zip(a, b, strict=True)}) == 200
    true_informations = np.unique(graph.information[loop_closures(graph)].reshape(-1, 9), axis=0)
    false_informations = noisy.information[graph.num_edges:].reshape(-1, 9)
    assert all(np.any(np.all(info == true_informations, axis=1)) for info in false_informations)
    measurements = noisy.measurements[graph.num_edges:]
    half_extent = 0.5 * np.max(np.ptp(graph.poses[:, :2], axis=0))
    assert np.all(np.abs(measurements[:, :2]) <= half_extent)
    assert np.all((measurements[:, 2] >= -np.pi) & (measurements[:, 2] < np.pi))
    # Random, not all near the truth: most false loops have a large error at the ground truth.
    false_only = PoseGraph(graph.poses, a, b, measurements, noisy.information[graph.num_edges:],
                           graph.vertex_ids)
    assert np.median(np.linalg.norm(edge_errors(false_only, noisy_world.ground_truth)[:, :2], axis=1)) > 1.0


def test_false_loops_are_reproducible_and_scored_on_true_edges(noisy_world):
    graph = noisy_world.graph
    first = with_false_loops(graph, 50, seed=9)
    again = with_false_loops(graph, 50, seed=9)
    other = with_false_loops(graph, 50, seed=10)
    np.testing.assert_array_equal(first.edge_from, again.edge_from)
    np.testing.assert_array_equal(first.measurements, again.measurements)
    assert not np.array_equal(first.edge_from, other.edge_from)
    truth = noisy_world.ground_truth
    assert true_edges_chi2(graph, truth) == pytest.approx(chi2(graph, truth))
    assert chi2(first, truth) > true_edges_chi2(graph, truth)
    with pytest.raises(GraphError):
        true_edges_chi2(graph, truth[:-1])


def test_false_loops_of_m3500_copy_its_loop_information():
    from optimizer.graph_files import read_graph

    graph = read_graph(shared_file("posegraphs/2d/M3500.g2o")).graph
    noisy = with_false_loops(graph, 100, seed=0)
    true_informations = np.unique(graph.information[loop_closures(graph)].reshape(-1, 9), axis=0)
    for info in noisy.information[graph.num_edges:].reshape(-1, 9):
        assert np.any(np.all(info == true_informations, axis=1))


def test_noisy_manhattan_has_m3500_size_and_the_asked_heading_noise():
    world = noisy_manhattan(sigma_theta=0.3, seed=1)
    assert world.graph.num_poses == 3500
    odometry = world.graph.is_odometry
    errors = edge_errors(world.graph, world.ground_truth)[odometry]
    assert np.std(errors[:, 2]) == pytest.approx(0.3, rel=0.05)
    assert np.std(errors[:, 0]) == pytest.approx(0.02, rel=0.05)
    expected_information = np.diag(1 / np.array([0.02, 0.02, 0.3]) ** 2)
    np.testing.assert_allclose(world.graph.information[odometry][0], expected_information)
    again = noisy_manhattan(sigma_theta=0.3, seed=1)
    np.testing.assert_array_equal(world.graph.measurements, again.graph.measurements)


def test_odometry_chain_composes_the_odometry_in_either_direction(noisy_world):
    graph = noisy_world.graph
    # The generated estimate is the dead reckoning of the odometry: the chain must reproduce it.
    np.testing.assert_allclose(odometry_chain(graph), graph.poses, atol=1e-9)
    odometry = np.flatnonzero(graph.is_odometry)
    flipped = odometry[::2]
    measurements = graph.measurements.copy()
    measurements[flipped] = se2.inverse(measurements[flipped])
    edge_from, edge_to = graph.edge_from.copy(), graph.edge_to.copy()
    edge_from[flipped], edge_to[flipped] = graph.edge_to[flipped], graph.edge_from[flipped]
    reversed_graph = PoseGraph(graph.poses, edge_from, edge_to, measurements, graph.information,
                               graph.vertex_ids)
    np.testing.assert_allclose(odometry_chain(reversed_graph), graph.poses, atol=1e-9)


def test_odometry_chain_needs_every_consecutive_pair(noisy_world):
    graph = noisy_world.graph
    keep = ~((graph.edge_from == 10) & (graph.edge_to == 11))
    broken = PoseGraph(graph.poses, graph.edge_from[keep], graph.edge_to[keep], graph.measurements[keep],
                       graph.information[keep], graph.vertex_ids)
    with pytest.raises(GraphError, match="10 and 11"):
        odometry_chain(broken)


def test_gtsam_bundled_graphs_are_found_in_the_wheels_data_folder_and_only_there(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package = tmp_path / "gtsam"
    (package / "Data").mkdir(parents=True)
    origin = package / "__init__.py"
    origin.write_text("")
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name: importlib.machinery.ModuleSpec(name, None, origin=str(origin)))
    assert benchmark_graphs.gtsam_bundled_graphs() == []
    (package / "Data" / "w10000.graph").write_text("VERTEX2 0 0 0 0\n")
    assert benchmark_graphs.gtsam_bundled_graphs() == [package / "Data" / "w10000.graph"]
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    assert benchmark_graphs.gtsam_bundled_graphs() == []
