"""Conjugate gradients preconditioned by smoothed-aggregation algebraic multigrid (pyamg), for the polish of
graphs too large to factorise.

The normal equations of a pose graph are a weighted graph Laplacian in 3×3 blocks: on a 10⁵-pose grid
world the chain preconditioner of `optimizer.damped_solvers` needs 300–500 CG iterations per step once the
loops matter, while one multigrid V-cycle per iteration brings a relative residual of 10⁻⁴ in about 16.
The hierarchy (aggregation of poses, prolongation, coarse operators; `optimizer.multigrid_hierarchy`) costs
about as much as 10–20 CG iterations to build. It is built for each linearisation and kept across the λ
tried on it: CG with it at a new λ gets `rebuild_growth` times the iterations the first solve after its
build needed (at least 20); past them, unless the rate it has shown projects the target within what a new
hierarchy's first solve took, it is rebuilt for the new λ and CG goes on from its partial solution. A kept
hierarchy gets the new λ's matrix as its finest level, with the smoother's inverted diagonal blocks of its
own (`_hook_in`); its coarse levels are stale, which only slows CG, it never changes the step CG converges
to. A hierarchy is not kept for the next linearisation: its candidates and prolongation come from the
poses it was built at, and in the last steps at 10⁶ grid-world poses, where the poses still move far along
the graph's softest modes while χ² hardly changes, CG with the hierarchy of an earlier step needed 15–40
iterations where a new one needed 11–15. The V-cycle is run directly
(`_v_cycle`), not through pyamg's `aspreconditioner`, which spends two extra products with H per
application, with compiled block Gauss–Seidel sweeps, restriction and prolongation
(`optimizer.block_smoother`). On the 3·10⁵-pose grid world (A/B on the same loaded machine) a CG iteration
fell from about 0.24 to 0.16 CPU s with those kernels and a build with CG's first 5 iterations from 5 to
3.5; at 10⁶ poses (2·10⁶ constraints, machine at load 2.4–3) a build cost about 5.9 CPU s and a CG
iteration 0.61 (benchmarks/README.md, scale section). pyamg is imported with this module, which
`optimizer.polish` loads only when it needs it.
"""

from __future__ import annotations

import math

import numpy as np
import pyamg
import scipy.sparse as sp
from numpy.typing import NDArray

from optimizer.block_normal_equations import BlockPattern, add_to_diagonal, scale_blocks
from optimizer.block_smoother import (
    gauss_seidel_sweep,
    inverted_diagonal,
    presmooth_from_zero,
    prolong_into,
    restrict,
)
from optimizer.damped_solvers import Linearisation, preconditioned_cg
from optimizer.multigrid_hierarchy import HierarchyPatterns, smoothed_aggregation
from optimizer.parallel_products import block_product

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_MIN_ITERATIONS_FOR_REBUILD = 20
"""Below this a solve is cheap whatever the hierarchy: no rebuild."""


class MultigridPCGSolver:
    """Inexact steps by CG on S·H·S + λ·I (BSR, 3×3 blocks) with a smoothed-aggregation V-cycle.

    CG stops once the residual is below `forcing` times the right-hand side, or after `max_iterations`.
    To save a copy of H (360 MB at 10⁶ poses) the solver turns the blocks of each linearisation it is
    given into those of S·H·S + λ·I in place: `linearisation.hessian` is no longer H afterwards.
    """

    exact = False

    def __init__(self, pattern: BlockPattern, *, max_iterations: int = 500,
                 rebuild_growth: float = 3.0, aggregation_order: IntArray | None = None) -> None:
        self._pattern = pattern
        self._aggregation_order = aggregation_order
        self._max_iterations = max_iterations
        self._rebuild_growth = rebuild_growth
        self._linearisation: Linearisation | None = None
        self._damping = 0.0
        self._preconditioner: pyamg.MultilevelSolver | None = None
        self._iterations_after_build = 0
        self._patterns = HierarchyPatterns()
        self.forcing = 1e-2
        self.last_iterations = 0
        self.last_converged = True
        self.builds = 0
        """Hierarchies built so far."""

    def step(self, linearisation: Linearisation, damping: float) -> FloatArray | None:
        """The scaled step y, or None when CG gives no finite step."""
        blocks = linearisation.hessian
        assert blocks is not None
        pattern = self._pattern
        if linearisation is not self._linearisation:
            scale_blocks(blocks, pattern.indptr, pattern.indices, linearisation.scale)
            self._linearisation, self._damping = linearisation, 0.0
        add_to_diagonal(blocks, pattern.diagonal_block, damping - self._damping)
        self._damping = damping
        size = 3 * pattern.free
        matrix = sp.bsr_matrix((blocks, pattern.indices, pattern.indptr), shape=(size, size))
        rhs = -linearisation.scale * linearisation.gradient
        iterations = 0
        partial: FloatArray | None = None
        if self._preconditioner is not None:
            # The same linearisation at a new λ: the kept hierarchy's finest level gets the damped matrix's
            # new diagonal blocks inverted for its smoother; the coarse levels stay from the build.
            _hook_in(self._preconditioner, matrix)
            # The kept hierarchy gets the budget a good one needs; past it, it is rebuilt and CG goes on
            # from where it got to (new search directions: the preconditioner changed).
            budget = min(self._max_iterations, max(_MIN_ITERATIONS_FOR_REBUILD,
                                                   int(self._rebuild_growth * self._iterations_after_build)))
            solution, iterations, converged = self._solve(matrix, rhs, budget)
            exhausted = not converged and iterations == budget < self._max_iterations
            if exhausted:
                # Close to the target at the rate it has shown, the kept hierarchy goes on: a new one would
                # cost a build and about as many iterations as the last build's first solve took.
                more = _iterations_to_finish(matrix, rhs, solution, iterations, self.forcing)
                if more <= self._iterations_after_build:
                    extension = int(min(2 * more, self._max_iterations - iterations))
                    solution, extra, converged = self._solve(matrix, rhs, extension, solution)
                    iterations += extra
                    exhausted = not converged and extra == extension
            if exhausted:
                self._preconditioner = None
                partial = solution if np.all(np.isfinite(solution)) else None
        if self._preconditioner is None:
            # No copy of H for the hierarchy (360 MB at 10⁶ poses): its finest level shares the blocks, so a
            # new λ on this linearisation reaches the V-cycle's residuals too, and its smoother only reads
            # the off-diagonal blocks (the inverted diagonal blocks are kept from the build).
            self._preconditioner = _hierarchy(matrix, linearisation, self._patterns, self._aggregation_order)
            self.builds += 1
            solution, fresh_iterations, converged = self._solve(matrix, rhs, self._max_iterations, partial)
            self._iterations_after_build = fresh_iterations
            iterations += fresh_iterations
        self.last_iterations, self.last_converged = iterations, converged
        return solution if np.all(np.isfinite(solution)) and iterations > 0 else None

    def accepted_step(self) -> None:
        """Told after every accepted step: the next linearisation gets a new hierarchy (see the module doc),
        and this one's blocks, which the hierarchy's finest level shares, can go before the next H is
        assembled (two H at once were the polish's peak at 10⁶ poses, 360 MB each)."""
        self._preconditioner = None
        self._linearisation = None

    def _solve(self, matrix: sp.bsr_matrix, rhs: FloatArray, max_iterations: int,
               start: FloatArray | None = None) -> tuple[FloatArray, int, bool]:
        preconditioner = self._preconditioner
        assert preconditioner is not None

        def precondition(residual: FloatArray, out: FloatArray) -> None:
            out[:] = _v_cycle(preconditioner, 0, residual)

        def apply(vector: FloatArray) -> FloatArray:
            return block_product(matrix, vector)  # scipy's matrix.dot to the bit, on all threads

        return preconditioned_cg(apply, precondition, rhs, self.forcing, max_iterations, start)


def _iterations_to_finish(matrix: sp.bsr_matrix, rhs: FloatArray, solution: FloatArray, iterations: int,
                          forcing: float) -> float:
    """How many more CG iterations `solution` (after `iterations` from zero) needs to reach `forcing` at the
    mean rate of residual reduction it has shown so far (inf when it has shown none)."""
    rhs_norm = float(np.linalg.norm(rhs))
    residual_norm = float(np.linalg.norm(rhs - block_product(matrix, solution)))
    reduction = residual_norm / rhs_norm if rhs_norm > 0.0 else math.nan
    if not 0.0 < reduction < 1.0 or iterations < 1:
        return math.inf
    rate = reduction ** (1.0 / iterations)
    return max(1.0, math.ceil(math.log(forcing / reduction) / math.log(rate)))


def _hook_in(hierarchy: pyamg.MultilevelSolver, matrix: sp.bsr_matrix) -> None:
    """`matrix` becomes the finest level of `hierarchy`, with block Gauss–Seidel smoothers of its own
    (their inverted diagonal blocks from `matrix`); the coarse levels stay."""
    finest = hierarchy.levels[0]
    finest.A = matrix
    _attach_smoothers(finest)


def _attach_smoothers(level: pyamg.MultilevelSolver.Level) -> None:
    """The inverted diagonal blocks of `level.A`, for the V-cycle's block Gauss–Seidel sweeps
    (`optimizer.block_smoother`)."""
    level.inverse_diagonal = inverted_diagonal(level.A)


def _v_cycle(hierarchy: pyamg.MultilevelSolver, level: int, rhs: FloatArray) -> FloatArray:
    """One V-cycle on `hierarchy`'s level `level` from zero: pyamg's own cycle with a forward block
    Gauss–Seidel sweep before the coarse correction and a backward one after it (symmetric, what CG needs),
    without what pyamg's `solve` adds around it as a preconditioner (`aspreconditioner`): a product with
    the finest matrix before and after the cycle, only to measure residual norms that one cycle never
    uses. The first sweep and the residual after it are one pass (`presmooth_from_zero`)."""
    levels = hierarchy.levels
    if len(levels) == 1:  # a system small enough for the coarse solver alone
        return np.asarray(hierarchy.coarse_solver(levels[0].A, rhs), dtype=np.float64)
    current = levels[level]
    solution = np.empty_like(rhs)
    residual = np.empty_like(rhs)
    presmooth_from_zero(current.A, current.inverse_diagonal, rhs, solution, residual)
    coarse_rhs = restrict(current.P, residual)
    del residual
    if level == len(levels) - 2:
        coarse_solution = hierarchy.coarse_solver(levels[-1].A, coarse_rhs)
    else:
        coarse_solution = _v_cycle(hierarchy, level + 1, coarse_rhs)
    prolong_into(current.P, coarse_solution, solution)
    gauss_seidel_sweep(current.A, current.inverse_diagonal, solution, rhs, forward=False)
    return solution


def _hierarchy(matrix: sp.bsr_matrix, linearisation: Linearisation,
               patterns: HierarchyPatterns | None = None,
               aggregation_order: IntArray | None = None) -> pyamg.MultilevelSolver:
    """Smoothed aggregation on the 3×3 blocks. The near-null space is that of H before the anchor pins the
    graph down: the rigid motions of all poses together, the two translations and the rotation about the
    centroid (δθ = 1, δt = R(π/2)·(t − centroid)), in the scaled variables (S⁻¹ times each motion). Without
    the rotation CG needs about five times the iterations (62 against 13 on a 10⁵-pose grid world)."""
    free_poses = linearisation.poses[1:]
    unscale = (1.0 / linearisation.scale).reshape(-1, 3)
    motions = np.zeros((free_poses.shape[0], 3, 4))
    motions[:, 0, 0] = motions[:, 1, 1] = motions[:, 2, 2] = 1.0
    centroid = free_poses[:, :2].mean(axis=0)
    motions[:, 0, 3] = -(free_poses[:, 1] - centroid[1])
    motions[:, 1, 3] = free_poses[:, 0] - centroid[0]
    motions[:, 2, 3] = 1.0
    near_null = (motions * unscale[:, :, None]).reshape(-1, 4)
    # (`optimizer.multigrid_hierarchy`: the candidates are not relaxed first, which saved a tenth of the
    # setup's memory and a third of its time at the same CG iteration count, 13 to 1e-6 on the 10⁵-pose grid
    # world; the prolongation smoother's Jacobi weight comes from each row's Gershgorin bound instead of an
    # Arnoldi estimate of ρ(D⁻¹A) on every level, which was 70 % of the setup at 10⁶ poses for the same CG
    # iteration counts on the 10⁵-pose grid world, and needs no random start vector.)
    # One forward Gauss–Seidel sweep before and one backward sweep after the coarse correction keep the
    # V-cycle symmetric (what CG needs) at half the smoothing of two symmetric sweeps: about 8 % more CG
    # iterations, a quarter less time per iteration.
    hierarchy = smoothed_aggregation(matrix, near_null, patterns, aggregation_order)
    for level in hierarchy.levels[:-1]:
        _attach_smoothers(level)
    return hierarchy
