"""The multigrid smoother's block Gauss–Seidel sweeps against pyamg's and against the residual they
define."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from optimizer import block_smoother
from optimizer.block_smoother import (
    gauss_seidel_sweep,
    inverted_diagonal,
    presmooth_from_zero,
    prolong_into,
    restrict,
)
from optimizer.errors import OptimizerError
from tests.conftest import MULTIGRID_STACK
from tests.optimizer_fixtures import symmetric_block_matrix

pytest.importorskip("pyamg")

from pyamg.relaxation.relaxation import block_gauss_seidel  # needs pyamg: after the skip

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


@pytest.mark.parametrize("size", [3, 4])
@pytest.mark.parametrize("forward", [True, False])
def test_a_sweep_is_pyamgs_block_gauss_seidel(size: int, forward: bool) -> None:
    matrix = symmetric_block_matrix(size, 300, seed=size)
    rng = np.random.default_rng(1)
    rhs = rng.normal(size=matrix.shape[0])
    start = rng.normal(size=matrix.shape[0])
    ours, theirs = start.copy(), start.copy()
    gauss_seidel_sweep(matrix, inverted_diagonal(matrix), ours, rhs, forward=forward)
    block_gauss_seidel(matrix, theirs, rhs, sweep="forward" if forward else "backward", blocksize=size)
    assert np.abs(ours - theirs).max() <= 1e-13 * np.abs(theirs).max()
    assert not np.allclose(ours, start)  # the sweep moved the solution


@pytest.mark.parametrize("size", [3, 4])
def test_the_sweep_from_zero_gives_the_sweep_and_its_residual(size: int) -> None:
    matrix = symmetric_block_matrix(size, 300, seed=10 + size)
    rhs = np.random.default_rng(2).normal(size=matrix.shape[0])
    inverse = inverted_diagonal(matrix)
    swept = np.zeros_like(rhs)
    gauss_seidel_sweep(matrix, inverse, swept, rhs, forward=True)
    solution, residual = np.empty_like(rhs), np.empty_like(rhs)
    presmooth_from_zero(matrix, inverse, rhs, solution, residual)
    assert np.abs(solution - swept).max() <= 1e-13 * np.abs(swept).max()
    expected = rhs - matrix @ solution
    assert np.abs(residual - expected).max() <= 1e-12 * np.abs(rhs).max()
    assert np.abs(expected).max() > 1e-3 * np.abs(rhs).max()  # one sweep is not a solve: the residual counts


def test_the_inverted_diagonal_is_the_inverse_of_each_diagonal_block() -> None:
    matrix = symmetric_block_matrix(3, 50, seed=3)
    dense = matrix.toarray()
    inverse = inverted_diagonal(matrix)
    for row in (0, 17, 49):
        block = dense[3 * row:3 * row + 3, 3 * row:3 * row + 3]
        assert np.allclose(inverse[row] @ block, np.eye(3), atol=1e-12)


def diagonal_blocks(matrix: sp.bsr_matrix) -> np.ndarray:
    dense, size = matrix.toarray(), matrix.blocksize[0]
    return np.array([dense[size * row:size * row + size, size * row:size * row + size]
                     for row in range(matrix.shape[0] // size)])


@pytest.mark.parametrize("size", [3, 4])
def test_each_diagonal_block_is_inverted_as_lapack_does_to_rounding(size: int) -> None:
    # More blocks than one chunk; some need a row swap (a zero first entry) to be inverted.
    rows = block_smoother.INVERSION_CHUNK + 50
    matrix = symmetric_block_matrix(size, rows, seed=5)
    diagonal = np.flatnonzero(matrix.indices == np.repeat(np.arange(rows), np.diff(matrix.indptr)))
    rng = np.random.default_rng(8)
    for position in diagonal[rng.choice(rows, 40, replace=False)]:
        block = rng.normal(size=(size, size))
        block[0, 0] = 0.0
        matrix.data[position] = block
    expected = np.linalg.inv(diagonal_blocks(matrix))
    inverse = inverted_diagonal(matrix)
    assert np.abs(inverse - expected).max() <= 1e-11 * np.abs(expected).max()
    identity = np.einsum("bij,bjk->bik", inverse, diagonal_blocks(matrix))
    assert np.abs(identity - np.eye(size)).max() <= 1e-10


def test_one_singular_block_makes_every_inverse_a_pseudo_inverse() -> None:
    # The singular block sits in the second chunk: the first chunk's inverses are not kept either.
    rows = block_smoother.INVERSION_CHUNK + 30
    matrix = symmetric_block_matrix(3, rows, seed=6)
    diagonal = matrix.indices == np.repeat(np.arange(rows), np.diff(matrix.indptr))
    matrix.data[np.flatnonzero(diagonal)[rows - 10]] = np.diag([1.0, 2.0, 0.0])
    np.testing.assert_array_equal(inverted_diagonal(matrix), np.linalg.pinv(diagonal_blocks(matrix)))


def test_other_block_sizes_are_refused() -> None:
    matrix = symmetric_block_matrix(2, 10, seed=4)
    vector = np.zeros(matrix.shape[0])
    with pytest.raises(OptimizerError, match="3×3 or 4×4"):
        gauss_seidel_sweep(matrix, np.zeros((10, 2, 2)), vector, vector, forward=True)


@pytest.mark.parametrize("rows", [3, 4])
def test_restriction_and_prolongation_are_the_products_with_p(rows: int) -> None:
    rng = np.random.default_rng(rows)
    dense = rng.normal(size=(rows * 40, 4 * 12)) * (rng.random((rows * 40, 4 * 12)) < 0.2)
    prolongation = sp.bsr_matrix(dense, blocksize=(rows, 4))
    fine = rng.normal(size=rows * 40)
    coarse = rng.normal(size=4 * 12)
    np.testing.assert_allclose(restrict(prolongation, fine), dense.T @ fine, rtol=1e-13, atol=1e-13)
    solution = fine.copy()
    prolong_into(prolongation, coarse, solution)
    np.testing.assert_allclose(solution, fine + dense @ coarse, rtol=1e-13, atol=1e-13)
