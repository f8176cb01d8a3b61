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
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.sgd_kernels import (
    sgd_iteration_linear,
    sgd_iteration_tree,
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
) -> Iterator[Iteration]:
    """Run `iterations` SGD iterations from `poses` (default: the graph's estimate), yielding each one.

    `implementation="tree"` is the O(log N)-per-constraint production path; `"linear"` is Algorithm 1
    (O(N) per constraint), the oracle the tree is tested against. `first_iteration` > 1 continues a
    schedule (a smaller learning rate) when re-optimizing an already aligned graph.
    """
    if iterations < 0:
        raise OptimizerError(f"iterations must be >= 0, got {iterations}")
    if first_iteration < 1:
        raise OptimizerError(f"first_iteration must be >= 1, got {first_iteration}")
    state = np.array(graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if state.shape != graph.poses.shape:
        raise OptimizerError(f"expected poses of shape {graph.poses.shape}, got {state.shape}")
    edges = (graph.edge_from, graph.edge_to)
    n = graph.num_poses
    gamma = np.empty(3)
    if implementation == "linear":
        stiffness = np.empty((n, 3))
    elif implementation == "tree":
        tree = np.empty((2 * tree_size(n), 3, 3))
    else:
        raise OptimizerError(f"unknown SGD implementation {implementation!r}")

    for offset in range(iterations):
        t = first_iteration + offset
        if implementation == "linear":
            if offset == 0 or recomputes_stiffness(t):
                stiffness_linear(state, *edges, graph.information, stiffness, gamma)
            sgd_iteration_linear(state, *edges, graph.measurements, graph.information, stiffness, gamma, t)
        else:
            if offset == 0 or recomputes_stiffness(t):
                stiffness_tree(state, *edges, graph.information, tree, gamma)
            sgd_iteration_tree(state, *edges, graph.measurements, graph.information, tree,
                               gamma, t)
        if not np.all(np.isfinite(state[-1])):
            raise OptimizerError(f"SGD diverged at iteration {t} (non-finite poses)")
        poses_out = state.copy()
        poses_out[:, 2] = se2.wrap_angle(poses_out[:, 2])
        yield Iteration("sgd", offset + 1, poses_out, chi2(graph, poses_out))
