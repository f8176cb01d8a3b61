"""Odometry from the scans themselves, for a localizer on a log without wheel odometry.

A localizer without odometry predicts each scan by constant velocity and searches the saved map in the
wide window that prediction needs; in a building of look-alike rooms the scan then fits a wrong place as
well as the true one, and the pose hops there a few decimetres a scan (the Intel Research Lab's second
half, localized without odometry in its first half's map: 2.2 m off at a score of 0.88, 13 m off by a
slide of 50 scans). The scans' own odometry, the SLAM's matching on its recent keyframes with no loop
closures, measures the motion from what the robot just saw, independently of the saved map; the
localizer then treats it as wheel odometry: a narrow window around it, the map's match weighed against it.
Its weakness is a corridor's plain walls, where the tracking's position along the corridor is its own
constant-velocity guess and wanders (ACES: 1 m backwards in 4 scans); taking constant velocity there
instead (on `ScorePlateau.is_slide` matches) was tried and lost more than it gained (benchmarks/README.md).
"""

from __future__ import annotations

import numpy as np

from frontends.protocol import FloatArray
from frontends.slam2d.config import Slam2DConfig
from frontends.slam2d.slam import LaserSlam2D
from optimizer import se2

MAX_SCANS = 20_000
"""The tracking also restarts after this many scans (a robot standing still makes no keyframes, and the
tracking keeps every scan's offset from its keyframe: a few hundred bytes each)."""


class ScanOdometry:
    """Feed every scan with `pose`; it returns the scan's pose in a frame of its own (only the motion
    between scans means anything, as for wheel odometry). Memory stays bounded: the tracking restarts
    after `max_keyframes` keyframes or `max_scans` scans, the restart's scan placed by both trackings so
    that the frame goes on."""

    def __init__(self, config: Slam2DConfig, max_keyframes: int, max_scans: int = MAX_SCANS) -> None:
        self._config = config.without_loop_closures()
        self._max_keyframes = max_keyframes
        self._max_scans = max_scans
        self._tracking = LaserSlam2D(self._config)
        self._frame = np.zeros(3)
        """The current tracking's origin in the odometry's frame."""

    def pose(self, stamp_ns: int, points: FloatArray, point_times: FloatArray | None) -> FloatArray:
        estimate = self._tracking.add_scan(stamp_ns, points, None, 0.0, point_times)
        pose = se2.compose(self._frame, estimate.pose)
        full = estimate.keyframe + 1 >= self._max_keyframes or estimate.index + 1 >= self._max_scans
        if full and not estimate.between:
            # The next tracking starts at this scan, where this one placed it.
            self._tracking = LaserSlam2D(self._config)
            self._tracking.add_scan(stamp_ns, points, None, 0.0, point_times)
            self._frame = pose
        return pose
