"""The recording of a localization in a saved 2D map (`replay LOG --map SESSION`).

Beside what `pipeline.recording.scans` records of every scan as it is processed (the scan placed at its
pose, the robot's trail, on the `scan` and `time` timelines):
- `world/saved_map` (static): the saved keyframe scans at their saved poses, thinned, over
- `world/occupancy/grid` (static): the saved map's occupancy grid (`pipeline.recording.map2d`);
- `world/final_trajectory` (static): every localized scan's pose, drawn by default here.
- `localization/score` and `localization/inlier_fraction` on `scan`: how well each matched scan fit the
  saved map (nothing for a scan whose pose is only the odometry's prediction).
The blueprint frames the saved map and the new trajectory and plots the match quality where a log replay
plots χ²; nothing is optimized, so there is no `iteration` timeline.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from frontends.slam2d import OccupancyGrid, place
from frontends.slam2d.session_frontends import LocalizingLaserFrontend
from pipeline.recording import (
    MAP_COLOR,
    MAP_DRAW_ORDER,
    MAP_POINT_RADIUS,
    MATCH_QUALITY_ENTITY,
    FloatArray,
    default_blueprint,
    log_legend,
    send_blueprint,
    send_match_quality,
)
from pipeline.recording import scans as scan_recording
from pipeline.recording.map2d import log_occupancy, placed_bounds, thin_scan

SAVED_MAP_ENTITY = "world/saved_map"
LEGEND_ROWS: dict[str, tuple[tuple[int, ...], str]] = {
    "saved map": (MAP_COLOR, "the saved keyframe scans at their saved poses, over its occupancy grid"),
    "trajectory": (scan_recording.FINAL_TRAJECTORY_COLOR, "every localized scan's pose in the map"),
    "scan playback": (scan_recording.SCAN_COLOR, "tab: the new scans up to the cursor on `scan`/`time` at "
                                                 "their poses when processed, robot trail (green)"),
}


def log_saved_map(recording: rr.RecordingStream, keyframe_scans: Sequence[FloatArray],
                  keyframe_poses: FloatArray) -> None:
    """Every saved keyframe scan at its saved pose, one static point cloud (thinned per keyframe)."""
    placed = [place(thin_scan(scan).astype(np.float64), pose)
              for scan, pose in zip(keyframe_scans, keyframe_poses, strict=True) if len(scan)]
    points = np.concatenate(placed) if placed else np.zeros((0, 2))
    recording.log(SAVED_MAP_ENTITY, rr.Points2D(points.astype(np.float32), colors=[MAP_COLOR],
                                                radii=[MAP_POINT_RADIUS], draw_order=MAP_DRAW_ORDER),
                  static=True)


MATCH_SERIES_2D = ("score", "inlier_fraction")
"""A laser match has two measures: the correlative score and the ICP inlier fraction."""


class MapLocalizationRecording(scan_recording.ScanReplayRecording):
    """`ScanReplayRecording` for a localization: the saved map under the new run (see the module
    docstring); `final(saved keyframe poses, localized poses, saved occupancy grid)`."""

    def __init__(self, recording: rr.RecordingStream, frontend: LocalizingLaserFrontend) -> None:
        super().__init__(recording, frontend)
        self._saved_scans = frontend.saved.keyframe_scans
        self._localizer = frontend

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: OccupancyGrid) -> None:
        log_saved_map(self._recording, self._saved_scans, planar_poses)
        log_occupancy(self._recording, map_export.image(), map_export.origin, map_export.resolution)
        scan_recording.log_final_trajectory(self._recording, estimates)
        log_legend(self._recording, rows=LEGEND_ROWS, note="")
        bounds = placed_bounds(self._saved_scans, planar_poses, estimates)
        send_match_quality(self._recording, self._localizer.localizations, MATCH_SERIES_2D)
        send_blueprint(self._recording, default_blueprint(
            bounds=bounds, extra_tabs=scan_recording.playback_views(bounds),
            excluded=scan_recording.PLAYBACK_ENTITIES, timeline=scan_recording.SCAN_TIMELINE,
            side=[rrb.TimeSeriesView(origin=MATCH_QUALITY_ENTITY, name="match quality per scan")]))
