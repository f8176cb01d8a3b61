"""The 3D LiDAR frontends of a log replay that starts from a saved map (`replay CLOUDLOG --map SESSION`,
`replay CLOUDLOG --continue SESSION`), both reading the new log as `LidarFrontend` does (tf mount,
odometry prior, KISS-ICP).

- `ContinuingLidarFrontend`: `LidarFrontend` whose SLAM is `ResumedLidarSlam3D` on the saved keyframe
  graph; the replay then optimizes the joint graph like any other, and every cloud of the session, old
  and new, gets its pose (`stamps_ns`, `estimates`).
- `LocalizingLidarFrontend`: every cloud goes to a `CloudLocalizer` over the saved keyframes; the saved
  map is never changed and nothing is optimized. Clouds never placed in the map have no pose: they are
  counted (`CloudLocalizations`), never given a made-up one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError, MapPlacementError
from frontends.logs import LogReader
from frontends.protocol import (
    FloatArray,
    FrontendOptions,
    SavedMapLocalization,
    ScanLocalizations,
    checked_on_saved_path,
)
from frontends.saved_arrays import (
    SavedArraysError,
    checked,
    checked_edges,
    checked_graph,
    checked_keyframes,
    checked_members,
)
from frontends.slam3d import planar, se3
from frontends.slam3d.config import Slam3DConfig
from frontends.slam3d.frontend import MAP_VOXEL, LidarFrontend
from frontends.slam3d.localization import (
    CloudLocalizationConfig,
    CloudLocalizer,
    LocalizedCloud,
    require_clouds,
)
from frontends.slam3d.odometry import OdometryStep, downsample
from frontends.slam3d.resume import ResumedLidarSlam3D, SavedGraph3D
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph
from optimizer.graph import PoseGraph, not_positive_definite

__all__ = ["CloudLocalizations", "ContinuingLidarFrontend", "LocalizingLidarFrontend", "SavedMap3D"]


CLOUD_SESSION_ARRAYS = ("keyframe_poses", "keyframe_stamps_ns", "edge_from", "edge_to", "relative",
                        "information", "is_loop", "cloud_stamps_ns", "cloud_keyframes", "cloud_offsets")
"""The arrays a 3D point-cloud session must hold (`LidarFrontend.session_content`; it also writes
`keyframe_planar_poses` and, since the sessions that continue, `sensor_to_base`, the LiDAR's mount, which
older files lack)."""


@dataclass(frozen=True, eq=False)
class SavedMap3D:
    """A saved 3D keyframe map: what a session file gives the frontends."""

    graph: SavedGraph3D
    sensor_to_base: FloatArray | None = None
    """The saved run's LiDAR mount (None: the session did not record it)."""

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, NDArray[Any]],
                    keyframe_points: Sequence[NDArray[Any]]) -> SavedMap3D:
        """The map a session's arrays hold (`LidarFrontend.session_content`'s), checked for consistency:
        `SavedArraysError` naming the array that is missing or does not fit the others."""
        poses, clouds = checked_keyframes(arrays, keyframe_points, CLOUD_SESSION_ARRAYS, (4, 4), 3, "clouds")
        keyframes = len(poses)
        if keyframes == 0:
            raise SavedArraysError("damaged session file (no keyframes)")
        edge_from, edge_to = checked_edges(arrays, keyframes)
        edges = len(edge_from)
        stamps, cloud_keyframes = checked_members(arrays, "cloud", keyframes)
        mount = checked("sensor_to_base", arrays, (4, 4), np.floating) if "sensor_to_base" in arrays else None
        information = checked("information", arrays, (edges, 6, 6), np.floating)
        # (the planar graph checks its own, projected from these: a singular one cannot be projected)
        bad = not_positive_definite(information)
        if bad.any():
            first = int(np.argmax(bad))
            raise SavedArraysError(f"damaged session file (constraint {first} ({edge_from[first]} → "
                                   f"{edge_to[first]}): its information matrix is not symmetric positive "
                                   "definite)")
        graph = SavedGraph3D(
            clouds, poses,
            checked("keyframe_stamps_ns", arrays, (keyframes,), np.integer).astype(np.int64),
            edge_from.astype(np.int64), edge_to.astype(np.int64),
            checked("relative", arrays, (edges, 4, 4), np.floating),
            information,
            checked("is_loop", arrays, (edges,), np.bool_),
            stamps.astype(np.int64), cloud_keyframes.astype(np.int64),
            checked("cloud_offsets", arrays, (len(stamps), 4, 4), np.floating))
        saved = cls(graph, mount)
        checked_graph(saved.planar_graph)
        return saved

    @property
    def keyframe_poses(self) -> FloatArray:
        """(K, 3) the keyframes' planar poses (as `SavedMap2D.keyframe_poses`: what the replay reports)."""
        return planar.planar(self.graph.keyframe_poses)

    def planar_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        g = self.graph
        return planar.project_graph(g.keyframe_poses, g.edge_from, g.edge_to, g.relative, g.information,
                                    planar_poses)

    def map_points(self, planar_poses: FloatArray, voxel: float) -> NDArray[np.float32]:
        """(P, 3) the keyframe clouds at the planar poses lifted with their saved height, roll and pitch."""
        poses = planar.lift(planar_poses, self.graph.keyframe_poses)
        placed = [se3.transform_points(pose, cloud) for pose, cloud in zip(poses, self.graph.keyframe_clouds,
                                                                             strict=True)]
        return downsample(np.concatenate(placed), voxel).astype(np.float32)


class ContinuingLidarFrontend(LidarFrontend):
    """Mapping continued from a saved map: see the module docstring and `frontends.slam3d.resume`."""

    def __init__(self, log: LogReader, topic: str, saved: SavedMap3D, config: Slam3DConfig | None = None,
                 options: FrontendOptions | None = None,
                 localization: CloudLocalizationConfig | None = None) -> None:
        require_clouds(saved.graph.keyframe_clouds)  # now, not at the first cloud: before the log is read
        super().__init__(log, topic, config, options)
        self.saved = saved
        self._localization = localization
        self._resumed: ResumedLidarSlam3D | None = None

    def _make_slam(self, sensor_to_base: FloatArray) -> LidarSlam3D:
        self._resumed = ResumedLidarSlam3D(self.saved.graph, self.config, sensor_to_base=sensor_to_base,
                                           localization=self._localization)
        return self._resumed

    def counts(self) -> dict[str, int]:
        """`LidarFrontend.counts` (its keyframes and constraints those of the joint graph) and what the
        session added: its keyframes and clouds, the new clouds left out (before any registered one),
        and the constraints tying new keyframes to old ones (the placement's included). The names are
        the 2D ones (`session_scans`: the session's clouds)."""
        assert self._resumed is not None
        result = self.result
        old = len(self.saved.graph.keyframe_poses)
        crossing = ((result.edge_from < old) != (result.edge_to < old)) & result.is_loop
        return {**super().counts(), "session_keyframes": old,
                "session_scans": len(self.saved.graph.cloud_stamps_ns),
                "scans_unplaced": self._resumed.clouds_unplaced, "loop_closures_old_new": int(crossing.sum())}

    def placement(self) -> dict[str, Any]:
        """Where the new run joined the saved map: the new log's cloud (index, stamp) placed by global
        localization, its planar pose and match quality."""
        found = None if self._resumed is None else self._resumed.placement
        if found is None:
            return {}
        return {"scan": found.index, "stamp_ns": found.stamp_ns, "pose": planar.planar(found.pose).tolist(),
                "saved_keyframe": found.anchor, "score": found.score,
                "inlier_fraction": found.inlier_fraction, "rms_m": found.rms}


@dataclass(frozen=True, eq=False)
class CloudLocalizations(ScanLocalizations):
    """How every cloud of a localized log ended, in log order (`ScanLocalizations`' fields; `poses` are
    (S, 4, 4), NaN for a cloud never placed; `score` is the fit's inlier fraction)."""


class _LocalizingSlam3D(LidarSlam3D):
    """The odometry of `LidarSlam3D` (registration, mount) feeding a `CloudLocalizer`: no keyframes."""

    def __init__(self, localizer: CloudLocalizer, config: Slam3DConfig, sensor_to_base: FloatArray) -> None:
        super().__init__(config, sensor_to_base=sensor_to_base)
        self.localizer = localizer
        self.found: list[LocalizedCloud] = []
        self._last_odometry: FloatArray | None = None

    def _add_step(self, index: int, stamp_ns: int, step: OdometryStep | None) -> CloudEstimate:
        if step is None:  # as in the SLAM, a cloud the odometry could not register keeps the last pose
            self._untracked += 1
            found = self.localizer.localize(index, stamp_ns, self._last_odometry, np.zeros((0, 3)))
        else:
            self._last_odometry = self._base_pose(step)
            found = self.localizer.localize(index, stamp_ns, self._last_odometry, self._keyframe_points(step))
        self.found.append(found)
        return CloudEstimate(index, stamp_ns, found.pose.copy(), found.matched, -1, ())


class LocalizingLidarFrontend(SavedMapLocalization[CloudLocalizations], LidarFrontend):
    """Localization only in a saved map: see the module docstring and `frontends.slam3d.localization`.

    After `finish`, `localizations` says how every cloud ended, `stamps_ns` / `localized_poses` are the
    clouds with a pose, and `keyframe_graph` / `map_export` are the saved map's, unchanged."""

    def __init__(self, log: LogReader, topic: str, saved: SavedMap3D, config: Slam3DConfig | None = None,
                 options: FrontendOptions | None = None, *, initial_pose: Sequence[float] | None = None,
                 localization: CloudLocalizationConfig | None = None) -> None:
        super().__init__(log, topic, config, options)
        self.saved = saved
        self.initial_pose = None if initial_pose is None else tuple(float(v) for v in initial_pose)
        self._localizer = CloudLocalizer(saved.graph.keyframe_clouds, saved.graph.keyframe_poses, self.config,
                                         localization, initial_pose=self.initial_pose)
        self._tracker: _LocalizingSlam3D | None = None
        self._localizations: CloudLocalizations | None = None
        self._on_path = (0, 0)
        """Clouds placed on the saved run's path, and how many of them did not match the saved map."""

    def _make_slam(self, sensor_to_base: FloatArray) -> LidarSlam3D:
        self._tracker = _LocalizingSlam3D(self._localizer, self.config, sensor_to_base)
        return self._tracker

    def finish(self) -> None:
        """Raises `MapPlacementError` when no cloud could be placed in the saved map."""
        if self._tracker is None:
            raise FrontendError(f"{self._log.path}: topic {self._topic} has no point clouds")
        rows = self._tracker.found
        poses = np.array([found.pose for found in rows]).reshape(-1, 4, 4)
        recovered = np.zeros(len(rows), dtype=bool)
        fixes = []
        for found in rows:
            if found.global_fix:
                fixes.append(found.index)
                poses[found.recovered_indices] = found.recovered_poses
                recovered[found.recovered_indices] = True
        localized = np.array([found.localized for found in rows], dtype=bool)
        matched = np.array([found.matched for found in rows], dtype=bool)
        self._localizations = CloudLocalizations(
            np.array([found.stamp_ns for found in rows], dtype=np.int64), poses, localized, matched,
            recovered & ~localized,
            np.array([found.score for found in rows], dtype=np.float64),
            np.array([found.inlier_fraction for found in rows], dtype=np.float64),
            np.array([found.rms for found in rows], dtype=np.float64), np.array(fixes, dtype=np.int64))
        if not self._localizations.has_pose.any():
            raise MapPlacementError(
                f"none of the {len(rows)} clouds of {self._log.path} could be placed in the saved map of "
                f"{len(self.saved.graph.keyframe_poses)} keyframes: no unambiguous match"
                + ("" if self.initial_pose is not None else " (an --initial-pose x,y,yaw may help)"))
        self._on_path = checked_on_saved_path(self._log.path, "clouds", poses[localized, :2, 3],
                                              matched[localized], self.saved.graph.keyframe_poses[:, :2, 3])

    @property
    def result(self) -> Slam3DGraph:
        raise FrontendError("a localization in a saved map makes no keyframe graph of its own")

    def keyframe_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        return self.saved.planar_graph(planar_poses)

    def map_export(self, planar_poses: FloatArray) -> NDArray[np.float32]:
        return self.saved.map_points(planar_poses, MAP_VOXEL)

    def counts(self) -> dict[str, int]:
        found = self.localizations
        return {"clouds": len(found.stamps_ns), **self._log.counts,
                "map_keyframes": len(self.saved.graph.keyframe_poses), **found.counts(),
                "scans_on_saved_path": self._on_path[0], "scans_on_saved_path_unmatched": self._on_path[1]}

    def loop_closures(self) -> dict[str, Any]:
        return {"accepted": 0, "rejected": 0, "candidates": {"accepted": 0, "unconfirmed": 0}}
