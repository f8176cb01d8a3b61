"""The point map of placed keyframe clouds, one point per voxel, in one compiled pass.

`place_one_per_voxel` keeps the same points as placing every cloud (`se3.transform_points`), concatenating
them and thinning with KISS-ICP's voxel filter (`odometry.downsample`: the first point seen in each voxel),
but in the clouds' order instead of a hash map's, without the 4×-larger concatenated float64 copy and its
two conversions to and from KISS-ICP's vector type (KITTI: 790 000 placed points, 0.2 s of the replay).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from frontends.slam3d.odometry import downsample

KEY_BITS = 21
"""Bits per axis of a voxel's key: ±2²⁰ voxels (±210 km at 0.2 m) around the origin; a map reaching
farther is thinned by KISS-ICP's filter instead."""
_KEY_OFFSET = 1 << (KEY_BITS - 1)


def place_one_per_voxel(
    poses: ArrayLike, clouds: Sequence[NDArray[np.floating]], voxel: float
) -> NDArray[np.float32]:
    """(P, 3) the clouds (each (Nᵢ, 3) in its own frame) placed at their 4×4 `poses`, the first point of
    each voxel of this size kept, in the clouds' order."""
    poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(clouds) == 0:
        return np.empty((0, 3), np.float32)
    points = np.ascontiguousarray(np.concatenate([np.asarray(c, np.float32).reshape(-1, 3) for c in clouds]))
    offsets = np.zeros(len(clouds) + 1, dtype=np.int64)
    np.cumsum([len(c) for c in clouds], out=offsets[1:])
    placed, keys, in_range = _place_and_key(points, offsets, poses, float(voxel))
    if not in_range:
        return downsample(placed, voxel).astype(np.float32)
    return placed[_first_per_key(keys)].astype(np.float32)


@njit(cache=True)
def _place_and_key(
    points: NDArray[np.float32], offsets: NDArray[np.int64], poses: NDArray[np.float64], voxel: float
) -> tuple[NDArray[np.float64], NDArray[np.int64], bool]:
    placed = np.empty((points.shape[0], 3), dtype=np.float64)
    keys = np.empty(points.shape[0], dtype=np.int64)
    in_range = True
    for cloud in range(offsets.shape[0] - 1):
        pose = poses[cloud]
        for i in range(offsets[cloud], offsets[cloud + 1]):
            x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
            key = np.int64(0)
            for axis in range(3):
                value = pose[axis, 0] * x + pose[axis, 1] * y + pose[axis, 2] * z + pose[axis, 3]
                placed[i, axis] = value
                cell = np.floor(value / voxel)
                if not abs(cell) < _KEY_OFFSET:  # NaN too
                    in_range = False
                    cell = 0.0
                key = (key << KEY_BITS) | (np.int64(cell) + _KEY_OFFSET)
            keys[i] = key
    return placed, keys, in_range


@njit(cache=True)
def _first_per_key(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Ascending indices of each key's first occurrence: an open-addressing table of the keys seen."""
    count = keys.shape[0]
    bits = 1
    while (1 << bits) < 2 * count:
        bits += 1
    size = 1 << bits
    table = np.full(size, -1, dtype=np.int64)
    mask = np.uint64(size - 1)
    # Fibonacci hashing: the product's top bits mix every bit of the key (x, y and z alike)
    shift = np.uint64(64 - bits)
    kept = np.zeros(count, dtype=np.bool_)
    for i in range(count):
        slot = (np.uint64(keys[i]) * np.uint64(0x9E3779B97F4A7C15)) >> shift
        while table[slot] >= 0 and keys[table[slot]] != keys[i]:
            slot = (slot + np.uint64(1)) & mask
        if table[slot] < 0:
            table[slot] = i
            kept[i] = True
    return np.flatnonzero(kept)
