"""The multithreaded kernels of the multigrid polish give the numbers of one thread, and scipy's/numpy's."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from optimizer import block_smoother, cost
from optimizer.block_smoother import inverted_diagonal, prolong_into
from optimizer.errors import OptimizerError
from optimizer.gridworld import generate_grid_world
from optimizer.parallel_products import add_scaled, block_product, scale_and_add
from tests.conftest import MULTIGRID_STACK
from tests.optimizer_fixtures import symmetric_block_matrix

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)

THREADS = sorted({1, 2, numba.config.NUMBA_NUM_THREADS})


@pytest.fixture(autouse=True)
def _restore_threads() -> Iterator[None]:
    before = numba.get_num_threads()
    yield
    numba.set_num_threads(before)


def for_each_thread_count(compute: Callable[[], np.ndarray]) -> list[np.ndarray]:
    results = []
    for threads in THREADS:
        numba.set_num_threads(threads)
        results.append(compute())
    return results


def random_block_sparse(rows: int, seed: int) -> sp.bsr_matrix:
    """Unsymmetric 3×3 blocks of all magnitudes on a pose-graph-like pattern (rows of 1 to ~12 blocks)."""
    matrix = symmetric_block_matrix(3, rows, seed)
    rng = np.random.default_rng(seed)
    shape = matrix.data.shape
    matrix.data[...] = rng.normal(size=shape) * 10.0 ** rng.integers(-8, 8, size=shape)
    return matrix


def test_the_block_product_is_scipys_to_the_bit_on_any_number_of_threads() -> None:
    matrix = random_block_sparse(4000, seed=5)
    vector = np.random.default_rng(6).normal(size=matrix.shape[1])
    expected = matrix @ vector
    for result in for_each_thread_count(lambda: block_product(matrix, vector)):
        np.testing.assert_array_equal(result, expected)


def test_the_block_product_of_empty_rows_is_zero() -> None:
    blocks = np.arange(18, dtype=np.float64).reshape(2, 3, 3)
    matrix = sp.bsr_matrix((blocks, np.array([0, 2]), np.array([0, 1, 1, 2])), shape=(9, 9))
    vector = np.arange(9, dtype=np.float64)
    result = block_product(matrix, vector)
    np.testing.assert_array_equal(result, matrix.toarray() @ vector)
    np.testing.assert_array_equal(result[3:6], 0.0)


def test_the_block_product_refuses_other_blocks_and_vectors() -> None:
    with pytest.raises(OptimizerError, match="3×3"):
        block_product(symmetric_block_matrix(4, 10, seed=1), np.zeros(40))
    with pytest.raises(OptimizerError, match="30 entries"):
        block_product(symmetric_block_matrix(3, 10, seed=1), np.zeros(31))


def test_the_vector_updates_are_numpys_to_the_bit() -> None:
    rng = np.random.default_rng(7)
    target, vector = rng.normal(size=100_003), rng.normal(size=100_003)
    factor = float(rng.normal())
    expected_added = target + factor * vector
    expected_scaled = target * factor + vector
    for threads in THREADS:
        numba.set_num_threads(threads)
        added, scaled = target.copy(), target.copy()
        add_scaled(added, factor, vector)
        scale_and_add(scaled, factor, vector)
        np.testing.assert_array_equal(added, expected_added)
        np.testing.assert_array_equal(scaled, expected_scaled)
    with pytest.raises(OptimizerError, match="shapes differ"):
        add_scaled(target, 1.0, vector[:-1])


@pytest.mark.parametrize("rows", [3, 4])
def test_the_prolongation_is_the_same_on_any_number_of_threads(rows: int) -> None:
    rng = np.random.default_rng(9)
    dense = sp.random(rows * 2000, 4 * 300, density=0.01, random_state=10, format="csr")
    prolongation = sp.bsr_matrix(dense, blocksize=(rows, 4))
    coarse, start = rng.normal(size=prolongation.shape[1]), rng.normal(size=prolongation.shape[0])

    def prolong() -> np.ndarray:
        solution = start.copy()
        prolong_into(prolongation, coarse, solution)
        return solution

    results = for_each_thread_count(prolong)
    np.testing.assert_allclose(results[0], start + prolongation @ coarse, rtol=1e-14, atol=1e-14)
    for result in results[1:]:
        np.testing.assert_array_equal(result, results[0])


@pytest.mark.parametrize("chunk", [1000, 65_536])
def test_chi2_is_the_one_thread_sum_to_the_bit(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    # Terms on all threads, summed in constraint order on one: `_chi2_kernel`'s number, chunk after chunk.
    monkeypatch.setattr(cost, "CHI2_CHUNK", chunk)
    monkeypatch.setattr(cost, "CHI2_PARALLEL_MIN", 0)  # this graph is small enough for the one-thread sum
    graph = generate_grid_world(3000, seed=3).graph
    poses = graph.poses + np.random.default_rng(12).normal(scale=0.1, size=graph.poses.shape)
    expected = cost._chi2_kernel(poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information)
    assert graph.num_edges > chunk or chunk == 65_536
    for threads in THREADS:
        numba.set_num_threads(threads)
        assert cost.chi2(graph, poses) == expected


def test_the_diagonal_is_inverted_the_same_on_any_number_of_threads() -> None:
    # Chunks of blocks on numba's threads (serially with one): the same inverses, bit for bit.
    matrix = symmetric_block_matrix(3, 3 * block_smoother.INVERSION_CHUNK + 5, seed=13)
    expected = inverted_diagonal(matrix)
    for result in for_each_thread_count(lambda: inverted_diagonal(matrix)):
        np.testing.assert_array_equal(result, expected)
