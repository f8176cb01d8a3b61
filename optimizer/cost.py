"""The χ² cost of a pose graph in g2o's convention: Σ eᵀ Ω e with e = t2v(z⁻¹ · (x_a⁻¹ · x_b)), θ wrapped."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from optimizer import se2
from optimizer.graph import PoseGraph

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


def chi2(graph: PoseGraph, poses: FloatArray | None = None) -> float:
    """Total χ² of the graph at `poses` (default: the graph's estimate)."""
    poses = graph.poses if poses is None else np.ascontiguousarray(poses, dtype=np.float64)
    return _chi2_kernel(poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information)


@njit(cache=True)
def _chi2_kernel(poses: FloatArray, edge_from: NDArray[np.int64], edge_to: NDArray[np.int64],
                 measurements: FloatArray, information: FloatArray) -> float:
    # Compiled rather than vectorized: it runs after every optimizer iteration, and on million-edge
    # graphs the vectorized form's (M, 3) temporaries would dominate the optimizer's memory.
    total = 0.0
    e = np.empty(3)
    for k in range(edge_from.shape[0]):
        a = poses[edge_from[k]]
        b = poses[edge_to[k]]
        ca, sa = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        px, py, pt = ca * dx + sa * dy, -sa * dx + ca * dy, b[2] - a[2]
        z = measurements[k]
        cz, sz = math.cos(z[2]), math.sin(z[2])
        ex, ey = px - z[0], py - z[1]
        e[0] = cz * ex + sz * ey
        e[1] = -sz * ex + cz * ey
        e[2] = se2.wrap_angle(pt - z[2])
        info = information[k]
        for i in range(3):
            for j in range(3):
                total += e[i] * info[i, j] * e[j]
    return total
