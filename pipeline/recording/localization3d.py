"""The recording of a localization in a saved 3D map (`replay CLOUDLOG --map SESSION`).

- `world3d/saved_map` (static): the saved keyframe clouds at their saved poses, one point per voxel;
- `world3d/final_trajectory` (static): every localized cloud's position, a line in the map;
- `world3d/robot` on `scan`: the base's axes at each cloud placed when processed;
- `localization/inlier_fraction` on `scan`: how well each matched cloud fit the saved map, the share of its
  points near the map after registration (`pipeline.recording.localization.send_match_quality`; a cloud's
  score is that same fraction, so it is drawn once).
Nothing is optimized: there is no `iteration` timeline and no χ² plot.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from frontends.logs import Cloud3D
from frontends.slam3d import CloudEstimate
from frontends.slam3d.session_frontends import LocalizingLidarFrontend
from pipeline.recording import LEGEND_ENTITY, MAP_COLOR, TRAJECTORY_COLOR, FloatArray
from pipeline.recording.clouds import KEYFRAME_AXIS_LENGTH, LINE_WIDTH, POINT_RADIUS, WORLD3D_ENTITY
from pipeline.recording.localization import MATCH_QUALITY_ENTITY, send_match_quality
from pipeline.recording.scans import SCAN_TIMELINE

SAVED_MAP3D_ENTITY = "world3d/saved_map"
FINAL_TRAJECTORY3D_ENTITY = "world3d/final_trajectory"
ROBOT3D_ENTITY = "world3d/robot"

LEGEND = "\n".join([
    "| colour | what |", "|---|---|",
    f"| saved map `#{MAP_COLOR[0]:02x}{MAP_COLOR[1]:02x}{MAP_COLOR[2]:02x}` | the saved keyframe clouds at "
    "their saved poses |",
    f"| trajectory `#{TRAJECTORY_COLOR[0]:02x}{TRAJECTORY_COLOR[1]:02x}{TRAJECTORY_COLOR[2]:02x}` | every "
    "localized cloud's position in the map; the axes on `scan` are the base at each cloud placed when "
    "processed |",
])


def localization3d_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin=WORLD3D_ENTITY, name="saved map and the new run (3D)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=MATCH_QUALITY_ENTITY, name="match quality per cloud"),
                rrb.TextDocumentView(origin=LEGEND_ENTITY, name="legend"),
                row_shares=[3, 1],
            ),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(timeline=SCAN_TIMELINE, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


class CloudLocalizationRecording:
    """The recording of a `LocalizingLidarFrontend` (`pipeline.replay_log.FrontendRecording`'s methods);
    `final(saved planar keyframe poses, localized 4×4 poses, saved map points)`."""

    with_map = False

    def __init__(self, recording: rr.RecordingStream, frontend: LocalizingLidarFrontend) -> None:
        self._recording = recording
        self._frontend = frontend
        recording.send_blueprint(localization3d_blueprint(), make_active=True, make_default=True)

    def measurement(self, measurement: Cloud3D, estimate: CloudEstimate) -> None:
        """Clouds placed when processed are recorded at once, after the run (`final`)."""

    def frontend_done(self) -> None:
        found = self._frontend.localizations
        placed = np.flatnonzero(found.localized)
        if len(placed) == 0:
            return
        poses = found.poses[placed]
        quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat().astype(np.float32)
        self._recording.log(ROBOT3D_ENTITY, rr.TransformAxes3D(KEYFRAME_AXIS_LENGTH), static=True)
        self._recording.send_columns(
            ROBOT3D_ENTITY, indexes=[rr.TimeColumn(SCAN_TIMELINE, sequence=placed.astype(np.int64))],
            columns=rr.Transform3D.columns(translation=poses[:, :3, 3].astype(np.float32),
                                           quaternion=quaternions))

    def iteration_sink(self) -> None:
        return None

    def keyframe_scans(self) -> None:
        return None

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: NDArray[Any]) -> None:
        self._recording.log(SAVED_MAP3D_ENTITY, rr.Points3D(np.asarray(map_export, dtype=np.float32),
                                                            colors=[MAP_COLOR], radii=[POINT_RADIUS]),
                            static=True)
        self._recording.log(FINAL_TRAJECTORY3D_ENTITY,
                            rr.LineStrips3D([np.asarray(estimates[:, :3, 3], dtype=np.float32)],
                                            colors=[TRAJECTORY_COLOR], radii=[LINE_WIDTH]), static=True)
        self._recording.log(LEGEND_ENTITY, rr.TextDocument(LEGEND, media_type=rr.MediaType.MARKDOWN),
                            static=True)
        send_match_quality(self._recording, self._frontend.localizations, ("inlier_fraction",))
