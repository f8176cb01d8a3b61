"""Wheel odometry that stops updating while the robot moves, then jumps by the whole motion at once.

CSAIL's log does it three times: one value for 4 scans of a turn in place, then +1.49 rad. The scans track
the motion meanwhile, and the jump holds that motion again: predicted from the last pose, the scan would be
sought a whole turn off, and a match there lands on the wrong wall. The SLAM and the localizer both predict
through `OdometryHold`. Wheels may also hold only their position, their heading still turning, or misreport
the motion; the localizer's saved map then overrules them, and `OverruledOdometry` takes what they missed off
the jump that pays it back.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from optimizer import se2

FloatArray = NDArray[np.float64]


class OdometryHold:
    """The motion the scans tracked while the odometry repeated its value."""

    def __init__(self) -> None:
        self._tracked: FloatArray | None = None

    @property
    def holding(self) -> bool:
        """The odometry repeated its value at the last scan: its motion says nothing of the robot's."""
        return self._tracked is not None

    def reset(self) -> None:
        self._tracked = None

    def corrected(self, motion: FloatArray, last_odometry: FloatArray | None, odometry: FloatArray | None,
                  last_motion: FloatArray, window_linear: float, window_angular: float) -> FloatArray:
        """The odometry's `motion` since the last scan, without what the scans already tracked during a hold
        it ends. Call once per scan, before its match; `last_motion` is the motion the last match gave.

        Only a held motion beyond the search window (`window_linear` m, `window_angular` rad) is taken
        off: within it the match finds the pose either way, and a robot standing still (its odometry
        repeating for good reason) changes nothing."""
        if odometry is None or last_odometry is None:
            self._tracked = None
            return motion
        if np.array_equal(odometry, last_odometry):
            self._tracked = np.zeros(3) if self._tracked is None else se2.compose(self._tracked, last_motion)
            return motion
        if self._tracked is None:
            return motion
        held = se2.compose(self._tracked, last_motion)
        self._tracked = None
        if np.hypot(held[0], held[1]) > window_linear or abs(held[2]) > window_angular:
            return se2.relative(held, motion)
        return motion


class OverruledOdometry:
    """The motion the map matched beyond the wheels' while it overruled them (`MapLocalizer`): wheels that
    stop counting and then report the whole motion at once owe it, and their jump pays it back. (CSAIL's
    odometry holds its position for two scans while the robot drives 0.4 m, its heading still turning, then
    jumps 0.83 m: predicted from the matched pose, the scan was sought 0.6 m ahead.)"""

    def __init__(self) -> None:
        self._owed: FloatArray | None = None

    def reset(self) -> None:
        self._owed = None

    def note(self, overruled: bool, odometry_motion: FloatArray, matched_motion: FloatArray) -> None:
        """After a scan: whether the map overruled the wheels, their motion and the matched one."""
        if not overruled:
            self._owed = None
            return
        step = se2.relative(odometry_motion, matched_motion)
        self._owed = step if self._owed is None else se2.compose(self._owed, step)

    def corrected(self, motion: FloatArray, last_motion: FloatArray, window_linear: float) -> FloatArray:
        """The wheels' `motion` since the last scan, without the motion they owe when it is a jump: longer
        than the last matched motion (`last_motion`) by more than the search window reaches
        (`window_linear`, m), the owed motion longer than the window too, and paying it shortens the
        motion. (A turn is no jump: wheels that hold their position still report their heading; a fast
        vehicle's steps are long, not jumps.)"""
        owed = self._owed
        length = float(np.hypot(motion[0], motion[1]))
        if owed is None or length - float(np.hypot(last_motion[0], last_motion[1])) <= window_linear \
                or np.hypot(owed[0], owed[1]) <= window_linear:
            return motion
        paid = se2.relative(owed, motion)
        if np.hypot(paid[0], paid[1]) >= length:
            return motion
        self._owed = None
        return paid
