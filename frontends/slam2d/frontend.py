"""The 2D laser SLAM as a `frontends.protocol.LogFrontend`: a log's scans (in the base frame) and wheel
odometry in, the keyframe graph, every scan's pose and an occupancy map out."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np

from frontends.errors import FrontendError, LogWarning
from frontends.logs import LogReader, Scan2D, Transform
from frontends.protocol import (
    FloatArray,
    FrontendOptions,
    IntArray,
    LogFrontendBase,
    SessionArrays,
    default_base_frame,
)
from frontends.slam2d.config import Slam2DConfig
from frontends.slam2d.deskew import MAX_DESKEW_INTERVAL, deskewed, velocity
from frontends.slam2d.log_input import OdometryTrack, read_odometry, scans_in_base_frame
from frontends.slam2d.occupancy import OccupancyGrid, occupancy_grid
from frontends.slam2d.slam import LaserSlam2D, ScanEstimate, Slam2DGraph
from optimizer import se2
from optimizer.graph import PoseGraph

SWEEP_OVER_PERIOD = 1.5
"""A scan's beam times are used when its sweep lasts at most this many times the interval since the previous
scan: a laser taking its beams over the whole period (a 360° scanner) fits, with room for the stamps'
jitter."""

ScanInBase = tuple[Scan2D, Transform | None]
"""A scan with its points in the base frame, and the mount tf gave (None: left in the sensor frame)."""


def deskewed_by_odometry(points: FloatArray, times: FloatArray, stamp_ns: int, odometry: OdometryTrack,
                         at_stamp: FloatArray, interval_ns: int) -> tuple[FloatArray, FloatArray | None]:
    """The scan's points deskewed under the wheel odometry read over the sweep itself, and None for their
    times; as given (points, times) when the odometry does not reach the sweep's end or is too sparse to
    tell the motion in it (messages over `MAX_DESKEW_INTERVAL` apart): the SLAM then estimates the
    motion (`frontends.slam2d.deskew.ScanDeskewer`), a whole scan period late.

    `at_stamp` is the odometry at the stamp, interpolated in an interval of `interval_ns`."""
    sweep = float(times[np.argmax(np.abs(times))]) if len(times) else 0.0  # the beam farthest from the stamp
    if sweep == 0.0:
        return points, times
    end, end_interval = odometry.interpolate(np.array([stamp_ns + round(sweep * 1e9)]))
    if not np.all(np.isfinite(end)) or max(interval_ns, int(end_interval[0])) > MAX_DESKEW_INTERVAL * 1e9:
        return points, times
    return deskewed(points, times, velocity(se2.relative(at_stamp, end[0]), sweep)), None


class LaserFrontend(LogFrontendBase[Slam2DConfig, Slam2DGraph]):
    """`LaserSlam2D` on the scans of `topic` in an open log; see `frontends.protocol.LogFrontend`."""

    odometry_starts_at_map_origin = True
    """The map frame is the first scan's: the odometry seen from its first pose is in it. Not so for a run
    placed in a saved map (`frontends.slam2d.session_frontends`)."""

    def __init__(self, log: LogReader, topic: str, config: Slam2DConfig | None = None,
                 options: FrontendOptions | None = None) -> None:
        super().__init__(log, topic, config or Slam2DConfig(), options)
        self._input_counts: dict[str, int] = {}  # what the input checks dropped, skipped or reordered
        self.odometry: OdometryTrack | None = read_odometry(log, self.odometry_topic,
                                                            counts=self._input_counts)
        if self.odometry is not None:
            self._odometry_read(self.odometry.frame, self.odometry.child_frame)
            if self.base_frame is None:  # the odometry's poses are of that frame
                self.base_frame = self.odometry.child_frame
        self._slam = LaserSlam2D(self.config)
        self._counts = {"scans": 0, "scans_with_tf_mount": 0, "scans_with_odometry": 0,
                        "scans_with_beam_times": 0, "scans_beam_times_ignored": 0}
        self._longest_ignored_sweep = 0.0
        self._last_estimate: tuple[int, FloatArray] | None = None
        """The stamp and pose given to the last scan."""
        self.odometry_poses: list[FloatArray] = []
        """The wheel-odometry pose at every scan that had one (for the recording; empty when the
        odometry's first pose is not the map's origin, see `odometry_starts_at_map_origin`)."""

    def measurements(self) -> Iterator[ScanInBase]:
        base = self.base_frame
        for scan, mount in scans_in_base_frame(self._log, self._topic, self._tree, base,
                                               min_points=self.config.matching.min_points,
                                               counts=self._input_counts):
            if not self.sensor_frame:
                self.sensor_frame = scan.frame_id if mount is None else mount.child_frame
                self.base_frame = base or default_base_frame(self._tree, self.sensor_frame)
                if mount is None and self._requested_base_frame not in (None, self.sensor_frame):
                    raise self._unlinked_base_frame(self.sensor_frame, "laser")
            yield scan, mount

    def add(self, measurement: ScanInBase) -> ScanEstimate:
        scan, mount = measurement
        prediction, interval = None, 0.0
        points, times = scan.points, self._beam_times(scan)
        if self.odometry is not None:
            at, intervals = self.odometry.interpolate(np.array([scan.stamp_ns]))
            prediction = None if np.isnan(at[0, 0]) else at[0]
            interval = float(intervals[0]) * 1e-9
            if prediction is not None and times is not None:
                points, times = deskewed_by_odometry(points, times, scan.stamp_ns, self.odometry,
                                                     prediction, int(intervals[0]))
        estimate = self._process(scan.stamp_ns, points, prediction, interval, times)
        if times is not None and not estimate.between:  # a scan between is not played back
            # The SLAM deskewed the scan under the motions of the scans before it, all it knew then; the
            # scan handed on (the recording's playback) is deskewed under its own matched motion.
            points = self._deskewed_for_display(scan.stamp_ns, points, times, estimate.pose)
        self._last_estimate = (scan.stamp_ns, estimate.pose)
        if points is not scan.points:
            estimate = dataclasses.replace(estimate, points=points)
        self._counts["scans"] += 1
        self._counts["scans_with_tf_mount"] += mount is not None
        self._counts["scans_with_beam_times"] += scan.point_times is not None
        if prediction is not None:
            self._counts["scans_with_odometry"] += 1
            if self.odometry_starts_at_map_origin:
                self.odometry_poses.append(prediction)
        return estimate

    def _beam_times(self, scan: Scan2D) -> FloatArray | None:
        """The scan's beam times, if deskewing is on and they fit: a laser ends a sweep before it starts the
        next, so a sweep longer than `SWEEP_OVER_PERIOD` times the time since the previous scan is a
        driver's wrong time_increment (counted, and said once the log is read)."""
        times = scan.point_times
        if times is None or not self.config.matching.deskew or not len(times):
            return None
        sweep = float(np.max(np.abs(times)))
        if self._last_estimate is not None and sweep > SWEEP_OVER_PERIOD * (
                (scan.stamp_ns - self._last_estimate[0]) * 1e-9):
            self._counts["scans_beam_times_ignored"] += 1
            self._longest_ignored_sweep = max(self._longest_ignored_sweep, sweep)
            return None
        return times

    def _deskewed_for_display(self, stamp_ns: int, points: FloatArray, times: FloatArray,
                              pose: FloatArray) -> FloatArray:
        if self._last_estimate is None:
            return points
        last_stamp, last_pose = self._last_estimate
        elapsed = (stamp_ns - last_stamp) * 1e-9
        motion = se2.relative(last_pose, pose)
        if not (0.0 < elapsed <= MAX_DESKEW_INTERVAL and np.all(np.isfinite(motion))):
            return points
        return deskewed(points, times, velocity(motion, elapsed))

    def _process(self, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
                 odometry_interval: float, point_times: FloatArray | None) -> ScanEstimate:
        """One scan (base-frame points, its interpolated wheel-odometry pose, its beams' times) through the
        SLAM."""
        return self._slam.add_scan(stamp_ns, points, odometry, odometry_interval, point_times)

    def keyframe_position(self, keyframe: int) -> FloatArray:
        return self._slam.keyframe_position(keyframe)

    def finish(self) -> None:
        if self._counts["scans"] == 0:
            raise FrontendError(f"{self._log.path}: topic {self._topic} has no scans")
        self._after_reading()
        self._result = self._finished(self._slam.finish)
        if self.odometry is not None:
            self._warn_if_odometry_covered_nothing(self.odometry.stamps_ns, self.result.scan_stamps_ns,
                                                   self._counts["scans_with_odometry"], "scans", "matched",
                                                   f" on {self.odometry_topic}")

    def _after_reading(self) -> None:
        """What the whole log says. No scan placed on a base by tf, and no base named by the user: the poses
        are the laser's, and the result says so (`base_frame` None), as the LiDAR frontend's does; with
        wheel odometry of another frame, a warning: its motion was taken as the laser's. Beam times ignored
        (`_beam_times`): a warning."""
        if not self._counts["scans_with_tf_mount"] and self._requested_base_frame is None:
            self.base_frame = None
            odometry_frame = None if self.odometry is None else self.odometry.child_frame
            if odometry_frame and odometry_frame != self.sensor_frame:
                laser = (f"the laser's frame {self.sensor_frame}" if self.sensor_frame
                         else "the scans, which name no frame (frame_id empty),")
                warnings.warn(f"{self._log.path}: tf gives no path from {laser} to the odometry's "
                              f"{odometry_frame}: the odometry was taken as the laser's own motion (a laser "
                              "off the robot's centre moves otherwise in turns), and the poses are the "
                              "laser's", LogWarning, stacklevel=2)
        ignored = self._counts["scans_beam_times_ignored"]
        if ignored:
            warnings.warn(f"{self._log.path}: {ignored} scans on {self._topic} said their beams took up to "
                          f"{self._longest_ignored_sweep:.3g} s (time_increment), longer than the time "
                          "between scans: they were read as if every beam were taken at the stamp",
                          LogWarning, stacklevel=2)

    def keyframe_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        graph = self.result.graph
        return graph if planar_poses is None else graph.with_poses(planar_poses)

    @property
    def stamps_ns(self) -> IntArray:
        return self.result.scan_stamps_ns

    def estimates(self, planar_poses: FloatArray) -> FloatArray:
        return self.result.scan_poses(planar_poses)

    def session_content(self, planar_poses: FloatArray) -> SessionArrays:
        result = self.result
        graph = result.graph
        arrays = {"keyframe_poses": planar_poses, "edge_from": graph.edge_from, "edge_to": graph.edge_to,
                  "measurements": graph.measurements, "information": graph.information,
                  "is_loop": ~graph.is_odometry, "scan_stamps_ns": result.scan_stamps_ns,
                  "scan_keyframes": result.scan_keyframes, "scan_offsets": result.scan_offsets}
        return arrays, result.keyframe_scans

    def keyframe_wheel_odometry(self) -> FloatArray | None:
        if self.odometry is None:
            return None
        first_scans = np.unique(self.result.scan_keyframes, return_index=True)[1]
        poses = self.odometry.interpolate(self.result.scan_stamps_ns[first_scans])[0]
        return poses if np.all(np.isfinite(poses)) else None

    def map_export(self, planar_poses: FloatArray) -> OccupancyGrid:
        return occupancy_grid(self.result.keyframe_scans, planar_poses)

    def counts(self) -> dict[str, int]:
        result = self.result
        return {**self._counts, **self._input_counts, **self._log.counts, "keyframes": result.graph.num_poses,
                "constraints": result.graph.num_edges, "scans_unmatched": result.scans_unmatched,
                "scans_between": result.scans_between}

    def loop_closures(self) -> dict[str, Any]:
        result = self.result
        return {"accepted": result.loop_closures_accepted, "rejected": result.loop_closures_rejected,
                "candidates": {"accepted": result.loop_closures_accepted + result.loop_closures_rejected,
                               "unconfirmed": result.loop_closures_unconfirmed}}
