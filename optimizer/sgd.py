"""Stochastic gradient descent on the incremental-pose state space: Olson, Leonard & Teller (2006).

The algorithm exactly as the paper states it (section III, Algorithm 1): residuals in the global frame,
W = (R Σ Rᵀ)⁻¹ with R = Rot(P_a), Jacobi preconditioner M ≈ diag(JᵀΣ⁻¹J), learning rate α = 1/(γ t)
with γ the per-dimension minimum of diag(W), steps clamped to the residual, constraints visited in their
stored order, M recomputed at iterations 1, 2, 4, 8, …
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph, read_only
from optimizer.iteration import Iteration
from optimizer.sgd_kernels import (
    TREE_BLOCK,
    sgd_iteration_linear,
    sgd_iteration_tree,
    spanning_count,
    stiffness_linear,
    stiffness_tree,
    tree_size,
)

Implementation = Literal["tree", "linear"]


def recomputes_stiffness(iteration: int) -> bool:
    """M is recomputed at iterations 1, 2, 4, 8, …: the map's rough alignment settles early."""
    return iteration >= 1 and iteration & (iteration - 1) == 0


def sgd(
    graph: PoseGraph,
    iterations: int,
    poses: NDArray[np.float64] | None = None,
    *,
    implementation: Implementation = "tree",
    first_iteration: int = 1,
    tree_block: int = TREE_BLOCK,
) -> Iterator[Iteration]:
    """Run `iterations` SGD iterations from `poses` (default: the graph's estimate), yielding each one.

    `implementation="tree"` is the O(log N)-per-constraint production path; `"linear"` is Algorithm 1
    (O(N) per constraint), the oracle the tree is tested against. `first_iteration` > 1 continues a
    schedule (a smaller learning rate) when re-optimizing an already aligned graph. `tree_block` is the
    number of increments per leaf of the tree (a memory/speed trade-off; results agree to rounding).

    Memory beyond the graph: the tree and its weights (`tree_block` = 8: about 43 bytes per pose), each
    loop's total weight (24 bytes per constraint whose loop spans more than one block, e.g. a loop
    closure), the yielded poses and the next iteration's: the tree is one pass ahead of its yields (a pass
    sums the χ² of the poses it starts from, the iteration it then yields).
    """
    if iterations < 0:
        raise OptimizerError(f"iterations must be >= 0, got {iterations}")
    if first_iteration < 1:
        raise OptimizerError(f"first_iteration must be >= 1, got {first_iteration}")
    if tree_block < 1:
        raise OptimizerError(f"tree_block must be >= 1, got {tree_block}")
    if implementation not in ("tree", "linear"):
        raise OptimizerError(f"unknown SGD implementation {implementation!r}")
    # The tree only reads its starting poses, so the graph's own (read-only) need no copy.
    start = graph.poses if poses is None and implementation == "tree" else np.array(
        graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if start.shape != graph.poses.shape:
        raise OptimizerError(f"expected poses of shape {graph.poses.shape}, got {start.shape}")
    if implementation == "linear":
        yield from _sgd_linear(graph, iterations, start, first_iteration)
    else:
        yield from _sgd_tree(graph, iterations, start, first_iteration, tree_block)


def _sgd_tree(graph: PoseGraph, iterations: int, base: NDArray[np.float64], first_iteration: int,
              block: int) -> Iterator[Iteration]:
    """Each iteration is yielded once the next pass has run: that pass sums the χ² of its starting poses
    (the iteration's) as it reads the constraints, instead of a separate χ² reading them all again. The
    last iteration's χ² is computed on its own. A receiver that stops early leaves one pass unused."""
    n = graph.num_poses
    edges = (graph.edge_from, graph.edge_to)
    gamma = np.empty(3)
    weights = np.empty((n, 3))
    tree = np.empty((2 * tree_size(n, block), 3, 3))
    spans = np.empty((spanning_count(*edges, block), 3))
    for offset in range(iterations):
        t = first_iteration + offset
        # Read-only, as the graph's own poses are: one compiled signature of the kernels for both.
        frozen = read_only(base)
        # The new poses' array is the kernels' `amounts` scratch until the pass writes the poses over it
        # (see `sgd_iteration_tree`): one (N, 3) array less.
        poses = np.empty_like(base)
        if offset == 0 or recomputes_stiffness(t):
            stiffness_tree(frozen, *edges, graph.information, weights, poses, tree, gamma, block, spans)
        base_chi2 = sgd_iteration_tree(frozen, *edges, graph.measurements, graph.information, weights,
                                       poses, tree, gamma, t, block, poses, offset > 0, spans)
        if offset > 0:
            yield Iteration("sgd", offset, base, base_chi2)
        if not np.all(np.isfinite(poses[-1])):
            raise OptimizerError(f"SGD diverged at iteration {t} (non-finite poses)")
        base = poses  # θ wrapped: the same poses for the SGD, whose angles only enter through sin, cos, wrap
    if iterations > 0:
        yield Iteration("sgd", iterations, base, chi2(graph, base))


def _sgd_linear(graph: PoseGraph, iterations: int, state: NDArray[np.float64],
                first_iteration: int) -> Iterator[Iteration]:
    edges = (graph.edge_from, graph.edge_to)
    gamma = np.empty(3)
    stiffness = np.empty((graph.num_poses, 3))
    for offset in range(iterations):
        t = first_iteration + offset
        if offset == 0 or recomputes_stiffness(t):
            stiffness_linear(state, *edges, graph.information, stiffness, gamma)
        sgd_iteration_linear(state, *edges, graph.measurements, graph.information, stiffness, gamma, t)
        if not np.all(np.isfinite(state[-1])):
            raise OptimizerError(f"SGD diverged at iteration {t} (non-finite poses)")
        poses = state.copy()
        poses[:, 2] = se2.wrap_angle(poses[:, 2])
        yield Iteration("sgd", offset + 1, poses, chi2(graph, poses))
