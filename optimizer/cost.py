"""The χ² cost of a pose graph in g2o's convention: Σ eᵀ Ω e with e = t2v(z⁻¹ · (x_a⁻¹ · x_b)), θ wrapped."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from optimizer import se2
from optimizer.errors import GraphError
from optimizer.graph import PoseGraph, read_only

FloatArray = NDArray[np.float64]


def edge_errors(graph: PoseGraph, poses: FloatArray | None = None) -> FloatArray:
    """(M, 3) error vectors of every constraint at `poses` (default: the graph's estimate)."""
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    predicted = se2.relative(poses[graph.edge_from], poses[graph.edge_to])
    return se2.relative(graph.measurements, predicted)


def edge_chi2(graph: PoseGraph, poses: FloatArray | None = None) -> FloatArray:
    """(M,) χ² contribution eᵀ Ω e of every constraint."""
    errors = edge_errors(graph, poses)
    return np.einsum("mi,mij,mj->m", errors, graph.information, errors)


CHI2_CHUNK = 65_536
"""Constraints whose χ² terms are computed at once on all threads before they are summed in order."""

CHI2_PARALLEL_MIN = 16_384
"""Fewer constraints than this are summed by `_chi2_kernel` on the calling thread: waking numba's threads
costs more than such a sum (a town loop's 80-keyframe graph: 12 ms a call on a loaded 2-core machine,
against microseconds on one thread), and the value is the same to the bit."""


def chi2(graph: PoseGraph, poses: FloatArray | None = None) -> float:
    """Total χ² of the graph at `poses` (default: the graph's estimate).

    The terms eᵢ·Ωᵢⱼ·eⱼ of `CHI2_CHUNK` constraints at a time are computed on all threads (the errors'
    trigonometry is most of the time: 0.3 s a call at 2·10⁶ constraints, once per SGD iteration and per
    polish trial), then added one by one in constraint order on one thread: the sum of `_chi2_kernel`, to
    the bit, whatever the threads."""
    # Read-only as the graph's own: one compiled signature of the kernel for both.
    poses = graph.poses if poses is None else read_only(np.ascontiguousarray(poses, dtype=np.float64))
    if poses.shape != (graph.num_poses, 3):  # the kernels index them by the constraints' ends, unchecked
        raise GraphError(f"poses must be ({graph.num_poses}, 3) for this graph, got {poses.shape}")
    edges = graph.num_edges
    if edges < CHI2_PARALLEL_MIN:
        return float(_chi2_kernel(poses, graph.edge_from, graph.edge_to, graph.measurements,
                                  graph.information))
    terms = np.empty((min(edges, CHI2_CHUNK), 9))
    total = 0.0
    for first in range(0, edges, CHI2_CHUNK):
        last = min(first + CHI2_CHUNK, edges)
        _chi2_terms(poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information, first, last,
                    terms)
        total = _add_terms(total, terms, last - first)
    return total


@njit(cache=True, parallel=True)
def _chi2_terms(poses: FloatArray, edge_from: NDArray[np.int64], edge_to: NDArray[np.int64],
                measurements: FloatArray, information: FloatArray, first: int, last: int,
                terms: FloatArray) -> None:
    """terms[k − first, 3i + j] = eᵢ·Ωᵢⱼ·eⱼ of constraint k, for k in [first, last): `_chi2_kernel`'s terms,
    each computed as there."""
    for offset in prange(last - first):
        k = first + offset
        e0, e1, e2 = _error(poses, edge_from, edge_to, measurements, k)
        info = information[k]
        row = terms[offset]
        row[0] = e0 * info[0, 0] * e0
        row[1] = e0 * info[0, 1] * e1
        row[2] = e0 * info[0, 2] * e2
        row[3] = e1 * info[1, 0] * e0
        row[4] = e1 * info[1, 1] * e1
        row[5] = e1 * info[1, 2] * e2
        row[6] = e2 * info[2, 0] * e0
        row[7] = e2 * info[2, 1] * e1
        row[8] = e2 * info[2, 2] * e2


@njit(cache=True)
def _add_terms(total: float, terms: FloatArray, count: int) -> float:
    """total + the first `count` rows of `terms`, one term at a time in order (as `_chi2_kernel` adds)."""
    for offset in range(count):
        for t in range(9):
            total += terms[offset, t]
    return total


@njit(cache=True)
def _chi2_kernel(poses: FloatArray, edge_from: NDArray[np.int64], edge_to: NDArray[np.int64],
                 measurements: FloatArray, information: FloatArray) -> float:
    # Compiled rather than vectorized: it runs after every optimizer iteration, and on million-edge
    # graphs the vectorized form's (M, 3) temporaries would dominate the optimizer's memory. One thread:
    # `chi2` sums small graphs with it, and its parallel terms must equal it
    # (tests/test_parallel_products.py).
    total = 0.0
    for k in range(edge_from.shape[0]):
        total = plus_edge_chi2(total, poses, edge_from, edge_to, measurements, information, k)
    return total


@njit(cache=True, inline="always")
def plus_edge_chi2(total: float, poses: FloatArray, edge_from: NDArray[np.int64], edge_to: NDArray[np.int64],
                   measurements: FloatArray, information: FloatArray, k: int) -> float:
    """total + constraint k's χ² term eᵀ·Ω·e, its nine products eᵢ·Ωᵢⱼ·eⱼ added one at a time (i, then j):
    what `chi2` adds for it, to the bit (also inside the SGD pass, `optimizer.sgd_kernels`)."""
    e0, e1, e2 = _error(poses, edge_from, edge_to, measurements, k)
    info = information[k]
    total += e0 * info[0, 0] * e0
    total += e0 * info[0, 1] * e1
    total += e0 * info[0, 2] * e2
    total += e1 * info[1, 0] * e0
    total += e1 * info[1, 1] * e1
    total += e1 * info[1, 2] * e2
    total += e2 * info[2, 0] * e0
    total += e2 * info[2, 1] * e1
    total += e2 * info[2, 2] * e2
    return total


@njit(cache=True, inline="always")
def _error(poses: FloatArray, edge_from: NDArray[np.int64], edge_to: NDArray[np.int64],
           measurements: FloatArray, k: int) -> tuple[float, float, float]:
    """Constraint k's error t2v(Z⁻¹·Xa⁻¹·Xb) in the stored direction (g2o's convention)."""
    a = poses[edge_from[k]]
    b = poses[edge_to[k]]
    ca, sa = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    px, py, pt = ca * dx + sa * dy, -sa * dx + ca * dy, b[2] - a[2]
    z = measurements[k]
    cz, sz = math.cos(z[2]), math.sin(z[2])
    ex, ey = px - z[0], py - z[1]
    return cz * ex + sz * ey, -sz * ex + cz * ey, se2.wrap_scalar(pt - z[2])
