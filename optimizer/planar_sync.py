"""Headings that use the translations: the planar SE-Sync relaxation, solved at low rank.

Rotation-only heading estimates (chordal, both SGDs) weigh each measured angle alone; with heavy heading
noise (M3500-shaped worlds at σθ = 0.3 rad) the headings are known mainly through the odometry
translations, and every rotation-only estimate leads the polish into a basin about 4 % above the best
known. This module estimates the headings from the whole isotropic problem instead (Rosen, Carlone,
Bandeira & Leonard 2019, "SE-Sync"; in the plane with complex numbers as in Fan & Murphey's CPL-SLAM):

- Each heading is a unit complex number r_i, each position a complex t_i. Constraint k, in its stored
  direction a → b, costs τ_k·|t_b − t_a − z_k·r_a|² + κ_k·|r_b − e^{iθ_k}·r_a|² (z_k = x_k + i·y_k), the
  isotropic version of g2o's χ² (κ the marginal θ information, τ half the trace of the translational one:
  for small errors |e^{iδ} − 1|² ≈ δ², so the weights are χ²'s own).
- The positions enter quadratically: they are eliminated exactly, leaving rᴴ·Q·r with
  Q = L_rot + D − Bᴴ·L_τ⁻¹·B (L_rot the connection Laplacian, L_τ the translation Laplacian anchored at
  pose 0, B the translation–rotation coupling, D its diagonal). Q is applied, never formed: one sparse LU
  of L_τ, then a pair of triangular solves per product.
- Burer–Monteiro: min tr(Yᴴ·Q·Y) over Y ∈ ℂ^{N×p} with unit rows (rows on the sphere of ℝ^{2p}), by
  L-BFGS on an unconstrained X whose rows are normalised inside the cost, started from the chordal
  headings in the first column. p = 2 (rank 1 is the non-convex problem itself) sufficed on every
  σθ = 0.3 world measured; no optimality certificate is computed (its eigenvalue solve cost more than the
  solve itself, and the polish after the rounding decides anyway).
- Rounding: the leading left singular vector of Y, each entry normalised to a heading. The complex form
  has no reflection ambiguity (conjugation is not a symmetry of Q); the common phase is fixed so that pose
  0 keeps its heading. Positions then come from `initialization.positions_given_headings`, on the file's
  exact anisotropic objective.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import splu

from optimizer import se2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.initialization import (
    chordal_initialization,
    floored_translational,
    positions_given_headings,
    rotation_weights,
)

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

RANK = 2
"""Columns of the relaxation: rank 1 is the original (non-convex) problem itself."""
SOLVER_ITERATIONS = 3_000
GRADIENT_TOLERANCE = 1e-9
"""L-BFGS's projected-gradient bound on the cost divided by N times Q's largest diagonal entry."""
COST_TOLERANCE = 1e-11
"""L-BFGS stops when an iteration lowers the cost by less than this fraction. At 1e-9 the σθ = 0.3,
seed 0 M3500-shaped world stopped after 1 363 products and its polish ended 0.37 % above the best known;
at 1e-11 (2 099 products) it reaches it, as 1e-15 does (benchmarks/strong_sgd_bench.py --only basin)."""
HISTORY = 20
"""L-BFGS correction pairs."""
SEED = 0
"""Of the small random start of the columns after the first (they must not start at 0, a saddle)."""


@dataclass(frozen=True)
class SyncResult:
    """The relaxation's solution and how it was reached."""

    poses: FloatArray
    """(N, 3) rounded headings, positions solved for them on the exact objective; pose 0 is the graph's."""
    relaxed_cost: float
    """tr(Yᴴ·Q·Y) where the low-rank solve stopped (a lower bound on the isotropic problem only if that is
    the relaxation's global minimum, which is not certified)."""
    rounded_cost: float
    """rᴴ·Q·r of the rounded headings: the isotropic cost with the best positions for them."""
    evaluations: int
    """Products with Q the solve took (each one pair of triangular solves)."""


class ReducedRotationForm:
    """Q = L_rot + D − Bᴴ·L_τ⁻¹·B of a graph: the isotropic cost with the positions eliminated."""

    def __init__(self, graph: PoseGraph) -> None:
        n = graph.num_poses
        a, b = graph.edge_from, graph.edge_to
        kappa = rotation_weights(graph.information)
        translational = floored_translational(graph.information)
        tau = 0.5 * (translational[:, 0, 0] + translational[:, 1, 1])
        turn = np.exp(1j * graph.measurements[:, 2])
        step = graph.measurements[:, 0] + 1j * graph.measurements[:, 1]

        # κ|r_b − c·r_a|²: diagonal κ at a and b, (b, a) entry −κc, (a, b) entry −κc̄.
        rotation_diagonal = np.bincount(a, kappa, n) + np.bincount(b, kappa, n)
        off = sp.coo_matrix((-kappa * turn, (b, a)), shape=(n, n)).tocsr()
        self._rotation = (off + off.conj().T + sp.diags(rotation_diagonal)).tocsr()
        # τ|t_b − t_a − z·r_a|² = τ|t_b − t_a|² − 2Re(conj(t_b − t_a)·τz·r_a) + τ|z|²|r_a|².
        self._coupling_diagonal = np.bincount(a, tau * np.abs(step) ** 2, n)
        weighted = tau * step
        coupling = sp.coo_matrix((np.r_[weighted, -weighted], (np.r_[b, a], np.r_[a, a])),
                                 shape=(n, n)).tocsr()
        self._coupling = coupling[1:]  # pose 0 is the anchor: t_0 = 0
        self._coupling_adjoint = self._coupling.conj().T.tocsr()
        laplacian_off = sp.coo_matrix((-tau, (a, b)), shape=(n, n))
        laplacian = (laplacian_off + laplacian_off.T
                     + sp.diags(np.bincount(a, tau, n) + np.bincount(b, tau, n))).tocsc()[1:, 1:]
        try:
            self._translation = splu(laplacian.tocsc(), permc_spec="MMD_AT_PLUS_A")
        except RuntimeError as error:  # SuperLU reports a singular matrix this way
            raise OptimizerError(f"the translation Laplacian is singular: {error}") from error
        self.scale = float(np.max(rotation_diagonal + self._coupling_diagonal))
        self.size = n

    def apply(self, y: ComplexArray) -> ComplexArray:
        """Q·y for an (N, p) complex y."""
        coupled = self._coupling @ y
        real_and_imaginary = np.hstack([coupled.real, coupled.imag])
        solved = self._translation.solve(np.asfortranarray(real_and_imaginary))
        p = y.shape[1]
        eliminated = solved[:, :p] + 1j * solved[:, p:]
        return (self._rotation @ y + self._coupling_diagonal[:, None] * y
                - self._coupling_adjoint @ eliminated)


def planar_sync(graph: PoseGraph, *, rank: int = RANK) -> SyncResult:
    """Headings from the planar SE-Sync relaxation of `rank` columns (module docstring), positions solved
    for them on the exact objective.

    Raises OptimizerError when a linear system is singular or the solve produces non-finite values.
    """
    if rank < 1:
        raise OptimizerError(f"the relaxation's rank must be at least 1, got {rank}")
    poses = np.array(graph.poses, dtype=np.float64, copy=True)
    poses[:, 2] = se2.wrap_angle(poses[:, 2])
    if graph.num_poses < 2:
        return SyncResult(poses, 0.0, 0.0, 0)
    form = ReducedRotationForm(graph)
    rng = np.random.default_rng(SEED)
    first = np.exp(1j * chordal_initialization(graph)[:, 2])[:, None]
    start = np.hstack([first, 1e-3 * _random_rows(rng, graph.num_poses, rank - 1)])
    y, relaxed, evaluations = _solve_at_rank(form, start)
    headings = _round(y)
    rounded = float(np.real(np.vdot(headings, form.apply(headings[:, None])[:, 0])))
    poses[:, 2] = se2.wrap_angle(np.angle(headings) - np.angle(headings[0]) + poses[0, 2])
    poses = positions_given_headings(graph, poses)
    return SyncResult(poses, relaxed, rounded, evaluations)


def sync_initialization(graph: PoseGraph) -> FloatArray:
    """(N, 3) poses from `planar_sync`: a start for the polish, as `chordal_initialization` is."""
    return planar_sync(graph).poses


# ----------------------------------------------------------------------------------------- the pieces


def _random_rows(rng: np.random.Generator, rows: int, columns: int) -> ComplexArray:
    return rng.standard_normal((rows, columns)) + 1j * rng.standard_normal((rows, columns))


def _solve_at_rank(form: ReducedRotationForm, start: ComplexArray) -> tuple[ComplexArray, float, int]:
    """Minimise tr(Yᴴ·Q·Y) over unit rows by L-BFGS on X with Y = rows of X normalised."""
    n, p = start.shape
    scale = form.scale * n

    def cost_and_gradient(flat: FloatArray) -> tuple[float, FloatArray]:
        x = flat[: n * p].reshape(n, p) + 1j * flat[n * p:].reshape(n, p)
        norms = np.sqrt(np.sum(np.abs(x) ** 2, axis=1))[:, None]
        y = x / norms
        qy = form.apply(y)
        cost = float(np.real(np.vdot(y, qy)))
        gradient = 2.0 * qy
        # Through the normalisation: remove the radial part, divide by the row norm.
        radial = np.real(np.sum(np.conj(y) * gradient, axis=1))[:, None]
        gradient = (gradient - radial * y) / norms
        return cost / scale, np.concatenate([gradient.real.ravel(), gradient.imag.ravel()]) / scale

    # Imported here: scipy.optimize adds about 0.2 s to every command's start-up; few graphs need this.
    from scipy.optimize import minimize

    flat = np.concatenate([start.real.ravel(), start.imag.ravel()])
    solution = minimize(cost_and_gradient, flat, jac=True, method="L-BFGS-B",
                        options={"maxiter": SOLVER_ITERATIONS, "gtol": GRADIENT_TOLERANCE,
                                 "ftol": COST_TOLERANCE, "maxcor": HISTORY})
    x = solution.x[: n * p].reshape(n, p) + 1j * solution.x[n * p:].reshape(n, p)
    if not np.all(np.isfinite(x)):
        raise OptimizerError("the synchronisation's low-rank solve diverged")
    y = x / np.sqrt(np.sum(np.abs(x) ** 2, axis=1))[:, None]
    return y, float(solution.fun) * scale, int(solution.nfev)


def _round(y: ComplexArray) -> ComplexArray:
    """Unit complex headings from the leading left singular vector of Y."""
    u, _, _ = np.linalg.svd(y, full_matrices=False)
    leading = u[:, 0]
    magnitude = np.abs(leading)
    if np.any(magnitude == 0.0):
        raise OptimizerError("the synchronisation's rounding is degenerate (a heading is zero)")
    return leading / magnitude
