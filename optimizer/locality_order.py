"""The polish's multigrid path works on its graph with the poses numbered for memory locality.

Poses come in trajectory order, so a loop closure couples two poses far apart in memory. The compiled
kernels of a CG iteration (block Gauss–Seidel sweeps, products with H) then wait on a cache miss for most
loop-closure blocks: on the 10⁶-pose grid world (half the constraints are loop closures) a forward sweep
took about twice the CPU time in trajectory order as with the poses numbered by reverse Cuthill–McKee
(scipy), whose block bandwidth there is about 2 000 poses instead of 10⁶. The constraints are listed by
their earlier pose in the new numbering, so that assembling H and evaluating χ² also meet the poses and the
blocks of H in memory order (at 10⁶ poses a linearisation took 1.8–1.9 CPU s with the poses renumbered and
the constraints left in file order, 0.6–1.2 sorted, 0.8 in the file's order). Only the numbering and the
listing change: every constraint keeps its direction, measurement and information; the pose with index 0
(the anchor) keeps index 0.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import reverse_cuthill_mckee

from optimizer.graph import PoseGraph

IntArray = NDArray[np.int64]


def locality_order(graph: PoseGraph) -> IntArray:
    """Pose indices in reverse Cuthill–McKee order of the constraint graph, pose 0 first: the new index
    of pose `order[k]` is k."""
    size = graph.num_poses
    adjacency = sp.csr_matrix((np.ones(graph.num_edges, dtype=np.int32), (graph.edge_from, graph.edge_to)),
                              shape=(size, size))
    order = reverse_cuthill_mckee(adjacency, symmetric_mode=False).astype(np.int64)
    return np.concatenate([[0], order[order != 0]])


def inverse(order: IntArray) -> IntArray:
    """The new index of each pose under `order` (`rank[order[k]] == k`)."""
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    return rank


def renumbered(graph: PoseGraph, order: IntArray) -> PoseGraph:
    """`graph` with pose `order[k]` as pose k, its constraints listed by their earlier new pose (stable:
    ties keep the graph's order), each with its own direction, measurement and information."""
    rank = inverse(order)
    edge_from, edge_to = rank[graph.edge_from], rank[graph.edge_to]
    listing = np.argsort(np.minimum(edge_from, edge_to), kind="stable")
    return PoseGraph(graph.poses[order], edge_from[listing], edge_to[listing], graph.measurements[listing],
                     graph.information[listing], graph.vertex_ids[order])
