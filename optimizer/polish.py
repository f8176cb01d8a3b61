"""The exact-minimum polish: sparse Levenberg–Marquardt (damped Gauss–Newton) on the χ² of `optimizer.cost`.

Poses are parameterised globally (x, y, θ) with an additive update, θ wrapped. The first pose is anchored:
its three columns are dropped from the system, so the normal equations are (3N−3)×(3N−3).

The information of real graphs (INTEL.g2o) is badly scaled — 3×3 edge informations with condition numbers
up to 2e11 — so the damped system is solved in Jacobi-scaled form: with S = diag(H)^(-1/2),
(S H S + λ·I) y = −S g, Δ = S y. This is exactly Marquardt's λ·diag(H) damping, but the matrix handed to
the factorisation has a unit diagonal. The sparsity pattern of H is computed once per call and every
iteration only refills the values; the factorisation is qdldl's LDLᵀ (OSQP's), whose fill-reducing order
and symbolic analysis are likewise done once and only the numeric factorisation repeats.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np
import qdldl
import scipy.sparse as sp
from numpy.typing import NDArray

from optimizer import se2
from optimizer.cost import chi2, edge_errors
from optimizer.errors import GraphError, OptimizerError
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

STAGE = "gauss-newton"
_INITIAL_LAMBDA = 1e-5
_MIN_LAMBDA = 1e-12
_MAX_LAMBDA = 1e12
"""Past this the step is a vanishing gradient-descent step: no further decrease can be found."""
_DIAGONAL_FLOOR = 1e-12
"""Relative floor of diag(H) for the scaling, for variables a singular information leaves unconstrained."""


def edge_jacobians(
    graph: PoseGraph, poses: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Errors (M, 3) and their Jacobians (M, 3, 3) with respect to x_a and x_b, for every constraint.

    With e = t2v(z⁻¹·(x_a⁻¹·x_b)): e_t = R(θ_a+θ_z)ᵀ (t_b − t_a) − R(θ_z)ᵀ t_z and e_θ = θ_b − θ_a − θ_z, so
    ∂e/∂x_b is the rotation R(θ_a+θ_z)ᵀ (with a 1 for θ) and ∂e/∂x_a is its negative, plus the derivative
    of R(θ_a+θ_z)ᵀ with respect to θ_a applied to t_b − t_a in the θ column.
    """
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    errors = edge_errors(graph, poses)
    pose_a = poses[graph.edge_from]
    pose_b = poses[graph.edge_to]
    phi = pose_a[:, 2] + graph.measurements[:, 2]
    c, s = np.cos(phi), np.sin(phi)
    dx = pose_b[:, 0] - pose_a[:, 0]
    dy = pose_b[:, 1] - pose_a[:, 1]

    jac_b = np.zeros((len(phi), 3, 3))
    jac_b[:, 0, 0] = c
    jac_b[:, 0, 1] = s
    jac_b[:, 1, 0] = -s
    jac_b[:, 1, 1] = c
    jac_b[:, 2, 2] = 1.0
    jac_a = -jac_b
    jac_a[:, 0, 2] = -s * dx + c * dy
    jac_a[:, 1, 2] = -c * dx - s * dy
    return errors, jac_a, jac_b


@dataclass(frozen=True)
class _NormalEquationsPattern:
    """The fixed sparsity of H = JᵀΩJ over the free poses, computed once.

    Every edge contributes four 3×3 blocks (aa, ab, ba, bb) = 36 values; `slot` sends each value that
    survives the anchoring to its position in the CSC data array, so refilling H is one `bincount`.
    """

    size: int
    kept: NDArray[np.bool_]
    """(M·36,) values not touching the anchored pose."""
    slot: IntArray
    """Position in the CSC data of each kept value."""
    indices: IntArray
    indptr: IntArray
    column_of_entry: IntArray
    """Column of each CSC data entry (the CSC `indices` give the row)."""
    diagonal: IntArray
    """Position in the CSC data of each diagonal entry, in variable order."""
    upper: IntArray
    """Positions in the CSC data of the upper triangle (row ≤ column), what the factorisation reads."""
    upper_indptr: IntArray

    @classmethod
    def of(cls, graph: PoseGraph) -> _NormalEquationsPattern:
        size = 3 * (graph.num_poses - 1)
        # Variable block of each pose: pose k > 0 owns variables 3(k−1)..3(k−1)+2; the anchor gets −1.
        block_a = graph.edge_from - 1
        block_b = graph.edge_to - 1
        row_block = np.stack([block_a, block_a, block_b, block_b], axis=1)  # (M, 4) for aa, ab, ba, bb
        col_block = np.stack([block_a, block_b, block_a, block_b], axis=1)
        within = np.arange(3)
        rows = 3 * row_block[:, :, None, None] + within[None, None, :, None]
        cols = 3 * col_block[:, :, None, None] + within[None, None, None, :]
        rows, cols = np.broadcast_arrays(rows, cols)
        kept = ((row_block >= 0) & (col_block >= 0))[:, :, None, None]
        kept = np.broadcast_to(kept, rows.shape).reshape(-1)
        rows = rows.reshape(-1)[kept].astype(np.int64)
        cols = cols.reshape(-1)[kept].astype(np.int64)

        keys, slot = _csc_keys(size, rows, cols)
        entry_rows = keys % size
        entry_cols = keys // size
        indptr = np.zeros(size + 1, dtype=np.int64)
        indptr[1:] = np.cumsum(np.bincount(entry_cols, minlength=size))
        diagonal_entries = np.flatnonzero(entry_rows == entry_cols)
        diagonal = np.empty(size, dtype=np.int64)
        diagonal[entry_rows[diagonal_entries]] = diagonal_entries
        upper = np.flatnonzero(entry_rows <= entry_cols)
        upper_indptr = np.zeros(size + 1, dtype=np.int64)
        upper_indptr[1:] = np.cumsum(np.bincount(entry_cols[upper], minlength=size))
        return cls(size, kept.copy(), slot, entry_rows, indptr, entry_cols, diagonal, upper, upper_indptr)

    def hessian_values(self, information: FloatArray, jac_a: FloatArray, jac_b: FloatArray) -> FloatArray:
        """CSC data of H = Σ JᵀΩJ."""
        omega_a = information @ jac_a
        omega_b = information @ jac_b
        jac_a_t = np.swapaxes(jac_a, 1, 2)
        jac_b_t = np.swapaxes(jac_b, 1, 2)
        blocks = np.stack([jac_a_t @ omega_a, jac_a_t @ omega_b, jac_b_t @ omega_a, jac_b_t @ omega_b],
                          axis=1)
        values = blocks.reshape(-1)[self.kept]
        return np.bincount(self.slot, weights=values, minlength=len(self.indices))


def _csc_keys(size: int, rows: IntArray, cols: IntArray) -> tuple[IntArray, IntArray]:
    """Distinct column-major keys col·size + row (sorted: the CSC order) and the key of every entry."""
    keys, slot = np.unique(cols * size + rows, return_inverse=True)
    return keys.astype(np.int64), slot.reshape(-1).astype(np.int64)


def _gradient(graph: PoseGraph, errors: FloatArray, jac_a: FloatArray, jac_b: FloatArray) -> FloatArray:
    """g = Σ JᵀΩe over the free variables (the anchor's three entries dropped)."""
    weighted = np.einsum("mij,mj->mi", graph.information, errors)
    grad_a = np.einsum("mji,mj->mi", jac_a, weighted)
    grad_b = np.einsum("mji,mj->mi", jac_b, weighted)
    within = np.arange(3)
    index = np.concatenate([(3 * graph.edge_from[:, None] + within).reshape(-1),
                            (3 * graph.edge_to[:, None] + within).reshape(-1)])
    full = np.bincount(index, weights=np.concatenate([grad_a.reshape(-1), grad_b.reshape(-1)]),
                       minlength=3 * graph.num_poses)
    return full[3:]


class _DampedSolver:
    """Solves (H + λ·diag(H)) Δ = −g for one linearisation, for as many λ as the step search needs.

    `factorisation` carries qdldl's ordering and symbolic analysis from one linearisation to the next.
    """

    def __init__(self, pattern: _NormalEquationsPattern, hessian: FloatArray, gradient: FloatArray,
                 factorisation: qdldl.Solver | None) -> None:
        self._pattern = pattern
        size = pattern.size
        self._hessian = sp.csc_matrix((hessian, pattern.indices, pattern.indptr), shape=(size, size))
        self._gradient = gradient
        diagonal = hessian[pattern.diagonal]
        floor = _DIAGONAL_FLOOR * max(float(diagonal.max(initial=0.0)), 1.0)
        self._scale = 1.0 / np.sqrt(np.maximum(diagonal, floor))
        self._scaled = hessian * self._scale[pattern.indices] * self._scale[pattern.column_of_entry]
        self._scaled_gradient = self._scale * self._gradient
        self.factorisation = factorisation

    def step(self, damping: float) -> FloatArray | None:
        """The damped step, or None when the factorisation fails or gives non-finite values."""
        data = self._scaled.copy()
        # λ·I in the scaled space is λ·diag(H), except that a variable H leaves unconstrained still gets
        # λ·floor, which keeps the damped matrix nonsingular.
        data[self._pattern.diagonal] += damping
        size = self._pattern.size
        upper = sp.csc_matrix((data[self._pattern.upper], self._pattern.indices[self._pattern.upper],
                               self._pattern.upper_indptr), shape=(size, size))
        try:
            # The damped matrix is symmetric positive definite in exact arithmetic: LDLᵀ needs no pivoting.
            if self.factorisation is None:
                self.factorisation = qdldl.Solver(upper, upper=True)
            else:
                self.factorisation.update(upper, upper=True)
            scaled_step = self.factorisation.solve(-self._scaled_gradient)
        except (ValueError, RuntimeError):  # qdldl reports a zero pivot this way
            self.factorisation = None
            return None
        if not np.all(np.isfinite(scaled_step)):
            return None
        return self._scale * scaled_step

    def predicted_decrease(self, step: FloatArray) -> float:
        """χ² decrease the linearisation predicts for `step`: −(2gᵀΔ + ΔᵀHΔ)."""
        return float(-(2.0 * self._gradient @ step + step @ (self._hessian @ step)))


@dataclass(frozen=True)
class PolishStatus:
    """How a polish ended: the generator's return value (`status = yield from gauss_newton(...)`)."""

    converged: bool
    reason: str
    iterations: int


def gauss_newton(
    graph: PoseGraph,
    poses: FloatArray | None = None,
    *,
    max_iterations: int = 50,
    relative_tolerance: float = 1e-9,
) -> Generator[Iteration, None, PolishStatus]:
    """Levenberg–Marquardt on the χ² of `graph`, from `poses` (default: the graph's estimate).

    Yields Iteration("gauss-newton", k, poses, χ²) after every accepted step, k from 1; rejected trial
    steps (χ² did not decrease, so λ is raised and the step recomputed) are not yielded. Stops when an
    accepted step decreases χ² by less than `relative_tolerance` of its value, after `max_iterations`
    accepted steps, or when λ grows past any useful value (no decrease can be found). Pose 0 stays fixed.
    """
    if max_iterations < 0:
        raise OptimizerError(f"max_iterations must be >= 0, got {max_iterations}")
    if not relative_tolerance >= 0.0:
        raise OptimizerError(f"relative_tolerance must be >= 0, got {relative_tolerance}")
    current = _starting_poses(graph, poses)
    current_chi2 = chi2(graph, current)
    if graph.num_poses < 2 or current_chi2 == 0.0:
        return PolishStatus(True, "nothing to optimize (χ² = 0)", 0)
    pattern = _NormalEquationsPattern.of(graph)
    damping = _INITIAL_LAMBDA
    growth = 2.0
    factorisation = None

    for index in range(1, max_iterations + 1):
        errors, jac_a, jac_b = edge_jacobians(graph, current)
        solver = _DampedSolver(pattern, pattern.hessian_values(graph.information, jac_a, jac_b),
                               _gradient(graph, errors, jac_a, jac_b), factorisation)
        while True:
            step = solver.step(damping)
            if step is not None:
                trial = current.copy()
                trial[1:] += step.reshape(-1, 3)
                trial[:, 2] = se2.wrap_angle(trial[:, 2])
                with np.errstate(over="ignore", invalid="ignore"):  # a wild trial step may overflow χ²
                    trial_chi2 = chi2(graph, trial)
                if np.isfinite(trial_chi2) and trial_chi2 < current_chi2:
                    break
            damping *= growth
            growth *= 2.0
            if damping > _MAX_LAMBDA:
                return PolishStatus(True, f"no decreasing step (λ > {_MAX_LAMBDA:g})", index - 1)
        factorisation = solver.factorisation

        # Nielsen's update: shrink λ the more the linear model predicted the actual decrease.
        predicted = solver.predicted_decrease(step)
        gain = (current_chi2 - trial_chi2) / predicted if predicted > 0.0 else 0.0
        damping = max(damping * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), _MIN_LAMBDA)
        growth = 2.0

        decrease = (current_chi2 - trial_chi2) / current_chi2
        current, current_chi2 = trial, trial_chi2
        current.setflags(write=False)
        yield Iteration(STAGE, index, current, current_chi2)
        if decrease < relative_tolerance or current_chi2 == 0.0:
            return PolishStatus(True, f"relative χ² change {decrease:.2g} < {relative_tolerance:g}", index)
    return PolishStatus(False, f"iteration cap {max_iterations} reached", max_iterations)


def _starting_poses(graph: PoseGraph, poses: FloatArray | None) -> FloatArray:
    start = np.array(graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if start.shape != graph.poses.shape:
        raise GraphError(f"expected poses of shape {graph.poses.shape}, got {start.shape}")
    if not np.all(np.isfinite(start)):
        raise GraphError("the starting poses contain non-finite values")
    start[:, 2] = se2.wrap_angle(start[:, 2])
    return start
