"""The prediction of a scan's motion without wheel odometry, for the SLAM (`LaserSlam2D`) and the localizer
(`MapLocalizer`) alike: the last motion carried at its velocity, and how far to search around it.

Found on ACES replayed without its odometry (relations error 1.78 ± 9.49 m, half the building mapped
rotated against the other half): its scan intervals run from 0.08 to 0.37 s, its motions in proportion,
and a 3 s gap in which the robot turned 83° in place was searched ±35° around one interval's motion, so
the scan matched 80° off. With both rules, 0.040 ± 0.040 m (0.036 with odometry).
"""

from __future__ import annotations

import math

import numpy as np

from frontends.slam2d.config import OdometryConfig
from frontends.slam2d.deskew import along_motion

FloatArray = np.ndarray

GAP_SPEED = 2.0
GAP_TURN_RATE = math.radians(120.0)
"""The search window without odometry, and the prediction's σ, cover this speed (m/s) and turn rate (rad/s)
over the time since the last scan, when that is more than the configured window (0.5 m and 35° cover them
over 0.25–0.3 s)."""
GAP_WIDENING = 2.0
"""A window widened this many times or more is a gap's: the prediction says little, and the wide window is
searched at once, not a narrow one around the prediction first."""
MAX_VELOCITY_EXTRAPOLATION = 3.0
"""The last motion is carried at its velocity for at most this many times the time it took: over a gap the
velocity says little, and the widened window does the work."""


def carried_motion(last_motion: FloatArray, span_ns: int, elapsed_ns: int) -> FloatArray:
    """`last_motion`, made over `span_ns`, carried at its velocity over `elapsed_ns` (at most
    `MAX_VELOCITY_EXTRAPOLATION` times its span); unchanged when its span is unknown (0)."""
    if span_ns <= 0:
        return last_motion
    fraction = min(elapsed_ns / span_ns, MAX_VELOCITY_EXTRAPOLATION)
    return along_motion(last_motion, np.array([fraction]))[0]


MAX_GAP_REACH = 10.0
"""However long the gap, the search reaches at most this far (m) from the prediction. The local map a scan
is matched on holds the last 25 keyframes, 0.3 m apart or more: farther, nothing in it is the place the
robot is in, and a wider search can only find a look-alike. Unbounded, the fr-clinic log without
odometry (1.4 Hz, gaps of up to 198 s: ±396 m at 2 m/s) asked the branch and bound for more memory than
the machine has; at 10 m a search costs ~1.7 s and ~120 MB once (ACES's longest gap, 3 s, needs 6 m)."""


def gap_widening(settings: OdometryConfig, elapsed_ns: int) -> tuple[float, float]:
    """How many times the configured window without odometry (linear, angular) a motion over `elapsed_ns`
    may span at `GAP_SPEED` and `GAP_TURN_RATE` (at least 1; the reach at most `MAX_GAP_REACH` and the
    angle at most π)."""
    elapsed = max(elapsed_ns, 0) * 1e-9
    configured = settings.window_linear_without_odometry
    linear = max(min(GAP_SPEED * elapsed, MAX_GAP_REACH), configured)
    angular = min(max(GAP_TURN_RATE * elapsed, settings.window_angular_without_odometry), math.pi)
    return linear / configured, angular / settings.window_angular_without_odometry


def after_gap(widening: tuple[float, float], elapsed_ns: int, typical_interval_ns: float) -> bool:
    """Whether a scan `elapsed_ns` after the last one comes after a gap, its wide window searched at once:
    its window widened `GAP_WIDENING` times or more (`gap_widening`), and `elapsed_ns` at least
    `GAP_WIDENING` of the laser's typical intervals (when known, else 0). A laser scanning at 1.4 Hz
    (fr-clinic) widens every window, and its next scan is no gap: the prediction is as good as a faster
    laser's, and the wide window searched at once took look-alikes (87 → 27 m median without odometry)."""
    return max(widening) >= GAP_WIDENING and elapsed_ns >= GAP_WIDENING * typical_interval_ns
