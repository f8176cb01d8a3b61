"""The 3D part of a point-cloud replay's recording (rerun is imported only under `pipeline.recording`).

Layout, beside the 2D pose graph of `pipeline.recording` (`world/…`, the SE(2) poses the backend
optimizes, and the χ² plots):
- `world3d/keyframes/kNNNNNN`: each keyframe's cloud (downsampled), static, in the keyframe's own frame,
  with the keyframe's pose as a Transform3D on the `iteration` timeline: the clouds move into place as the
  graph converges;
- `world3d/trajectory` on `iteration`: the 3D keyframe trajectory after every iteration;
- `world3d/initial_trajectory` (static) and `world3d/map` (static): the starting trajectory and the final
  map (all keyframe clouds at their optimized poses, one point per voxel; off by default in the
  blueprint: the keyframe clouds are that map already, and they move);
- each keyframe entity also draws its axes (`TransformAxes3D`).

The blueprint shows the 3D scene beside the 2D graph and the χ² plots, with the time panel on `iteration`.

`CloudLocalizationRecording` is the recording of a localization in a saved 3D map (`replay CLOUDLOG --map
SESSION`, see its docstring).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from frontends.logs import Cloud3D
from frontends.slam3d import CloudEstimate, LidarFrontend, Slam3DGraph, downsample
from frontends.slam3d.session_frontends import LocalizingLidarFrontend
from optimizer.iteration import Iteration
from pipeline.recording import (
    INITIAL_TRAJECTORY_COLOR,
    ITERATION_TIMELINE,
    MAP_COLOR,
    MATCH_QUALITY_ENTITY,
    SCAN_TIMELINE,
    TRAJECTORY_COLOR,
    Bounds,
    FloatArray,
    PoseBatches,
    chi2_views,
    layout,
    log_legend,
    map_view,
    send_blueprint,
    send_match_quality,
    transform3d_columns,
    ui_points,
    world_bounds,
)

WORLD3D_ENTITY = "world3d"
KEYFRAMES_ENTITY = "world3d/keyframes"
TRAJECTORY3D_ENTITY = "world3d/trajectory"
INITIAL_TRAJECTORY3D_ENTITY = "world3d/initial_trajectory"
MAP3D_ENTITY = "world3d/map"

MAP3D_COLOR = (60, 60, 60, 255)
POINT_RADIUS = ui_points(1.5)
LINE_WIDTH = ui_points(2.0)
RECORDING_KEYFRAME_VOXEL = 0.5
"""Keyframe clouds in the recording are thinned to this voxel (m): hundreds of them stay light to view."""
KEYFRAME_AXIS_LENGTH = 1.5
"""Length (m) of the axes drawn at every keyframe pose."""


def keyframe_entity(index: int) -> str:
    return f"{KEYFRAMES_ENTITY}/k{index:06d}"


def cloud_blueprint(bounds: Bounds | None = None) -> rrb.Blueprint:
    """The 3D scene (the static final map off by default: the keyframe clouds already are the map, moving
    with the iterations), the planar pose graph (y up, framing `bounds` once the final poses are known),
    χ² on a log scale, the stage log and the legend; the time panel on `iteration`."""
    scene = rrb.Spatial3DView(origin=WORLD3D_ENTITY, name="keyframes and map (3D)",
                              overrides={f"/{MAP3D_ENTITY}": rrb.EntityBehavior(visible=False)})
    return layout(scene, [map_view(bounds=bounds), *chi2_views()], row_shares=[3, 2, 2, 1],
                  column_shares=[3, 2])


def _colour(index: int, count: int) -> tuple[int, int, int, int]:
    """Keyframes coloured along the drive (a hue wheel), so that a loop's two passes are told apart."""
    hue = index / max(count, 1)
    r, g, b = (np.clip(np.abs((hue * 6.0 + shift) % 6.0 - 3.0) - 1.0, 0.0, 1.0) for shift in (0.0, 4.0, 2.0))
    return int(60 + 180 * r), int(60 + 180 * g), int(60 + 180 * b), 255


def log_keyframe_clouds(recording: rr.RecordingStream, clouds: Sequence[NDArray[np.floating]]) -> None:
    """Each keyframe's cloud, static, in its keyframe's frame (its pose comes per iteration), with the
    keyframe's axes, so the poses the optimizer moves stand out of the clouds."""
    for index, points in enumerate(clouds):
        recording.log(
            keyframe_entity(index),
            rr.Points3D(
                np.asarray(points, dtype=np.float32),
                colors=[_colour(index, len(clouds))],
                radii=[POINT_RADIUS],
            ),
            rr.TransformAxes3D(KEYFRAME_AXIS_LENGTH),
            static=True,
        )


def log_initial_trajectory3d(recording: rr.RecordingStream, poses: FloatArray) -> None:
    """The starting 3D keyframe trajectory, static and faint; `poses` (K, 4, 4)."""
    log_static_trajectory3d(recording, INITIAL_TRAJECTORY3D_ENTITY, poses, INITIAL_TRAJECTORY_COLOR)
    recording.log(
        TRAJECTORY3D_ENTITY,
        rr.LineStrips3D.from_fields(colors=[TRAJECTORY_COLOR], radii=[LINE_WIDTH]),
        static=True,
    )


def log_static_trajectory3d(recording: rr.RecordingStream, entity: str, poses: FloatArray,
                            color: tuple[int, ...]) -> None:
    """A static line through the positions of (K, 4, 4) `poses`."""
    recording.log(entity, rr.LineStrips3D([np.asarray(poses[:, :3, 3], dtype=np.float32)], colors=[color],
                                          radii=[LINE_WIDTH]), static=True)


def log_map(recording: rr.RecordingStream, points: NDArray[np.floating], *, entity: str = MAP3D_ENTITY,
            color: tuple[int, ...] = MAP3D_COLOR) -> None:
    """A map, static: by default the final one."""
    recording.log(entity, rr.Points3D(np.asarray(points, dtype=np.float32), colors=[color],
                                      radii=[POINT_RADIUS]), static=True)


def transform_columns(poses: FloatArray) -> list[rr.ComponentColumn]:
    """`Transform3D` columns of (T, 4, 4) poses, the rotations as quaternions: rerun converts a column of
    3×3 matrices one Python object at a time."""
    return keyframe_transform_columns(poses[:, None])[0]


def keyframe_transform_columns(poses: NDArray[np.floating]) -> list[list[rr.ComponentColumn]]:
    """For each keyframe k, the `Transform3D` columns (translation, quaternion) of (T, K, 4, 4) poses[:, k]:
    what `rr.Transform3D.columns(translation=…, quaternion=…)` makes, with the quaternions of all keyframes
    found in one call and the component columns built directly (`Transform3D.columns` validates every field
    of the archetype, once per keyframe: a third of the cost of recording a town loop's iterations)."""
    count, keyframes = poses.shape[:2]
    rotations = np.asarray(poses[..., :3, :3], dtype=np.float64).reshape(-1, 3, 3)
    # The rotations are lifted from planar poses and odometry's roll and pitch, orthonormal to float32's
    # precision: scipy's projection onto the nearest rotation (an SVD per matrix) changes the quaternions by
    # one float32 ulp at most and cost 0.3 s per 65 000 matrices (a town loop's iterations × keyframes).
    quaternions = Rotation.from_matrix(rotations, assume_valid=True).as_quat().astype(np.float32)  # x,y,z,w
    quaternions = quaternions.reshape(count, keyframes, 4)
    translations = np.asarray(poses[..., :3, 3], dtype=np.float32)
    return [transform3d_columns(translations[:, k], quaternions[:, k]) for k in range(keyframes)]


class KeyframePoseRecorder(PoseBatches):
    """Logs the 3D keyframe poses of every iteration (the planar poses lifted by `graph`: height, roll and
    pitch from odometry): one Transform3D per keyframe entity and the 3D trajectory, on `iteration`, in
    column batches."""

    def __init__(self, recording: rr.RecordingStream, graph: Slam3DGraph) -> None:
        super().__init__(recording)
        self._graph = graph

    def _keyframe_poses(self, iteration: Iteration) -> FloatArray:
        return self._graph.lift(iteration.poses)

    def _send_batch(self, steps: NDArray[np.int64], poses: NDArray[np.float32], *, final: bool) -> None:
        """(T, K, 4, 4) poses of the iterations at `steps`."""
        index = rr.TimeColumn(ITERATION_TIMELINE, sequence=steps)
        for keyframe, columns in enumerate(keyframe_transform_columns(poses)):
            self._recording.send_columns(keyframe_entity(keyframe), indexes=[index], columns=columns)
        self._recording.send_columns(
            TRAJECTORY3D_ENTITY,
            indexes=[index],
            columns=rr.LineStrips3D.columns(strips=[trajectory[:, :3, 3] for trajectory in poses]),
        )


class CloudReplayRecording:
    """The 3D part of a log replay's recording (`pipeline.replay_log.FrontendRecording`): keyframe clouds
    that move into place as the planar graph converges (height, roll and pitch from odometry), the map."""

    with_map = False

    def __init__(self, recording: rr.RecordingStream, frontend: LidarFrontend) -> None:
        self._recording = recording
        self._frontend = frontend
        send_blueprint(recording, self.blueprint())

    def blueprint(self) -> rrb.Blueprint:
        return cloud_blueprint()

    def measurement(self, measurement: Cloud3D, estimate: CloudEstimate) -> None:
        """Clouds are recorded after the run, all at once (per keyframe once the graph is known)."""

    def frontend_done(self) -> None:
        result = self._frontend.result
        clouds = [downsample(cloud, RECORDING_KEYFRAME_VOXEL) for cloud in result.keyframe_clouds]
        log_keyframe_clouds(self._recording, clouds)
        log_initial_trajectory3d(self._recording, result.keyframe_odometry)

    def iteration_sink(self) -> KeyframePoseRecorder:
        return KeyframePoseRecorder(self._recording, self._frontend.result)

    def keyframe_scans(self) -> None:
        return None  # the clouds are recorded by the iteration sink, moving with their keyframes

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: NDArray[Any]) -> None:
        log_map(self._recording, map_export)
        send_blueprint(self._recording, cloud_blueprint(world_bounds(planar_poses)))


SAVED_MAP3D_ENTITY = "world3d/saved_map"
FINAL_TRAJECTORY3D_ENTITY = "world3d/final_trajectory"
ROBOT3D_ENTITY = "world3d/robot"

LOCALIZATION_LEGEND_ROWS = {
    "saved map": (MAP_COLOR, "the saved keyframe clouds at their saved poses"),
    "trajectory": (TRAJECTORY_COLOR, "every localized cloud's position in the map; the axes on `scan` are "
                                     "the base at each cloud placed when processed"),
}


class CloudLocalizationRecording(CloudReplayRecording):
    """`CloudReplayRecording` for a localization in a saved 3D map (a `pipeline.replay_log.
    FrontendRecording`): the saved map under the new run; `final(saved planar keyframe poses, localized
    4×4 poses, saved map points)`.

    - `world3d/saved_map` (static): the saved keyframe clouds at their saved poses, one point per voxel;
    - `world3d/final_trajectory` (static): every localized cloud's position, a line in the map;
    - `world3d/robot` on `scan`: the base's axes at each cloud placed when processed;
    - `localization/inlier_fraction` on `scan`: how well each matched cloud fit the saved map, the share of
      its points near the map after registration (`pipeline.recording.send_match_quality`; a cloud's
      score is that same fraction, so it is drawn once).
    Nothing is optimized: there is no `iteration` timeline and no χ² plot.
    """

    _frontend: LocalizingLidarFrontend

    def blueprint(self) -> rrb.Blueprint:
        scene = rrb.Spatial3DView(origin=WORLD3D_ENTITY, name="saved map and the new run (3D)")
        match_quality = rrb.TimeSeriesView(origin=MATCH_QUALITY_ENTITY, name="match quality per cloud")
        return layout(scene, [match_quality], row_shares=[3, 1], timeline=SCAN_TIMELINE, play_state=None)

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
        log_map(self._recording, map_export, entity=SAVED_MAP3D_ENTITY, color=MAP_COLOR)
        log_static_trajectory3d(self._recording, FINAL_TRAJECTORY3D_ENTITY, estimates, TRAJECTORY_COLOR)
        log_legend(self._recording, rows=LOCALIZATION_LEGEND_ROWS, note="")
        send_match_quality(self._recording, self._frontend.localizations, ("inlier_fraction",))
