"""The polish's smoothed-aggregation hierarchy against pyamg's own with the same options."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from tests.conftest import MULTIGRID_STACK
from tests.optimizer_fixtures import system_and_candidates

pytest.importorskip("pyamg")

import pyamg  # needs pyamg: after the skip
from pyamg.aggregation.aggregate import standard_aggregation
from pyamg.aggregation.tentative import fit_candidates
from pyamg.strength import symmetric_strength_of_connection

from optimizer.hierarchy_products import GalerkinPattern
from optimizer.multigrid_hierarchy import (
    MAX_COARSE,
    CoarsestSolver,
    HierarchyPatterns,
    _absolute_row_sums,
    _aggregated_in_order,
    _tentative_prolongation,
    smoothed_aggregation,
)

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


def test_the_hierarchy_is_pyamgs_smoothed_aggregation_to_rounding() -> None:
    matrix, near_null = system_and_candidates(5000)
    ours = smoothed_aggregation(matrix, near_null)
    theirs = pyamg.smoothed_aggregation_solver(
        matrix, B=near_null, symmetry="hermitian", strength="symmetric", max_coarse=MAX_COARSE,
        improve_candidates=None, smooth=("jacobi", {"omega": 4.0 / 3.0, "weighting": "local"}))
    assert len(ours.levels) == len(theirs.levels) >= 3
    for mine, reference in zip(ours.levels, theirs.levels, strict=True):
        assert mine.A.shape == reference.A.shape
        assert abs(mine.A - reference.A).max() <= 1e-12 * abs(reference.A).max()
        if hasattr(reference, "P"):
            assert abs(mine.P - reference.P).max() <= 1e-12 * abs(reference.P).max()


def test_absolute_row_sums_read_the_blocks_in_place() -> None:
    rng = np.random.default_rng(3)
    dense = rng.normal(size=(12, 8)) * (rng.random((12, 8)) < 0.4)
    matrix = sp.bsr_matrix(dense, blocksize=(3, 4))
    sums = np.zeros(12)
    _absolute_row_sums(matrix.indptr, matrix.data, sums)
    np.testing.assert_allclose(sums, np.abs(dense).sum(axis=1), rtol=1e-15)


def test_no_level_stores_a_restriction() -> None:
    # The V-cycle restricts with P's blocks read transposed: a stored R = Pᵀ (pyamg's default) would be
    # 232 MB at 10⁶ poses, at the build's peak.
    matrix, near_null = system_and_candidates(5000)
    levels = smoothed_aggregation(matrix, near_null).levels
    assert len(levels) >= 3
    assert [getattr(level, "R", None) for level in levels] == [None] * len(levels)


def assert_same_levels(mine: pyamg.MultilevelSolver, reference: pyamg.MultilevelSolver) -> None:
    """Every level's A and P equal bit for bit, blocks in the same order."""
    assert len(mine.levels) == len(reference.levels)
    for ours, theirs in zip(mine.levels, reference.levels, strict=True):
        for name in ("A", "P"):
            if hasattr(theirs, name):
                a, b = getattr(ours, name), getattr(theirs, name)
                assert a.shape == b.shape and a.blocksize == b.blocksize
                np.testing.assert_array_equal(a.indptr, b.indptr)
                np.testing.assert_array_equal(a.indices, b.indices)
                np.testing.assert_array_equal(a.data, b.data)


def same_pattern_other_values(matrix: sp.bsr_matrix, near_null: np.ndarray,
                              seed: int) -> tuple[sp.bsr_matrix, np.ndarray]:
    """D·A·D (D positive diagonal, one factor per pose: still symmetric positive definite, A's pattern)
    and candidates moved as poses move between two linearisations."""
    rng = np.random.default_rng(seed)
    factors = rng.uniform(0.5, 2.0, matrix.shape[0] // 3)
    rows = np.repeat(np.arange(factors.shape[0]), np.diff(matrix.indptr))
    data = matrix.data * (factors[rows] * factors[matrix.indices])[:, None, None]
    other = sp.bsr_matrix((data, matrix.indices.copy(), matrix.indptr.copy()), shape=matrix.shape)
    return other, near_null * rng.uniform(0.9, 1.1, near_null.shape)


def test_a_build_on_kept_patterns_is_the_fresh_build_bit_for_bit() -> None:
    # The polish builds a hierarchy at each linearisation of one graph: aggregation and the products'
    # symbolic passes read patterns only (strength θ = 0), so the second build reuses the first's.
    matrix, near_null = system_and_candidates(5000)
    patterns = HierarchyPatterns()
    first = smoothed_aggregation(matrix, near_null, patterns)
    assert patterns.reused_levels == 0
    assert_same_levels(first, smoothed_aggregation(matrix, near_null))
    other, other_null = same_pattern_other_values(matrix, near_null, seed=1)
    kept = smoothed_aggregation(other, other_null, patterns)
    assert patterns.reused_levels == len(kept.levels) - 1 >= 2
    assert_same_levels(kept, smoothed_aggregation(other, other_null))


def test_another_pattern_is_built_afresh() -> None:
    matrix, near_null = system_and_candidates(5000)
    patterns = HierarchyPatterns()
    smoothed_aggregation(matrix, near_null, patterns)
    smaller, smaller_null = system_and_candidates(3000)
    rebuilt = smoothed_aggregation(smaller, smaller_null, patterns)
    assert patterns.reused_levels == 0
    assert_same_levels(rebuilt, smoothed_aggregation(smaller, smaller_null))
    # ... and what it kept now is the new pattern's.
    other, other_null = same_pattern_other_values(smaller, smaller_null, seed=2)
    kept = smoothed_aggregation(other, other_null, patterns)
    assert patterns.reused_levels == len(kept.levels) - 1


def test_a_prolongation_of_another_pattern_gets_a_new_coarse_level(monkeypatch: pytest.MonkeyPatch) -> None:
    # A prolongation block that cancels to exactly zero is dropped, so P's pattern can differ between two
    # matrices of one pattern; then the Galerkin product counts afresh, and so does every coarser level.
    matrix, near_null = system_and_candidates(5000)
    patterns = HierarchyPatterns()
    smoothed_aggregation(matrix, near_null, patterns)
    monkeypatch.setattr(GalerkinPattern, "fits", lambda self, prolongation: False)
    other, other_null = same_pattern_other_values(matrix, near_null, seed=3)
    rebuilt = smoothed_aggregation(other, other_null, patterns)
    assert patterns.reused_levels == 0
    assert_same_levels(rebuilt, smoothed_aggregation(other, other_null))


def aggregate_of_each_row(aggregates: sp.csr_array) -> np.ndarray:
    labels = np.full(aggregates.shape[0], -1)
    rows = np.repeat(np.arange(aggregates.shape[0]), np.diff(aggregates.indptr))
    labels[rows] = aggregates.indices
    return labels


def test_aggregation_in_a_visit_order_is_the_aggregation_of_the_rows_in_that_order() -> None:
    matrix, _ = system_and_candidates(3000)
    strength = symmetric_strength_of_connection(matrix)
    shuffle = np.random.default_rng(3).permutation(strength.shape[0])  # row shuffle[k] becomes row k
    shuffled = sp.csr_array(strength)[shuffle][:, shuffle]
    shuffled.sort_indices()
    position = np.empty_like(shuffle)
    position[shuffle] = np.arange(shuffle.shape[0])
    # Visiting the shuffled rows in the strength's own order: the same aggregates as pyamg's in that order.
    aggregates, formed = _aggregated_in_order(shuffled, position)
    reference, _ = standard_aggregation(sp.csr_array(strength))
    mine, theirs = aggregate_of_each_row(aggregates), aggregate_of_each_row(reference)[shuffle]
    assert np.all(mine >= 0) and aggregates.shape[1] == reference.shape[1]
    pairs = set(zip(mine.tolist(), theirs.tolist(), strict=True))
    assert len(pairs) == aggregates.shape[1]  # one to one: the same partition of the rows
    # pyamg's aggregate j (formed j-th) is ours formed[j]; ours are numbered by their first row.
    assert pairs == set(zip(formed.tolist(), range(reference.shape[1]), strict=True))
    first_rows = [int(np.flatnonzero(mine == label)[0]) for label in range(aggregates.shape[1])]
    assert first_rows == sorted(first_rows)


def test_the_tentative_prolongation_is_pyamgs_bit_for_bit() -> None:
    matrix, near_null = system_and_candidates(3000)
    aggregates, _ = standard_aggregation(symmetric_strength_of_connection(matrix))
    tentative, coarse = _tentative_prolongation(aggregates, near_null)
    reference, reference_coarse = fit_candidates(aggregates, near_null)
    reference = sp.bsr_matrix(reference)
    assert tentative.blocksize == reference.blocksize == (3, 4) and tentative.shape == reference.shape
    np.testing.assert_array_equal(tentative.indptr, reference.indptr)
    np.testing.assert_array_equal(tentative.indices, reference.indices)
    np.testing.assert_array_equal(tentative.data, reference.data)
    np.testing.assert_array_equal(coarse, reference_coarse)


def test_the_coarsest_level_is_solved_exactly_when_regular_and_by_pseudo_inverse_when_singular() -> None:
    rng = np.random.default_rng(9)
    factors = rng.normal(size=(40, 40))
    regular = factors @ factors.T + np.eye(40)
    rhs = rng.normal(size=40)
    np.testing.assert_allclose(CoarsestSolver()(sp.csr_array(regular), rhs), np.linalg.solve(regular, rhs),
                               rtol=1e-10)
    # A dropped candidate: a zero row and column. The pseudo-inverse's answer, as pyamg's "pinv" gives.
    singular = regular.copy()
    singular[7, :] = singular[:, 7] = 0.0
    solver = CoarsestSolver()
    solution = solver(sp.csr_array(singular), rhs)
    np.testing.assert_allclose(solution, np.linalg.pinv(singular) @ rhs, rtol=1e-9, atol=1e-12)
    assert abs(solution[7]) <= 1e-12 * np.abs(solution).max()
    # Factorised once: later right-hand sides reuse it (the level's matrix is not read again).
    np.testing.assert_allclose(solver(sp.csr_array(regular), rhs), solution)
