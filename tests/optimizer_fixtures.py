"""Fixtures shared by the optimizer tests: a multi-lap square graph, helpers for polish generators and a
block-sparse matrix shaped like a pose graph's normal equations."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
import scipy.sparse as sp

from optimizer import se2
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.polish import PolishStatus


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
