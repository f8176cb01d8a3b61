"""Gauss–Newton normal equations of the χ² of `optimizer.cost`, assembled by compiled kernels.

The variables are the poses 1..N−1 (pose 0 is the anchor), three each (x, y, θ), so pose k owns variables
3(k−1)..3(k−1)+2. H = Σ JᵀΩJ is kept as the upper triangle (row ≤ column) in CSC form, what an LDLᵀ
factorisation reads; every kernel works edge by edge straight into the CSC data, so no per-edge temporary
arrays of the whole graph are ever made (at 10⁶ poses an (M, 36) float array alone is 0.6 GB).
The same per-edge Jacobians give the matrix-free product H·v the conjugate-gradient solver uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from optimizer import se2
from optimizer.graph import PoseGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class UpperPattern:
    """The fixed sparsity of the upper triangle of H over the free poses, computed once per graph.

    Block column j (pose j+1) holds its off-diagonal blocks (rows of smaller poses) in increasing order,
    then its diagonal block; scalar column 3j+c holds three rows per off-diagonal block and the c+1 rows
    3j..3j+c of the diagonal block.
    """

    size: int
    indptr: IntArray
    indices: IntArray
    block_count: IntArray
    """(N−1,) blocks stored in each block column (the diagonal included)."""
    edge_block: IntArray
    """(M,) position of each edge's off-diagonal block within its block column; −1 if it has the anchor."""

    @classmethod
    def of(cls, graph: PoseGraph) -> UpperPattern:
        free = graph.num_poses - 1
        low = np.minimum(graph.edge_from, graph.edge_to) - 1
        high = np.maximum(graph.edge_from, graph.edge_to) - 1
        touches_anchor = low < 0
        # Column-major keys of the distinct off-diagonal blocks and of every diagonal block: sorted keys
        # list each block column's blocks in row order, the diagonal last (it has the largest row).
        diagonal = np.arange(free, dtype=np.int64)
        keys, inverse = np.unique(
            np.concatenate([np.where(touches_anchor, -1, high * free + low), diagonal * free + diagonal]),
            return_inverse=True,
        )
        inverse = inverse.reshape(-1)
        if keys[0] == -1:  # the anchor's edges share one dummy key, dropped
            keys, inverse = keys[1:], inverse - 1
        block_column = keys // free
        block_count = np.bincount(block_column, minlength=free).astype(np.int64)
        block_start = np.zeros(free + 1, dtype=np.int64)
        block_start[1:] = np.cumsum(block_count)
        edge_inverse = inverse[: graph.num_edges]
        edge_block = np.where(touches_anchor, -1, edge_inverse - block_start[np.maximum(high, 0)])
        indptr, indices = _upper_structure(keys % free, block_start, block_count)
        return cls(3 * free, indptr, indices, block_count, edge_block.astype(np.int64))

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1])


@njit(cache=True)
def _upper_structure(block_rows: IntArray, block_start: IntArray,
                     block_count: IntArray) -> tuple[IntArray, IntArray]:
    free = block_count.shape[0]
    indptr = np.zeros(3 * free + 1, dtype=np.int64)
    for j in range(free):
        for c in range(3):
            indptr[3 * j + c + 1] = indptr[3 * j + c] + 3 * (block_count[j] - 1) + c + 1
    indices = np.empty(indptr[-1], dtype=np.int64)
    for j in range(free):
        for c in range(3):
            position = indptr[3 * j + c]
            for i in range(block_count[j] - 1):
                row = block_rows[block_start[j] + i]
                for p in range(3):
                    indices[position] = 3 * row + p
                    position += 1
            for p in range(c + 1):
                indices[position] = 3 * j + p
                position += 1
    return indptr, indices


@njit(cache=True)
def edge_linearisation(poses: FloatArray, a: int, b: int, z: FloatArray, e: FloatArray,
                        jac_a: FloatArray, jac_b: FloatArray) -> None:
    """Error e = t2v(z⁻¹·x_a⁻¹·x_b) (θ wrapped) and its Jacobians, as `polish.edge_jacobians` states them."""
    phi = poses[a, 2] + z[2]
    c, s = math.cos(phi), math.sin(phi)
    dx, dy = poses[b, 0] - poses[a, 0], poses[b, 1] - poses[a, 1]
    cz, sz = math.cos(z[2]), math.sin(z[2])
    e[0] = c * dx + s * dy - (cz * z[0] + sz * z[1])
    e[1] = -s * dx + c * dy - (-sz * z[0] + cz * z[1])
    e[2] = se2.wrap_scalar(poses[b, 2] - poses[a, 2] - z[2])
    jac_b[:] = 0.0
    jac_b[0, 0], jac_b[0, 1], jac_b[1, 0], jac_b[1, 1], jac_b[2, 2] = c, s, -s, c, 1.0
    for i in range(3):
        for k in range(3):
            jac_a[i, k] = -jac_b[i, k]
    jac_a[0, 2] = -s * dx + c * dy
    jac_a[1, 2] = -c * dx - s * dy


@njit(cache=True, inline="always")
def linearise_edge_into_gradient(poses: FloatArray, a: int, b: int, z: FloatArray, info: FloatArray,
                                 e: FloatArray, jac_a: FloatArray, jac_b: FloatArray, omega_a: FloatArray,
                                 omega_b: FloatArray, gradient: FloatArray) -> None:
    """One edge's share of the normal equations before H is scattered: its Jacobians, Ω·J_a and Ω·J_b,
    and its gradient Jᵀ Ω e added to `gradient` (pose 0, the anchor, has no variables)."""
    edge_linearisation(poses, a, b, z, e, jac_a, jac_b)
    for i in range(3):
        for j in range(3):
            omega_a[i, j] = info[i, 0] * jac_a[0, j] + info[i, 1] * jac_a[1, j] + info[i, 2] * jac_a[2, j]
            omega_b[i, j] = info[i, 0] * jac_b[0, j] + info[i, 1] * jac_b[1, j] + info[i, 2] * jac_b[2, j]
    for i in range(3):
        weighted = info[i, 0] * e[0] + info[i, 1] * e[1] + info[i, 2] * e[2]
        if a > 0:
            for p in range(3):
                gradient[3 * (a - 1) + p] += jac_a[i, p] * weighted
        if b > 0:
            for p in range(3):
                gradient[3 * (b - 1) + p] += jac_b[i, p] * weighted


@njit(cache=True)
def assemble(poses: FloatArray, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
             information: FloatArray, edge_block: IntArray, indptr: IntArray, block_count: IntArray,
             hessian: FloatArray, gradient: FloatArray) -> None:
    """Fill `hessian` (the upper CSC data of H = Σ JᵀΩJ) and `gradient` (g = Σ JᵀΩe) over the free poses."""
    hessian[:] = 0.0
    gradient[:] = 0.0
    e = np.empty(3)
    jac_a = np.empty((3, 3))
    jac_b = np.empty((3, 3))
    omega_a = np.empty((3, 3))
    omega_b = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a, b = edge_from[k], edge_to[k]
        linearise_edge_into_gradient(poses, a, b, measurements[k], information[k], e, jac_a, jac_b, omega_a,
                                     omega_b, gradient)
        if a > 0:
            _add_diagonal_block(hessian, indptr, block_count, a - 1, jac_a, omega_a)
        if b > 0:
            _add_diagonal_block(hessian, indptr, block_count, b - 1, jac_b, omega_b)
        if edge_block[k] >= 0:
            # The stored block sits in the column of the later pose: J_lowᵀ Ω J_high.
            low_jac, high_omega = (jac_a, omega_b) if a < b else (jac_b, omega_a)
            column = 3 * (max(a, b) - 1)
            for c in range(3):
                start = indptr[column + c] + 3 * edge_block[k]
                for p in range(3):
                    hessian[start + p] += (low_jac[0, p] * high_omega[0, c] + low_jac[1, p] * high_omega[1, c]
                                           + low_jac[2, p] * high_omega[2, c])


@njit(cache=True)
def _add_diagonal_block(hessian: FloatArray, indptr: IntArray, block_count: IntArray, block: int,
                        jac: FloatArray, omega_jac: FloatArray) -> None:
    for c in range(3):
        start = indptr[3 * block + c] + 3 * (block_count[block] - 1)
        for p in range(c + 1):
            hessian[start + p] += (jac[0, p] * omega_jac[0, c] + jac[1, p] * omega_jac[1, c]
                                   + jac[2, p] * omega_jac[2, c])


@njit(cache=True)
def diagonal_of(hessian: FloatArray, indptr: IntArray) -> FloatArray:
    """diag(H): the last entry of every upper-triangle column."""
    size = indptr.shape[0] - 1
    out = np.empty(size)
    for column in range(size):
        out[column] = hessian[indptr[column + 1] - 1]
    return out


@njit(cache=True)
def scaled_upper(hessian: FloatArray, indices: IntArray, indptr: IntArray, scale: FloatArray,
                 damping: float, out: FloatArray) -> None:
    """out = upper CSC data of S·H·S + λ·I, S = diag(scale)."""
    for column in range(indptr.shape[0] - 1):
        for position in range(indptr[column], indptr[column + 1]):
            out[position] = hessian[position] * scale[indices[position]] * scale[column]
        out[indptr[column + 1] - 1] += damping


@njit(cache=True, inline="always")
def _edge_times(jac_a: FloatArray, jac_b: FloatArray, a: int, b: int, vector: FloatArray,
                moved: FloatArray) -> None:
    """moved = J·v for one edge: how v over the free variables (pose 0 anchored) changes its error."""
    for i in range(3):
        total = 0.0
        for p in range(3):
            if a > 0:
                total += jac_a[i, p] * vector[3 * (a - 1) + p]
            if b > 0:
                total += jac_b[i, p] * vector[3 * (b - 1) + p]
        moved[i] = total


@njit(cache=True)
def hessian_product(poses: FloatArray, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
                    information: FloatArray, vector: FloatArray, out: FloatArray) -> None:
    """out = H·v over the free variables, edge by edge (J v, then Jᵀ Ω J v), without storing H."""
    out[:] = 0.0
    e = np.empty(3)
    jac_a = np.empty((3, 3))
    jac_b = np.empty((3, 3))
    moved = np.empty(3)
    for k in range(edge_from.shape[0]):
        a, b = edge_from[k], edge_to[k]
        edge_linearisation(poses, a, b, measurements[k], e, jac_a, jac_b)
        _edge_times(jac_a, jac_b, a, b, vector, moved)
        info = information[k]
        for i in range(3):
            weighted = info[i, 0] * moved[0] + info[i, 1] * moved[1] + info[i, 2] * moved[2]
            for p in range(3):
                if a > 0:
                    out[3 * (a - 1) + p] += jac_a[i, p] * weighted
                if b > 0:
                    out[3 * (b - 1) + p] += jac_b[i, p] * weighted


@njit(cache=True)
def quadratic_form(poses: FloatArray, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
                   information: FloatArray, vector: FloatArray) -> float:
    """vᵀHv = Σ (J v)ᵀ Ω (J v), edge by edge."""
    total = 0.0
    e = np.empty(3)
    jac_a = np.empty((3, 3))
    jac_b = np.empty((3, 3))
    moved = np.empty(3)
    for k in range(edge_from.shape[0]):
        a, b = edge_from[k], edge_to[k]
        edge_linearisation(poses, a, b, measurements[k], e, jac_a, jac_b)
        _edge_times(jac_a, jac_b, a, b, vector, moved)
        info = information[k]
        for i in range(3):
            for j in range(3):
                total += moved[i] * info[i, j] * moved[j]
    return total


@njit(cache=True)
def hessian_diagonal(poses: FloatArray, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
                     information: FloatArray, diagonal: FloatArray, gradient: FloatArray) -> None:
    """diag(H) and g over the free variables, for the matrix-free solver that never stores H."""
    diagonal[:] = 0.0
    gradient[:] = 0.0
    e = np.empty(3)
    jac_a = np.empty((3, 3))
    jac_b = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a, b = edge_from[k], edge_to[k]
        edge_linearisation(poses, a, b, measurements[k], e, jac_a, jac_b)
        info = information[k]
        for i in range(3):
            weighted = info[i, 0] * e[0] + info[i, 1] * e[1] + info[i, 2] * e[2]
            for p in range(3):
                if a > 0:
                    gradient[3 * (a - 1) + p] += jac_a[i, p] * weighted
                if b > 0:
                    gradient[3 * (b - 1) + p] += jac_b[i, p] * weighted
        for p in range(3):
            for i in range(3):
                for j in range(3):
                    if a > 0:
                        diagonal[3 * (a - 1) + p] += jac_a[i, p] * info[i, j] * jac_a[j, p]
                    if b > 0:
                        diagonal[3 * (b - 1) + p] += jac_b[i, p] * info[i, j] * jac_b[j, p]
