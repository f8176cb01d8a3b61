"""The recording of a localization in a saved 3D map (`replay CLOUDLOG --map SESSION`).

- `world3d/saved_map` (static): the saved keyframe clouds at their saved poses, one point per voxel;
- `world3d/final_trajectory` (static): every localized cloud's position, a line in the map;
- `world3d/robot` on `scan`: the base's axes at each cloud placed when processed;
- `localization/inlier_fraction` on `scan`: how well each matched cloud fit the saved map, the share of its
  points near the map after registration (`pipeline.recording.send_match_quality`; a cloud's
  score is that same fraction, so it is drawn once).
Nothing is optimized: there is no `iteration` timeline and no χ² plot.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray

from frontends.slam3d.session_frontends import LocalizingLidarFrontend
from pipeline.recording import (
    MAP_COLOR,
    MATCH_QUALITY_ENTITY,
    SCAN_TIMELINE,
    TRAJECTORY_COLOR,
    FloatArray,
    layout,
    log_legend,
    send_match_quality,
)
from pipeline.recording.clouds import (
    KEYFRAME_AXIS_LENGTH,
    LINE_WIDTH,
    POINT_RADIUS,
    WORLD3D_ENTITY,
    CloudReplayRecording,
    transform_columns,
)

SAVED_MAP3D_ENTITY = "world3d/saved_map"
FINAL_TRAJECTORY3D_ENTITY = "world3d/final_trajectory"
ROBOT3D_ENTITY = "world3d/robot"

LEGEND_ROWS = {
    "saved map": (MAP_COLOR, "the saved keyframe clouds at their saved poses"),
    "trajectory": (TRAJECTORY_COLOR, "every localized cloud's position in the map; the axes on `scan` are "
                                     "the base at each cloud placed when processed"),
}


def localization3d_blueprint() -> rrb.Blueprint:
    scene = rrb.Spatial3DView(origin=WORLD3D_ENTITY, name="saved map and the new run (3D)")
    return layout(scene, [rrb.TimeSeriesView(origin=MATCH_QUALITY_ENTITY, name="match quality per cloud")],
                  row_shares=[3, 1], timeline=SCAN_TIMELINE, play_state=None)


class CloudLocalizationRecording(CloudReplayRecording):
    """`CloudReplayRecording` for a localization (a `pipeline.replay_log.MeasurementRecording`): the saved
    map under the new run; `final(saved planar keyframe poses, localized 4×4 poses, saved map points)`."""

    _frontend: LocalizingLidarFrontend  # type: ignore[assignment]

    def blueprint(self) -> rrb.Blueprint:
        return localization3d_blueprint()

    def frontend_done(self) -> None:
        found = self._frontend.localizations
        placed = np.flatnonzero(found.localized)
        if len(placed) == 0:
            return
        self._recording.log(ROBOT3D_ENTITY, rr.TransformAxes3D(KEYFRAME_AXIS_LENGTH), static=True)
        self._recording.send_columns(
            ROBOT3D_ENTITY, indexes=[rr.TimeColumn(SCAN_TIMELINE, sequence=placed.astype(np.int64))],
            columns=transform_columns(found.poses[placed]))

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: NDArray[Any]) -> None:
        self._recording.log(SAVED_MAP3D_ENTITY, rr.Points3D(np.asarray(map_export, dtype=np.float32),
                                                            colors=[MAP_COLOR], radii=[POINT_RADIUS]),
                            static=True)
        self._recording.log(FINAL_TRAJECTORY3D_ENTITY,
                            rr.LineStrips3D([np.asarray(estimates[:, :3, 3], dtype=np.float32)],
                                            colors=[TRAJECTORY_COLOR], radii=[LINE_WIDTH]), static=True)
        log_legend(self._recording, rows=LEGEND_ROWS, note="")
        send_match_quality(self._recording, self._frontend.localizations, ("inlier_fraction",))
