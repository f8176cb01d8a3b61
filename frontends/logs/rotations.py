"""Vectorized unit-quaternion helpers on (..., 4) arrays in (x, y, z, w) order (as in ROS and Foxglove)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def normalize(q: ArrayLike) -> FloatArray:
    """Unit quaternions; an all-zero quaternion (an unset message field) becomes the identity."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    identity = np.zeros_like(q)
    identity[..., 3] = 1.0
    return np.where(norm > 0.0, q / np.where(norm > 0.0, norm, 1.0), identity)


def multiply(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Hamilton product a·b (the rotation b first, then a)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        (
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ),
        axis=-1,
    )


def conjugate(q: ArrayLike) -> FloatArray:
    """The inverse rotation of a unit quaternion."""
    q = np.array(q, dtype=np.float64)
    q[..., :3] *= -1.0
    return q


def to_matrix(q: ArrayLike) -> FloatArray:
    """(..., 3, 3) rotation matrices of unit quaternions."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        (
            np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)), axis=-1),
            np.stack((2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)), axis=-1),
            np.stack((2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)), axis=-1),
        ),
        axis=-2,
    )


def rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Rotate vectors (..., 3) by unit quaternions (..., 4) (broadcasting)."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u = q[..., :3]
    w = q[..., 3:4]
    # v' = v + 2w(u×v) + 2u×(u×v): cheaper than building matrices for a handful of vectors.
    uv = np.cross(u, v)
    return v + 2.0 * (w * uv + np.cross(u, uv))


def yaw(q: ArrayLike) -> FloatArray | float:
    """Heading (rotation about z) of unit quaternions, in (-π, π]."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    result = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return float(result) if np.ndim(result) == 0 else result


def from_yaw(theta: ArrayLike) -> FloatArray:
    """Unit quaternions of rotations by `theta` about z."""
    half = 0.5 * np.asarray(theta, dtype=np.float64)
    zeros = np.zeros_like(half)
    return np.stack((zeros, zeros, np.sin(half), np.cos(half)), axis=-1)


def slerp(a: ArrayLike, b: ArrayLike, fraction: ArrayLike) -> FloatArray:
    """Spherical interpolation from a (fraction 0) to b (fraction 1) along the shorter arc."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.asarray(fraction, dtype=np.float64)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0.0, -b, b)  # q and -q are the same rotation: take the short way round
    # The angle between a and b from atan2 of chord lengths: accurate for small angles, where arccos of
    # the dot product loses half the digits.
    angle = 2.0 * np.arctan2(
        np.linalg.norm(a - b, axis=-1, keepdims=True), np.linalg.norm(a + b, axis=-1, keepdims=True)
    )
    tiny = angle < 1e-9  # lerp is exact to rounding there, and sin(angle) would divide by ~0
    sin_angle = np.where(tiny, 1.0, np.sin(angle))
    wa = np.where(tiny, 1.0 - t, np.sin((1.0 - t) * angle) / sin_angle)
    wb = np.where(tiny, t, np.sin(t * angle) / sin_angle)
    return normalize(wa * a + wb * b)
