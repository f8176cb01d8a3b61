"""Which scans of a fast laser the SLAM matches.

A laser scanning 40 times a second moves the robot 2.5 cm between scans at 1 m/s; matching every scan
costs four times the work of matching every fourth, and on simulated 40 Hz drives with ground truth the
maps and trajectories came out as accurate matched at 10 or 5 Hz as at 40 (`benchmarks/fast_laser_bench.py`).
So a scan is matched once `min_match_interval` has passed since the last matched one; the scans between
are posed from the two matched scans around them (`LaserSlam2D`). The stride is counted in scans, from the
laser's typical interval, so that the stamps' jitter does not make a steady laser's matched scans come at
a wavering rate: every n-th scan, n = ⌊`min_match_interval` / interval + ¼⌋ (40 Hz and 0.1 s: every 4th;
25 Hz: every 2nd; 15 Hz or slower: every scan). The typical interval is the mean of the recent ones (their
span over their count), not their median: a logger that stamps scans in bursts (the Intel Research Lab
log: a 5 Hz laser, half its intervals under 0.1 s, many of 1 ms) has a median interval far below its
rate, and its scans were skipped as if it were fast.
"""

from __future__ import annotations

import math
from collections import deque

RECENT_INTERVALS = 15
"""The typical interval between scans is the mean of this many recent ones."""
SHORT_INTERVAL_SHARE = 0.25
"""An interval shorter than this share of the typical one is not the time the laser took for a scan (no laser
speeds up fourfold): the logger stamped the scans as they reached it, in bursts, not as they were taken."""
UNPACED_SHARE = 0.1
"""Once this share of the intervals seen (after the first `RECENT_INTERVALS`) is short, the stamps are taken
as not pacing the scans. The Intel Research Lab log: 40 % of its intervals are under a quarter of its mean
(many of 1 ms), and the robot moves 5 cm per scan whatever the interval, 1 ms or 1 s; ACES (0.08–0.37 s,
its motions in proportion) has none, a steady laser none."""
PACE_GAP = 5.0
"""Where the stamps do not pace the scans, an interval of this many typical ones or more is still a gap (the
logger stopped): the time since the last scan counts."""
STRIDE_ROUNDING = 0.25
"""A stride of n scans is taken once n − ¼ intervals fit in the matching interval: a 15 Hz laser (1.5
intervals in 0.1 s) has every scan matched, not every other one, and an 18 Hz laser every other one."""


class ScanRate:
    """The laser's typical interval between scans: the mean of the recent intervals (their span over their
    count; a stamp not after the last one is not counted)."""

    def __init__(self) -> None:
        self._recent: deque[int] = deque(maxlen=RECENT_INTERVALS + 1)
        self._counted = 0
        self._short = 0

    def add(self, stamp_ns: int) -> None:
        if self._recent and stamp_ns <= self._recent[-1]:
            return
        if self.known:
            self._counted += 1
            self._short += stamp_ns - self._recent[-1] < SHORT_INTERVAL_SHARE * self.typical_ns
        self._recent.append(stamp_ns)

    @property
    def paced(self) -> bool:
        """Whether the stamps tell the time between scans: not so once `UNPACED_SHARE` of the intervals are
        short (`SHORT_INTERVAL_SHARE`); so until `RECENT_INTERVALS` have been judged."""
        return self._counted < RECENT_INTERVALS or self._short < UNPACED_SHARE * self._counted

    def scan_time(self, elapsed_ns: int) -> int:
        """The time over which a scan `elapsed_ns` after another moved (ns): as stamped; where the stamps do
        not pace the scans (`paced`), one typical interval, unless `elapsed_ns` is a gap (`PACE_GAP`)."""
        if self.paced or elapsed_ns >= PACE_GAP * self.typical_ns:
            return elapsed_ns
        return round(self.typical_ns)

    @property
    def known(self) -> bool:
        """Whether a whole window of intervals was seen (the first stamps of a bursty logger are 1 ms apart,
        whatever the rate)."""
        return len(self._recent) == self._recent.maxlen

    @property
    def typical_ns(self) -> float:
        """The mean of the recent intervals (ns); 0 until `known`."""
        return (self._recent[-1] - self._recent[0]) / (len(self._recent) - 1) if self.known else 0.0


class MatchCadence:
    """Tell, scan by scan in time order, whether the scan is due to be matched (`due`), and hear which were
    (`matched`). `min_interval` 0: every scan is due."""

    def __init__(self, min_interval: float) -> None:
        self._min_interval_ns = round(min_interval * 1e9)
        self.rate = ScanRate()
        self._last_matched: int | None = None
        self._since_matched = 0

    def due(self, stamp_ns: int) -> bool:
        """Whether the scan at `stamp_ns` is to be matched: `min_interval` since the last matched scan, in
        whole strides of the typical interval, or after a gap; always the first `RECENT_INTERVALS` scans."""
        self.rate.add(stamp_ns)
        self._since_matched += 1
        # Until the laser's rate is known, every scan is matched.
        if self._last_matched is None or self._min_interval_ns <= 0 or not self.rate.known:
            return True
        if stamp_ns - self._last_matched >= self._min_interval_ns:
            return True
        typical = self.rate.typical_ns
        return self._since_matched >= max(1, math.floor(self._min_interval_ns / typical + STRIDE_ROUNDING))

    def matched(self, stamp_ns: int) -> None:
        """The scan at `stamp_ns` was matched (due or not: the SLAM matches what it must)."""
        self._last_matched = stamp_ns
        self._since_matched = 0
