"""Keyframe scans placed in the map frame, ready for matching: likelihood grid, points and normals."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.slam2d.grid import LikelihoodGrid, build_likelihood_grid, stamp_more

FloatArray = NDArray[np.float64]


def rotation(theta: float) -> FloatArray:
    """The matrix that rotates row vectors by θ: `points @ rotation(θ)`."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s], [-s, c]])


def place(points: FloatArray, pose: FloatArray) -> FloatArray:
    """Robot-frame points (N, 2) expressed in the frame where the robot is at `pose`."""
    return points @ rotation(pose[2]) + pose[:2]


def one_per_cell(points: FloatArray, cell: float, keep_last: bool = False) -> NDArray[np.int64]:
    """Indices (ascending) of the first point, or the last with `keep_last`, in each square cell of `cell`
    metres: thinning that keeps the points' order."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    return _one_per_cell(points, float(cell), keep_last)


def one_per_cell_each(points: FloatArray, offsets: NDArray[np.int64],
                      cell: float) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """`one_per_cell` (first points) of each segment `points[offsets[s]:offsets[s + 1]]` in one call, the
    non-finite points dropped: which points are kept, and how many of each segment."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    # keep_last passed in, not the constant False: a constant is typed as a literal, which compiled
    # `_one_per_cell` and `_one_per_key` a second time (seconds each on a cold cache)
    return _one_per_cell_each(points, np.asarray(offsets, dtype=np.int64), float(cell), False)


@njit(cache=True, nogil=True)
def _one_per_cell_each(points: FloatArray, offsets: NDArray[np.int64], cell: float,
                       keep_last: bool) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    keep = np.zeros(points.shape[0], dtype=np.bool_)
    counts = np.zeros(offsets.shape[0] - 1, dtype=np.int64)
    for segment in range(offsets.shape[0] - 1):
        start, end = offsets[segment], offsets[segment + 1]
        finite = np.empty(end - start, dtype=np.int64)
        count = 0
        for i in range(start, end):
            if np.isfinite(points[i, 0]) and np.isfinite(points[i, 1]):
                finite[count] = i
                count += 1
        kept = _one_per_cell(points[finite[:count]], cell, keep_last)
        for k in kept:
            keep[finite[k]] = True
        counts[segment] = kept.shape[0]
    return keep, counts


@njit(cache=True, nogil=True)
def _one_per_cell(points: FloatArray, cell: float, keep_last: bool) -> NDArray[np.int64]:
    # One integer per cell, distinct for every cell within ±2³¹ cells (no map spans that many); computed
    # here rather than in numpy, whose four temporaries cost more than the table on a scan's few hundred
    # points.
    keys = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        column, row = np.floor(points[i, 0] / cell), np.floor(points[i, 1] / cell)
        keys[i] = np.int64(column) * 4_294_967_296 + np.int64(row)
    return _one_per_key(keys, keep_last)


@njit(cache=True, nogil=True)
def _one_per_key(keys: NDArray[np.int64], keep_last: bool) -> NDArray[np.int64]:
    """What np.unique's first indices give (of the reversed keys, for the last), in linear time: an
    open-addressing table of the keys seen, each with the index kept for it."""
    count = keys.shape[0]
    size = 2
    size_bits = 1
    while size < 2 * count:
        size *= 2
        size_bits += 1
    table_keys = np.empty(size, dtype=np.int64)
    table_index = np.full(size, -1, dtype=np.int64)
    mask = np.uint64(size - 1)
    # Fibonacci hashing: the product's top bits, which every bit of the key reaches (its bits 17 and up,
    # taken before, depended on the row alone: a row's cells all probed from one slot).
    shift = np.uint64(64 - size_bits)
    for i in range(count):
        slot = (np.uint64(keys[i]) * np.uint64(0x9E3779B97F4A7C15)) >> shift
        while table_index[slot] >= 0 and table_keys[slot] != keys[i]:
            slot = (slot + np.uint64(1)) & mask
        if table_index[slot] < 0:
            table_keys[slot] = keys[i]
            table_index[slot] = i
        elif keep_last:
            table_index[slot] = i
    kept = np.zeros(count, dtype=np.bool_)
    for entry in range(size):
        if table_index[entry] >= 0:
            kept[table_index[entry]] = True
    return np.flatnonzero(kept)


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A keyframe's scan in its own frame: points (N, 2) and their normals (NaN where no line)."""

    points: FloatArray
    normals: FloatArray
    _placed: dict[tuple[float, float, float], tuple[FloatArray, FloatArray]] = field(
        default_factory=dict, repr=False
    )

    def placed(self, pose: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Points and normals in the frame where the keyframe is at `pose`. A keyframe joins a few dozen
        local maps at the same pose (until an optimization moves it): placed once for all of them."""
        key = (float(pose[0]), float(pose[1]), float(pose[2]))
        cached = self._placed.get(key)
        if cached is None:
            cached = (place(self.points, pose), self.normals @ rotation(pose[2]))
            self._placed.clear()  # the previous pose is not coming back
            self._placed[key] = cached
        return cached


@dataclass(frozen=True, eq=False)
class Submap:
    grid: LikelihoodGrid
    points: FloatArray
    normals: FloatArray

    @classmethod
    def of(
        cls,
        keyframes: Sequence[Keyframe],
        poses: Sequence[FloatArray],
        *,
        resolution: float,
        likelihood_sigma: float,
        margin: float,
        pairing_distance: float,
        reach: float | None = None,
    ) -> Submap:
        """The keyframes' points placed at their poses (the last one being the newest or the centre);
        with `reach`, only keyframes within it of the last pose."""
        if reach is not None:
            # Keyframes farther from the newest than two scan reaches share no point with what is matched
            # against this map; leaving them out keeps the grid small after a jump in the poses.
            positions = np.asarray(poses, dtype=np.float64).reshape(-1, 3)[:, :2]
            offsets = positions - positions[-1]
            near = np.hypot(offsets[:, 0], offsets[:, 1]) <= reach
            keyframes = [k for k, n in zip(keyframes, near, strict=True) if n]
            poses = [p for p, n in zip(poses, near, strict=True) if n]
        placed = [k.placed(p) for k, p in zip(keyframes, poses, strict=True)]
        points = np.concatenate([p for p, _ in placed])
        normals = np.concatenate([n for _, n in placed])
        # Several keyframes see the same wall: keep one point per half cell, the latest keyframe's
        # (the best placed relative to the robot), which keeps pairing even without changing the grid.
        keep = one_per_cell(points, 0.5 * resolution, keep_last=True)
        points = np.ascontiguousarray(points[keep])
        normals = np.ascontiguousarray(normals[keep])
        grid = build_likelihood_grid(points, resolution, likelihood_sigma, margin, pairing_distance)
        return cls(grid, points, normals)

    def extended(self, keyframe: Keyframe, pose: FloatArray, *, likelihood_sigma: float, margin: float,
                 pairing_distance: float) -> Submap | None:
        """This map with `keyframe` added at `pose`, its points thinned among themselves (the map's own
        stay: a wall seen again gets a second point per half cell) and stamped into the grid in place
        (`stamp_more`: this map must not be used again). None, and this map untouched, when a point would
        fall within `margin` of the grid's edge: the map must then be built again, larger."""
        points, normals = keyframe.placed(pose)
        keep = one_per_cell(points, 0.5 * self.grid.resolution, keep_last=True)
        points, normals = points[keep], normals[keep]
        grid = self.grid
        if len(points):
            size = np.array(grid.values.shape[::-1]) * grid.resolution
            low, high = points.min(axis=0) - grid.origin, points.max(axis=0) - grid.origin
            if not (np.all(low >= margin) and np.all(high <= size - margin)):
                return None
        all_points = np.concatenate([self.points, points])
        grid = stamp_more(grid, all_points, len(self.points), likelihood_sigma, pairing_distance)
        return Submap(grid, all_points, np.concatenate([self.normals, normals]))
