"""Tree-parameterised SGD: the SGD of Olson et al. (2006) on a spanning tree's paths, as in TORO.

Grisetti, Stachniss, Grzonka & Burgard (RSS 2007) replace Olson's incremental state (the odometry
chain: a loop closure from pose 10 to pose 3000 moves 2990 increments) by differences along a spanning
tree of the constraint graph: a constraint then moves only the parameters on the tree path between its
poses, which a breadth-first tree keeps short. The rest is the paper's SGD: residuals and W = R Ω Rᵀ in
the global frame, Jacobi preconditioner M (summed over paths, recomputed at iterations 1, 2, 4, 8, …),
steps clamped to the residual, learning rate 1/(γ t). One choice differs from TORO's default, measured
(see benchmarks/strong_sgd_bench.py): constraints are visited by path length, shortest first (TORO's
alternative order), so each loop is closed over local structure that is already consistent; by the depth
of the path's top node (TORO's default) ends up to 10× higher on grid worlds with heavy heading noise.
A smaller learning rate (`learning_rate_scale` = 2) lowers χ² at iteration 100 on the large graphs
(M3500 300 instead of 309) but slows small loops to a polynomial crawl (pg1.g2o: 3.9 instead of 7e-7),
so the paper's rate stays the default.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.sgd import recomputes_stiffness
from optimizer.sgd_tree_kernels import (
    lowest_common_ancestors,
    parameters_from_poses,
    poses_from_parameters,
    tree_depths,
    tree_sgd_iteration,
    tree_stiffness,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

STAGE = "sgd-tree"
DEFAULT_LEARNING_RATE_SCALE = 1.0


@dataclass(frozen=True, eq=False)
class SpanningTree:
    """A breadth-first spanning tree of a pose graph's constraints and each constraint's path in it."""

    root: int
    order: IntArray
    """(N,) the poses in breadth-first order (every parent before its children)."""
    parent: IntArray
    """(N,) parent of every pose; the root's is itself."""
    depth: IntArray
    """(N,) number of tree edges between each pose and the root."""
    top: IntArray
    """(M,) lowest common ancestor of each constraint's two poses: where its path turns."""
    path_length: IntArray
    """(M,) number of parameters each constraint moves: depth(a) + depth(b) − 2·depth(top)."""


def spanning_tree(graph: PoseGraph, root: int = 0) -> SpanningTree:
    """Breadth-first tree from `root` over the undirected constraint graph: every path to the root is a
    shortest one in constraint hops, which keeps every constraint's path short."""
    n = graph.num_poses
    adjacency = coo_matrix((np.ones(graph.num_edges, dtype=np.int8), (graph.edge_from, graph.edge_to)),
                           shape=(n, n)).tocsr()
    order, predecessors = breadth_first_order(adjacency, root, directed=False, return_predecessors=True)
    if len(order) != n:
        raise OptimizerError(f"the graph is not connected: {n - len(order)} poses unreachable from {root}")
    parent = predecessors.astype(np.int64)
    parent[root] = root
    order = order.astype(np.int64)
    depth = tree_depths(order, parent)
    top = lowest_common_ancestors(graph.edge_from, graph.edge_to, parent, depth)
    path_length = depth[graph.edge_from] + depth[graph.edge_to] - 2 * depth[top]
    return SpanningTree(root, order, parent, depth, top, path_length)


def sgd_tree(
    graph: PoseGraph,
    iterations: int,
    poses: FloatArray | None = None,
    *,
    first_iteration: int = 1,
    learning_rate_scale: float = DEFAULT_LEARNING_RATE_SCALE,
) -> Iterator[Iteration]:
    """Run `iterations` tree-parameterised SGD iterations from `poses` (default: the graph's estimate).

    Yields Iteration("sgd-tree", k, poses, χ²) after every iteration k ≥ 1; pose 0 stays fixed.
    `first_iteration` > 1 continues a schedule (a smaller learning rate), as in `optimizer.sgd.sgd`;
    `learning_rate_scale` s sets the learning rate 1/(s γ t) (s = 1 is the paper's).
    """
    if iterations < 0:
        raise OptimizerError(f"iterations must be >= 0, got {iterations}")
    if first_iteration < 1:
        raise OptimizerError(f"first_iteration must be >= 1, got {first_iteration}")
    if not learning_rate_scale > 0.0:
        raise OptimizerError(f"learning_rate_scale must be > 0, got {learning_rate_scale}")
    state = np.array(graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if state.shape != graph.poses.shape:
        raise OptimizerError(f"expected poses of shape {graph.poses.shape}, got {state.shape}")
    if not np.all(np.isfinite(state)):
        raise OptimizerError("the starting poses contain non-finite values")
    if iterations == 0:
        return
    tree = spanning_tree(graph)
    visit_order = np.argsort(tree.path_length, kind="stable").astype(np.int64)
    params = np.empty_like(state)
    parameters_from_poses(state, tree.parent, tree.root, params)
    poses_from_parameters(params, tree.parent, tree.order, state)
    stiffness = np.empty_like(state)
    gamma = np.empty(3)

    for offset in range(iterations):
        t = first_iteration + offset
        if offset == 0 or recomputes_stiffness(t):
            tree_stiffness(state, graph.edge_from, graph.edge_to, tree.top, graph.information, tree.parent,
                           stiffness, gamma)
        tree_sgd_iteration(params, graph.edge_from, graph.edge_to, tree.top, visit_order, graph.measurements,
                           graph.information, tree.parent, tree.root, stiffness, gamma,
                           learning_rate_scale, t)
        poses_from_parameters(params, tree.parent, tree.order, state)
        if not np.all(np.isfinite(state)):
            raise OptimizerError(f"tree SGD diverged at iteration {t} (non-finite poses)")
        poses_out = state.copy()
        poses_out[:, 2] = se2.wrap_angle(poses_out[:, 2])
        yield Iteration(STAGE, offset + 1, poses_out, chi2(graph, poses_out))
