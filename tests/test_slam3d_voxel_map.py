"""The compiled map thinning keeps, in the clouds' order, the first placed point of every voxel."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.slam3d.odometry import downsample
from frontends.slam3d.voxel_map import place_one_per_voxel


def _poses(count: int, rng: np.random.Generator, reach: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=rng.integers(1 << 31)).as_matrix()
    poses[:, :3, 3] = rng.uniform(-reach, reach, (count, 3))
    return poses


def _placed(poses: np.ndarray, clouds: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([c.astype(np.float64) @ p[:3, :3].T + p[:3, 3]
                           for p, c in zip(poses, clouds, strict=True)])


def _first_per_voxel(poses: np.ndarray, clouds: list[np.ndarray], voxel: float) -> np.ndarray:
    """Plain numpy: place every point, then np.unique's first index of each voxel, in input order."""
    placed = _placed(poses, clouds)
    _, first = np.unique(np.floor(placed / voxel).astype(np.int64), axis=0, return_index=True)
    return placed[np.sort(first)].astype(np.float32)


@pytest.mark.parametrize("reach", [5.0, 1e6])  # 1e6 m: beyond the compiled keys, KISS-ICP's filter
def test_the_map_keeps_the_first_placed_point_of_each_voxel_in_the_clouds_order(reach: float) -> None:
    rng = np.random.default_rng(7)
    # a coarse lattice of offsets so that neighbouring clouds share voxels, and no point sits on a border
    clouds = [(rng.integers(-20, 20, (n, 3)) * 0.25 + 0.03).astype(np.float32) for n in (300, 0, 500, 1)]
    poses = _poses(len(clouds), rng, reach)
    poses[1] = poses[0]
    poses[2, :3, :3], poses[2, :3, 3] = poses[0, :3, :3], poses[0, :3, 3] + 0.5  # overlaps cloud 0
    expected = _first_per_voxel(poses, clouds, 0.4)
    kept = place_one_per_voxel(poses, clouds, 0.4)
    assert kept.dtype == np.float32
    if reach < 1e3:
        np.testing.assert_allclose(kept, expected, atol=1e-4)
    else:  # KISS-ICP's filter returns its hash map's order: the same points
        np.testing.assert_allclose(kept[np.lexsort(kept.T)], expected[np.lexsort(expected.T)], atol=1e-1)
    assert len(kept) < sum(len(c) for c in clouds)  # the overlap was thinned


def test_the_map_holds_the_same_points_as_kiss_icp_s_filter() -> None:
    rng = np.random.default_rng(3)
    clouds = [rng.normal(0.0, 10.0, (2000, 3)).astype(np.float32) for _ in range(6)]
    poses = _poses(len(clouds), rng, 20.0)
    theirs = downsample(_placed(poses, clouds), 0.5).astype(np.float32)
    ours = place_one_per_voxel(poses, clouds, 0.5)
    assert len(ours) == len(theirs)
    np.testing.assert_allclose(ours[np.lexsort(ours.T)], theirs[np.lexsort(theirs.T)], atol=1e-5)


def test_no_clouds_make_an_empty_map() -> None:
    assert place_one_per_voxel(np.empty((0, 4, 4)), [], 0.2).shape == (0, 3)
    assert place_one_per_voxel(np.eye(4)[None], [np.empty((0, 3), np.float32)], 0.2).shape == (0, 3)
