"""Block Gauss–Seidel sweeps on square-block BSR matrices, the multigrid V-cycle's smoother.

pyamg's own block Gauss–Seidel (`amg_core.block_gauss_seidel`) multiplies every block through a general
dense-product routine with temporaries of its own: on the 3×3 blocks of a 2·10⁵-pose grid world's normal
equations one sweep cost about four products with the matrix, and the two sweeps of the finest level were
most of a CG iteration's time in the multigrid polish. These sweeps do the same arithmetic, block by block,
in compiled loops. The inverted diagonal blocks are passed in (`inverted_diagonal`), computed once per
matrix.

The V-cycle's first sweep starts from zero and is followed by the residual b − A·x. From zero a forward
sweep reads only the blocks below the diagonal (those above multiply zeros), and what it leaves as the
residual is −U·x, the blocks above the diagonal times the final x; for a symmetric A those are the
transposes of the blocks below, so one pass over the lower blocks gives both (`presmooth_from_zero`): half
the matrix read once, where a sweep and a product read it whole twice.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import literally, njit, prange
from numpy.typing import NDArray

from optimizer.errors import OptimizerError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32] | NDArray[np.int64]
Four = tuple[float, float, float, float]

INVERSION_CHUNK = 4096
"""Diagonal blocks each thread inverts with one scratch array (`_invert_blocks`)."""


def inverted_diagonal(matrix: sp.bsr_matrix) -> FloatArray:
    """The inverses of the square diagonal blocks of `matrix` (pseudo-inverses of all of them where one is
    singular). Each block by Gauss–Jordan elimination with partial pivoting, compiled, on all threads:
    numpy's `inv` calls LAPACK once per block, 0.5 CPU s for the 10⁶ 3×3 blocks of the finest level, which
    the polish inverts at every build and every λ; this takes a few milliseconds (equal to LAPACK's to
    rounding, tested). A block is singular when a pivot is exactly zero, as for LAPACK's `getrf`."""
    blocks = _diagonal_of(matrix)
    if not _invert_blocks(blocks):  # a pose or aggregate its constraints leave free in some direction
        return np.linalg.pinv(_diagonal_of(matrix)).astype(np.float64, copy=False)
    return blocks


@njit(cache=True, parallel=True)
def _invert_blocks(blocks: FloatArray) -> bool:
    """Inverts each (n, n) block of `blocks` in place; False when one of them is singular (the others
    may then be inverted or not)."""
    count, size = blocks.shape[0], blocks.shape[1]
    chunks = (count + INVERSION_CHUNK - 1) // INVERSION_CHUNK
    regular = np.ones(chunks, dtype=np.bool_)
    for chunk in prange(chunks):
        augmented = np.empty((size, 2 * size))
        for block in range(chunk * INVERSION_CHUNK, min(count, (chunk + 1) * INVERSION_CHUNK)):
            for i in range(size):
                for j in range(size):
                    augmented[i, j] = blocks[block, i, j]
                    augmented[i, size + j] = 1.0 if i == j else 0.0
            for column in range(size):
                pivot_row = column
                for i in range(column + 1, size):
                    if abs(augmented[i, column]) > abs(augmented[pivot_row, column]):
                        pivot_row = i
                pivot = augmented[pivot_row, column]
                if pivot == 0.0:
                    regular[chunk] = False
                    break
                if pivot_row != column:
                    for j in range(2 * size):
                        swapped = augmented[column, j]
                        augmented[column, j] = augmented[pivot_row, j]
                        augmented[pivot_row, j] = swapped
                for j in range(2 * size):
                    augmented[column, j] /= pivot
                for i in range(size):
                    if i != column:
                        factor = augmented[i, column]
                        if factor != 0.0:
                            for j in range(2 * size):
                                augmented[i, j] -= factor * augmented[column, j]
            for i in range(size):
                for j in range(size):
                    blocks[block, i, j] = augmented[i, size + j]
    return bool(np.all(regular))


def _diagonal_of(matrix: sp.bsr_matrix) -> FloatArray:
    size = matrix.blocksize[0]
    blocks = np.zeros((matrix.shape[0] // size, size, size))
    _diagonal_blocks(matrix.indptr, matrix.indices, matrix.data, blocks)
    return blocks


def gauss_seidel_sweep(matrix: sp.bsr_matrix, inverse_diagonal: FloatArray, solution: FloatArray,
                       rhs: FloatArray, forward: bool) -> None:
    """One block Gauss–Seidel sweep on matrix·x = rhs, over the block rows in order (`forward`) or in
    reverse, updating `solution` in place: x_i ← D_i⁻¹·(b_i − Σ_{j≠i} A_ij·x_j). Blocks of 3×3 (poses)
    or 4×4 (the coarse levels' aggregates, one unknown per rigid motion)."""
    _check_block_size(matrix)
    # Sequential in both directions: each row reads the rows swept before it. (Taking the backward sweep's
    # blocks left of the diagonal first, on all threads, was slower on this 2-core machine, 129–153 ms
    # against 94–100 at 3·10⁵ poses: a second pass over the rows costs more than the threads save.)
    _sweep(matrix.indptr, matrix.indices, matrix.data.reshape(-1), inverse_diagonal.reshape(-1),
           matrix.blocksize[0], solution, rhs, forward)


def presmooth_from_zero(matrix: sp.bsr_matrix, inverse_diagonal: FloatArray, rhs: FloatArray,
                        solution: FloatArray, residual: FloatArray) -> None:
    """The forward sweep of `gauss_seidel_sweep` from x = 0 into `solution`, and rhs − matrix·x into
    `residual`, for a symmetric `matrix` (its blocks above the diagonal are read as the transposes of
    those below)."""
    _check_block_size(matrix)
    _forward_from_zero(matrix.indptr, matrix.indices, matrix.data.reshape(-1), inverse_diagonal.reshape(-1),
                       matrix.blocksize[0], rhs, solution, residual)


def _check_block_size(matrix: sp.bsr_matrix) -> None:
    if matrix.blocksize not in ((3, 3), (4, 4)):
        raise OptimizerError(f"block Gauss–Seidel sweeps take 3×3 or 4×4 blocks, not {matrix.blocksize}")


@njit(cache=True, parallel=True)
def _diagonal_blocks(indptr: IntArray, indices: IntArray, data: FloatArray, out: FloatArray) -> None:
    size = out.shape[1]
    for row in prange(out.shape[0]):  # each row's block written by one thread
        for position in range(indptr[row], indptr[row + 1]):
            if indices[position] == row:
                # Entry by entry: `out[row] += data[position]` made a temporary block per row, 0.12 s at
                # 10⁶ poses, at every build and every λ.
                for p in range(size):
                    for q in range(size):
                        out[row, p, q] += data[position, p, q]


@njit(cache=True)
def _subtract_row(indptr: IntArray, indices: IntArray, data: FloatArray, size: int, row: int,
                  solution: FloatArray, rhs: FloatArray, lower_only: bool) -> Four:
    """b_row − Σ A_(row,column)·x_column over the row's blocks off the diagonal (only those left of it with
    `lower_only`), as four numbers (the fourth zero for 3×3 blocks). Written out per block size: through a
    scratch array the compiled loop re-reads it on every product, at twice the time of the sweep."""
    literally(size)
    four = size == 4
    base = row * size
    r0, r1, r2 = rhs[base], rhs[base + 1], rhs[base + 2]
    r3 = rhs[base + 3] if four else 0.0
    area = size * size
    for position in range(indptr[row], indptr[row + 1]):
        column = indices[position]
        if column == row or (lower_only and column > row):
            continue
        k = position * area
        o = column * size
        x0, x1, x2 = solution[o], solution[o + 1], solution[o + 2]
        if four:
            x3 = solution[o + 3]
            r0 -= data[k] * x0 + data[k + 1] * x1 + data[k + 2] * x2 + data[k + 3] * x3
            r1 -= data[k + 4] * x0 + data[k + 5] * x1 + data[k + 6] * x2 + data[k + 7] * x3
            r2 -= data[k + 8] * x0 + data[k + 9] * x1 + data[k + 10] * x2 + data[k + 11] * x3
            r3 -= data[k + 12] * x0 + data[k + 13] * x1 + data[k + 14] * x2 + data[k + 15] * x3
        else:
            r0 -= data[k] * x0 + data[k + 1] * x1 + data[k + 2] * x2
            r1 -= data[k + 3] * x0 + data[k + 4] * x1 + data[k + 5] * x2
            r2 -= data[k + 6] * x0 + data[k + 7] * x1 + data[k + 8] * x2
    return r0, r1, r2, r3


@njit(cache=True)
def _solve_row(inverse: FloatArray, size: int, row: int, remainder: Four, solution: FloatArray) -> None:
    """x_row ← D_row⁻¹·remainder (the inverses flat, size² numbers per row)."""
    literally(size)
    r0, r1, r2, r3 = remainder
    k = row * size * size
    base = row * size
    if size == 4:
        solution[base] = inverse[k] * r0 + inverse[k + 1] * r1 + inverse[k + 2] * r2 + inverse[k + 3] * r3
        solution[base + 1] = (inverse[k + 4] * r0 + inverse[k + 5] * r1 + inverse[k + 6] * r2
                              + inverse[k + 7] * r3)
        solution[base + 2] = (inverse[k + 8] * r0 + inverse[k + 9] * r1 + inverse[k + 10] * r2
                              + inverse[k + 11] * r3)
        solution[base + 3] = (inverse[k + 12] * r0 + inverse[k + 13] * r1 + inverse[k + 14] * r2
                              + inverse[k + 15] * r3)
    else:
        solution[base] = inverse[k] * r0 + inverse[k + 1] * r1 + inverse[k + 2] * r2
        solution[base + 1] = inverse[k + 3] * r0 + inverse[k + 4] * r1 + inverse[k + 5] * r2
        solution[base + 2] = inverse[k + 6] * r0 + inverse[k + 7] * r1 + inverse[k + 8] * r2


@njit(cache=True)
def _sweep(indptr: IntArray, indices: IntArray, data: FloatArray, inverse: FloatArray, size: int,
           solution: FloatArray, rhs: FloatArray, forward: bool) -> None:
    # The block size as a compile-time constant (`literally` in the callee): the block loops are then
    # unrolled, a third less time per sweep. Passed from here, not from Python: a function that asks for
    # `literally` arguments raises and retries when called from Python (see `hierarchy_products`).
    if size == 3:
        _sweep_sized(indptr, indices, data, inverse, 3, solution, rhs, forward)
    else:
        _sweep_sized(indptr, indices, data, inverse, 4, solution, rhs, forward)


@njit(cache=True)
def _sweep_sized(indptr: IntArray, indices: IntArray, data: FloatArray, inverse: FloatArray, size: int,
                 solution: FloatArray, rhs: FloatArray, forward: bool) -> None:
    literally(size)
    rows = indptr.shape[0] - 1
    for step in range(rows):
        row = step if forward else rows - 1 - step
        remainder = _subtract_row(indptr, indices, data, size, row, solution, rhs, False)
        _solve_row(inverse, size, row, remainder, solution)


@njit(cache=True)
def _forward_from_zero(indptr: IntArray, indices: IntArray, data: FloatArray, inverse: FloatArray, size: int,
                       rhs: FloatArray, solution: FloatArray, residual: FloatArray) -> None:
    if size == 3:  # the block size as a constant, as in `_sweep`
        _forward_from_zero_sized(indptr, indices, data, inverse, 3, rhs, solution, residual)
    else:
        _forward_from_zero_sized(indptr, indices, data, inverse, 4, rhs, solution, residual)


@njit(cache=True)
def _forward_from_zero_sized(indptr: IntArray, indices: IntArray, data: FloatArray, inverse: FloatArray,
                             size: int, rhs: FloatArray, solution: FloatArray, residual: FloatArray) -> None:
    literally(size)
    rows = indptr.shape[0] - 1
    residual[:] = 0.0
    for row in range(rows):
        remainder = _subtract_row(indptr, indices, data, size, row, solution, rhs, True)
        _solve_row(inverse, size, row, remainder, solution)
        # Row `row`'s own residual is zero up to rounding; the earlier rows' gain −A_(column,row)·x_row,
        # A_(column,row) = A_(row,column)ᵀ.
        _subtract_transposed_lower(indptr, indices, data, size, row, solution, residual)


@njit(cache=True)
def _subtract_transposed_lower(indptr: IntArray, indices: IntArray, data: FloatArray, size: int, row: int,
                               solution: FloatArray, residual: FloatArray) -> None:
    """residual_column −= A_(row,column)ᵀ·x_row for the row's blocks left of the diagonal (written out per
    block size, as `_subtract_row`)."""
    literally(size)
    four = size == 4
    base = row * size
    x0, x1, x2 = solution[base], solution[base + 1], solution[base + 2]
    x3 = solution[base + 3] if four else 0.0
    area = size * size
    for position in range(indptr[row], indptr[row + 1]):
        column = indices[position]
        if column >= row:
            continue
        k = position * area
        o = column * size
        if four:
            residual[o] -= data[k] * x0 + data[k + 4] * x1 + data[k + 8] * x2 + data[k + 12] * x3
            residual[o + 1] -= data[k + 1] * x0 + data[k + 5] * x1 + data[k + 9] * x2 + data[k + 13] * x3
            residual[o + 2] -= data[k + 2] * x0 + data[k + 6] * x1 + data[k + 10] * x2 + data[k + 14] * x3
            residual[o + 3] -= data[k + 3] * x0 + data[k + 7] * x1 + data[k + 11] * x2 + data[k + 15] * x3
        else:
            residual[o] -= data[k] * x0 + data[k + 3] * x1 + data[k + 6] * x2
            residual[o + 1] -= data[k + 1] * x0 + data[k + 4] * x1 + data[k + 7] * x2
            residual[o + 2] -= data[k + 2] * x0 + data[k + 5] * x1 + data[k + 8] * x2


def restrict(prolongation: sp.bsr_matrix, vector: FloatArray) -> FloatArray:
    """Pᵀ·vector for a BSR prolongation of 3×4 or 4×4 blocks, read in place: the V-cycle's restriction
    without R = Pᵀ stored beside P (224 MB at 10⁶ poses)."""
    rows = _prolongation_rows(prolongation)
    out = np.zeros(prolongation.shape[1])
    _transposed_product(prolongation.indptr, prolongation.indices, prolongation.data.reshape(-1), rows,
                        vector, out)
    return out


def prolong_into(prolongation: sp.bsr_matrix, coarse: FloatArray, solution: FloatArray) -> None:
    """solution += P·coarse for a BSR prolongation of 3×4 or 4×4 blocks, without a temporary."""
    rows = _prolongation_rows(prolongation)
    _product_into(prolongation.indptr, prolongation.indices, prolongation.data.reshape(-1), rows, coarse,
                  solution)


def _prolongation_rows(prolongation: sp.bsr_matrix) -> int:
    rows, columns = prolongation.blocksize
    if columns != 4 or rows not in (3, 4):
        raise OptimizerError(f"prolongations here have 3×4 or 4×4 blocks, not {prolongation.blocksize}")
    return int(rows)


@njit(cache=True)
def _product_into(indptr: IntArray, indices: IntArray, data: FloatArray, rows: int, vector: FloatArray,
                  out: FloatArray) -> None:
    if rows == 3:  # the block size as a constant, as in `_sweep`
        _product_into_sized(indptr, indices, data, 3, vector, out)
    else:
        _product_into_sized(indptr, indices, data, 4, vector, out)


@njit(cache=True, parallel=True)
def _product_into_sized(indptr: IntArray, indices: IntArray, data: FloatArray, rows: int, vector: FloatArray,
                        out: FloatArray) -> None:
    """out += P·vector over blocks of `rows`×4, written out as `_subtract_row`; block rows split among the
    threads (each output row is one thread's, summed in one order)."""
    literally(rows)
    four = rows == 4
    area = 4 * rows
    for block_row in prange(indptr.shape[0] - 1):
        base = block_row * rows
        s0 = s1 = s2 = s3 = 0.0
        for position in range(indptr[block_row], indptr[block_row + 1]):
            k = position * area
            o = indices[position] * 4
            v0, v1, v2, v3 = vector[o], vector[o + 1], vector[o + 2], vector[o + 3]
            s0 += data[k] * v0 + data[k + 1] * v1 + data[k + 2] * v2 + data[k + 3] * v3
            s1 += data[k + 4] * v0 + data[k + 5] * v1 + data[k + 6] * v2 + data[k + 7] * v3
            s2 += data[k + 8] * v0 + data[k + 9] * v1 + data[k + 10] * v2 + data[k + 11] * v3
            if four:
                s3 += data[k + 12] * v0 + data[k + 13] * v1 + data[k + 14] * v2 + data[k + 15] * v3
        out[base] += s0
        out[base + 1] += s1
        out[base + 2] += s2
        if four:
            out[base + 3] += s3


@njit(cache=True)
def _transposed_product(indptr: IntArray, indices: IntArray, data: FloatArray, rows: int, vector: FloatArray,
                        out: FloatArray) -> None:
    if rows == 3:  # the block size as a constant, as in `_sweep`
        _transposed_product_sized(indptr, indices, data, 3, vector, out)
    else:
        _transposed_product_sized(indptr, indices, data, 4, vector, out)


@njit(cache=True)
def _transposed_product_sized(indptr: IntArray, indices: IntArray, data: FloatArray, rows: int,
                              vector: FloatArray, out: FloatArray) -> None:
    """out += Pᵀ·vector over blocks of `rows`×4, written out as `_subtract_row`."""
    literally(rows)
    four = rows == 4
    area = 4 * rows
    for block_row in range(indptr.shape[0] - 1):
        base = block_row * rows
        v0, v1, v2 = vector[base], vector[base + 1], vector[base + 2]
        v3 = vector[base + 3] if four else 0.0
        for position in range(indptr[block_row], indptr[block_row + 1]):
            k = position * area
            o = indices[position] * 4
            if four:
                out[o] += data[k] * v0 + data[k + 4] * v1 + data[k + 8] * v2 + data[k + 12] * v3
                out[o + 1] += data[k + 1] * v0 + data[k + 5] * v1 + data[k + 9] * v2 + data[k + 13] * v3
                out[o + 2] += data[k + 2] * v0 + data[k + 6] * v1 + data[k + 10] * v2 + data[k + 14] * v3
                out[o + 3] += data[k + 3] * v0 + data[k + 7] * v1 + data[k + 11] * v2 + data[k + 15] * v3
            else:
                out[o] += data[k] * v0 + data[k + 4] * v1 + data[k + 8] * v2
                out[o + 1] += data[k + 1] * v0 + data[k + 5] * v1 + data[k + 9] * v2
                out[o + 2] += data[k + 2] * v0 + data[k + 6] * v1 + data[k + 10] * v2
                out[o + 3] += data[k + 3] * v0 + data[k + 7] * v1 + data[k + 11] * v2
