"""Tree-parameterised SGD: the SGD of Olson et al. (2006) on a spanning tree's paths, as in TORO.

Grisetti, Stachniss, Grzonka & Burgard (RSS 2007) replace Olson's incremental state (the odometry
chain: a loop closure from pose 10 to pose 3000 moves 2990 increments) by differences along a spanning
tree of the constraint graph: a constraint then moves only the parameters on the tree path between its
poses. The rest is the paper's SGD: residuals and W = R Ω Rᵀ in the global frame, Jacobi preconditioner
M (summed over paths, recomputed at iterations 1, 2, 4, 8, …), steps clamped to the residual, learning
rate 1/(γ t).

Two trees, each with the constraint order and schedule measured best for it (benchmarks/strong_sgd_bench.py):
- "incremental", TORO's default tree (`buildSimpleTree`): the parent of pose v is the lowest-numbered pose
  it shares a constraint with, so a pose that revisits a place hangs from the first visit. Constraints are
  visited by the depth of their path's top node, shallowest first, and the learning rate's counter starts
  at 2, all as TORO does (its `propagateErrors` increments the counter before the first pass). On M3500 this
  is TORO's 248.8 after 100 iterations (the breadth-first tree: 309). Unlike TORO, poses are summed
  exactly from the root at every visit (TORO reads the top's cached pose, which may be stale), and M is
  recomputed on the paper's schedule rather than every iteration (no difference on M3500).
- "breadth-first": shortest paths to pose 0 in constraint hops; constraints visited by path length,
  shortest first, so each loop is closed over local structure that is already consistent. Far better
  than the incremental tree on FR079 (136 against 485 after 100 iterations), INTEL (1.1e3 against 1.3e5)
  and generated worlds whose loop closures are less certain than their odometry (1.7e4 against 1.0e5).
- "auto" (default) takes the incremental tree only where its paths are shorter in total (TORO's
  "complexity of an iteration", the parameters one pass moves) and, in every dimension, carry less
  variance relative to their constraints' own (`path_variance`): the incremental tree hangs revisits from
  loop closures, which hurts where those are less certain than odometry. Breadth-first otherwise, and on
  ties. Neither rule alone separates the graphs measured (path length alone picks the incremental tree
  on generated worlds, path variance alone on INTEL).

Like the paper's, the heading step follows an approximate gradient: it ignores that θ_a turns the measured
translation R(θ_a)·z, so the descent settles where that gradient vanishes, not at the minimum (pg1.g2o:
χ² 6.87·10⁻⁷ after 10⁴ iterations of either SGD, its minimum 1.54·10⁻⁸). Once an iteration leaves χ²
all but unchanged (`settled`: the descent has reached that point), every later heading step takes the
turn into account (`optimizer.sgd_tree_kernels.tree_sgd_iteration`'s `coupled_headings`). After 10⁴
iterations: pg1.g2o 4.8·10⁻⁸ (3.68·10⁻⁷ already after 100, the paper's SGD 6.80·10⁻⁷), pose2example
1.214 against 1.302 (minimum 1.099), w100 1.1686 against 1.1948 (minimum 1.1378). Not from the start: far
from the minimum the turn's linearisation misleads (pg1.g2o from its file estimate, coupled throughout:
χ² 435 after 100 iterations). Nor where it misleads later: a coupled iteration that raises χ² by more than
`SETTLED_CHANGE` of it returns the run to the paper's heading step for good (M3500 settles at iteration
683; coupled from there on its χ² rose from 235.4 to 245 by iteration 800 and was 240.9 at 1000, against
235.38 uncoupled; with the return 235.35).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

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
    path_variance_ratios,
    poses_from_parameters,
    subtree_intervals,
    tree_depths,
    tree_sgd_iteration,
    tree_stiffness,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
TreeKind = Literal["auto", "breadth-first", "incremental"]
TREE_KINDS: tuple[str, ...] = ("auto", "breadth-first", "incremental")

STAGE = "sgd-tree"
DEFAULT_LEARNING_RATE_SCALE = 1.0
_COUNTER_OFFSET = {"breadth-first": 0, "incremental": 1}
"""Added to the iteration number in the learning rate 1/(γ t): TORO's counter starts at 2."""


SETTLED_CHANGE = 1e-5
"""An iteration that changes χ² by less than this fraction of it, either way, has settled (`settled`)."""


def settled(previous_chi2: float, chi2_now: float) -> bool:
    """Whether the descent has reached the point where its approximate gradient vanishes: an iteration
    changed χ² by less than `SETTLED_CHANGE` of its value.

    Not merely an iteration that fails to lower χ²: the descent's transients (its first, clamped
    iterations; after a recomputation of M; alternating visits) raise χ² by 5.5·10⁻⁴ of it or more on every
    graph of benchmarks/strong_sgd_bench.py, and the coupled heading step started there (INTEL at iteration
    6, the heavy-heading-noise worlds at 2–5) was misled by linearising large turns: INTEL +1.7 % after 30
    iterations, and after the paper's SGD in the default method, LM from the σθ = 0.2 and 0.3 worlds in
    worse minima. pg1.g2o's settled descent changes χ² by 1.6·10⁻⁶ … 10⁻⁵ of it per iteration.
    """
    return abs(chi2_now - previous_chi2) < SETTLED_CHANGE * previous_chi2


@dataclass(frozen=True, eq=False)
class SpanningTree:
    """A spanning tree of a pose graph's constraints and each constraint's path in it."""

    kind: str
    """"breadth-first" or "incremental" (see the module's docstring)."""
    root: int
    order: IntArray
    """(N,) the poses with every parent before its children."""
    parent: IntArray
    """(N,) parent of every pose; the root's is itself."""
    depth: IntArray
    """(N,) number of tree edges between each pose and the root."""
    top: IntArray
    """(M,) lowest common ancestor of each constraint's two poses: where its path turns."""
    path_length: IntArray
    """(M,) number of parameters each constraint moves: depth(a) + depth(b) − 2·depth(top)."""

    @property
    def total_path_length(self) -> int:
        """Parameters moved by one pass over all constraints."""
        return int(self.path_length.sum())

    def visit_order(self) -> IntArray:
        """Constraint indices in the order one iteration visits them (stable: ties keep the stored order)."""
        key = self.depth[self.top] if self.kind == "incremental" else self.path_length
        return np.argsort(key, kind="stable").astype(np.int64)


def _with_paths(kind: str, graph: PoseGraph, root: int, order: IntArray, parent: IntArray) -> SpanningTree:
    depth = tree_depths(order, parent)
    top = lowest_common_ancestors(graph.edge_from, graph.edge_to, parent, depth)
    path_length = depth[graph.edge_from] + depth[graph.edge_to] - 2 * depth[top]
    return SpanningTree(kind, root, order, parent, depth, top, path_length)


def breadth_first_tree(graph: PoseGraph, root: int = 0) -> SpanningTree:
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
    return _with_paths("breadth-first", graph, root, order.astype(np.int64), parent)


def incremental_tree(graph: PoseGraph) -> SpanningTree | None:
    """TORO's tree: each pose's parent is the lowest-numbered pose it shares a constraint with, if lower
    than itself. None when a pose other than 0 has no lower neighbour (the tree would be a forest)."""
    n = graph.num_poses
    parent = np.full(n, n, dtype=np.int64)
    np.minimum.at(parent, graph.edge_high, graph.edge_low)
    if np.count_nonzero(parent == n) != 1:
        return None
    parent[0] = 0
    # Parents are lower-numbered, so the pose order itself has every parent before its children.
    return _with_paths("incremental", graph, 0, np.arange(n, dtype=np.int64), parent)


def spanning_tree(graph: PoseGraph, kind: TreeKind = "auto") -> SpanningTree:
    """The tree of `kind`. "auto": the incremental tree if its paths are both shorter in total and, in
    every dimension, less uncertain relative to their constraints (`path_variance`); else breadth-first."""
    if kind not in TREE_KINDS:
        raise OptimizerError(f"unknown tree {kind!r}; expected one of {', '.join(TREE_KINDS)}")
    if kind == "breadth-first":
        return breadth_first_tree(graph)
    incremental = incremental_tree(graph)
    if kind == "incremental":
        if incremental is None:
            raise OptimizerError("no incremental tree: some pose has no constraint to a lower-numbered one")
        return incremental
    breadth_first = breadth_first_tree(graph)
    if (incremental is not None and incremental.total_path_length < breadth_first.total_path_length
            and np.all(path_variance(graph, incremental) < path_variance(graph, breadth_first))):
        return incremental
    return breadth_first


def path_variance(graph: PoseGraph, tree: SpanningTree) -> FloatArray:
    """(3,) per dimension, Σ over constraints of their path's variance over their own (see
    `optimizer.sgd_tree_kernels.path_variance_ratios`)."""
    out = np.empty(3)
    path_variance_ratios(tree.parent, graph.edge_from, graph.edge_to, tree.top, graph.information, out)
    return out


def sgd_tree(
    graph: PoseGraph,
    iterations: int,
    poses: FloatArray | None = None,
    *,
    first_iteration: int = 1,
    learning_rate_scale: float = DEFAULT_LEARNING_RATE_SCALE,
    tree: TreeKind = "auto",
    coupled_headings: bool = True,
) -> Iterator[Iteration]:
    """Run `iterations` tree-parameterised SGD iterations from `poses` (default: the graph's estimate).

    Yields Iteration("sgd-tree", k, poses, χ²) after every iteration k ≥ 1; pose 0 stays fixed.
    `first_iteration` > 1 continues a schedule (a smaller learning rate), as in `optimizer.sgd.sgd`;
    `learning_rate_scale` s sets the learning rate 1/(s γ t) (s = 1 is the paper's); `tree` chooses the
    spanning tree; `coupled_headings`=False keeps the paper's heading step throughout, even once the
    descent has settled (see the module's docstring). Whether a run is coupled is decided anew by each
    call (`optimizer.robust.robust_sgd` calls one iteration at a time: never coupled).
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
    spanning = spanning_tree(graph, tree)
    if iterations == 0:
        return
    visit_order = spanning.visit_order()
    counter_offset = _COUNTER_OFFSET[spanning.kind]
    params = np.empty_like(state)
    parameters_from_poses(state, spanning.parent, spanning.root, params)
    entry, exit_ = subtree_intervals(spanning.parent, spanning.root)
    sums = np.empty((len(state) + 1, 3))
    poses_from_parameters(params, spanning.parent, spanning.order, state)
    stiffness = np.empty_like(state)
    gamma = np.empty(3)

    coupled = False
    may_couple = coupled_headings
    previous_chi2 = np.inf
    for offset in range(iterations):
        t = first_iteration + offset
        if offset == 0 or recomputes_stiffness(t):
            tree_stiffness(state, graph.edge_from, graph.edge_to, spanning.top, graph.information,
                           spanning.parent, stiffness, gamma)
        tree_sgd_iteration(params, graph.edge_from, graph.edge_to, spanning.top, visit_order,
                           graph.measurements, graph.information, spanning.parent, entry, exit_, sums,
                           stiffness, gamma, learning_rate_scale, t + counter_offset, coupled)
        poses_from_parameters(params, spanning.parent, spanning.order, state)
        if not np.all(np.isfinite(state)):
            raise OptimizerError(f"tree SGD diverged at iteration {t} (non-finite poses)")
        poses_out = state.copy()
        poses_out[:, 2] = se2.wrap_angle(poses_out[:, 2])
        current_chi2 = chi2(graph, poses_out)
        if coupled and current_chi2 > previous_chi2 * (1.0 + SETTLED_CHANGE):  # the turn misleads here
            coupled = may_couple = False
        elif may_couple and not coupled:
            coupled = settled(previous_chi2, current_chi2)
        previous_chi2 = current_chi2
        yield Iteration(STAGE, offset + 1, poses_out, current_chi2)
