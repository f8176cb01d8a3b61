"""Solvers of the damped, Jacobi-scaled normal equations (S·H·S + λ·I) y = −S·g of one linearisation.

Two interchangeable solvers behind one interface:

- `DirectSolver`: qdldl's LDLᵀ of the assembled upper triangle. Exact; its fill-reducing order and symbolic
  analysis are done once per graph and only the numeric factorisation repeats. Its fill grows too fast
  for the largest graphs (10⁵ grid-world poses: 12·10⁶ factor entries, 2·10⁹ flops per factorisation).
- `ChainPCGSolver`: matrix-free preconditioned conjugate gradients (inexact Levenberg–Marquardt). The
  preconditioner is the exact block-tridiagonal part of the system along the pose chain, the spanning
  tree the odometry forms: a subgraph preconditioner (Dellaert, Carlson, Ila, Ni, Thorpe, IROS 2010),
  solved in O(N) by block LDLᵀ. Memory is O(N + M), a handful of vectors.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import qdldl
import scipy.sparse as sp
from numba import njit
from numpy.typing import NDArray

from optimizer.graph import PoseGraph
from optimizer.normal_equations import UpperPattern, edge_linearisation, hessian_product, scaled_upper
from optimizer.parallel_products import add_scaled, scale_and_add

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Linearisation:
    """H (upper CSC data, or None for the matrix-free solver), g, and the poses they were taken at."""

    poses: FloatArray
    gradient: FloatArray
    diagonal: FloatArray
    scale: FloatArray
    """S = diag(H)^(-1/2), floored for variables the information leaves unconstrained."""
    hessian: FloatArray | None


class DirectSolver:
    """Exact steps from qdldl's LDLᵀ; the factorisation's ordering and symbolic analysis are kept."""

    exact = True
    forcing = 0.0
    """The CG solvers' stopping rule, here for the same interface: a factorisation solves to rounding."""
    last_converged = True

    def __init__(self, pattern: UpperPattern) -> None:
        self._pattern = pattern
        self._factorisation: qdldl.Solver | None = None
        self._data = np.empty(pattern.nnz)

    def step(self, linearisation: Linearisation, damping: float) -> FloatArray | None:
        """The scaled step y, or None when the factorisation fails or gives non-finite values."""
        assert linearisation.hessian is not None
        pattern = self._pattern
        scaled_upper(linearisation.hessian, pattern.indices, pattern.indptr, linearisation.scale, damping,
                     self._data)
        upper = sp.csc_matrix((self._data, pattern.indices, pattern.indptr), shape=(pattern.size,) * 2)
        try:
            # The damped matrix is symmetric positive definite in exact arithmetic: LDLᵀ needs no pivoting.
            if self._factorisation is None:
                self._factorisation = qdldl.Solver(upper, upper=True)
            else:
                self._factorisation.update(upper, upper=True)
            scaled_step = self._factorisation.solve(-linearisation.scale * linearisation.gradient)
        except (ValueError, RuntimeError):  # qdldl reports a zero pivot this way
            self._factorisation = None
            return None
        return scaled_step if np.all(np.isfinite(scaled_step)) else None

    def accepted_step(self) -> None:
        """Told after every accepted step; nothing this solver keeps depends on the poses."""


class ChainPCGSolver:
    """Inexact steps by conjugate gradients preconditioned with the pose chain's block-tridiagonal part.

    CG stops once the residual is below `forcing` times the right-hand side, or after `max_iterations`.
    """

    exact = False

    def __init__(self, graph: PoseGraph, *, max_iterations: int = 500) -> None:
        self._graph = graph
        self._max_iterations = max_iterations
        self.forcing = 1e-2
        self.last_iterations = 0
        self.last_converged = True

    def step(self, linearisation: Linearisation, damping: float) -> FloatArray | None:
        graph = self._graph
        scale = linearisation.scale
        free = graph.num_poses - 1
        diagonal_blocks = np.empty((free, 3, 3))
        chain_blocks = np.empty((max(free - 1, 0), 3, 3))
        _chain_blocks(linearisation.poses, graph.edge_from, graph.edge_to, graph.measurements,
                      graph.information, scale, damping, diagonal_blocks, chain_blocks)
        if not _block_tridiagonal_factorise(diagonal_blocks, chain_blocks):
            return None
        rhs = -scale * linearisation.gradient
        product = np.empty_like(rhs)

        def apply(vector: FloatArray) -> FloatArray:
            hessian_product(linearisation.poses, graph.edge_from, graph.edge_to, graph.measurements,
                            graph.information, scale * vector, product)
            return scale * product + damping * vector

        def precondition(residual: FloatArray, out: FloatArray) -> None:
            _block_tridiagonal_solve(diagonal_blocks, chain_blocks, residual, out)

        solution, self.last_iterations, self.last_converged = preconditioned_cg(
            apply, precondition, rhs, self.forcing, self._max_iterations)
        return solution if np.all(np.isfinite(solution)) and self.last_iterations > 0 else None

    def accepted_step(self) -> None:
        """Told after every accepted step; nothing this solver keeps depends on the poses."""


def preconditioned_cg(apply: Callable[[FloatArray], FloatArray],
                      precondition: Callable[[FloatArray, FloatArray], None], rhs: FloatArray,
                      forcing: float, max_iterations: int,
                      start: FloatArray | None = None) -> tuple[FloatArray, int, bool]:
    """Conjugate gradients on A·x = rhs from x = `start` (default 0): (x, iterations, whether
    ‖r‖ ≤ `forcing`·‖rhs‖ held; the target is relative to rhs, not to the starting residual).

    `apply(v)` returns A·v; `precondition(r, out)` writes M⁻¹·r into `out`. It stops early, not converged,
    when a direction has no positive curvature (A is then not positive definite to rounding).
    """
    if start is None:
        solution = np.zeros_like(rhs)
        residual = rhs.copy()
    else:
        solution = start.copy()
        residual = rhs - apply(solution)
        if float(np.linalg.norm(residual)) <= forcing * float(np.linalg.norm(rhs)):
            return solution, 0, True
    preconditioned = np.empty_like(rhs)
    precondition(residual, preconditioned)
    direction = preconditioned.copy()
    rho = float(residual @ preconditioned)
    target = forcing * float(np.linalg.norm(rhs))
    converged = False
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        moved = apply(direction)
        curvature = float(direction @ moved)
        if not curvature > 0.0:
            break
        alpha = rho / curvature
        # In place on all threads, numpy's numbers to the bit (`optimizer.parallel_products`).
        add_scaled(solution, alpha, direction)
        add_scaled(residual, -alpha, moved)
        if float(np.linalg.norm(residual)) <= target:
            converged = True
            break
        precondition(residual, preconditioned)
        rho_next = float(residual @ preconditioned)
        scale_and_add(direction, rho_next / rho, preconditioned)
        rho = rho_next
    return solution, iterations, converged


@njit(cache=True)
def _chain_blocks(poses: FloatArray, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
                  information: FloatArray, scale: FloatArray, damping: float, diagonal_blocks: FloatArray,
                  chain_blocks: FloatArray) -> None:
    """Diagonal blocks of S·H·S + λ·I, and its blocks between consecutive free poses (j, j+1)."""
    diagonal_blocks[:] = 0.0
    chain_blocks[:] = 0.0
    e = np.empty(3)
    jac_a = np.empty((3, 3))
    jac_b = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a, b = edge_from[k], edge_to[k]
        edge_linearisation(poses, a, b, measurements[k], e, jac_a, jac_b)
        info = information[k]
        for first, jac_first in ((a, jac_a), (b, jac_b)):
            if first == 0:
                continue
            for second, jac_second in ((a, jac_a), (b, jac_b)):
                if second == 0:
                    continue
                if second == first:
                    target = diagonal_blocks[first - 1]
                elif second == first + 1:
                    target = chain_blocks[first - 1]
                else:
                    continue
                for p in range(3):
                    for q in range(3):
                        value = 0.0
                        for i in range(3):
                            for j in range(3):
                                value += jac_first[i, p] * info[i, j] * jac_second[j, q]
                        target[p, q] += value * scale[3 * (first - 1) + p] * scale[3 * (second - 1) + q]
    for block in range(diagonal_blocks.shape[0]):
        for p in range(3):
            diagonal_blocks[block, p, p] += damping


@njit(cache=True)
def _inverse_3x3(m: FloatArray, out: FloatArray) -> bool:
    det = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
           - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
           + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))
    if not det > 0.0:
        return False
    out[0, 0] = (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) / det
    out[0, 1] = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) / det
    out[0, 2] = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) / det
    out[1, 0] = (m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]) / det
    out[1, 1] = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) / det
    out[1, 2] = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) / det
    out[2, 0] = (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]) / det
    out[2, 1] = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) / det
    out[2, 2] = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) / det
    return True


@njit(cache=True)
def _block_tridiagonal_factorise(diagonal_blocks: FloatArray, chain_blocks: FloatArray) -> bool:
    """In place: diagonal_blocks[j] becomes C_j⁻¹, C_j = D_j − B_{j−1}ᵀ C_{j−1}⁻¹ B_{j−1} (block LDLᵀ)."""
    pivot = np.empty((3, 3))
    inverse = np.empty((3, 3))
    for j in range(diagonal_blocks.shape[0]):
        pivot[:, :] = diagonal_blocks[j]
        if j > 0:
            previous = diagonal_blocks[j - 1]
            coupling = chain_blocks[j - 1]
            for p in range(3):
                for q in range(3):
                    value = 0.0
                    for r in range(3):
                        for s in range(3):
                            value += coupling[r, p] * previous[r, s] * coupling[s, q]
                    pivot[p, q] -= value
        if not _inverse_3x3(pivot, inverse):
            return False
        diagonal_blocks[j] = inverse
    return True


@njit(cache=True)
def _block_tridiagonal_solve(inverses: FloatArray, chain_blocks: FloatArray, rhs: FloatArray,
                             out: FloatArray) -> None:
    """out = A⁻¹ rhs for the block-tridiagonal A factorised by `_block_tridiagonal_factorise`."""
    count = inverses.shape[0]
    forward = rhs.copy()
    local = np.empty(3)
    for j in range(1, count):
        # forward_j −= B_{j−1}ᵀ C_{j−1}⁻¹ forward_{j−1}
        for p in range(3):
            value = 0.0
            for r in range(3):
                solved = 0.0
                for s in range(3):
                    solved += inverses[j - 1, r, s] * forward[3 * (j - 1) + s]
                value += chain_blocks[j - 1, r, p] * solved
            forward[3 * j + p] -= value
    for j in range(count - 1, -1, -1):
        for p in range(3):
            local[p] = forward[3 * j + p]
            if j + 1 < count:
                for q in range(3):
                    local[p] -= chain_blocks[j, p, q] * out[3 * (j + 1) + q]
        for p in range(3):
            out[3 * j + p] = (inverses[j, p, 0] * local[0] + inverses[j, p, 1] * local[1]
                              + inverses[j, p, 2] * local[2])
