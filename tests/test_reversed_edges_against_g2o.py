"""Edges stored from the later to the earlier pose are solved as the file states them: g2o, an independent
implementation of the same objective (e = t2v(z⁻¹·x_a⁻¹·x_b)), agrees with our χ² and finds nothing lower."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from optimizer import se2
from optimizer.cost import chi2
from optimizer.graph import PoseGraph
from optimizer.graph_files import read_graph, write_g2o
from optimizer.gridworld import generate_grid_world
from optimizer.solve import optimize

g2o = pytest.importorskip("g2opy", reason="g2opy (the test extras) checks our objective independently")


Edges = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(edge_from, edge_to, measurements, information) as the file states them."""


def _reversed_anisotropic(seed: int) -> tuple[PoseGraph, Edges]:
    """A noisy city whose loop closures are measured from the later pose, with information 10⁴ times
    stronger along one random direction than across it (the case where flipping an edge changes the
    problem)."""
    world = generate_grid_world(400, seed=seed, odometry_sigma=(0.02, 0.02, 0.02))
    graph = world.graph
    rng = np.random.default_rng(seed)
    loops = ~graph.is_odometry
    edge_from = np.where(loops, graph.edge_to, graph.edge_from)
    edge_to = np.where(loops, graph.edge_from, graph.edge_to)
    truth = se2.relative(world.ground_truth[edge_from], world.ground_truth[edge_to])
    noise = rng.normal(scale=[0.05, 0.05, 0.02], size=truth.shape)
    measurements = np.where(loops[:, None], se2.compose(truth, noise), graph.measurements)
    angle = rng.uniform(0, np.pi, size=len(loops))
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    anisotropic = np.zeros_like(graph.information)
    anisotropic[:, :2, :2] = np.einsum("mij,j,mkj->mik", rotation, [4e4, 4.0], rotation)
    anisotropic = 0.5 * (anisotropic + np.swapaxes(anisotropic, 1, 2))  # files store the upper triangle
    anisotropic[:, 2, 2] = 2500.0
    information = np.where(loops[:, None, None], anisotropic, graph.information)
    edges = (edge_from, edge_to, measurements, information)
    return PoseGraph.build(np.arange(graph.num_poses), graph.poses, *edges), edges


def _g2o_graph(edges: Edges, poses: np.ndarray) -> tuple[object, list[object]]:
    """g2o's problem built from the edges as given, not from our PoseGraph."""
    optimizer = g2o.SparseOptimizer()
    optimizer.set_algorithm(g2o.OptimizationAlgorithmLevenberg(g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())))
    vertices = []
    for index, pose in enumerate(poses):
        vertex = g2o.VertexSE2()
        vertex.set_id(index)
        vertex.set_estimate(g2o.SE2(*pose))
        vertex.set_fixed(index == 0)
        optimizer.add_vertex(vertex)
        vertices.append(vertex)
    for a, b, z, omega in zip(edges[0].tolist(), edges[1].tolist(), edges[2], edges[3], strict=True):
        edge = g2o.EdgeSE2()
        edge.set_vertex(0, vertices[a])
        edge.set_vertex(1, vertices[b])
        edge.set_measurement(g2o.SE2(*z))
        edge.set_information(omega)
        optimizer.add_edge(edge)
    optimizer.initialize_optimization()
    return optimizer, vertices


def _g2o_chi2(edges: Edges, poses: np.ndarray) -> float:
    optimizer, _ = _g2o_graph(edges, poses)
    optimizer.compute_active_errors()
    return float(optimizer.chi2())


@pytest.mark.parametrize("seed", [0, 1])
def test_our_optimum_of_reversed_anisotropic_edges_is_g2os(seed: int, tmp_path: Path) -> None:
    graph, edges = _reversed_anisotropic(seed)
    assert graph.is_reversed.sum() > 50
    run = optimize(graph)
    poses = list(run)[-1].poses
    assert run.result.converged
    ours = chi2(graph, poses)
    # Same objective: g2o evaluates our result to our χ²...
    assert _g2o_chi2(edges, poses) == pytest.approx(ours, rel=1e-9)
    # ...and its own Levenberg–Marquardt, started there, finds nothing lower: a minimum of the file's problem.
    optimizer, vertices = _g2o_graph(edges, poses)
    optimizer.optimize(50)
    refined = np.array([vertex.estimate().vector() for vertex in vertices])
    assert chi2(graph, refined) >= ours * (1 - 1e-6)
    # The written file holds the input's edges, as stored, around our poses.
    write_g2o(tmp_path / "out.g2o", graph, poses)
    written = read_graph(tmp_path / "out.g2o").graph
    for name, given in zip(("edge_from", "edge_to", "measurements", "information"), edges, strict=True):
        np.testing.assert_array_equal(getattr(written, name), given)
