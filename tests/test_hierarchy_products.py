"""The hierarchy build's compiled products against scipy's sparse products, block for block."""

from __future__ import annotations

import gc
import weakref

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from optimizer.errors import OptimizerError
from optimizer.hierarchy_products import galerkin_product, smoothed_prolongation
from tests.conftest import MULTIGRID_STACK
from tests.optimizer_fixtures import system_and_candidates

pytest.importorskip("pyamg")

from pyamg.aggregation.aggregate import standard_aggregation  # needs pyamg: after the skip
from pyamg.aggregation.tentative import fit_candidates
from pyamg.strength import symmetric_strength_of_connection

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


def tentative_of(matrix: sp.bsr_matrix, near_null: np.ndarray) -> sp.bsr_matrix:
    aggregates, _ = standard_aggregation(symmetric_strength_of_connection(matrix))
    return fit_candidates(aggregates, near_null)[0]


def chain_system(poses: int) -> tuple[sp.bsr_matrix, np.ndarray]:
    """A chain's Laplacian plus the identity in 3×3 blocks, and the rigid motions of poses along x as its
    candidates: aggregates of consecutive poses, so A·T has increasing block columns in every row."""
    laplacian = sp.diags([-np.ones(poses - 1), 3.0 * np.ones(poses), -np.ones(poses - 1)], [-1, 0, 1])
    coupling = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.25], [0.0, 0.25, 3.0]])
    motions = np.zeros((poses, 3, 4))
    motions[:, 0, 0] = motions[:, 1, 1] = motions[:, 2, 2] = motions[:, 2, 3] = 1.0
    motions[:, 1, 3] = np.arange(poses)  # the rotation about the origin moves pose k along y
    return sp.bsr_matrix(sp.kron(laplacian, coupling), blocksize=(3, 3)), motions.reshape(-1, 4)


def scipys_prolongation(matrix: sp.bsr_matrix, tentative: sp.bsr_matrix,
                        weights: np.ndarray) -> sp.bsr_matrix:
    """T − W·(A·T) through scipy, as the hierarchy formed it before the compiled kernel."""
    product = sp.bsr_matrix(matrix @ tentative, blocksize=tentative.blocksize)
    block_rows = np.repeat(np.arange(product.shape[0] // 3), np.diff(product.indptr))
    product.data *= weights.reshape(-1, 3)[block_rows][:, :, None]
    return sp.bsr_matrix(tentative - product, blocksize=tentative.blocksize)


def ours(matrix: sp.bsr_matrix, tentative: sp.bsr_matrix, weights: np.ndarray) -> sp.bsr_matrix:
    return smoothed_prolongation(matrix, tentative, weights)[0]


def assert_same_blocks(mine: sp.bsr_matrix, reference: sp.bsr_matrix) -> None:
    """Equal bit for bit, blocks in the same order in every row."""
    assert mine.shape == reference.shape and mine.blocksize == reference.blocksize
    np.testing.assert_array_equal(mine.indptr, reference.indptr)
    np.testing.assert_array_equal(mine.indices, reference.indices)
    np.testing.assert_array_equal(mine.data, reference.data)


def random_weights(rows: int) -> np.ndarray:
    weights = np.random.default_rng(4).uniform(0.1, 1.0, rows)
    weights[::7] = 0.0  # rows of |A| summing to zero keep T
    return weights


def test_the_prolongation_is_scipys_on_a_pose_graph() -> None:
    # A grid world's loops make A·T's rows unsorted: scipy's difference takes its general path.
    matrix, near_null = system_and_candidates(3000)
    tentative = tentative_of(matrix, near_null)
    weights = random_weights(matrix.shape[0])
    reference = scipys_prolongation(matrix, tentative, weights)
    assert not reference.has_sorted_indices
    assert_same_blocks(ours(matrix, tentative, weights), reference)


def test_the_prolongation_is_scipys_on_a_chain() -> None:
    # Sorted rows everywhere: scipy's difference merges them, in increasing block columns.
    matrix, near_null = chain_system(400)
    tentative = tentative_of(matrix, near_null)
    weights = random_weights(matrix.shape[0])
    reference = scipys_prolongation(matrix, tentative, weights)
    assert reference.has_sorted_indices
    assert_same_blocks(ours(matrix, tentative, weights), reference)


@pytest.mark.parametrize("system", [system_and_candidates, chain_system])
def test_blocks_that_cancel_are_dropped(system: object) -> None:
    # W·A = I (a power-of-two diagonal and its inverse: exact), so T − W·A·T is zero: no block is kept.
    matrix, near_null = system(300)  # type: ignore[operator]
    tentative = tentative_of(matrix, near_null)
    diagonal = sp.bsr_matrix(sp.identity(matrix.shape[0]) * 4.0, blocksize=(3, 3))
    prolongation = ours(diagonal, tentative, np.full(matrix.shape[0], 0.25))
    assert prolongation.indptr[-1] == 0 and prolongation.data.shape == (0, *tentative.blocksize)
    assert_same_blocks(prolongation, scipys_prolongation(diagonal, tentative, np.full(matrix.shape[0], 0.25)))


@pytest.mark.parametrize("blocks", [3, 4])
def test_the_galerkin_product_is_scipys(blocks: int) -> None:
    # 3: the finest level (3×3 blocks of A, 3×4 of P); 4: a coarse one (4×4 both).
    matrix, near_null = system_and_candidates(3000)
    tentative = tentative_of(matrix, near_null)
    prolongation = ours(matrix, tentative, random_weights(matrix.shape[0]))
    if blocks == 4:
        matrix = galerkin_product(matrix, prolongation)[0]
        prolongation = ours(matrix, tentative_of(matrix, np.eye(4)[np.arange(matrix.shape[0]) % 4]),
                            random_weights(matrix.shape[0]))
    reference = (sp.bsr_matrix(prolongation.T) @ matrix) @ prolongation  # pyamg's R·A·P, R = Pᵀ
    assert not reference.has_sorted_indices
    assert_same_blocks(galerkin_product(matrix, prolongation)[0], reference)


def test_the_products_hold_no_reference_to_what_they_were_given() -> None:
    # A hierarchy let go must be freed at once, not when the cyclic collector next runs (800 MB at 10⁶
    # poses): nothing the kernels did may keep their arguments in a reference cycle.
    matrix, near_null = system_and_candidates(300)
    tentative = tentative_of(matrix, near_null)
    enabled = gc.isenabled()
    gc.disable()
    try:
        prolongation = ours(matrix, tentative, random_weights(matrix.shape[0]))
        coarse = galerkin_product(matrix, prolongation)[0]
        arrays = (matrix.data, tentative.data, prolongation.data, coarse.data)
        given = [weakref.ref(array) for array in arrays]
        del arrays
        del matrix, tentative, prolongation, coarse
        assert [reference() is None for reference in given] == [True] * 4
    finally:
        if enabled:
            gc.enable()


def test_other_block_sizes_are_refused() -> None:
    matrix, near_null = system_and_candidates(300)
    tentative = tentative_of(matrix, near_null[:, :3])  # 3×3 blocks of P
    with pytest.raises(OptimizerError, match="b×4"):
        smoothed_prolongation(matrix, tentative, np.ones(matrix.shape[0]))
    with pytest.raises(OptimizerError, match="b×4"):
        galerkin_product(matrix, tentative)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_galerkin_product_is_scipys_on_any_number_of_threads(threads: int) -> None:
    # Its rows are counted and filled in one range per thread: the same blocks, bit for bit, whatever the
    # ranges.
    matrix, near_null = system_and_candidates(2000)
    prolongation = ours(matrix, tentative_of(matrix, near_null), random_weights(matrix.shape[0]))
    reference = (sp.bsr_matrix(prolongation.T) @ matrix) @ prolongation
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        assert_same_blocks(galerkin_product(matrix, prolongation)[0], reference)
    finally:
        numba.set_num_threads(before)


@pytest.mark.parametrize("threads", [1, 2])
def test_the_prolongation_is_scipys_on_any_number_of_threads(threads: int) -> None:
    # Rows filled in one range per thread, then moved down over the blocks that cancelled: scipy's blocks
    # bit for bit whatever the ranges. Every third pose's row cancels exactly (W·A = I there, as in
    # `test_blocks_that_cancel_are_dropped`), so the rows after it move.
    matrix, near_null = system_and_candidates(2000)
    tentative = tentative_of(matrix, near_null)
    diagonal = sp.bsr_matrix(sp.identity(matrix.shape[0]) * 4.0, blocksize=(3, 3))
    weights = np.where(np.arange(matrix.shape[0]) // 3 % 3 == 0, 0.25, 0.1)
    pose_weights = random_weights(matrix.shape[0])
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        partly = ours(diagonal, tentative, weights)
        assert 0 < partly.indptr[-1] < tentative.indptr[-1]
        assert_same_blocks(partly, scipys_prolongation(diagonal, tentative, weights))
        assert_same_blocks(ours(matrix, tentative, pose_weights),
                           scipys_prolongation(matrix, tentative, pose_weights))
    finally:
        numba.set_num_threads(before)


def test_a_prolongation_on_a_kept_pattern_drops_the_blocks_that_cancel_now() -> None:
    # The symbolic pass's pattern counts blocks before any is dropped: a product with values that cancel
    # a block (W·A = I on every third pose) fills from the pattern of one where none cancelled, and is
    # still scipy's; the Galerkin pattern of the first P does not fit the second.
    matrix, near_null = system_and_candidates(2000)
    tentative = tentative_of(matrix, near_null)
    diagonal = sp.bsr_matrix(sp.identity(matrix.shape[0]) * 4.0, blocksize=(3, 3))
    whole, pattern = smoothed_prolongation(diagonal, tentative, np.full(matrix.shape[0], 0.1))
    assert whole.indptr[-1] == tentative.indptr[-1]
    weights = np.where(np.arange(matrix.shape[0]) // 3 % 3 == 0, 0.25, 0.1)
    partly, same_pattern = smoothed_prolongation(diagonal, tentative, weights, pattern)
    assert same_pattern is pattern and 0 < partly.indptr[-1] < whole.indptr[-1]
    assert_same_blocks(partly, scipys_prolongation(diagonal, tentative, weights))
    galerkin = galerkin_product(diagonal, whole)[1]
    assert galerkin.fits(whole) and not galerkin.fits(partly)


def test_a_galerkin_product_on_a_kept_pattern_is_scipys() -> None:
    matrix, near_null = system_and_candidates(2000)
    prolongation = ours(matrix, tentative_of(matrix, near_null), random_weights(matrix.shape[0]))
    _, pattern = galerkin_product(matrix, prolongation)
    rng = np.random.default_rng(5)
    scaled = sp.bsr_matrix((matrix.data * rng.uniform(0.5, 2.0, (matrix.data.shape[0], 1, 1)),
                            matrix.indices, matrix.indptr), shape=matrix.shape)
    moved = sp.bsr_matrix((prolongation.data * rng.uniform(0.5, 2.0, prolongation.data.shape),
                           prolongation.indices, prolongation.indptr), shape=prolongation.shape)
    reference = (sp.bsr_matrix(moved.T) @ scaled) @ moved
    product, same_pattern = galerkin_product(scaled, moved, pattern)
    assert same_pattern is pattern
    assert_same_blocks(product, reference)
