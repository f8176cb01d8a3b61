"""What a log replay adds to the recording: the scans as they were processed, and the final trajectory.

Timelines: `scan` (the scan's index) and `time` (its sensor stamp) carry, per scan, its points placed at
the pose estimated when it was processed (`world/scan`) and that pose (`world/robot`); loop closures are
logged when they are found (`world/loop_closures_found`). The blueprint's "scan playback" tab shows them
with a visible time range from the start to the cursor, so the scans build up the map, the robot leaves
a trail and the loop closures found stay drawn. A fast laser's scans between matched ones
(`ScanEstimate.between`) are left out of the playback: it plays the matched scans, at most one a
`min_match_interval`, and the recording stays the size a slower laser's would. Static: the wheel-odometry
trajectory and the final trajectory of every scan (both off by default in the map view). Per-scan data is
buffered and sent in column batches, which keeps the cost of recording a small part of a replay.

`MapLocalizationRecording` is the recording of a localization in a saved 2D map (`replay LOG --map
SESSION`): the scans as above, under the saved map (see its docstring).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from frontends.slam2d import LaserFrontend, OccupancyGrid, ScanEstimate, ScanInBase, one_per_cell_each, place
from frontends.slam2d.session_frontends import LocalizingLaserFrontend
from optimizer import se2
from pipeline.recording import (
    INITIAL_TRAJECTORY_COLOR,
    ITERATION_TIMELINE,
    MAP_COLOR,
    MAP_DRAW_ORDER,
    MAP_POINT_RADIUS,
    MATCH_QUALITY_ENTITY,
    SCAN_TIMELINE,
    TIME_TIMELINE,
    TRAJECTORY_COLOR,
    VIEWER_BACKGROUND,
    Bounds,
    FloatArray,
    IterationSink,
    chi2_views,
    default_blueprint,
    log_legend,
    log_static_trajectory,
    map2d,
    send_blueprint,
    send_match_quality,
    ui_points,
    visual_bounds,
)

SCAN_ENTITY, ROBOT_ENTITY = "world/scan", "world/robot"
FOUND_LOOP_CLOSURES_ENTITY = "world/loop_closures_found"
ODOMETRY_TRAJECTORY_ENTITY, FINAL_TRAJECTORY_ENTITY = "world/odometry_trajectory", "world/final_trajectory"
# Colours of the legend's rows; each entity's other looks are set where it is logged.
SCAN_COLOR, ODOMETRY_COLOR = (255, 210, 90, 255), (190, 150, 255, 200)
FINAL_TRAJECTORY_COLOR = (255, 140, 30, 255)

HIDDEN_BY_DEFAULT = (FINAL_TRAJECTORY_ENTITY, ODOMETRY_TRAJECTORY_ENTITY)
"""Static trajectories the map view starts with switched off: drawn over the animated estimate they
would hide it."""
PLAYBACK_ENTITIES = (SCAN_ENTITY, ROBOT_ENTITY, FOUND_LOOP_CLOSURES_ENTITY)

LEGEND_ROWS: dict[str, tuple[tuple[int, ...], str]] = {
    "final trajectory": (FINAL_TRAJECTORY_COLOR, "every scan's final pose (off by default)"),
    "wheel odometry": (ODOMETRY_COLOR, "what wheel odometry alone believed (off by default)"),
    "scan playback": (SCAN_COLOR, "tab: scans up to the cursor on `scan`/`time`, robot trail "
                                  "(green), loop closures found (magenta)"),
}


def log_replay_blueprint(bounds: Bounds | None = None) -> rrb.Blueprint:
    """A log replay's blueprint: the map view (static trajectories off, scan-time data left to the
    playback tab) framing `bounds`, the scan playback tab beside it, χ², stages and legend."""
    return default_blueprint(bounds=bounds, hidden=HIDDEN_BY_DEFAULT, extra_tabs=playback_views(bounds),
                             excluded=PLAYBACK_ENTITIES)


def playback_views(bounds: Bounds | None = None) -> list[rrb.Spatial2DView]:
    """The scan playback tab: everything up to the cursor of `scan` or `time` stays drawn (the scans
    build the map, the robot leaves a trail), over the same framing as the map view."""
    up_to_cursor = [
        rrb.VisibleTimeRange(timeline, start=rrb.TimeRangeBoundary.infinite(),
                             end=rrb.TimeRangeBoundary.cursor_relative())
        for timeline in (SCAN_TIMELINE, TIME_TIMELINE)
    ]
    return [rrb.Spatial2DView(
        origin="/",
        contents=[f"/{entity}" for entity in PLAYBACK_ENTITIES],
        name="scan playback (timeline scan)",
        background=VIEWER_BACKGROUND,
        visual_bounds=visual_bounds(bounds),
        time_ranges=up_to_cursor,
    )]


SCAN_BATCH_POINTS = 2_000_000
"""Scan points buffered before a column batch is sent."""
PLAYBACK_CELL = 0.1
"""Each played-back scan keeps one point per cell of this size (m): the accumulated scans are drawn over
the whole map, where a pixel is several centimetres, and they were the recording's largest part."""


def log_loop_closures_found(
    recording: rr.RecordingStream, scan_index: int, stamp_ns: int, segments: FloatArray
) -> None:
    """Loop closures found at this scan, as segments between the two keyframes' estimated positions."""
    recording.set_time(SCAN_TIMELINE, sequence=scan_index)
    recording.set_time(TIME_TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))
    recording.log(
        FOUND_LOOP_CLOSURES_ENTITY,
        rr.LineStrips2D(segments.astype(np.float32), colors=[(255, 80, 220, 255)],
                        radii=[ui_points(2.5)], draw_order=45.0),
    )
    recording.reset_time()


class ScanRecorder:
    """Buffers each processed scan (its points in the robot's frame and its pose) and sends them in
    columns, placed in the map frame and thinned a batch at a time."""

    def __init__(self, recording: rr.RecordingStream) -> None:
        self._recording = recording
        self._scans: list[tuple[int, int, FloatArray, FloatArray]] = []
        """The buffered scans: (index, stamp, points, pose)."""
        self._buffered = 0

    def add(self, index: int, stamp_ns: int, points: FloatArray, pose: FloatArray) -> None:
        """A scan's `points` in the robot's frame, and the robot's `pose` in the map frame."""
        self._scans.append((index, int(stamp_ns), points, np.asarray(pose, dtype=np.float64)))
        self._buffered += len(points)
        if self._buffered >= SCAN_BATCH_POINTS:
            self.flush()

    def flush(self) -> None:
        if not self._scans:
            return
        indices, stamps, scans, robot_poses = zip(*self._scans, strict=True)
        indexes = [
            rr.TimeColumn(SCAN_TIMELINE, sequence=np.asarray(indices, dtype=np.int64)),
            rr.TimeColumn(TIME_TIMELINE, timestamp=np.asarray(stamps, dtype="datetime64[ns]")),
        ]
        # Placed and thinned for the whole batch at once: per scan, numpy's call overhead was most of it.
        counts = np.array([len(p) for p in scans])
        poses = np.stack(robot_poses)
        per_point = np.repeat(poses, counts, axis=0)
        local = np.concatenate(scans).reshape(-1, 2)
        cos, sin = np.cos(per_point[:, 2]), np.sin(per_point[:, 2])
        points = np.column_stack([cos * local[:, 0] - sin * local[:, 1] + per_point[:, 0],
                                  sin * local[:, 0] + cos * local[:, 1] + per_point[:, 1]])
        offsets = np.concatenate([[0], np.cumsum(counts)])
        keep, lengths = one_per_cell_each(points, offsets, PLAYBACK_CELL)
        self._recording.send_columns(
            SCAN_ENTITY,
            indexes=indexes,
            columns=rr.Points2D.columns(positions=points[keep].astype(np.float32)).partition(lengths),
        )
        robot = poses[:, :2].astype(np.float32)
        self._recording.send_columns(ROBOT_ENTITY, indexes=indexes,
                                     columns=rr.Points2D.columns(positions=robot))
        self._scans = []
        self._buffered = 0


class ScanReplayRecording:
    """The 2D part of a log replay's recording (`pipeline.replay_log.FrontendRecording`)."""

    with_map = True

    def __init__(self, recording: rr.RecordingStream, frontend: LaserFrontend) -> None:
        self._recording = recording
        self._frontend = frontend
        self._scans = ScanRecorder(recording)
        # The static looks of the played-back scans and of the robot's trail (their columns carry positions).
        for entity, color, radius, draw_order in ((SCAN_ENTITY, SCAN_COLOR, 1.0, 20.0),
                                                  (ROBOT_ENTITY, (90, 230, 120, 255), 2.0, 40.0)):
            recording.log(entity, rr.Points2D.from_fields(colors=[color], radii=[ui_points(radius)],
                                                          draw_order=draw_order), static=True)

    def measurement(self, measurement: ScanInBase, estimate: ScanEstimate) -> None:
        if estimate.between or not np.all(np.isfinite(estimate.pose)):
            return  # between matched scans, or not placed yet (a run joining a saved map): no pose
        points = measurement[0].points if estimate.points is None else estimate.points
        self._scans.add(estimate.index, estimate.stamp_ns, points, estimate.pose)
        if estimate.new_loop_closures:
            position = self._frontend.keyframe_position
            segments = np.array([[position(a), position(b)] for a, b in estimate.new_loop_closures])
            log_loop_closures_found(self._recording, estimate.index, estimate.stamp_ns, segments)

    def frontend_done(self) -> None:
        self._scans.flush()
        if len(self._frontend.odometry_poses) >= 2:
            # In the map frame, which starts at the first scan: the odometry seen from its own first pose.
            track = np.array(self._frontend.odometry_poses)
            log_static_trajectory(self._recording, ODOMETRY_TRAJECTORY_ENTITY,
                                  se2.relative(track[0], track), ODOMETRY_COLOR)

    def iteration_sink(self) -> IterationSink | None:
        return None

    def keyframe_scans(self) -> Sequence[FloatArray]:
        return self._frontend.result.keyframe_scans

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: OccupancyGrid) -> None:
        log_static_trajectory(self._recording, FINAL_TRAJECTORY_ENTITY, estimates, FINAL_TRAJECTORY_COLOR)
        map2d.log_occupancy(self._recording, map_export.image(), map_export.origin, map_export.resolution)


SAVED_MAP_ENTITY = "world/saved_map"
LOCALIZATION_LEGEND_ROWS: dict[str, tuple[tuple[int, ...], str]] = {
    "saved map": (MAP_COLOR, "the saved keyframe scans at their saved poses, over its occupancy grid"),
    "trajectory": (FINAL_TRAJECTORY_COLOR, "every localized scan's pose in the map"),
    "scan playback": (SCAN_COLOR, "tab: the new scans up to the cursor on `scan`/`time` at "
                                  "their poses when processed, robot trail (green)"),
}
NEW_RUN_WALLS_COLOR = SCAN_COLOR
"""The new run's keyframe scans moving into the saved map (`--map`): the colour of its scans played back."""
HELD_MAP_LEGEND_ROWS: dict[str, tuple[tuple[int, ...], str]] = {
    "new run": (TRAJECTORY_COLOR, "on `iteration`: the new run's keyframes at that iteration of its graph "
                                  "solved with the saved map held"),
    "new walls": (NEW_RUN_WALLS_COLOR, "their scans at those poses"),
    "start": (INITIAL_TRAJECTORY_COLOR, "the new run's odometry chain, the optimization's first start"),
}
HELD_MAP_NOTE = ("\nThe time panel's `iteration` plays the new run's keyframe graph solved with the saved "
                 "map held, from each start; the trajectory written is the orange one.")


def log_saved_map(recording: rr.RecordingStream, keyframe_scans: Sequence[FloatArray],
                  keyframe_poses: FloatArray) -> None:
    """Every saved keyframe scan at its saved pose, one static point cloud (thinned per keyframe)."""
    placed = [place(map2d.thin_scan(scan).astype(np.float64), pose)
              for scan, pose in zip(keyframe_scans, keyframe_poses, strict=True) if len(scan)]
    points = np.concatenate(placed) if placed else np.zeros((0, 2))
    recording.log(SAVED_MAP_ENTITY, rr.Points2D(points.astype(np.float32), colors=[MAP_COLOR],
                                                radii=[MAP_POINT_RADIUS], draw_order=MAP_DRAW_ORDER),
                  static=True)


MATCH_SERIES_2D = ("score", "inlier_fraction")
"""A laser match has two measures: the correlative score and the ICP inlier fraction."""


class MapLocalizationRecording(ScanReplayRecording):
    """`ScanReplayRecording` for a localization in a saved 2D map (`replay LOG --map SESSION`);
    `final(saved keyframe poses, localized poses, saved occupancy grid)`.

    Beside what `ScanReplayRecording` records of every scan as it is processed (the scan placed at its
    pose, the robot's trail, on the `scan` and `time` timelines):
    - `world/saved_map` (static): the saved keyframe scans at their saved poses, thinned, over
    - `world/occupancy/grid` (static): the saved map's occupancy grid (`pipeline.recording.map2d`);
    - `world/final_trajectory` (static): every localized scan's pose, drawn by default here.
    - `localization/score` and `localization/inlier_fraction` on `scan`: how well each matched scan fit the
      saved map (nothing for a scan whose pose is only the odometry's prediction).
    The blueprint frames the saved map and the new trajectory and plots the match quality. When the run's
    own keyframe graph was solved with the saved map held (`frontends.slam2d.held_map`), its iterations
    are on `iteration` as a log replay's (`pipeline.keyframe_optimization.held_map_solver`: the new
    keyframes' walls moving into the saved map, which stays where it is), the time panel opens on it and
    χ² shares a tab strip with the match quality; otherwise the time panel opens on `scan`.
    """

    _frontend: LocalizingLaserFrontend

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: OccupancyGrid) -> None:
        saved_scans = self._frontend.saved.keyframe_scans
        log_saved_map(self._recording, saved_scans, planar_poses)
        super().final(planar_poses, estimates, map_export)  # the final trajectory and the occupancy grid
        held_map = self._frontend.held_map_solved
        log_legend(self._recording, HELD_MAP_LEGEND_ROWS if held_map else None, rows=LOCALIZATION_LEGEND_ROWS,
                   note=HELD_MAP_NOTE if held_map else "")
        bounds = map2d.placed_bounds(saved_scans, planar_poses, estimates)
        send_match_quality(self._recording, self._frontend.localizations, MATCH_SERIES_2D)
        match_quality = rrb.TimeSeriesView(origin=MATCH_QUALITY_ENTITY, name="match quality per scan (scan)")
        # A plot shows the time panel's timeline only: χ² (on `iteration`) and the match quality (on `scan`)
        # share a tab strip rather than leave one plot empty.
        chi2, stages = chi2_views()
        send_blueprint(self._recording, default_blueprint(
            bounds=bounds, extra_tabs=playback_views(bounds), excluded=PLAYBACK_ENTITIES,
            timeline=ITERATION_TIMELINE if held_map else SCAN_TIMELINE,
            side=[rrb.Tabs(chi2, match_quality), stages] if held_map else [match_quality]))
