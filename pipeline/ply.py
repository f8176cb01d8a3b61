"""Point clouds as files: binary little-endian PLY (CloudCompare, MeshLab, Open3D) and binary PCD (PCL).

`write_ply` writes vertices with float32 x, y, z (and optional uchar red, green, blue); `read_ply` reads
back binary little-endian vertex-only files with scalar properties, which is what it writes.
`write_map_pcd` writes the same map as a PCL `.pcd` (binary, float32 x y z, through `pypcd4`, the
maintained PCD reader/writer on PyPI, so that PCL's and ROS's tools read it without surprises).

Maps are written as they are given: the 3D replay passes the keyframe clouds placed at their optimized
poses, in the map frame (the base frame of the first keyframe), one point per voxel of
`pipeline.replay_cloud.MAP_VOXEL` (0.2 m); `write_map_pcd(..., voxel=...)` thins further when asked.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pypcd4 import PointCloud

from pipeline.errors import OutputError
from pipeline.trajectory_io import DataFileError

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


class PlyFileError(DataFileError):
    """A PLY file is missing, unreadable, or not a binary little-endian vertex list we can read."""


def write_ply(path: str | Path, points: ArrayLike, colors: ArrayLike | None = None) -> None:
    """Write (N, 3) points (stored as float32) and optional (N, 3) uint8 colours as a binary
    little-endian PLY. Writes `path` directly (stage it with `pipeline.outputs.staged_outputs`); raises
    `OutputError` when it cannot be written, ValueError on arrays of the wrong shape."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by sgdslam",
        f"element vertex {len(points)}",
        *(f"property float {axis}" for axis in "xyz"),
    ]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8)
        if colors.shape != points.shape:
            raise ValueError(f"colors must be (N, 3) like the points, got {colors.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    vertices = np.empty(len(points), dtype=fields)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    if colors is not None:
        vertices["red"], vertices["green"], vertices["blue"] = colors.T
    try:
        with Path(path).open("wb") as stream:
            stream.write(("\n".join(header) + "\n").encode("ascii"))
            stream.write(vertices.tobytes())
    except OSError as error:
        raise OutputError(f"{path}: cannot write the file: {error.strerror or error}") from error


def read_ply(path: str | Path) -> NDArray[np.void]:
    """The vertices of a binary little-endian PLY as a structured array (fields named as in the file).
    Raises `PlyFileError` for anything else (ASCII or big-endian files, other elements, list properties,
    a truncated body)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise PlyFileError(path, f"cannot read the file: {error.strerror or error}") from error
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise PlyFileError(path, "not a PLY file (no 'ply' … 'end_header' header)")
    count: int | None = None
    fields: list[tuple[str, str]] = []
    for number, line in enumerate(data[:end].decode("ascii", errors="replace").splitlines()[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if words[1:] != ["binary_little_endian", "1.0"]:
                raise PlyFileError(path, f"format {' '.join(words[1:])} is not supported", number)
        elif words[0] == "element":
            if words[1] != "vertex" or count is not None:
                raise PlyFileError(path, f"element {words[1]} is not supported (vertices only)", number)
            count = int(words[2])
        elif words[0] == "property":
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise PlyFileError(path, f"property {' '.join(words[1:])} is not supported", number)
            fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
        else:
            raise PlyFileError(path, f"unexpected header line {line!r}", number)
    if count is None or not fields:
        raise PlyFileError(path, "the header declares no vertex element")
    dtype = np.dtype(fields)
    body = data[end + len(b"end_header\n") :]
    if len(body) < count * dtype.itemsize:
        raise PlyFileError(path, f"truncated: {count} vertices need {count * dtype.itemsize} bytes")
    return np.frombuffer(body, dtype=dtype, count=count).copy()


def write_map_pcd(
    path: str | Path,
    points: ArrayLike,
    *,
    voxel: float | None = None,
) -> None:
    """Write (N, 3) map points as a binary PCD (fields x y z, float32, one row: an unorganized cloud).

    `voxel` (m): keep one point per voxel of this size first (None: the points as given, which the
    replay has already thinned to its map voxel). The PCD viewpoint is the identity: the points are in
    the map frame. Writes `path` directly; raises `OutputError` when it cannot be written, ValueError
    on arrays of the wrong shape."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    if voxel is not None:
        if not voxel > 0.0:
            raise ValueError(f"voxel must be positive, got {voxel}")
        cells = np.floor(points / voxel).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        points = points[np.sort(first)]
    cloud = PointCloud.from_xyz_points(points)
    try:
        with Path(path).open("wb") as stream:
            cloud.save(stream)
    except OSError as error:
        raise OutputError(f"{path}: cannot write the file: {error.strerror or error}") from error
