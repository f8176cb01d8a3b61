"""Rigid transforms as (..., 4, 4) homogeneous float64 matrices, and the few SE(3) operations the 3D
frontend needs. Tangent vectors are (tx, ty, tz, rx, ry, rz), translation first like Sophus (KISS-ICP)
and g2o's SE3 information order."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

SMALL_ANGLE = 1e-9
"""Below this rotation angle (rad) the exponential and logarithm take their first-order forms."""


def inverse(transforms: ArrayLike) -> FloatArray:
    """Inverse of every (..., 4, 4) rigid transform, exact (transposed rotation)."""
    transforms = np.asarray(transforms, dtype=np.float64)
    rotation_t = np.swapaxes(transforms[..., :3, :3], -1, -2)
    out = np.zeros_like(transforms)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, transforms[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def relative(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """a⁻¹ b: the pose of b in the frame of a."""
    return inverse(a) @ np.asarray(b, dtype=np.float64)


def transform_points(transform: FloatArray, points: ArrayLike) -> FloatArray:
    """(N, 3) points mapped by one 4×4 transform."""
    points = np.asarray(points, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def rotation_angle(transforms: ArrayLike) -> FloatArray:
    """Angle of the rotation of every (..., 4, 4) transform (rad, in [0, π])."""
    transforms = np.asarray(transforms, dtype=np.float64)
    trace = np.trace(transforms[..., :3, :3], axis1=-2, axis2=-1)
    return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _so3_exp(omega: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation matrix of `omega` and the left Jacobian V (translation part of the SE(3) exponential)."""
    theta = float(np.linalg.norm(omega))
    skew = _skew(omega)
    if theta < SMALL_ANGLE:
        return np.eye(3) + skew, np.eye(3) + 0.5 * skew
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta**2
    c = (1.0 - a) / theta**2
    skew2 = skew @ skew
    return np.eye(3) + a * skew + b * skew2, np.eye(3) + b * skew + c * skew2


def exp(tangent: ArrayLike) -> FloatArray:
    """The SE(3) exponential of (tx, ty, tz, rx, ry, rz)."""
    tangent = np.asarray(tangent, dtype=np.float64)
    rotation, v = _so3_exp(tangent[3:])
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = v @ tangent[:3]
    return out


def log(transform: ArrayLike) -> FloatArray:
    """The SE(3) logarithm (tx, ty, tz, rx, ry, rz) of one 4×4 transform (rotation below π)."""
    transform = np.asarray(transform, dtype=np.float64)
    rotation = transform[:3, :3]
    theta = float(rotation_angle(transform))
    axis_sin = np.array(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )
    omega = 0.5 * axis_sin if theta < SMALL_ANGLE else theta / (2.0 * np.sin(theta)) * axis_sin
    _, v = _so3_exp(omega)
    return np.concatenate([np.linalg.solve(v, transform[:3, 3]), omega])


def from_rotation_translation(rotation: ArrayLike, translation: ArrayLike) -> FloatArray:
    """(..., 4, 4) transforms from (..., 3, 3) rotations and (..., 3) translations."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    out = np.zeros((*rotation.shape[:-2], 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out
