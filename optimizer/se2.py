"""SE(2) algebra on arrays of poses (x, y, θ), vectorized over a leading axis.

A pose p = (x, y, θ) is the transform [[R(θ), t], [0, 1]]. `relative(a, b)` is a⁻¹·b, the pose of b
seen from a, which is what a constraint measures.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def wrap_scalar(theta: float) -> float:  # pragma: no cover  (compiled)
    """(θ + π) mod 2π − π with Python's float modulo, to the bit, for compiled kernels (inlined).

    Python's modulo is fmod and a sign fix, and compiled code calls the C library's fmod for it (a
    noticeable part of an SGD pass). For the shifted angles that occur, fmod's exact result is known
    without it: x itself in [0, 2π), and x − 2π in [2π, 4π), a subtraction that is exact (Sterbenz's
    lemma); below 0, Python's x + 2π. Anything else (far angles, inf, NaN) takes the modulo itself."""
    shifted = theta + math.pi
    if 0.0 <= shifted < TWO_PI:
        return shifted - math.pi
    if -TWO_PI < shifted < 0.0:
        return (shifted + TWO_PI) - math.pi
    if TWO_PI <= shifted < 2.0 * TWO_PI:
        return (shifted - TWO_PI) - math.pi
    return shifted % TWO_PI - math.pi


def wrap_angle(theta: ArrayLike) -> Any:
    """Wrap angles to [-π, π): the project's one definition, (θ + π) mod 2π − π, with numpy's modulo (the
    sign rule of Python's, to the bit). Scalars and arrays of any shape; compiled kernels call
    `wrap_scalar`, the same bits.

    Not a numba ufunc: numba compiled a ufunc's loop at every import of this module, cache or not."""
    return np.remainder(np.add(theta, math.pi, dtype=np.float64), TWO_PI) - math.pi


def _one_pose_each(a: FloatArray, b: FloatArray) -> bool:
    """Whether `a` and `b` are single poses, float64 arrays of shape (3,): the frontends' per-scan calls,
    which the arithmetic on Python floats below serves in a fifth of the array code's time."""
    return (type(a) is np.ndarray and type(b) is np.ndarray and a.shape == (3,) == b.shape
            and a.dtype == np.float64 == b.dtype)


def _wrapped(theta: float) -> float:
    """`wrap_angle` of one Python float, to the bit: its definition with Python's float modulo."""
    return (theta + math.pi) % TWO_PI - math.pi


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """a·b for arrays of poses of shape (..., 3); θ of the result is wrapped."""
    if _one_pose_each(a, b):
        ax, ay, at = a.tolist()
        bx, by, bt = b.tolist()
        # numpy's cosine, not math's: numpy's array code may use its own (SIMD) one, and the two paths
        # must give the same bits.
        c, s = float(np.cos(at)), float(np.sin(at))
        return np.array([ax + c * bx - s * by, ay + s * bx + c * by, _wrapped(at + bt)])
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cosines, sines = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = a[..., 0] + cosines * b[..., 0] - sines * b[..., 1]
    out[..., 1] = a[..., 1] + sines * b[..., 0] + cosines * b[..., 1]
    out[..., 2] = wrap_angle(a[..., 2] + b[..., 2])
    return out


def inverse(a: FloatArray) -> FloatArray:
    """a⁻¹ for an array of poses of shape (..., 3)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty_like(a)
    out[..., 0] = -(c * a[..., 0] + s * a[..., 1])
    out[..., 1] = -(-s * a[..., 0] + c * a[..., 1])
    out[..., 2] = wrap_angle(-a[..., 2])
    return out


def relative(a: FloatArray, b: FloatArray) -> FloatArray:
    """a⁻¹·b: the pose of b in the frame of a."""
    if _one_pose_each(a, b):
        ax, ay, at = a.tolist()
        bx, by, bt = b.tolist()
        c, s = float(np.cos(at)), float(np.sin(at))
        dx, dy = bx - ax, by - ay
        return np.array([c * dx + s * dy, -s * dx + c * dy, _wrapped(bt - at)])
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cosines, sines = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = cosines * dx + sines * dy
    out[..., 1] = -sines * dx + cosines * dy
    out[..., 2] = wrap_angle(b[..., 2] - a[..., 2])
    return out


def adjoint(a: FloatArray) -> FloatArray:
    """Adjoint matrices (..., 3, 3) of poses: Ad(a)·ξ expresses a local-frame twist ξ in a's parent frame."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.zeros((*a.shape[:-1], 3, 3), dtype=np.float64)
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 0, 2] = a[..., 1]
    out[..., 1, 2] = -a[..., 0]
    out[..., 2, 2] = 1.0
    return out


def compose_chain(steps: FloatArray, start: FloatArray | None = None) -> FloatArray:
    """Poses reached by composing relative steps one after another from `start` (default: the origin).

    Returns len(steps) + 1 poses, the first being `start`. Sequential by nature (each step turns the next).
    """
    steps = np.asarray(steps, dtype=np.float64).reshape(-1, 3)
    theta = np.empty(len(steps) + 1)
    theta[0] = 0.0 if start is None else float(start[2])
    theta[1:] = theta[0] + np.cumsum(steps[:, 2])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    dx = c * steps[:, 0] - s * steps[:, 1]
    dy = s * steps[:, 0] + c * steps[:, 1]
    poses = np.empty((len(steps) + 1, 3))
    x0, y0 = (0.0, 0.0) if start is None else (float(start[0]), float(start[1]))
    poses[0] = (x0, y0, theta[0])
    poses[1:, 0] = x0 + np.cumsum(dx)
    poses[1:, 1] = y0 + np.cumsum(dy)
    poses[:, 2] = wrap_angle(theta)
    return poses


def rigid_fit(source: FloatArray, target: FloatArray) -> FloatArray:
    """The pose T minimising Σ |T·p_i − q_i|² over the positions p_i of `source` and q_i of `target`
    ((N, 2+) each, headings ignored): the least-squares rigid alignment (Umeyama's, without scale)."""
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    mean_s, mean_t = source[:, :2].mean(axis=0), target[:, :2].mean(axis=0)
    a, b = source[:, :2] - mean_s, target[:, :2] - mean_t
    angle = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]),
                       np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    c, s = np.cos(angle), np.sin(angle)
    shift = mean_t - np.array([c * mean_s[0] - s * mean_s[1], s * mean_s[0] + c * mean_s[1]])
    return np.array([shift[0], shift[1], angle])
