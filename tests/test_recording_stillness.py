"""The recorder's compiled still test against the vectorized expressions it replaced."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.recording.stillness import finite_extent, moved_within


def _extent_by_numpy(poses: np.ndarray) -> float:
    finite = poses[np.all(np.isfinite(poses[:, :2]), axis=1), :2]
    return float(np.max(np.ptp(finite, axis=0))) if len(finite) else 0.0


def _within_by_numpy(poses: np.ndarray, drawn: np.ndarray, distance: float) -> bool:
    with np.errstate(invalid="ignore"):  # inf − inf of non-finite poses: NaN, which the max keeps, silently
        return bool(np.max(np.abs(poses[:, :2] - drawn), initial=0.0) <= distance)


@pytest.mark.parametrize("seed", range(6))
def test_same_answers_as_the_vectorized_form(seed: int) -> None:
    rng = np.random.default_rng(seed)
    poses = rng.normal(0.0, 10.0 ** rng.uniform(-3, 6), size=(int(rng.integers(1, 300)), 3))
    specials = rng.random(poses.shape) < 0.03 * (seed % 3)  # none, some, more non-finite values
    poses[specials] = rng.choice([np.nan, np.inf, -np.inf], size=int(specials.sum()))
    assert finite_extent(poses) == _extent_by_numpy(poses)
    drawn = np.array(poses[:, :2]) + rng.normal(0.0, 1e-3, size=(len(poses), 2)) * (rng.random() < 0.5)
    for distance in (0.0, 1e-4, 1e-3, 5e-3, 1.0, np.inf):
        assert moved_within(poses, drawn, distance) == _within_by_numpy(poses, drawn, distance)


def test_no_finite_pose_has_no_extent() -> None:
    poses = np.full((4, 3), np.nan)
    poses[1, 0] = 3.0  # x finite, y not: not counted
    assert finite_extent(poses) == 0.0
