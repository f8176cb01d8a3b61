"""The ground-vehicle projection: the one place where the 3D keyframe graph meets the planar backend.

The frontend keeps everything in 3D: keyframe poses as 4×4 matrices, constraints as relative 4×4
transforms with 6×6 information in (tx, ty, tz, rx, ry, rz) order. The backend (the paper's SGD) is SE(2).
For a ground vehicle the motion that drifts and that loop closures correct is in the plane (x, y, yaw);
height, roll and pitch are observed well by LiDAR odometry locally (the ground is always in view) and are
kept from it. So:

- `project_graph` turns the 3D graph into an SE(2) `PoseGraph` (x, y, yaw; heading = the ZYX yaw);
- `lift` puts optimized planar poses back into 3D, with each keyframe's height, roll and pitch from the
  pose it was projected from.

A full SE(3) backend would consume the 3D graph directly and replace these two functions; the frontend
does not change. The assumption breaks for a sensor whose frame is not roughly level (a hand-held or
steeply tilted unit: put its mount in tf so that poses are those of a level base) and for large changes
in height over a loop (ramps, multi-storey car parks), where a planar loop closure cannot fix z drift.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.slam3d import se3
from optimizer.graph import PoseGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

PLANAR_AXES = (0, 1, 5)
"""x, y and yaw in the (tx, ty, tz, rx, ry, rz) order of the 6×6 information."""


def yaw(transforms: ArrayLike) -> FloatArray:
    """Heading about z of every (..., 4, 4) transform: the ZYX yaw."""
    transforms = np.asarray(transforms, dtype=np.float64)
    return np.arctan2(transforms[..., 1, 0], transforms[..., 0, 0])


def planar(transforms: ArrayLike) -> FloatArray:
    """(..., 3) planar poses (x, y, yaw) of (..., 4, 4) transforms."""
    transforms = np.asarray(transforms, dtype=np.float64)
    return np.stack([transforms[..., 0, 3], transforms[..., 1, 3], yaw(transforms)], axis=-1)


def _rotation_z(theta: FloatArray) -> FloatArray:
    c, s = np.cos(theta), np.sin(theta)
    out = np.zeros((*np.shape(theta), 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = 1.0
    return out


def level(transforms: ArrayLike) -> FloatArray:
    """The same transforms with roll and pitch removed: rotation about z by the yaw, same translation."""
    transforms = np.asarray(transforms, dtype=np.float64)
    return se3.from_rotation_translation(_rotation_z(yaw(transforms)), transforms[..., :3, 3])


def lift(planar_poses: ArrayLike, reference: ArrayLike) -> FloatArray:
    """(K, 4, 4) poses with x, y, yaw from `planar_poses` (K, 3) and height, roll, pitch from `reference`
    (K, 4, 4): R = Rz(yaw) · Rz(−yaw_ref) · R_ref, t = (x, y, z_ref). `lift(planar(T), T) == T`."""
    planar_poses = np.asarray(planar_poses, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    tilt = _rotation_z(-yaw(reference)) @ reference[..., :3, :3]
    translation = np.concatenate([planar_poses[..., :2], reference[..., 2:3, 3]], axis=-1)
    return se3.from_rotation_translation(_rotation_z(planar_poses[..., 2]) @ tilt, translation)


def project_constraints(
    poses_from: ArrayLike, relative: ArrayLike, information: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Planar measurements (M, 3) and information (M, 3, 3) of 3D constraints.

    A constraint a → b measures `relative` = T_a⁻¹ T_b. Its planar measurement is the planar pose of
    T_b = T_a · relative seen from the level frame of a (a's yaw and position, no roll or pitch), so that
    a tilted a (a car on a slope) does not fold its pitch into x. For odometry this is exactly
    `se2.relative(planar(T_a), planar(T_b))`. The information is the 6×6 one marginalised onto (x, y, yaw).
    """
    poses_from = np.asarray(poses_from, dtype=np.float64)
    seen_from_level = se3.inverse(level(poses_from)) @ poses_from @ np.asarray(relative, dtype=np.float64)
    covariance = np.linalg.inv(np.asarray(information, dtype=np.float64))
    marginal = covariance[..., PLANAR_AXES, :][..., :, PLANAR_AXES]
    planar_information = cast(FloatArray, np.linalg.inv(marginal))
    return planar(seen_from_level), 0.5 * (planar_information + np.swapaxes(planar_information, -1, -2))


def project_graph(
    poses: ArrayLike,
    edge_from: ArrayLike,
    edge_to: ArrayLike,
    relative: ArrayLike,
    information: ArrayLike,
    planar_poses: ArrayLike | None = None,
) -> PoseGraph:
    """The SE(2) pose graph of a 3D keyframe graph: keyframe poses (K, 4, 4), constraints `edge_from` →
    `edge_to` (M,) measuring `relative` (M, 4, 4) with `information` (M, 6, 6). The planar poses are those
    of `poses` unless `planar_poses` (K, 3) is given (another estimate of the same keyframes)."""
    poses = np.asarray(poses, dtype=np.float64)
    edge_from = np.asarray(edge_from, dtype=np.int64)
    measurements, planar_information = project_constraints(poses[edge_from], relative, information)
    return PoseGraph.build(
        np.arange(len(poses)),
        planar(poses) if planar_poses is None else np.asarray(planar_poses, dtype=np.float64),
        edge_from,
        np.asarray(edge_to, dtype=np.int64),
        measurements.reshape(-1, 3),
        planar_information.reshape(-1, 3, 3),
    )
