"""Gauss–Seidel relaxation, the baseline Olson et al. (2006) compare SGD against.

One sweep visits the poses in order (the first stays anchored) and moves each one to minimise the cost of
its own constraints with every neighbour held fixed: one 3×3 Gauss–Newton step, linearised at the current
pose. Each move uses the moves already made in the sweep, so the sweep is sequential and runs in numba over
a CSR adjacency (pose → its constraints).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numba import njit
from numpy.typing import NDArray

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import GraphError, OptimizerError
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

STAGE = "gauss-seidel"


def gauss_seidel(
    graph: PoseGraph, poses: FloatArray | None = None, *, iterations: int = 100
) -> Iterator[Iteration]:
    """Run `iterations` Gauss–Seidel sweeps from `poses` (default: the graph's estimate).

    Yields Iteration("gauss-seidel", k, poses, χ²) after every sweep, k from 1. Pose 0 stays fixed.
    """
    if iterations < 0:
        raise OptimizerError(f"iterations must be >= 0, got {iterations}")
    current = np.array(graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if current.shape != graph.poses.shape:
        raise GraphError(f"expected poses of shape {graph.poses.shape}, got {current.shape}")
    if not np.all(np.isfinite(current)):
        raise GraphError("the starting poses contain non-finite values")
    current[:, 2] = se2.wrap_angle(current[:, 2])
    adjacency_start, adjacency_edges = _adjacency(graph)
    for index in range(1, iterations + 1):
        current = current.copy()
        _sweep(current, graph.edge_from, graph.edge_to, graph.measurements, graph.information,
               adjacency_start, adjacency_edges)
        current.setflags(write=False)
        yield Iteration(STAGE, index, current, chi2(graph, current))


def _adjacency(graph: PoseGraph) -> tuple[IntArray, IntArray]:
    """CSR of pose → constraints touching it: the constraints of pose i are edges[start[i]:start[i+1]]."""
    endpoints = np.concatenate([graph.edge_from, graph.edge_to])
    edges = np.concatenate([np.arange(graph.num_edges), np.arange(graph.num_edges)]).astype(np.int64)
    order = np.argsort(endpoints, kind="stable")
    start = np.zeros(graph.num_poses + 1, dtype=np.int64)
    start[1:] = np.cumsum(np.bincount(endpoints, minlength=graph.num_poses))
    return start, edges[order]


@njit(cache=True)
def _sweep(
    poses: FloatArray,
    edge_from: IntArray,
    edge_to: IntArray,
    measurements: FloatArray,
    information: FloatArray,
    adjacency_start: IntArray,
    adjacency_edges: IntArray,
) -> None:
    """One in-place sweep over poses 1..N-1 (see the module docstring)."""
    hessian = np.empty((3, 3))
    gradient = np.empty(3)
    jac = np.empty((3, 3))
    error = np.empty(3)
    weighted = np.empty((3, 3))
    weighted_error = np.empty(3)
    for pose in range(1, poses.shape[0]):
        hessian[:, :] = 0.0
        gradient[:] = 0.0
        for k in range(adjacency_start[pose], adjacency_start[pose + 1]):
            edge = adjacency_edges[k]
            a = edge_from[edge]
            b = edge_to[edge]
            # e = t2v(z⁻¹·(x_a⁻¹·x_b)): e_t = R(θ_a+θ_z)ᵀ(t_b − t_a) − R(θ_z)ᵀ t_z, e_θ = θ_b − θ_a − θ_z.
            phi = poses[a, 2] + measurements[edge, 2]
            c = np.cos(phi)
            s = np.sin(phi)
            cz = np.cos(measurements[edge, 2])
            sz = np.sin(measurements[edge, 2])
            dx = poses[b, 0] - poses[a, 0]
            dy = poses[b, 1] - poses[a, 1]
            error[0] = c * dx + s * dy - (cz * measurements[edge, 0] + sz * measurements[edge, 1])
            error[1] = -s * dx + c * dy - (-sz * measurements[edge, 0] + cz * measurements[edge, 1])
            error[2] = se2.wrap_scalar(poses[b, 2] - poses[a, 2] - measurements[edge, 2])
            # ∂e/∂x_b is the rotation R(θ_a+θ_z)ᵀ; ∂e/∂x_a is its negative plus the θ_a column.
            sign = 1.0 if pose == b else -1.0
            jac[0, 0] = sign * c
            jac[0, 1] = sign * s
            jac[1, 0] = -sign * s
            jac[1, 1] = sign * c
            jac[2, 0] = 0.0
            jac[2, 1] = 0.0
            jac[2, 2] = sign
            if pose == b:
                jac[0, 2] = 0.0
                jac[1, 2] = 0.0
            else:
                jac[0, 2] = -s * dx + c * dy
                jac[1, 2] = -c * dx - s * dy
            omega = information[edge]
            for i in range(3):
                weighted_error[i] = omega[i, 0] * error[0] + omega[i, 1] * error[1] + omega[i, 2] * error[2]
                for j in range(3):
                    weighted[i, j] = (omega[i, 0] * jac[0, j] + omega[i, 1] * jac[1, j]
                                      + omega[i, 2] * jac[2, j])
            for i in range(3):
                gradient[i] += (jac[0, i] * weighted_error[0] + jac[1, i] * weighted_error[1]
                                + jac[2, i] * weighted_error[2])
                for j in range(3):
                    hessian[i, j] += (jac[0, i] * weighted[0, j] + jac[1, i] * weighted[1, j]
                                      + jac[2, i] * weighted[2, j])
        if _solve_3x3_spd(hessian, gradient):
            poses[pose, 0] -= gradient[0]
            poses[pose, 1] -= gradient[1]
            poses[pose, 2] = se2.wrap_scalar(poses[pose, 2] - gradient[2])


@njit(cache=True)
def _solve_3x3_spd(matrix: FloatArray, rhs: FloatArray) -> bool:
    """Overwrite `rhs` with matrix⁻¹·rhs by Cholesky; False (rhs unusable) when matrix is not safely SPD.

    A pose whose constraints leave a direction unconstrained (singular information) is then left in place.
    """
    scale = max(matrix[0, 0], matrix[1, 1], matrix[2, 2])
    if not scale > 0.0:
        return False
    tiny = 1e-14 * scale
    l00 = matrix[0, 0]
    if not l00 > tiny:
        return False
    l00 = np.sqrt(l00)
    l10 = matrix[1, 0] / l00
    l20 = matrix[2, 0] / l00
    l11 = matrix[1, 1] - l10 * l10
    if not l11 > tiny:
        return False
    l11 = np.sqrt(l11)
    l21 = (matrix[2, 1] - l20 * l10) / l11
    l22 = matrix[2, 2] - l20 * l20 - l21 * l21
    if not l22 > tiny:
        return False
    l22 = np.sqrt(l22)
    y0 = rhs[0] / l00
    y1 = (rhs[1] - l10 * y0) / l11
    y2 = (rhs[2] - l20 * y0 - l21 * y1) / l22
    rhs[2] = y2 / l22
    rhs[1] = (y1 - l21 * rhs[2]) / l11
    rhs[0] = (y0 - l10 * rhs[1] - l20 * rhs[2]) / l00
    return True
