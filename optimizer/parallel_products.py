"""Products of the multigrid polish's conjugate gradients on all cores, with the numbers of one core.

scipy's BSR product with a vector (`bsr_matvec`) runs on one thread; at 10⁶ poses it is a seventh of a CG
iteration. `block_product` computes the same product with its block rows split among numba's threads.
Each output row is summed by one thread, over its blocks in stored order and within a block left to
right, starting from zero: scipy's `gemv` order, so the result is scipy's bit for bit whatever the number
of threads (`numba.set_num_threads`, `NUMBA_NUM_THREADS`). `add_scaled` is CG's y += a·x the same way:
elementwise, what numpy's `y += a * x` gives, without its temporary (and `scale_and_add`, CG's new
direction). Nothing here reduces across rows;
dot products and norms stay numpy's, whose order does not depend on numba's threads.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit, prange
from numpy.typing import NDArray

from optimizer.errors import OptimizerError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32] | NDArray[np.int64]


def block_product(matrix: sp.bsr_matrix, vector: FloatArray) -> FloatArray:
    """matrix·vector for a BSR matrix of 3×3 blocks: scipy's `matrix @ vector` to the bit, on all threads."""
    if matrix.blocksize != (3, 3):
        raise OptimizerError(f"block_product takes 3×3 blocks, not {matrix.blocksize}")
    if vector.shape != (matrix.shape[1],):
        raise OptimizerError(f"a vector of {matrix.shape[1]} entries is needed, not shape {vector.shape}")
    out = np.empty(matrix.shape[0])
    _product_3x3(matrix.indptr, matrix.indices, matrix.data, np.ascontiguousarray(vector, dtype=np.float64),
                 out)
    return out


def add_scaled(target: FloatArray, factor: float, vector: FloatArray) -> None:
    """target += factor·vector in place (numpy's `target += factor * vector` to the bit)."""
    if target.shape != vector.shape:
        raise OptimizerError(f"shapes differ: {target.shape} and {vector.shape}")
    _add_scaled(target, float(factor), vector)


def scale_and_add(target: FloatArray, factor: float, vector: FloatArray) -> None:
    """target ← factor·target + vector in place (numpy's `target *= factor; target += vector`)."""
    if target.shape != vector.shape:
        raise OptimizerError(f"shapes differ: {target.shape} and {vector.shape}")
    _scale_and_add(target, float(factor), vector)


@njit(cache=True, parallel=True)
def _product_3x3(indptr: IntArray, indices: IntArray, data: FloatArray, vector: FloatArray,
                 out: FloatArray) -> None:
    # One term at a time into the running sum, as scipy's gemv: (s + a₀x₀) + a₁x₁, never s + (a₀x₀ + a₁x₁).
    for row in prange(indptr.shape[0] - 1):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for position in range(indptr[row], indptr[row + 1]):
            block = data[position]
            o = 3 * indices[position]
            x0, x1, x2 = vector[o], vector[o + 1], vector[o + 2]
            s0 = s0 + block[0, 0] * x0
            s0 = s0 + block[0, 1] * x1
            s0 = s0 + block[0, 2] * x2
            s1 = s1 + block[1, 0] * x0
            s1 = s1 + block[1, 1] * x1
            s1 = s1 + block[1, 2] * x2
            s2 = s2 + block[2, 0] * x0
            s2 = s2 + block[2, 1] * x1
            s2 = s2 + block[2, 2] * x2
        out[3 * row] = s0
        out[3 * row + 1] = s1
        out[3 * row + 2] = s2


@njit(cache=True, parallel=True)
def _add_scaled(target: FloatArray, factor: float, vector: FloatArray) -> None:
    for i in prange(target.shape[0]):
        target[i] = target[i] + factor * vector[i]


@njit(cache=True, parallel=True)
def _scale_and_add(target: FloatArray, factor: float, vector: FloatArray) -> None:
    for i in prange(target.shape[0]):
        target[i] = target[i] * factor + vector[i]
