"""Fixtures shared by the optimizer tests: a multi-lap square graph, a small graph with edges in both
directions, helpers for polish generators, a block-sparse matrix shaped like a pose graph's normal
equations, the dense normal equations of a graph, and the scaled block system of a grid world."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
import scipy.sparse as sp

from optimizer import se2
from optimizer.block_normal_equations import BlockPattern, add_to_diagonal, scale_blocks
from optimizer.damped_solvers import Linearisation
from optimizer.graph import PoseGraph
from optimizer.gridworld import generate_grid_world
from optimizer.iteration import Iteration
from optimizer.polish import PolishStatus, _linearise, edge_jacobians


def square_loop_graph(noise: float, seed: int = 0, laps: int = 3, side: int = 5,
                 reverse_every: int = 0) -> tuple[PoseGraph, np.ndarray]:
    """A robot driving `laps` laps of a square; odometry edges plus loop closures to the first lap.

    With `reverse_every` = k > 0, every k-th edge is stored from its later to its earlier pose (measured
    that way, not turned around)."""
    rng = np.random.default_rng(seed)
    per_lap = 4 * side
    steps = np.tile(np.array([1.0, 0.0, 0.0]), (laps * per_lap, 1))
    steps[side - 1 :: side, 2] = np.pi / 2
    truth = se2.compose_chain(steps)
    n = len(truth)
    edges = [(i, i + 1) for i in range(n - 1)]
    edges += [(i, i + per_lap * lap) for lap in range(1, laps) for i in range(0, per_lap, 3)
              if i + per_lap * lap < n]
    if reverse_every:
        edges = [(b, a) if k % reverse_every == 0 else (a, b) for k, (a, b) in enumerate(edges)]
    a = np.array([e[0] for e in edges])
    b = np.array([e[1] for e in edges])
    z = se2.relative(truth[a], truth[b]) + rng.normal(0.0, noise, (len(edges), 3)) * [1.0, 1.0, 0.2]
    info = np.tile(np.diag([100.0, 100.0, 400.0]), (len(edges), 1, 1))
    steps = se2.relative(truth[:-1], truth[1:]) + rng.normal(0.0, noise, (n - 1, 3)) * [1.0, 1.0, 0.2]
    odometry = se2.compose_chain(steps)
    return PoseGraph.build(np.arange(n), odometry, a, b, z, info), truth


def run(polish: Generator[Iteration, None, PolishStatus]) -> tuple[list[Iteration], PolishStatus]:
    """Every yielded iteration and the generator's return value."""
    iterations: list[Iteration] = []

    def collect() -> Generator[Iteration, None, PolishStatus]:
        return (yield from polish)

    generator = collect()
    while True:
        try:
            iterations.append(next(generator))
        except StopIteration as stop:
            return iterations, stop.value


def random_information(rng: np.random.Generator, count: int) -> np.ndarray:
    factors = rng.normal(size=(count, 3, 3))
    return factors @ np.swapaxes(factors, 1, 2) + 0.5 * np.eye(3)


def symmetric_block_matrix(size: int, rows: int, seed: int) -> sp.bsr_matrix:
    """A symmetric, diagonally dominant BSR matrix of `rows` block rows with random off-diagonal blocks
    (a chain and random pairs, as the poses of a pose graph)."""
    rng = np.random.default_rng(seed)
    first = np.concatenate([np.arange(rows - 1), rng.integers(0, rows, 2 * rows)])
    second = np.concatenate([np.arange(1, rows), rng.integers(0, rows, 2 * rows)])
    keep = first != second
    first, second = first[keep], second[keep]
    blocks = rng.normal(size=(len(first), size, size))
    dense_rows = np.repeat(first * size, size * size) + np.tile(np.repeat(np.arange(size), size), len(first))
    dense_cols = np.repeat(second * size, size * size) + np.tile(np.tile(np.arange(size), size), len(first))
    off = sp.coo_matrix((blocks.reshape(-1), (dense_rows, dense_cols)), shape=(rows * size,) * 2).tocsr()
    dominance = 4.0 * size * np.abs(off + off.T).sum(axis=1).max()
    matrix = off + off.T + sp.identity(rows * size) * dominance
    return sp.bsr_matrix(matrix, blocksize=(size, size))


def tangled_graph(seed: int) -> PoseGraph:
    """Seven poses; edges in both directions (a > b kept as given), a duplicate, edges at the anchor."""
    rng = np.random.default_rng(seed)
    poses = rng.uniform([-4, -4, -np.pi], [4, 4, np.pi], size=(7, 3))
    edge_from = np.array([0, 1, 2, 3, 4, 5, 6, 3, 5, 5, 2])
    edge_to = np.array([1, 2, 3, 4, 5, 6, 0, 1, 2, 2, 6])
    measurements = rng.uniform([-2, -2, -np.pi], [2, 2, np.pi], size=(len(edge_from), 3))
    return PoseGraph(poses, edge_from, edge_to, measurements, random_information(rng, len(edge_from)),
                     np.arange(7))


def dense_system(graph: PoseGraph) -> tuple[np.ndarray, np.ndarray]:
    """H = JᵀΩJ and g = JᵀΩe from the stacked per-edge Jacobians, anchor columns dropped."""
    errors, jac_a, jac_b = edge_jacobians(graph)
    jacobian = np.zeros((3 * graph.num_edges, 3 * graph.num_poses))
    for k, (a, b) in enumerate(zip(graph.edge_from, graph.edge_to, strict=True)):
        jacobian[3 * k:3 * k + 3, 3 * a:3 * a + 3] += jac_a[k]
        jacobian[3 * k:3 * k + 3, 3 * b:3 * b + 3] += jac_b[k]
    omega = sp.block_diag(list(graph.information)).toarray()
    jacobian = jacobian[:, 3:]
    return jacobian.T @ omega @ jacobian, jacobian.T @ omega @ errors.reshape(-1)


def scaled_system(num_poses: int) -> tuple[sp.bsr_matrix, Linearisation]:
    """S·H·S + 1e-6·I of a grid world of `num_poses` at its file estimate, and its linearisation."""
    graph = generate_grid_world(num_poses, seed=6).graph
    pattern = BlockPattern.of(graph)
    linearisation = _linearise(graph, pattern, graph.poses)
    blocks = linearisation.hessian
    scale_blocks(blocks, pattern.indptr, pattern.indices, linearisation.scale)
    add_to_diagonal(blocks, pattern.diagonal_block, 1e-6)
    size = 3 * pattern.free
    return sp.bsr_matrix((blocks, pattern.indices, pattern.indptr), shape=(size, size)), linearisation


def system_and_candidates(num_poses: int) -> tuple[sp.bsr_matrix, np.ndarray]:
    """`scaled_system` and the rigid motions as near-null candidates (in the scaled variables)."""
    matrix, linearisation = scaled_system(num_poses)
    poses = linearisation.poses[1:]
    motions = np.zeros((poses.shape[0], 3, 4))
    motions[:, 0, 0] = motions[:, 1, 1] = motions[:, 2, 2] = motions[:, 2, 3] = 1.0
    motions[:, 0, 3] = -poses[:, 1]
    motions[:, 1, 3] = poses[:, 0]
    return matrix, (motions / linearisation.scale.reshape(-1, 3)[:, :, None]).reshape(-1, 4)
