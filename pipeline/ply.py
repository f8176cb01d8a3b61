"""Point-cloud maps as files: binary little-endian PLY (CloudCompare, MeshLab, Open3D) and binary PCD (PCL).

Both hold float32 x, y, z, as given: the 3D replay passes the keyframe clouds placed at their optimized
poses, in the map frame (the base frame of the first keyframe), one point per voxel of its map voxel. The
PLY header is a few fixed lines (the well-kept PLY library, plyfile, is GPL; the project is MIT); the PCD
goes through `pypcd4`, the maintained PCD reader/writer on PyPI, so that PCL's and ROS's tools read it
without surprises (its viewpoint is the identity: the points are in the map frame). Both write `path`
directly (stage it with `pipeline.outputs.staged_outputs`) and raise `OutputError` when it cannot be
written, ValueError on arrays of the wrong shape.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pypcd4 import PointCloud

from pipeline.outputs import write_bytes

PLY_HEADER = ("ply\nformat binary_little_endian 1.0\ncomment written by sgdslam\nelement vertex {count}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")


def write_ply(path: str | Path, points: ArrayLike) -> None:
    """Write (N, 3) points as a binary little-endian PLY of float32 vertices."""
    points = _xyz(points)
    write_bytes(Path(path), PLY_HEADER.format(count=len(points)).encode("ascii") + points.tobytes())


def write_map_pcd(path: str | Path, points: ArrayLike) -> None:
    """Write (N, 3) map points as a binary PCD (fields x y z, float32, one row: an unorganized cloud)."""
    buffer = io.BytesIO()
    PointCloud.from_xyz_points(_xyz(points)).save(buffer)
    write_bytes(Path(path), buffer.getvalue())


def _xyz(points: ArrayLike) -> NDArray[np.float32]:
    points = np.asarray(points, dtype="<f4")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    return points
