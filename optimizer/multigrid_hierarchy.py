"""The smoothed-aggregation multigrid hierarchy of the polish's CG preconditioner, built from pyamg's parts.

The steps are pyamg's `smoothed_aggregation_solver` with the options the polish used (strength "symmetric"
with θ = 0, standard aggregation, candidates not improved, one Jacobi step of prolongation smoothing with
ω = 4/3 and the "local" weighting, Galerkin coarse operators), but the coarsest level is solved by
Cholesky where it is positive definite instead of pyamg's pseudo-inverse (`CoarsestSolver`), and the
prolongation is smoothed as P = T − ω·D⁻¹·(A·T), D the row sums of |A|, where pyamg forms |A|, D⁻¹·A and
ω·D⁻¹·A, three copies of A (360 MB each at 10⁶ poses), to multiply T once; the two sparse products are
compiled (`optimizer.hierarchy_products`: scipy's arithmetic in scipy's order, without its intermediates),
and no level stores R. The levels are pyamg's to rounding (same sizes and sparsity, prolongations equal
to 1e-15 relative; where a block of P cancels to exactly zero one of the two drops it). At 10⁶ poses
(grid world after paper SGD) a build took 6.4–8.0 CPU s and peaked 765 MB above where it started, its
levels then holding 582 MB, where pyamg's parts with scipy's products had taken 10.6–11.5 s and 1 017 MB
(834 MB kept); most of the difference is pyamg's R.

With strength θ = 0 every step that reads only sparsity patterns (strength, aggregation, the products'
symbolic passes) gives the same result for every matrix of one pattern, which is what the polish builds a
hierarchy for at each linearisation of one graph: `HierarchyPatterns` keeps those results from one build
for the next, level by level, as long as the patterns it was derived from are met again. The numbers are
the same with and without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyamg
import scipy.linalg
import scipy.sparse as sp
from numba import njit
from numpy.typing import NDArray
from pyamg import amg_core
from pyamg.aggregation.aggregate import standard_aggregation
from pyamg.strength import symmetric_strength_of_connection

from optimizer.freed_memory import return_freed_memory
from optimizer.hierarchy_products import (
    GalerkinPattern,
    ProlongationPattern,
    galerkin_product,
    smoothed_prolongation,
)
from optimizer.locality_order import inverse

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32] | NDArray[np.int64]

MAX_COARSE = 500
"""Block rows at which coarsening stops and the coarsest level is solved directly (`CoarsestSolver`)."""
CHOLESKY_MIN_PIVOT = 1e-12
"""Relative to the largest, the smallest Cholesky pivot (squared) a coarsest level is solved with; below
it the level counts as singular and gets the pseudo-inverse."""
MAX_LEVELS = 10
OMEGA = 4.0 / 3.0
"""The prolongation smoother's Jacobi weight, relative to the Gershgorin bound of each row."""


@dataclass(frozen=True)
class _LevelPatterns:
    """What one level's build derived from patterns alone: its aggregates, and the symbolic passes of its
    two products."""

    aggregates: sp.csr_array
    prolongation: ProlongationPattern
    galerkin: GalerkinPattern
    coarse_visit_order: IntArray | None
    """The order the next level's aggregation visits its block rows in (`_aggregated_in_order`)."""


class HierarchyPatterns:
    """The pattern-only results of a build, level by level, for the next build of a matrix of the same
    pattern (`smoothed_aggregation`). A level's are reused only when its matrix has the pattern they were
    derived from: the finest level's is compared, a coarse level's follows from the finer level's products
    when both were reused (a prolongation block that cancels to exactly zero is dropped, so P's pattern,
    and with it the next level's, can differ between two matrices of one pattern: P's is compared)."""

    def __init__(self) -> None:
        self._finest_indptr: IntArray | None = None
        self._finest_indices: IntArray | None = None
        self._levels: list[_LevelPatterns] = []
        self.reused_levels = 0
        """Levels of the last build that reused all three."""

    def keep(self, levels: list[_LevelPatterns], reused: int) -> None:
        """A build's levels, the first `reused` of them from the kept ones."""
        self._levels, self.reused_levels = levels, reused

    def matching_levels(self, matrix: sp.bsr_matrix) -> list[_LevelPatterns]:
        """The kept levels when `matrix` has the finest pattern they come from, else none (and forgets
        them: the new pattern's replace them)."""
        if (self._finest_indptr is not None and self._finest_indices is not None
                and np.array_equal(matrix.indptr, self._finest_indptr)
                and np.array_equal(matrix.indices, self._finest_indices)):
            return self._levels
        self._finest_indptr, self._finest_indices = matrix.indptr.copy(), matrix.indices.copy()
        self._levels = []
        return []


def smoothed_aggregation(matrix: sp.bsr_matrix, near_null: FloatArray,
                         patterns: HierarchyPatterns | None = None,
                         visit_order: IntArray | None = None) -> pyamg.MultilevelSolver:
    """The hierarchy of the symmetric positive definite `matrix` (BSR, square blocks) whose near-null space
    is spanned by the columns of `near_null`; every level's A and P in BSR. No R: the restriction is Pᵀ,
    applied from P's blocks in place (`optimizer.block_smoother.restrict`), not stored (232 MB at 10⁶
    poses). `patterns` (optional) carries the pattern-only results from one call to the next."""
    return_freed_memory()  # what the caller freed since the last build, before the levels go on top of it
    levels = [pyamg.MultilevelSolver.Level()]
    levels[0].A = matrix
    candidates = np.asarray(near_null, dtype=np.float64)
    known = patterns.matching_levels(matrix) if patterns is not None else []
    derived: list[_LevelPatterns] = []
    reused = 0
    while len(levels) < MAX_LEVELS and levels[-1].A.shape[0] // levels[-1].A.blocksize[0] > MAX_COARSE:
        fine = levels[-1]
        # This level's matrix has the kept pattern if every finer level reused its products.
        same = known[reused] if reused == len(derived) < len(known) else None
        if same is not None:
            aggregates, coarse_visit_order = same.aggregates, same.coarse_visit_order
        elif visit_order is not None:
            aggregates, coarse_visit_order = _aggregated_in_order(symmetric_strength_of_connection(fine.A),
                                                                  visit_order)
        else:
            aggregates, _ = standard_aggregation(symmetric_strength_of_connection(fine.A))
            coarse_visit_order = None
        tentative, candidates = _tentative_prolongation(aggregates, candidates)
        fine.P, prolongation = _smoothed_prolongation(fine.A, tentative,
                                                      same.prolongation if same is not None else None)
        del tentative
        galerkin = same.galerkin if same is not None and same.galerkin.fits(fine.P) else None
        reused += galerkin is not None
        coarse = pyamg.MultilevelSolver.Level()
        coarse.A, galerkin = galerkin_product(fine.A, fine.P, galerkin)
        derived.append(_LevelPatterns(aggregates, prolongation, galerkin, coarse_visit_order))
        del aggregates
        visit_order = coarse_visit_order
        levels.append(coarse)
    if patterns is not None:
        patterns.keep(derived, reused)
    for level in levels[:-1]:
        # pyamg's MultilevelSolver stores R = Pᵀ on every level that has none: 232 MB at 10⁶ poses, and a
        # second copy while it is made (the transpose, then its conjugate), at the end of the build.
        level.R = None
    return_freed_memory()  # the build's scratch, freed below the levels
    return pyamg.MultilevelSolver(levels, coarse_solver=CoarsestSolver())


FIT_TOLERANCE = 1e-10
"""pyamg's `fit_candidates` default: a candidate whose norm on an aggregate falls below it is dropped
there."""


def _tentative_prolongation(aggregates: sp.csr_array,
                            candidates: FloatArray) -> tuple[sp.bsr_matrix, FloatArray]:
    """pyamg's `fit_candidates(aggregates, candidates)`: the tentative prolongation T (BSR, one block per
    aggregated row) and the coarse candidates, from pyamg's own compiled fit, but with T's blocks put in
    row order directly. pyamg builds Tᵀ and transposes it, with a copy of the blocks on the way: 0.5 of a
    build's 3.4 s at 10⁶ poses. The same arrays, bit for bit (tested)."""
    rows, count = aggregates.shape
    per_row = candidates.shape[0] // rows
    width = candidates.shape[1]
    by_aggregate = aggregates.tocsc()
    flat_candidates = np.ascontiguousarray(candidates, dtype=np.float64).reshape(-1)
    fitted = np.empty((aggregates.nnz, per_row, width))
    coarse = np.empty((count, width, width))
    amg_core.fit_candidates(rows, count, per_row, width, by_aggregate.indptr, by_aggregate.indices,
                            fitted.reshape(-1), flat_candidates, coarse.reshape(-1), FIT_TOLERANCE)
    blocks = np.empty_like(fitted)
    blocks[aggregates.indptr[by_aggregate.indices]] = fitted  # the fit lists each aggregate's rows in turn
    tentative = sp.bsr_matrix((blocks, aggregates.indices, aggregates.indptr),
                              shape=(per_row * rows, width * count))
    return tentative, coarse.reshape(-1, width)


def _aggregated_in_order(strength: sp.csr_array, visit_order: IntArray) -> tuple[sp.csr_array, IntArray]:
    """pyamg's standard aggregation of the rows of `strength` visited in `visit_order` (row `visit_order[k]`
    k-th; within a row its neighbours in that order too), the aggregates numbered by their first row, and
    the order they were formed in (the number of the aggregate formed j-th, for each j).

    Standard aggregation is greedy, so the shape of the aggregates depends on the order it meets the rows in;
    numbering the aggregates by their first row keeps the coarse levels in the rows' order."""
    visit_order = np.asarray(visit_order, dtype=np.int64)
    visited = sp.csr_array(strength)[visit_order][:, visit_order]
    visited.sort_indices()
    aggregates_visited, _ = standard_aggregation(visited)
    aggregates_visited = sp.csr_array(aggregates_visited)
    rows = visit_order.shape[0]
    position = inverse(visit_order)
    in_rows = aggregates_visited[position]  # row r of the strength is visited row position[r]
    members = np.diff(in_rows.indptr) > 0
    member_rows = np.flatnonzero(members)
    formation = in_rows.indices.astype(np.int64)
    count = aggregates_visited.shape[1]
    first_row = np.full(count, rows, dtype=np.int64)
    np.minimum.at(first_row, formation, member_rows)
    number = np.empty(count, dtype=np.int64)
    number[np.argsort(first_row, kind="stable")] = np.arange(count)
    renumbered = sp.csr_array((np.ones(member_rows.shape[0], dtype=np.int32),
                               number[formation].astype(in_rows.indices.dtype), in_rows.indptr),
                              shape=(rows, count))
    return renumbered, number


class CoarsestSolver:
    """The coarsest level's solve, factorised at its first call: Cholesky, or where the level is singular
    (a candidate dropped on some aggregate leaves zero rows) the pseudo-inverse, from the symmetric
    eigendecomposition (`scipy.linalg.pinvh`), as pyamg's "pinv" does from the SVD. With up to
    `MAX_COARSE` block rows of 4 unknowns, pyamg's SVD took 1.2 s at every build of a 3·10⁵-pose
    graph's hierarchy, a quarter of its polish; the Cholesky factor, a few milliseconds."""

    def __init__(self) -> None:
        self._cholesky: tuple[FloatArray, bool] | None = None
        self._pseudo_inverse: FloatArray | None = None

    def __call__(self, matrix: sp.sparray | sp.spmatrix, rhs: FloatArray) -> FloatArray:
        if self._cholesky is None and self._pseudo_inverse is None:
            dense = matrix.toarray()
            try:
                factor = scipy.linalg.cho_factor(dense, lower=True)
                pivots = np.diag(factor[0])
                if not pivots.min() ** 2 > CHOLESKY_MIN_PIVOT * pivots.max() ** 2:
                    raise np.linalg.LinAlgError("a pivot too small for the level to count as regular")
                self._cholesky = factor
            except np.linalg.LinAlgError:
                self._pseudo_inverse = scipy.linalg.pinvh(dense)
        if self._cholesky is not None:
            return scipy.linalg.cho_solve(self._cholesky, rhs)
        assert self._pseudo_inverse is not None
        return self._pseudo_inverse @ rhs


def _smoothed_prolongation(matrix: sp.bsr_matrix, tentative: sp.bsr_matrix,
                           pattern: ProlongationPattern | None) -> tuple[sp.bsr_matrix, ProlongationPattern]:
    """T − ω·D⁻¹·(A·T), D the row sums of |A| (pyamg's "local" weighting; rows with D = 0 keep T)."""
    weights = np.zeros(matrix.shape[0])
    _absolute_row_sums(matrix.indptr, matrix.data, weights)
    nonzero = weights != 0.0
    weights[nonzero] = OMEGA / weights[nonzero]
    return smoothed_prolongation(matrix, tentative, weights, pattern)


@njit(cache=True)
def _absolute_row_sums(indptr: IntArray, data: FloatArray, out: FloatArray) -> None:
    """out[r] += Σ |A[r, :]| over the BSR blocks (`data` (blocks, rows, columns)), without a copy of |A|."""
    rows, columns = data.shape[1], data.shape[2]
    for block_row in range(indptr.shape[0] - 1):
        for position in range(indptr[block_row], indptr[block_row + 1]):
            for p in range(rows):
                total = 0.0
                for q in range(columns):
                    total += abs(data[position, p, q])
                out[block_row * rows + p] += total
