"""From an opened log to what the 2D SLAM consumes: scans in the robot's base frame and wheel odometry.

Real logs are imperfect: odometry may be missing, repeated, or have gaps; stamps may glitch out of order.
The odometry track drops exact repeats and answers "no prediction" across gaps instead of inventing one.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontends.errors import TransformLookupError
from frontends.log import LogReader
from frontends.transforms import TransformTree
from frontends.types import Scan2D, Transform
from optimizer import se2

FloatArray = NDArray[np.float64]

MAX_ODOMETRY_GAP_NS = 5_000_000_000
"""Odometry is interpolated between two messages at most this far apart; across a longer gap a scan gets
no wheel-odometry prediction. Shorter gaps still predict well (the poses at both ends are known), but the
SLAM is told how long the interval was and widens its search (see `LaserSlam2D.add_scan`)."""


@dataclass(frozen=True, eq=False)
class OdometryTrack:
    """Planar wheel-odometry poses sorted by stamp, exact repeats removed."""

    stamps_ns: NDArray[np.int64]
    poses: FloatArray
    frame: str
    child_frame: str

    def at(self, stamps_ns: NDArray[np.int64]) -> FloatArray:
        """(S, 3) poses interpolated at `stamps_ns`; NaN rows outside the track or across a gap."""
        return self.interpolate(stamps_ns)[0]

    def interpolate(self, stamps_ns: NDArray[np.int64]) -> tuple[FloatArray, NDArray[np.int64]]:
        """Poses as `at`, and the length (ns) of the odometry interval each was interpolated in (0 when a
        message has the exact stamp)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        out = np.full((len(stamps), 3), np.nan)
        if len(self.stamps_ns) < 2:
            return out, np.zeros(len(stamps), dtype=np.int64)
        after = np.searchsorted(self.stamps_ns, stamps, side="left")
        exact = (after < len(self.stamps_ns)) & (
            self.stamps_ns[np.minimum(after, len(self.stamps_ns) - 1)] == stamps
        )
        inside = (after > 0) & (after < len(self.stamps_ns))
        before = np.maximum(after - 1, 0)
        after = np.minimum(after, len(self.stamps_ns) - 1)
        gap = self.stamps_ns[after] - self.stamps_ns[before]
        usable = inside & (gap <= MAX_ODOMETRY_GAP_NS) & (gap > 0)
        fraction = np.zeros(len(stamps))
        fraction[usable] = (stamps[usable] - self.stamps_ns[before[usable]]) / gap[usable]
        start = self.poses[before]
        motion = se2.relative(start, self.poses[after])
        out[usable] = se2.compose(start[usable], motion[usable] * fraction[usable, None])
        out[exact] = self.poses[after[exact]]
        interval = np.where(exact, 0, gap)
        return out, interval


def read_odometry(log: LogReader, topic: str | None = None) -> OdometryTrack | None:
    """The log's wheel odometry (its odometry topic, else the tf edge out of `odom`), None without any."""
    stamps: list[int] = []
    poses: list[FloatArray] = []
    frames: tuple[str, str] = ("odom", "base_link")
    for pose in log.odometry(topic):
        stamps.append(pose.stamp_ns)
        poses.append(pose.se2)
        frames = (pose.frame_id, pose.child_frame_id)
    if len(stamps) < 2:
        return None
    stamp_array = np.array(stamps, dtype=np.int64)
    pose_array = np.array(poses)
    order = np.argsort(stamp_array, kind="stable")
    stamp_array, pose_array = stamp_array[order], pose_array[order]
    keep = np.ones(len(stamp_array), dtype=bool)
    keep[1:] = stamp_array[1:] != stamp_array[:-1]  # repeated stamps: the first message wins
    return OdometryTrack(stamp_array[keep], pose_array[keep], frames[0], frames[1])


def laser_mount(tree: TransformTree, base_frame: str, laser_frame: str, stamp_ns: int) -> Transform | None:
    """The transform placing laser points in the base frame, None when tf does not link the two frames
    (the laser is then taken to sit at the base's origin)."""
    if not laser_frame or laser_frame == base_frame:
        return None
    try:
        return tree.lookup(base_frame, laser_frame, stamp_ns)
    except TransformLookupError:
        return None


def scans_in_base_frame(
    log: LogReader, topic: str, tree: TransformTree, base_frame: str
) -> Iterator[tuple[Scan2D, bool]]:
    """Every scan of `topic` with its points moved into `base_frame`, and whether tf gave the mount."""
    mount: Transform | None = None
    looked_up_for: str | None = None
    for scan in log.scans(topic):
        if scan.frame_id != looked_up_for:
            looked_up_for = scan.frame_id
            mount = laser_mount(tree, base_frame, scan.frame_id, scan.stamp_ns)
        yield (scan.transformed(mount) if mount is not None else scan), mount is not None
