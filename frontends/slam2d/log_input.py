"""From an opened log to what the 2D SLAM consumes: scans in the robot's base frame and wheel odometry.

Real logs are imperfect: odometry may be missing, repeated, or have gaps; stamps may glitch out of order.
The odometry track drops exact repeats and answers "no prediction" across gaps instead of inventing one.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, MutableMapping
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.errors import FrontendError, LogFileError, UnusableLogError
from frontends.logs import rotations
from frontends.logs.log import LogReader
from frontends.logs.transforms import TransformTree
from frontends.logs.types import Scan2D, Transform
from frontends.protocol import default_base_frame
from frontends.slam2d.config import DataChecksConfig, MatchingConfig
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
        if stamps.shape == (1,) and len(self.stamps_ns) >= 2:
            pose, one_interval = self._interpolate_one(int(stamps[0]))
            return pose[None, :], np.array([one_interval], dtype=np.int64)
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

    def _interpolate_one(self, stamp: int) -> tuple[FloatArray, int]:
        """`interpolate` of one stamp (the replay asks scan by scan) in scalar arithmetic: the same
        operations in the same order as the array code, without its dozens of small array operations."""
        stamps = self.stamps_ns
        count = len(stamps)
        after = int(np.searchsorted(stamps, stamp, side="left"))
        if after < count and int(stamps[after]) == stamp:
            return self.poses[after].copy(), 0
        inside = 0 < after < count
        before, after = max(after - 1, 0), min(after, count - 1)
        gap = int(stamps[after]) - int(stamps[before])
        if not (inside and 0 < gap <= MAX_ODOMETRY_GAP_NS):
            return np.full(3, np.nan), gap
        fraction = (stamp - int(stamps[before])) / gap
        x0, y0, theta0 = (float(v) for v in self.poses[before])
        x1, y1, theta1 = (float(v) for v in self.poses[after])
        c, s = math.cos(theta0), math.sin(theta0)
        dx, dy = x1 - x0, y1 - y0
        # se2.relative(start, end) * fraction, then se2.compose(start, ·), written out.
        forward = (c * dx + s * dy) * fraction
        sideways = (-s * dx + c * dy) * fraction
        turn = _wrap(theta1 - theta0) * fraction
        return np.array([x0 + c * forward - s * sideways, y0 + s * forward + c * sideways,
                         _wrap(theta0 + turn)]), gap


def _wrap(theta: float) -> float:
    return (theta + math.pi) % (2.0 * math.pi) - math.pi


def read_odometry(
    log: LogReader,
    topic: str | None = None,
    checks: DataChecksConfig | None = None,
    counts: MutableMapping[str, int] | None = None,
) -> OdometryTrack | None:
    """The log's wheel odometry (its odometry topic, else the tf edge out of `odom`), None without any.

    Messages out of stamp order are sorted (`odometry_reordered` counts them); non-finite poses, poses
    beyond `checks.world_extent`, and jumps faster than `checks.max_speed` / `max_turn_rate` from the
    previous kept message are dropped (`odometry_dropped_nonfinite`, `_out_of_world`, `_jumps`)."""
    checks = checks or DataChecksConfig()
    counts = counts if counts is not None else {}
    odometry = log.odometry_arrays(topic)
    if odometry is None:
        return None
    stamp_array = odometry.stamps_ns
    # Headings of all messages at once (`OdometryPose.se2` one by one: 13 us each, 0.2 s of a 3-minute log
    # with odometry at 80 Hz).
    pose_array = np.column_stack([odometry.translations[:, :2], rotations.yaw(odometry.rotations)])
    _add(counts, "odometry_reordered", int(np.count_nonzero(stamp_array[1:] < stamp_array[:-1])))
    order = np.argsort(stamp_array, kind="stable")
    stamp_array, pose_array = stamp_array[order], pose_array[order]
    finite = np.isfinite(pose_array).all(axis=1)
    _add(counts, "odometry_dropped_nonfinite", int(np.count_nonzero(~finite)))
    inside = finite & (np.hypot(pose_array[:, 0], pose_array[:, 1]) <= checks.world_extent)
    _add(counts, "odometry_dropped_out_of_world", int(np.count_nonzero(finite & ~inside)))
    stamp_array, pose_array = stamp_array[inside], pose_array[inside]
    keep = np.ones(len(stamp_array), dtype=bool)
    keep[1:] = stamp_array[1:] != stamp_array[:-1]  # repeated stamps: the first message wins
    stamp_array, pose_array = stamp_array[keep], pose_array[keep]
    # float(): a limit a config file wrote as an integer would compile the kernels again (seconds, cold)
    plausible = _plausible_motion(stamp_array, pose_array, float(checks.max_speed),
                                  float(checks.max_turn_rate))
    _add(counts, "odometry_dropped_jumps", int(np.count_nonzero(~plausible)))
    stamp_array, pose_array = stamp_array[plausible], pose_array[plausible]
    if len(stamp_array) < 2:
        return None
    return OdometryTrack(stamp_array, pose_array, odometry.frame_id, odometry.child_frame_id)


def _add(counts: MutableMapping[str, int], name: str, value: int) -> None:
    if value:
        counts[name] = counts.get(name, 0) + value


ODOMETRY_RESTART_RUN = 10
ODOMETRY_STAMP_JITTER = 0.1
"""Two odometry messages are judged as at least this far apart in time (s). Stamps jitter: a logger that
stamps messages when it gets round to them (the Intel Research Lab log: stamps up to 0.6 s out of order,
bursts 1 ms apart) puts poses taken a second apart 1 ms apart once sorted, and 5 cm over 1 ms is 50 m/s.
Judged over the stamps alone, such a log lost a third of its odometry as "jumps", and the rest,
interpolated across the holes, turned the robot the wrong way in a fast turn. Glitches are metres or
kilometres off; 0.1 s still allows only 3 m and 2 rad at the default limits."""


@njit(cache=True)
def _plausible_motion(
    stamps_ns: NDArray[np.int64], poses: FloatArray, max_speed: float, max_turn_rate: float
) -> NDArray[np.bool_]:
    """Keep each pose reachable from the previous kept one within the speed limits. A glitch is one pose
    (or a few) far off. A run of `ODOMETRY_RESTART_RUN` rejected poses agreeing with each other is the
    track starting over (an odometry reset): kept from there on. When the first poses were the glitch
    (the kept track is shorter than that run), they are dropped instead."""
    count = stamps_ns.shape[0]
    keep = np.zeros(count, dtype=np.bool_)
    if count == 0:
        return keep
    keep[0] = True
    # Not the literal 0: `_reachable` was compiled for Literal[int](0) besides int64.
    last: int | np.int64 = np.int64(0)
    kept_run = 1
    rejected_start = -1
    for i in range(1, count):
        if _reachable(stamps_ns, poses, last, i, max_speed, max_turn_rate):
            keep[i] = True
            last = i
            kept_run += 1
            rejected_start = -1
            continue
        if rejected_start < 0 or not _reachable(stamps_ns, poses, i - 1, i, max_speed, max_turn_rate):
            rejected_start = i
        if i - rejected_start + 1 >= ODOMETRY_RESTART_RUN or i - rejected_start + 1 > kept_run:
            if kept_run < ODOMETRY_RESTART_RUN:  # what was kept was the glitch
                keep[:rejected_start] = False
            keep[rejected_start : i + 1] = True
            last = i
            kept_run = i - rejected_start + 1
            rejected_start = -1
    return keep


@njit(cache=True)
def _reachable(
    stamps_ns: NDArray[np.int64], poses: FloatArray, a: int | np.int64, b: int, max_speed: float,
    max_turn_rate: float
) -> bool:
    seconds = max((stamps_ns[b] - stamps_ns[a]) * 1e-9, ODOMETRY_STAMP_JITTER)
    distance = math.hypot(poses[b, 0] - poses[a, 0], poses[b, 1] - poses[a, 1])
    turn = abs(se2.wrap_scalar(poses[b, 2] - poses[a, 2]))
    return distance <= max_speed * seconds and turn <= max_turn_rate * seconds


def scans_in_base_frame(
    log: LogReader,
    topic: str,
    tree: TransformTree,
    base_frame: str | None,
    *,
    min_points: int = MatchingConfig.min_points,
    checks: DataChecksConfig | None = None,
    counts: MutableMapping[str, int] | None = None,
) -> Iterator[tuple[Scan2D, Transform | None]]:
    """Every scan of `topic` with a valid return, its points moved into `base_frame` (None: the frame the
    first scan's sensor is mounted on, `frontends.protocol.default_base_frame`), and the mount tf gave
    (None: the scan is left in its sensor frame).

    Scans without any valid return (all NaN, inf, negative, out of range, or angles that are not a sweep)
    are skipped and counted (`scans_without_returns`); once the log is read, an `UnusableLogError` says so
    when fewer than `checks.min_usable_scan_share` of the scans had `min_points` valid returns."""
    checks = checks or DataChecksConfig()
    counts = counts if counts is not None else {}
    mount: Transform | None = None
    mounted: _Mount | None = None
    looked_up_for: str | None = None
    read = usable = 0
    for scan in log.scans(topic):
        read += 1
        valid = scan.points.shape[0]
        usable += valid >= min_points
        if valid == 0:
            _add(counts, "scans_without_returns", 1)
            continue
        if scan.frame_id != looked_up_for:
            looked_up_for = scan.frame_id
            try:
                base_frame = base_frame or default_base_frame(tree, scan.frame_id)
            except FrontendError as error:  # a cycle in tf
                raise LogFileError(log.path, str(error)) from None
            mount = tree.sensor_mount(base_frame, scan.frame_id, scan.stamp_ns)
            mounted = None if mount is None else _Mount(mount)
        yield (mounted.apply(scan) if mounted is not None else scan), mount
    if read and usable < checks.min_usable_scan_share * read:
        raise UnusableLogError(
            log.path,
            f"only {usable} of the {read} scans on {topic} have {min_points} or more valid returns "
            f"(need {checks.min_usable_scan_share:.0%}): the ranges are NaN, infinite, negative or out of "
            "range, or the beam angles are invalid",
        )


class _Mount:
    """`Scan2D.transformed(mount)` with the mount's rotation matrix built once, not once per scan (the
    same arithmetic on the same matrix: the points are equal)."""

    def __init__(self, mount: Transform) -> None:
        self._mount = mount
        self._rotation_t = rotations.to_matrix(mount.rotation).T

    def apply(self, scan: Scan2D) -> Scan2D:
        if scan.frame_id != self._mount.child_frame:
            return scan.transformed(self._mount)  # raises: the mount is for another frame
        xyz = np.zeros((scan.points.shape[0], 3))
        xyz[:, :2] = scan.points
        points = np.ascontiguousarray((xyz @ self._rotation_t + self._mount.translation)[:, :2])
        return Scan2D(scan.stamp_ns, scan.log_time_ns, self._mount.parent_frame, points, scan.ranges,
                      scan.bearings, scan.beam_count, scan.point_times)
