"""Motion compensation of a planar laser scan: each beam moved to where the robot was at the scan's stamp.

A laser takes its beams one after the other: a 10 Hz laser spends up to 0.1 s on a scan, and a robot
turning at 1 rad/s meanwhile turns by up to 6°, which bends straight walls and, on a 360° laser, puts the
last beams beside the first ones a few centimetres off. Under constant velocity across the scan (the
motion predicted since the previous scan, spread evenly over that time) the beam taken t seconds after the
stamp is moved by exp(t·ξ), ξ the robot's velocity twist in its own frame.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numba import njit
from numpy.typing import NDArray

from optimizer import se2

FloatArray = NDArray[np.float64]

MAX_DESKEW_INTERVAL = 1.0
"""A scan more than this many seconds after the previous one is not deskewed: the motion averaged over a
gap in the log says little about the motion during the scan's sweep."""
VELOCITY_MOTIONS = 2
"""Without wheel odometry the velocity is the mean of this many matched motions, the last ones. The last one
alone feeds each match's error back into the next scan's deskewing, which bends that scan the other way:
on simulated lidar-only drives the poses then swung from scan to scan until the track was lost. Over two
the feedback dies out; over more, the velocity lags further behind the robot's, which costs more at turns
than it gains. The SLAM deskews a scan twice (`LaserSlam2D.add_scan`): under the last two motions before
it, then, matched, under the last one and its own, one scan period less late
(`benchmarks/deskew2d_bench.py`)."""


class ScanDeskewer:
    """Deskews the scans of one run in time order: under the wheel odometry's motion since the previous
    scan when there is one, else under the velocity of the last matched motions (`VELOCITY_MOTIONS`), the
    scan's own among them once it is matched.

    It keeps motions, not poses: a loop closure or an optimization moves the poses of the recent scans,
    not the motions between them."""

    def __init__(self) -> None:
        self._recent: deque[tuple[float, FloatArray]] = deque(maxlen=VELOCITY_MOTIONS)
        """(seconds, matched motion from the previous scan) of the last scans, oldest first."""
        self._last_stamp: int | None = None

    def deskewed(self, points: FloatArray, times: FloatArray | None, stamp_ns: int,
                 odometry_motion: FloatArray | None, own_motion: FloatArray | None = None) -> FloatArray:
        """`points` (N, 2) taken at `times` (N,) (s after `stamp_ns`) in the robot frame at the stamp, under
        `odometry_motion`, the wheel odometry's motion since the previous scan (None: no odometry), else
        under the recent matched motions, and `own_motion` when given: the scan's own, matched from the
        previous scan. As given without times, for a first scan, or after a gap (`MAX_DESKEW_INTERVAL`)."""
        if times is None or self._last_stamp is None:
            return points
        elapsed = (stamp_ns - self._last_stamp) * 1e-9
        if not 0.0 < elapsed <= MAX_DESKEW_INTERVAL:
            return points
        if odometry_motion is not None:
            return deskewed(points, times, velocity(odometry_motion, elapsed))
        recent = list(self._recent)
        if own_motion is not None:
            recent = [*recent[max(0, len(recent) - VELOCITY_MOTIONS + 1):],
                      (elapsed, np.asarray(own_motion, dtype=np.float64))]
        if not recent:
            return points
        motion = se2.compose_chain(np.array([step for _, step in recent]))[-1]
        return deskewed(points, times, velocity(motion, sum(seconds for seconds, _ in recent)))

    def moved(self, stamp_ns: int, motion: FloatArray | None) -> None:
        """The scan at `stamp_ns` was matched `motion` (x, y, θ) from the previous one (None: the first
        scan, or the first after the track was lost)."""
        elapsed = math.inf if self._last_stamp is None else (stamp_ns - self._last_stamp) * 1e-9
        if motion is None or not 0.0 < elapsed <= MAX_DESKEW_INTERVAL:
            self._recent.clear()  # after a gap the velocity before it is not the velocity now
        else:
            self._recent.append((elapsed, np.array(motion, dtype=np.float64)))
        self._last_stamp = int(stamp_ns)


def velocity(motion: FloatArray, elapsed: float) -> FloatArray:
    """The constant twist (vx, vy, ω) per second, in the robot's frame, that moves it by `motion` (x, y, θ)
    in `elapsed` seconds: the SE(2) logarithm of the motion, divided by the time."""
    x, y, theta = (float(value) for value in motion)
    along, across = _arc_factors(theta)
    scale = along * along + across * across  # V(θ) = [[along, −across], [across, along]], inverted below
    vx = (along * x + across * y) / scale
    vy = (-across * x + along * y) / scale
    return np.array([vx / elapsed, vy / elapsed, theta / elapsed])


def deskewed(points: FloatArray, times: FloatArray, twist: FloatArray) -> FloatArray:
    """`points` (N, 2) in the robot frame at their own `times` (N,) (s after the stamp) → in the robot frame
    at the stamp: exp(t·`twist`) applied to each."""
    return _deskewed(np.ascontiguousarray(points, dtype=np.float64), np.asarray(times, dtype=np.float64),
                     float(twist[0]), float(twist[1]), float(twist[2]))


def along_motion(motion: FloatArray, fractions: FloatArray) -> FloatArray:
    """(F, 3) the poses a fraction of the way through `motion` (x, y, θ) at constant velocity: exp(f·log
    `motion`) for each of `fractions` (0: none of it, 1: all of it)."""
    vx, vy, turn = velocity(motion, 1.0)
    return _exp(np.asarray(fractions, dtype=np.float64), float(vx), float(vy), float(turn))


def interpolated(start: FloatArray, end: FloatArray, fractions: FloatArray) -> FloatArray:
    """(F, 3) poses between `start` and `end` (x, y, θ in one frame), each a fraction of the way along the
    constant-velocity arc from one to the other."""
    return se2.compose(start, along_motion(se2.relative(start, end), fractions))


# Compiled: the SLAM calls these for every scan, on one pose or one scan's beams, where numpy's per-call
# overhead was most of their cost (a simulated 40 Hz laser without odometry: 0.1 s of a 1.2 s replay).
@njit(cache=True, nogil=True)
def _arc_factors(theta: float) -> tuple[float, float]:
    """(sin θ / θ, (1 − cos θ) / θ) of the SE(2) exponential's V(θ), exact at and near θ = 0."""
    if theta == 0.0:
        return 1.0, 0.0
    half = 0.5 * theta
    sine_half = math.sin(half)
    return math.sin(theta) / theta, sine_half * (sine_half / half)


@njit(cache=True, nogil=True)
def _exp(times: FloatArray, vx: float, vy: float, turn_rate: float) -> FloatArray:
    """(N, 3) x, y, θ of exp(t·(vx, vy, ω)) for each of `times`."""
    poses = np.empty((times.shape[0], 3))
    for k in range(times.shape[0]):
        t = times[k]
        turn = t * turn_rate
        along, across = _arc_factors(turn)
        poses[k, 0] = t * (along * vx - across * vy)
        poses[k, 1] = t * (across * vx + along * vy)
        poses[k, 2] = turn
    return poses


@njit(cache=True, nogil=True)
def _deskewed(points: FloatArray, times: FloatArray, vx: float, vy: float, turn_rate: float) -> FloatArray:
    moved = np.empty_like(points)
    for k in range(points.shape[0]):
        t = times[k]
        turn = t * turn_rate
        along, across = _arc_factors(turn)
        tx = t * (along * vx - across * vy)
        ty = t * (across * vx + along * vy)
        cos, sin = math.cos(turn), math.sin(turn)
        x, y = points[k, 0], points[k, 1]
        moved[k, 0] = cos * x - sin * y + tx
        moved[k, 1] = sin * x + cos * y + ty
    return moved
