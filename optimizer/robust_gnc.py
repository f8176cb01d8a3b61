"""Graduated non-convexity over chordal solves: which loop closures to trust, from no estimate at all.

A robust kernel's cost Σ ρ(u_k) has a local minimum wherever a set of false loops agrees with a bent map,
and a local descent started from dead reckoning (SGD, Levenberg–Marquardt) finds one of those: on M3500
with 500 random false loops the robust SGD ends 1.5e3× above the clean optimum on the true edges and the
reweighted polish cannot recover. Graduated non-convexity (Blake & Zisserman 1987; Black & Rangarajan
1996; Yang, Antonante, Tzoumas & Carlone, RA-L 2020) starts the kernel's scale above every χ² term, where
the weighted problem is plain least squares, and shrinks it round by round towards the kernel's own
scale, each round solving the problem weighted by ρ'(u) at the previous round's poses.

Each round is solved by the chordal initialisation (`optimizer.initialization`), not by a local descent:
it reads no estimate, so a round whose weights the false loops still bend leaves nothing behind that a
later round would have to undo (an annealed SGD keeps the bend: see `optimizer.robust`). This is the role
the globally optimal solver plays in Yang et al.

Constraints whose weight has fallen below `DROP_WEIGHT` are left out of the round's solve: they no longer
change it, and random false loops are what fills the sparse factorisation (M3500 + 500 false loops:
a chordal solve about 11× slower than M3500's own, measured on a loaded machine). With odometry protected
(|a − b| = 1, never weighted) what is left stays connected on a trajectory graph; a round that would
disconnect the graph keeps every constraint.
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from optimizer.cost import edge_chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.initialization import chordal_initialization
from optimizer.iteration import Iteration
from optimizer.polish import PolishStatus
from optimizer.robust import (
    adaptive_scale,
    check_kernel,
    kernel_cost,
    masked_weights,
    robust_mask,
    robust_polish,
)

FloatArray = NDArray[np.float64]

STAGE = "gnc"
SHRINK = 2.0
"""The scale is divided by this every round (Yang et al. use 1.4 for Geman–McClure)."""
DROP_WEIGHT = 1e-6
"""Constraints weighted below this are left out of a round's chordal solve."""
MAX_ROUNDS = 200
"""Far above what a halving schedule needs (from χ² 1e30 to a scale of 1e-6: 120 rounds)."""


def graduated_chordal(
    graph: PoseGraph,
    kernel: str,
    *,
    scale: float | None = None,
    shrink: float = SHRINK,
    protect_odometry: bool = True,
) -> Generator[Iteration, None, FloatArray]:
    """Graduated non-convexity of `kernel`'s cost, every round a chordal solve of the weighted graph.

    Round 1 solves the unweighted graph; each later round weights the robustified constraints (the loop
    closures, with `protect_odometry`) by ρ'(u_k) at the previous round's poses, at a scale that starts
    at the largest χ² term and is divided by `shrink` every round down to the target: `scale` when
    given, else `optimizer.robust.adaptive_scale` of the current χ² terms (re-estimated every round).
    The last round runs at the target. Yields Iteration("gnc", k, poses, Σρ(u) at the round's scale);
    returns the last round's poses. Pose 0 is the graph's own.
    """
    check_kernel(kernel, scale)
    if not shrink > 1.0:
        raise OptimizerError(f"the scale's shrink factor must be > 1, got {shrink}")
    robust = robust_mask(graph, protect_odometry)
    poses = chordal_initialization(graph)
    terms = edge_chi2(graph, poses)
    target = _target(kernel, terms[robust], scale)
    round_scale = max(target, float(np.max(terms[robust], initial=0.0)))
    rounds = 1
    yield Iteration(STAGE, rounds, poses, _cost(kernel, terms, robust, round_scale))
    while round_scale > target and rounds < MAX_ROUNDS:
        round_scale = max(target, round_scale / shrink)
        weights = masked_weights(graph, terms, kernel, round_scale, robust)
        poses = chordal_initialization(_without_negligible(graph, weights))
        terms = edge_chi2(graph, poses)
        rounds += 1
        yield Iteration(STAGE, rounds, poses, _cost(kernel, terms, robust, round_scale))
        target = _target(kernel, terms[robust], scale)
    return poses


def robust_optimize(
    graph: PoseGraph,
    kernel: str,
    *,
    scale: float | None = None,
    polish_iterations: int = 300,
    protect_odometry: bool = True,
) -> Generator[Iteration, None, PolishStatus]:
    """The robust method with a polish: `graduated_chordal`, then `optimizer.robust.robust_polish`.

    Both minimize `kernel`'s cost at `scale` when given (by default each at `adaptive_scale`). The
    estimate is not read (apart from pose 0, the anchor): the rounds are chordal solves. Yields every
    round and every polish step with its robust cost; returns the polish's status.
    """
    check_kernel(kernel, scale)
    poses = yield from graduated_chordal(graph, kernel, scale=scale, protect_odometry=protect_odometry)
    return (yield from robust_polish(graph, poses, kernel=kernel, scale=scale,
                                     max_iterations=polish_iterations, protect_odometry=protect_odometry))


def _target(kernel: str, robust_terms: FloatArray, scale: float | None) -> float:
    return adaptive_scale(kernel, robust_terms) if scale is None else scale


def _cost(kernel: str, terms: FloatArray, robust: NDArray[np.bool_], scale: float) -> float:
    return float(terms[~robust].sum() + kernel_cost(kernel, terms[robust], scale).sum())


def _without_negligible(graph: PoseGraph, weights: FloatArray) -> PoseGraph:
    """The graph with information w_k·Ω_k, constraints of weight below DROP_WEIGHT left out if what is left
    stays connected."""
    keep = weights >= DROP_WEIGHT
    if not np.all(keep):
        adjacency = coo_matrix((np.ones(int(keep.sum())), (graph.edge_from[keep], graph.edge_to[keep])),
                               shape=(graph.num_poses, graph.num_poses))
        if connected_components(adjacency, directed=False, return_labels=False) != 1:
            keep[:] = True
    information = graph.information[keep] * weights[keep, None, None]
    return PoseGraph(graph.poses, graph.edge_from[keep], graph.edge_to[keep], graph.measurements[keep],
                     information, graph.vertex_ids)
