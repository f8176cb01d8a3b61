"""Keyframe scans placed in the map frame, ready for matching: likelihood grid, points and normals."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontends.slam2d.grid import LikelihoodGrid, build_likelihood_grid

FloatArray = NDArray[np.float64]


def rotation(theta: float) -> FloatArray:
    """The matrix that rotates row vectors by θ: `points @ rotation(θ)`."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s], [-s, c]])


def place(points: FloatArray, pose: FloatArray) -> FloatArray:
    """Robot-frame points (N, 2) expressed in the frame where the robot is at `pose`."""
    return points @ rotation(pose[2]) + pose[:2]


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A keyframe's scan in its own frame: points (N, 2) and their normals (NaN where no line)."""

    points: FloatArray
    normals: FloatArray


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
            centre = np.asarray(poses[-1])[:2]
            near = [np.hypot(*(np.asarray(p)[:2] - centre)) <= reach for p in poses]
            keyframes = [k for k, n in zip(keyframes, near, strict=True) if n]
            poses = [p for p, n in zip(poses, near, strict=True) if n]
        points = np.concatenate([place(k.points, p) for k, p in zip(keyframes, poses, strict=True)])
        normals = np.concatenate([k.normals @ rotation(p[2]) for k, p in zip(keyframes, poses, strict=True)])
        # Several keyframes see the same wall: keep one point per half cell, the latest keyframe's
        # (the best placed relative to the robot), which keeps pairing even without changing the grid.
        cells = np.floor(points / (0.5 * resolution)).astype(np.int64)
        keys = cells[:, 0] * 2_000_003 + cells[:, 1]
        _, last = np.unique(keys[::-1], return_index=True)
        keep = np.sort(len(keys) - 1 - last)
        points = np.ascontiguousarray(points[keep])
        normals = np.ascontiguousarray(normals[keep])
        grid = build_likelihood_grid(points, resolution, likelihood_sigma, margin, pairing_distance)
        return cls(grid, points, normals)
