"""The smoothed-aggregation multigrid hierarchy of the polish's CG preconditioner, built from pyamg's parts.

The steps are pyamg's `smoothed_aggregation_solver` with the options the polish used (strength "symmetric"
with θ = 0, standard aggregation, candidates not improved, one Jacobi step of prolongation smoothing with
ω = 4/3 and the "local" weighting, Galerkin coarse operators, pinv on the coarsest level), but the
prolongation is smoothed as P = T − ω·D⁻¹·(A·T), D the row sums of |A|, where pyamg forms |A|, D⁻¹·A and
ω·D⁻¹·A, three copies of A (360 MB each at 10⁶ poses), to multiply T once. On the 2·10⁵-pose grid world
after paper SGD that halved the build's traced peak memory (489 → 261 MB) and its time; the levels are
pyamg's to rounding (same sizes and sparsity, prolongations equal to 1e-15 relative; where a block of P
cancels to exactly zero one of the two drops it).
"""

from __future__ import annotations

import itertools

import numpy as np
import pyamg
import scipy.sparse as sp
from numba import njit
from numpy.typing import NDArray
from pyamg.aggregation.aggregate import standard_aggregation
from pyamg.aggregation.tentative import fit_candidates
from pyamg.strength import symmetric_strength_of_connection

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32] | NDArray[np.int64]

MAX_COARSE = 500
"""Block rows at which coarsening stops and pinv solves the level."""
MAX_LEVELS = 10
GALERKIN_BAND_ROWS = 32_768
"""Coarse block rows per band of the Galerkin product (`_galerkin`): 6 bands at 10⁶ poses."""
OMEGA = 4.0 / 3.0
"""The prolongation smoother's Jacobi weight, relative to the Gershgorin bound of each row."""


def smoothed_aggregation(matrix: sp.bsr_matrix, near_null: FloatArray) -> pyamg.MultilevelSolver:
    """The hierarchy of the symmetric positive definite `matrix` (BSR, square blocks) whose near-null space
    is spanned by the columns of `near_null`; every level's A and P in BSR. No R: the restriction is Pᵀ,
    applied from P's blocks in place (`optimizer.block_smoother.restrict`), not stored (224 MB at 10⁶
    poses)."""
    levels = [pyamg.MultilevelSolver.Level()]
    levels[0].A = matrix
    candidates = np.asarray(near_null, dtype=np.float64)
    while len(levels) < MAX_LEVELS and levels[-1].A.shape[0] // levels[-1].A.blocksize[0] > MAX_COARSE:
        fine = levels[-1]
        aggregates, _ = standard_aggregation(symmetric_strength_of_connection(fine.A))
        tentative, candidates = fit_candidates(aggregates, candidates)
        del aggregates
        fine.P = _smoothed_prolongation(fine.A, tentative)
        del tentative
        coarse = pyamg.MultilevelSolver.Level()
        coarse.A = _galerkin(fine.A, fine.P)
        levels.append(coarse)
    return pyamg.MultilevelSolver(levels, coarse_solver="pinv")


def _smoothed_prolongation(matrix: sp.bsr_matrix, tentative: sp.bsr_matrix) -> sp.bsr_matrix:
    """T − ω·D⁻¹·(A·T), D the row sums of |A| (pyamg's "local" weighting; rows with D = 0 keep T)."""
    size = matrix.blocksize[0]
    weights = np.zeros(matrix.shape[0])
    _absolute_row_sums(matrix.indptr, matrix.data, weights)
    nonzero = weights != 0.0
    weights[nonzero] = OMEGA / weights[nonzero]
    product = sp.bsr_matrix(matrix @ tentative, blocksize=tentative.blocksize)
    block_rows = np.repeat(np.arange(product.shape[0] // size), np.diff(product.indptr))
    product.data *= weights.reshape(-1, size)[block_rows][:, :, None]
    del block_rows
    return sp.bsr_matrix(tentative - product, blocksize=tentative.blocksize)


def _galerkin(matrix: sp.bsr_matrix, prolongation: sp.bsr_matrix) -> sp.bsr_matrix:
    """Pᵀ·A·P, pyamg's (R·A)·P with R = Pᵀ, computed for bands of the coarse block rows and stacked: R·A whole
    (it has more blocks than A) was the build's largest transient. The product works row by row, so the
    bands' rows are the whole product's, in the same order."""
    restriction = sp.bsr_matrix(prolongation.T)
    rows = restriction.shape[0] // restriction.blocksize[0]
    bands = max(1, -(-rows // GALERKIN_BAND_ROWS))
    bounds = np.linspace(0, rows, bands + 1).astype(np.int64).tolist()
    pieces = []
    for start, stop in itertools.pairwise(bounds):
        pieces.append(sp.bsr_matrix((_band(restriction, start, stop) @ matrix) @ prolongation,
                                    blocksize=(restriction.blocksize[0], prolongation.blocksize[1])))
    del restriction
    offsets = np.cumsum([0] + [piece.indptr[-1] for piece in pieces[:-1]])
    indptr = np.concatenate([pieces[0].indptr[:1].astype(np.int64)]
                            + [piece.indptr[1:].astype(np.int64) + offset
                               for piece, offset in zip(pieces, offsets, strict=True)])
    indices = np.concatenate([piece.indices for piece in pieces])
    data = np.concatenate([piece.data for piece in pieces])
    del pieces
    return sp.bsr_matrix((data, indices, indptr), shape=(prolongation.shape[1],) * 2)


def _band(matrix: sp.bsr_matrix, start: int, stop: int) -> sp.bsr_matrix:
    """Block rows start..stop−1 of `matrix`, sharing its arrays."""
    first, last = matrix.indptr[start], matrix.indptr[stop]
    return sp.bsr_matrix((matrix.data[first:last], matrix.indices[first:last],
                          matrix.indptr[start:stop + 1] - first),
                         shape=((stop - start) * matrix.blocksize[0], matrix.shape[1]))


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
