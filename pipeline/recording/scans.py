"""What a log replay adds to the recording: the scans as they were processed, and the final map.

Timelines: `scan` (the scan's index) and `time` (its sensor stamp) carry, per scan, its points placed at
the pose estimated when it was processed (`world/scan`) and that pose (`world/robot`); loop closures are
logged when they are found (`world/loop_closures_found`). Static: the odometry-only trajectory, the
final trajectory of every scan, the occupancy grid (`occupancy/grid`, an image of its own view).
Per-scan data is buffered and sent in column batches, which keeps the cost of recording a small part of
a replay.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from frontends.slam2d import LaserFrontend, OccupancyGrid, ScanEstimate, ScanInBase, place
from optimizer import se2
from pipeline.keyframe_optimization import IterationSink
from pipeline.recording import log_final_map

SCAN_TIMELINE = "scan"
TIME_TIMELINE = "time"

SCAN_ENTITY = "world/scan"
ROBOT_ENTITY = "world/robot"
FOUND_LOOP_CLOSURES_ENTITY = "world/loop_closures_found"
ODOMETRY_TRAJECTORY_ENTITY = "world/odometry_trajectory"
FINAL_TRAJECTORY_ENTITY = "world/final_trajectory"
OCCUPANCY_ENTITY = "occupancy/grid"

SCAN_COLOR = (214, 39, 40, 255)
ROBOT_COLOR = (44, 160, 44, 255)
ODOMETRY_COLOR = (148, 103, 189, 160)
FINAL_TRAJECTORY_COLOR = (255, 127, 14, 255)
FOUND_LOOP_COLOR = (230, 85, 13, 200)
SCAN_POINT_RADIUS = rr.Radius.ui_points(1.5)
ROBOT_RADIUS = rr.Radius.ui_points(4.0)
LINE_WIDTH = rr.Radius.ui_points(0.75)

SCAN_BATCH_POINTS = 2_000_000
"""Scan points buffered before a column batch is sent."""

FloatArray = NDArray[np.float64]


def log_scan_styles(recording: rr.RecordingStream) -> None:
    recording.log(
        SCAN_ENTITY, rr.Points2D.from_fields(colors=[SCAN_COLOR], radii=[SCAN_POINT_RADIUS]), static=True
    )
    recording.log(
        ROBOT_ENTITY, rr.Points2D.from_fields(colors=[ROBOT_COLOR], radii=[ROBOT_RADIUS]), static=True
    )


def log_odometry_trajectory(recording: rr.RecordingStream, poses: FloatArray) -> None:
    """What wheel odometry alone believed (static, beside the SLAM estimate)."""
    if len(poses) >= 2:
        recording.log(
            ODOMETRY_TRAJECTORY_ENTITY,
            rr.LineStrips2D([poses[:, :2].astype(np.float32)], colors=[ODOMETRY_COLOR], radii=[LINE_WIDTH]),
            static=True,
        )


def log_final_trajectory(recording: rr.RecordingStream, poses: FloatArray) -> None:
    recording.log(
        FINAL_TRAJECTORY_ENTITY,
        rr.LineStrips2D(
            [poses[:, :2].astype(np.float32)], colors=[FINAL_TRAJECTORY_COLOR], radii=[LINE_WIDTH]
        ),
        static=True,
    )


def log_occupancy(recording: rr.RecordingStream, image: NDArray[np.uint8]) -> None:
    """The occupancy grid as a grey image (north up), static."""
    recording.log(OCCUPANCY_ENTITY, rr.Image(image, color_model="L"), static=True)


def log_loop_closures_found(
    recording: rr.RecordingStream, scan_index: int, stamp_ns: int, segments: FloatArray
) -> None:
    """Loop closures found at this scan, as segments between the two keyframes' estimated positions."""
    recording.set_time(SCAN_TIMELINE, sequence=scan_index)
    recording.set_time(TIME_TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))
    recording.log(
        FOUND_LOOP_CLOSURES_ENTITY,
        rr.LineStrips2D(segments.astype(np.float32), colors=[FOUND_LOOP_COLOR], radii=[LINE_WIDTH]),
    )
    recording.reset_time()


class ScanRecorder:
    """Buffers each processed scan (its points in the map frame and its pose) and sends them in columns."""

    def __init__(self, recording: rr.RecordingStream) -> None:
        self._recording = recording
        self._indices: list[int] = []
        self._stamps: list[int] = []
        self._points: list[NDArray[np.float32]] = []
        self._poses: list[FloatArray] = []
        self._buffered = 0

    def add(self, index: int, stamp_ns: int, points: FloatArray, pose: FloatArray) -> None:
        self._indices.append(index)
        self._stamps.append(int(stamp_ns))
        self._points.append(np.asarray(points, dtype=np.float32).reshape(-1, 2))
        self._poses.append(np.asarray(pose[:2], dtype=np.float32))
        self._buffered += len(points)
        if self._buffered >= SCAN_BATCH_POINTS:
            self.flush()

    def flush(self) -> None:
        if not self._indices:
            return
        indexes = [
            rr.TimeColumn(SCAN_TIMELINE, sequence=np.asarray(self._indices, dtype=np.int64)),
            rr.TimeColumn(TIME_TIMELINE, timestamp=np.asarray(self._stamps, dtype="datetime64[ns]")),
        ]
        lengths = np.array([len(p) for p in self._points])
        self._recording.send_columns(
            SCAN_ENTITY,
            indexes=indexes,
            columns=rr.Points2D.columns(positions=np.concatenate(self._points)).partition(lengths),
        )
        self._recording.send_columns(
            ROBOT_ENTITY, indexes=indexes, columns=rr.Points2D.columns(positions=np.stack(self._poses))
        )
        self._indices, self._stamps, self._points, self._poses = [], [], [], []
        self._buffered = 0


class ScanReplayRecording:
    """The 2D part of a log replay's recording (`pipeline.replay_log.FrontendRecording`)."""

    with_map = True

    def __init__(self, recording: rr.RecordingStream, frontend: LaserFrontend) -> None:
        self._recording = recording
        self._frontend = frontend
        self._scans = ScanRecorder(recording)
        log_scan_styles(recording)

    def measurement(self, measurement: ScanInBase, estimate: ScanEstimate) -> None:
        scan, _ = measurement
        self._scans.add(estimate.index, estimate.stamp_ns, place(scan.points, estimate.pose), estimate.pose)
        if estimate.new_loop_closures:
            position = self._frontend.keyframe_position
            segments = np.array([[position(a), position(b)] for a, b in estimate.new_loop_closures])
            log_loop_closures_found(self._recording, estimate.index, estimate.stamp_ns, segments)

    def frontend_done(self) -> None:
        self._scans.flush()
        if self._frontend.odometry_poses:
            # In the map frame, which starts at the first scan: the odometry seen from its own first pose.
            track = np.array(self._frontend.odometry_poses)
            log_odometry_trajectory(self._recording, se2.relative(track[0], track))

    def iteration_sink(self) -> IterationSink | None:
        return None

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: OccupancyGrid) -> None:
        log_final_map(self._recording, self._frontend.result.keyframe_scans, planar_poses)
        log_final_trajectory(self._recording, estimates)
        log_occupancy(self._recording, map_export.image())
