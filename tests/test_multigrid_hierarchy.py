"""The polish's smoothed-aggregation hierarchy against pyamg's own with the same options."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from tests.conftest import MULTIGRID_STACK
from tests.test_multigrid_polish import scaled_system

pytest.importorskip("pyamg")

import pyamg  # needs pyamg: after the skip

from optimizer.multigrid_hierarchy import MAX_COARSE, _absolute_row_sums, smoothed_aggregation

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


def system_and_candidates(num_poses: int) -> tuple[sp.bsr_matrix, np.ndarray]:
    """`scaled_system` and the rigid motions as near-null candidates (in the scaled variables)."""
    matrix, linearisation = scaled_system(num_poses)
    poses = linearisation.poses[1:]
    motions = np.zeros((poses.shape[0], 3, 4))
    motions[:, 0, 0] = motions[:, 1, 1] = motions[:, 2, 2] = motions[:, 2, 3] = 1.0
    motions[:, 0, 3] = -poses[:, 1]
    motions[:, 1, 3] = poses[:, 0]
    return matrix, (motions / linearisation.scale.reshape(-1, 3)[:, :, None]).reshape(-1, 4)


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
