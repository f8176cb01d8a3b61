"""The two sparse products of the multigrid hierarchy's build, compiled: the smoothed prolongation
P = T − W·(A·T) and the Galerkin coarse operator Pᵀ·A·P, on BSR blocks.

Through scipy each is several whole matrices: A·T (zero-filled for every block A has, 480 MB at 10⁶ poses)
and its difference with T, then R = Pᵀ and R·A (more blocks than A) before (R·A)·P. These kernels go row
by row with one row's worth of scratch and write P and Pᵀ·A·P only, each counted in a symbolic pass
first so that nothing is allocated twice. The arithmetic is scipy's, term for term and in the same order
(`bsr_matmat`'s block products accumulated in the order A's and T's blocks are met; `bsr_transpose`
listing a column's rows in increasing order; the difference T − W·(A·T) through `bsr_binop_bsr`), and so
is the order of the blocks in each row: the next level's aggregation reads them in that order, so the
hierarchy is scipy's bit for bit. Each product returns what its symbolic pass found (`ProlongationPattern`,
`GalerkinPattern`), so that the next build on the same patterns (the polish's next linearisation of the
same graph) fills without counting again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import get_num_threads, literally, njit, prange
from numpy.typing import NDArray

from optimizer.errors import OptimizerError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32] | NDArray[np.int64]
Int32Array = NDArray[np.int32]


@dataclass(frozen=True)
class ProlongationPattern:
    """What `smoothed_prolongation` derives from the patterns of A and T alone (its symbolic pass), for
    another product on the same patterns: each row's blocks before zero blocks are dropped, the longest
    row, and whether scipy's difference takes its merging path."""

    indptr: IntArray
    longest: int
    canonical: bool


@dataclass(frozen=True)
class GalerkinPattern:
    """What `galerkin_product` derives from the patterns of A and P alone (its symbolic pass), for another
    product on the same patterns: P's block columns (Pᵀ's rows), the coarse rows' blocks, and the longest
    row of R·A. `prolongation_indptr`/`prolongation_indices` are the P pattern it was derived from."""

    prolongation_indptr: IntArray
    prolongation_indices: IntArray
    column_indptr: NDArray[np.int64]
    column_rows: Int32Array
    column_positions: NDArray[np.int64]
    longest: int
    indptr: IntArray

    def fits(self, prolongation: sp.bsr_matrix) -> bool:
        """Whether `prolongation` has the pattern this was derived from."""
        return (np.array_equal(prolongation.indptr, self.prolongation_indptr)
                and np.array_equal(prolongation.indices, self.prolongation_indices))


def smoothed_prolongation(matrix: sp.bsr_matrix, tentative: sp.bsr_matrix, row_weights: FloatArray,
                          pattern: ProlongationPattern | None = None
                          ) -> tuple[sp.bsr_matrix, ProlongationPattern]:
    """T − W·(A·T): A (`matrix`) of 3×3 or 4×4 blocks, T (`tentative`) of b×4 blocks (A's b), W the
    diagonal `row_weights` (one per scalar row). Blocks that cancel to exactly zero are dropped, as
    scipy's difference drops them. `pattern`, when given, must be the one returned for a product on the
    same patterns of A and T: its symbolic pass is then skipped (the numbers are the same either way)."""
    _check_block_sizes(matrix, tentative)
    a_indptr, a_indices, a_data = matrix.indptr, matrix.indices, matrix.data
    t_indptr, t_indices, t_data = tentative.indptr, tentative.indices, tentative.data
    rows, coarse_columns = a_indptr.shape[0] - 1, tentative.shape[1] // tentative.blocksize[1]
    chunks = get_num_threads()  # one range of rows per thread (see `galerkin_product`)
    if pattern is None:
        counts = np.empty(rows, dtype=np.int64)
        canonical = _prolongation_counts(a_indptr, a_indices, t_indptr, t_indices, coarse_columns, counts,
                                         chunks)
        counted = np.zeros(rows + 1, dtype=_index_type(counts))
        np.cumsum(counts, out=counted[1:])
        pattern = ProlongationPattern(counted, int(counts.max(initial=0)), canonical)
        del counts
    indptr = pattern.indptr.copy()  # the fill moves the rows down over the blocks it drops
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty((int(indptr[-1]), *tentative.blocksize))
    kept = _prolongation_fill_sized(a_indptr, a_indices, a_data, t_indptr, t_indices, t_data, coarse_columns,
                                    row_weights, pattern.canonical, pattern.longest, indptr, indices, data,
                                    chunks)
    return sp.bsr_matrix((data[:kept], indices[:kept], indptr), shape=tentative.shape), pattern


def galerkin_product(matrix: sp.bsr_matrix, prolongation: sp.bsr_matrix,
                     pattern: GalerkinPattern | None = None) -> tuple[sp.bsr_matrix, GalerkinPattern]:
    """Pᵀ·A·P, computed as scipy's (R·A)·P with R = Pᵀ: A (`matrix`) of 3×3 or 4×4 blocks, P
    (`prolongation`) of b×4 blocks (A's b); the result in 4×4 blocks. `pattern`, when given, must be the
    one returned for a product with A of the same pattern and must fit P (`GalerkinPattern.fits`): its
    symbolic pass is then skipped (the numbers are the same either way)."""
    _check_block_sizes(matrix, prolongation)
    a_indptr, a_indices, a_data = matrix.indptr, matrix.indices, matrix.data
    p_indptr, p_indices, p_data = prolongation.indptr, prolongation.indices, prolongation.data
    fine_rows, coarse_columns = p_indptr.shape[0] - 1, prolongation.shape[1] // prolongation.blocksize[1]
    # One range of rows per thread (numba's threads asked for here: asked inside a compiled function, the
    # count is a ctypes call that keeps the function out of numba's cache).
    chunks = get_num_threads()
    if pattern is None:
        column_indptr = np.zeros(coarse_columns + 1, dtype=np.int64)
        column_rows = np.empty(p_indices.shape[0], dtype=np.int32)
        column_positions = np.empty(p_indices.shape[0], dtype=np.int64)
        _transpose_pattern(p_indptr, p_indices, column_indptr, column_rows, column_positions)
        counts = np.empty(coarse_columns, dtype=np.int64)
        longest = _galerkin_counts(a_indptr, a_indices, p_indptr, p_indices, column_indptr, column_rows,
                                   fine_rows, counts, chunks)
        counted = np.zeros(coarse_columns + 1, dtype=_index_type(counts))
        np.cumsum(counts, out=counted[1:])
        del counts
        pattern = GalerkinPattern(p_indptr.copy(), p_indices.copy(), column_indptr, column_rows,
                                  column_positions, longest, counted)
    indptr = pattern.indptr.copy()  # the coarse level's own: its reader may sort or change it
    size = prolongation.blocksize[1]
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty((int(indptr[-1]), size, size))
    _galerkin_fill_sized(a_indptr, a_indices, a_data, p_indptr, p_indices, p_data, pattern.column_indptr,
                         pattern.column_rows, pattern.column_positions, pattern.longest, indptr, indices,
                         data, chunks)
    return sp.bsr_matrix((data, indices, indptr), shape=(prolongation.shape[1],) * 2), pattern


def _index_type(counts: NDArray[np.int64]) -> type[np.signedinteger]:
    """32-bit block positions where they fit (scipy's choice too), 64-bit beyond."""
    return np.int32 if int(counts.sum()) <= np.iinfo(np.int32).max else np.int64


def _check_block_sizes(matrix: sp.bsr_matrix, prolongation: sp.bsr_matrix) -> None:
    """The sizes the kernels are compiled for: A of 3×3 or 4×4 blocks (poses, aggregates), b×4 for P."""
    size = matrix.blocksize[0]
    if matrix.blocksize != (size, size) or size not in (3, 4) or prolongation.blocksize != (size, 4):
        raise OptimizerError(f"the hierarchy's products take A in 3×3 or 4×4 blocks and P in b×4, not "
                             f"{matrix.blocksize} and {prolongation.blocksize}")


@njit(cache=True, parallel=True)
def _prolongation_counts(a_indptr: IntArray, a_indices: IntArray, t_indptr: IntArray, t_indices: IntArray,
                         coarse_columns: int, counts: NDArray[np.int64], chunks: int) -> bool:
    """Distinct block columns of T and A·T in every row, into `counts`; whether T and A·T both have
    strictly increasing columns in every row (scipy's difference then takes its merging path, whose rows
    come out sorted, instead of its general one). In `chunks` ranges of rows, as `_galerkin_counts`."""
    rows = a_indptr.shape[0] - 1
    canonical = np.ones(chunks, dtype=np.bool_)
    for chunk in prange(chunks):
        first, last = _row_range(rows, chunks, np.int64(chunk))
        canonical[chunk] = _prolongation_counts_of(a_indptr, a_indices, t_indptr, t_indices, coarse_columns,
                                                   counts, first, last)
    return bool(canonical.all())


@njit(cache=True)
def _prolongation_counts_of(a_indptr: IntArray, a_indices: IntArray, t_indptr: IntArray, t_indices: IntArray,
                            coarse_columns: int, counts: NDArray[np.int64], first: int, last: int) -> bool:
    """`_prolongation_counts` for the rows [first, last)."""
    seen = np.full(coarse_columns, -1, dtype=np.int64)
    in_product = np.full(coarse_columns, -1, dtype=np.int64)
    canonical = True
    for row in range(first, last):
        count = 0
        previous = -1
        for kk in range(t_indptr[row], t_indptr[row + 1]):
            column = t_indices[kk]
            canonical = canonical and column > previous
            previous = column
            if seen[column] != row:
                seen[column] = row
                count += 1
        previous = -1
        for jj in range(a_indptr[row], a_indptr[row + 1]):
            neighbour = a_indices[jj]
            for kk in range(t_indptr[neighbour], t_indptr[neighbour + 1]):
                column = t_indices[kk]
                if in_product[column] != row:
                    in_product[column] = row
                    canonical = canonical and column > previous
                    previous = column
                if seen[column] != row:
                    seen[column] = row
                    count += 1
        counts[row] = count
    return canonical


@njit(cache=True, parallel=True)
def _prolongation_fill_sized(a_indptr: IntArray, a_indices: IntArray, a_data: FloatArray, t_indptr: IntArray,
                             t_indices: IntArray, t_data: FloatArray, coarse_columns: int,
                             row_weights: FloatArray, canonical: bool, longest: int, indptr: IntArray,
                             indices: Int32Array, data: FloatArray, chunks: int) -> int:
    """`_prolongation_fill` for A's block size, passed as a constant: called from Python, a function that
    asks for `literally` arguments raises and retries, and the exception's traceback keeps the arrays it
    was given alive until the cyclic garbage collector runs (hierarchies of 800 MB at 10⁶ poses).

    In `chunks` ranges of rows, as `_galerkin_fill_sized`: each row fills the blocks the counts gave it
    (`indptr` on entry), the blocks it keeps first; `_close_gaps` then moves the rows down over the
    blocks dropped, in order. Returns the blocks kept."""
    rows = a_indptr.shape[0] - 1
    kept = np.empty(rows, dtype=np.int64)
    for chunk in prange(chunks):
        first, last = _row_range(rows, chunks, np.int64(chunk))
        if a_data.shape[1] == 3:
            _prolongation_fill(a_indptr, a_indices, a_data, t_indptr, t_indices, t_data, coarse_columns,
                               row_weights, canonical, longest, indptr, indices, data, kept, first, last,
                               3, 4)
        else:
            _prolongation_fill(a_indptr, a_indices, a_data, t_indptr, t_indices, t_data, coarse_columns,
                               row_weights, canonical, longest, indptr, indices, data, kept, first, last,
                               4, 4)
    return _close_gaps(indptr, indices, data, kept)


@njit(cache=True)
def _close_gaps(indptr: IntArray, indices: Int32Array, data: FloatArray, kept: NDArray[np.int64]) -> int:
    """Rows of `kept[row]` blocks each from `indptr[row]` on, moved down to follow one another (rewrites
    `indptr`); the blocks in all."""
    total = 0
    for row in range(kept.shape[0]):
        start = indptr[row]
        indptr[row] = total
        if start != total:  # only after a row that dropped a block: rows never move up
            for k in range(kept[row]):
                indices[total + k] = indices[start + k]
                data[total + k] = data[start + k]
        total += kept[row]
    indptr[kept.shape[0]] = total
    return total


@njit(cache=True)
def _prolongation_fill(a_indptr: IntArray, a_indices: IntArray, a_data: FloatArray, t_indptr: IntArray,
                       t_indices: IntArray, t_data: FloatArray, coarse_columns: int, row_weights: FloatArray,
                       canonical: bool, longest: int, indptr: IntArray, indices: Int32Array,
                       data: FloatArray, kept: NDArray[np.int64], first: int, last: int, b: int,
                       c: int) -> None:
    """Fills the rows [first, last) of T − W·(A·T), each from `indptr[row]` on, zero blocks dropped; the
    blocks each keeps into `kept`.

    A row's columns are listed as scipy's general difference meets them (T's, then A·T's in the order the
    product first meets them) and written in reverse, the order of its linked list; on the merging path
    (`canonical`) in increasing order. The block sizes b×b (A) and b×c (T) are compile-time constants, as
    in `_galerkin_fill`."""
    literally(b)
    literally(c)
    slot = np.full(coarse_columns, -1, dtype=np.int64)
    columns = np.empty(longest, dtype=np.int64)
    tentative = np.empty((longest, b, c))
    product = np.empty((longest, b, c))
    order = np.empty(longest, dtype=np.int64)
    for row in range(first, last):
        length = 0
        for kk in range(t_indptr[row], t_indptr[row + 1]):
            column = t_indices[kk]
            s = slot[column]
            if s < 0:
                s = slot[column] = length
                columns[length] = column
                tentative[length] = 0.0
                product[length] = 0.0
                length += 1
            for p in range(b):
                for q in range(c):
                    tentative[s, p, q] += t_data[kk, p, q]
        for jj in range(a_indptr[row], a_indptr[row + 1]):
            neighbour = a_indices[jj]
            for kk in range(t_indptr[neighbour], t_indptr[neighbour + 1]):
                column = t_indices[kk]
                s = slot[column]
                if s < 0:
                    s = slot[column] = length
                    columns[length] = column
                    tentative[length] = 0.0
                    product[length] = 0.0
                    length += 1
                for p in range(b):
                    for q in range(c):
                        total = product[s, p, q]
                        for d in range(b):
                            total += a_data[jj, p, d] * t_data[kk, d, q]
                        product[s, p, q] = total
        if canonical:
            order[:length] = np.argsort(columns[:length])
        else:
            for k in range(length):
                order[k] = length - 1 - k
        position = indptr[row]
        for k in range(length):
            s = order[k]
            slot[columns[s]] = -1
            nonzero = False
            for p in range(b):
                weight = row_weights[row * b + p]
                for q in range(c):
                    value = tentative[s, p, q] - (0.0 + product[s, p, q] * weight)
                    data[position, p, q] = value
                    nonzero = nonzero or value != 0.0
            if nonzero:
                indices[position] = columns[s]
                position += 1
        kept[row] = position - indptr[row]


@njit(cache=True)
def _transpose_pattern(indptr: IntArray, indices: IntArray, column_indptr: NDArray[np.int64],
                       column_rows: Int32Array, column_positions: NDArray[np.int64]) -> None:
    """Each block column's rows (increasing, as `bsr_transpose` lists them) and their blocks' positions."""
    for position in range(indices.shape[0]):
        column_indptr[indices[position] + 1] += 1
    for column in range(column_indptr.shape[0] - 1):
        column_indptr[column + 1] += column_indptr[column]
    cursor = column_indptr[:-1].copy()
    for row in range(indptr.shape[0] - 1):
        for position in range(indptr[row], indptr[row + 1]):
            column = indices[position]
            column_rows[cursor[column]] = row
            column_positions[cursor[column]] = position
            cursor[column] += 1


@njit(cache=True, parallel=True)
def _galerkin_counts(a_indptr: IntArray, a_indices: IntArray, p_indptr: IntArray, p_indices: IntArray,
                     column_indptr: NDArray[np.int64], column_rows: Int32Array, fine_rows: int,
                     counts: NDArray[np.int64], chunks: int) -> int:
    """Blocks of every coarse row of Pᵀ·A·P into `counts`; the longest row of R·A. The coarse rows are
    split into `chunks` contiguous ranges (`_row_range`; one per thread), each with scratch of its own:
    every row's count is the same whoever counts it."""
    coarse_rows = column_indptr.shape[0] - 1
    longest = np.zeros(chunks, dtype=np.int64)
    for chunk in prange(chunks):
        first, last = _row_range(coarse_rows, chunks, np.int64(chunk))
        longest[chunk] = _galerkin_counts_of(a_indptr, a_indices, p_indptr, p_indices, column_indptr,
                                             column_rows, fine_rows, counts, first, last)
    return int(longest.max())


@njit(cache=True)
def _row_range(rows: int, chunks: int, chunk: int | np.int64) -> tuple[int, int]:
    """Rows [first, last) of chunk `chunk` of `chunks` contiguous, near-equal ranges. Callers pass the
    prange index as np.int64: numba types it int64 before its parallel pass and uint64 after, which
    compiled this twice."""
    return int(rows * chunk // chunks), int(rows * (chunk + 1) // chunks)


@njit(cache=True)
def _galerkin_counts_of(a_indptr: IntArray, a_indices: IntArray, p_indptr: IntArray, p_indices: IntArray,
                        column_indptr: NDArray[np.int64], column_rows: Int32Array, fine_rows: int,
                        counts: NDArray[np.int64], first: int, last: int) -> int:
    """`_galerkin_counts` for the coarse rows [first, last)."""
    coarse_rows = column_indptr.shape[0] - 1
    seen_fine = np.zeros(fine_rows, dtype=np.bool_)
    seen_coarse = np.zeros(coarse_rows, dtype=np.bool_)
    fine = np.empty(fine_rows, dtype=np.int64)
    coarse = np.empty(coarse_rows, dtype=np.int64)
    longest = 0
    for coarse_row in range(first, last):
        length = 0
        for t in range(column_indptr[coarse_row], column_indptr[coarse_row + 1]):
            row = column_rows[t]
            for jj in range(a_indptr[row], a_indptr[row + 1]):
                neighbour = a_indices[jj]
                if not seen_fine[neighbour]:
                    seen_fine[neighbour] = True
                    fine[length] = neighbour
                    length += 1
        count = 0
        for s in range(length):
            neighbour = fine[s]
            seen_fine[neighbour] = False
            for kk in range(p_indptr[neighbour], p_indptr[neighbour + 1]):
                column = p_indices[kk]
                if not seen_coarse[column]:
                    seen_coarse[column] = True
                    coarse[count] = column
                    count += 1
        for s in range(count):
            seen_coarse[coarse[s]] = False
        counts[coarse_row] = count
        longest = max(longest, length)
    return longest


@njit(cache=True, parallel=True)
def _galerkin_fill_sized(a_indptr: IntArray, a_indices: IntArray, a_data: FloatArray, p_indptr: IntArray,
                         p_indices: IntArray, p_data: FloatArray, column_indptr: NDArray[np.int64],
                         column_rows: Int32Array, column_positions: NDArray[np.int64], longest: int,
                         indptr: IntArray, indices: Int32Array, data: FloatArray, chunks: int) -> None:
    """`_galerkin_fill` for A's block size, passed as a constant (see `_prolongation_fill_sized`), in
    `chunks` contiguous ranges of coarse rows (one per thread). A row's blocks go where the counts put them
    and are summed by one thread in `_galerkin_fill`'s order: the same numbers whatever the threads."""
    coarse_rows = column_indptr.shape[0] - 1
    for chunk in prange(chunks):
        first, last = _row_range(coarse_rows, chunks, np.int64(chunk))
        if a_data.shape[1] == 3:
            _galerkin_fill(a_indptr, a_indices, a_data, p_indptr, p_indices, p_data, column_indptr,
                           column_rows, column_positions, longest, indptr, indices, data, first, last, 3, 4)
        else:
            _galerkin_fill(a_indptr, a_indices, a_data, p_indptr, p_indices, p_data, column_indptr,
                           column_rows, column_positions, longest, indptr, indices, data, first, last, 4, 4)


@njit(cache=True)
def _galerkin_fill(a_indptr: IntArray, a_indices: IntArray, a_data: FloatArray, p_indptr: IntArray,
                   p_indices: IntArray, p_data: FloatArray, column_indptr: NDArray[np.int64],
                   column_rows: Int32Array, column_positions: NDArray[np.int64], longest: int,
                   indptr: IntArray, indices: Int32Array, data: FloatArray, first: int, last: int, b: int,
                   c: int) -> None:
    """Rows [first, last) of Pᵀ·A·P. Row I: row I of R·A (Σ over the rows i of P's column I, increasing,
    of P_iIᵀ·A_i·), then that row times P, each accumulated block by block in the order its terms are met
    (`bsr_matmat`). The block sizes b (A) and c (P's columns) are compile-time constants (`literally`):
    the block products' loops are then unrolled, at two thirds of the time."""
    literally(b)
    literally(c)
    fine_rows = p_indptr.shape[0] - 1
    coarse_rows = column_indptr.shape[0] - 1
    fine_slot = np.full(fine_rows, -1, dtype=np.int64)
    coarse_slot = np.full(coarse_rows, -1, dtype=np.int64)
    fine = np.empty(longest, dtype=np.int64)
    restricted = np.empty((longest, c, b))
    for coarse_row in range(first, last):
        length = 0
        for t in range(column_indptr[coarse_row], column_indptr[coarse_row + 1]):
            row = column_rows[t]
            position = column_positions[t]
            for jj in range(a_indptr[row], a_indptr[row + 1]):
                neighbour = a_indices[jj]
                s = fine_slot[neighbour]
                if s < 0:
                    s = fine_slot[neighbour] = length
                    fine[length] = neighbour
                    restricted[length] = 0.0
                    length += 1
                for p in range(c):
                    for q in range(b):
                        total = restricted[s, p, q]
                        for d in range(b):
                            total += p_data[position, d, p] * a_data[jj, d, q]
                        restricted[s, p, q] = total
        start = indptr[coarse_row]
        count = 0
        for s in range(length):
            neighbour = fine[s]
            fine_slot[neighbour] = -1
            for kk in range(p_indptr[neighbour], p_indptr[neighbour + 1]):
                column = p_indices[kk]
                target = coarse_slot[column]
                if target < 0:
                    target = coarse_slot[column] = start + count
                    indices[target] = column
                    data[target] = 0.0
                    count += 1
                for p in range(c):
                    for q in range(c):
                        total = data[target, p, q]
                        for d in range(b):
                            total += restricted[s, p, d] * p_data[kk, d, q]
                        data[target, p, q] = total
        for target in range(start, start + count):
            coarse_slot[indices[target]] = -1
