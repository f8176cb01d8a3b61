"""Localization in a saved 3D keyframe map: the new run's clouds are registered against a map that never
changes.

The new run is tracked by its own KISS-ICP odometry (`LidarSlam3D`'s registration); the map ← odometry
transform ties it to the saved map.

- Tracking: each cloud, placed at its prediction (the map ← odometry transform times its odometry pose),
  is registered by GICP (small_gicp) onto the saved keyframe clouds nearest it (the target is rebuilt
  when the estimate has moved `retarget_distance` from where it was built). A fit with enough inliers, a
  small surface residual and a correction below `max_correction_*` is a match: the transform follows it.
  Otherwise the cloud keeps its prediction (odometry carries the pose) for at most `max_dead_reckoning`
  metres since the last match; beyond that the run is lost.
- Global localization (no start pose, or lost): at every `global_every` metres, the cloud's Scan Context
  descriptor is compared with every saved keyframe's, and the nearest few are verified as the SLAM
  verifies loop closures (GICP onto the candidate's submap from the descriptor's heading, then the
  ambiguity test, `loop_closure.verify_loop`). The best verified match places the run; the clouds tracked
  meanwhile get their map poses back through the same transform (`recovered_*`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from frontends.errors import EmptySavedMapError
from frontends.protocol import FloatArray, IntArray, LocalizedMeasurement
from frontends.slam3d import planar, se3
from frontends.slam3d.config import Slam3DConfig
from frontends.slam3d.loop_closure import (
    RegistrationTarget,
    descriptor_distances,
    prepare_source,
    verify_loop,
)
from frontends.slam3d.slam import keyframe_descriptor
from optimizer import se2

SUBMAP_CACHE = 32
"""Registration targets of global localization kept for reuse (the most recently used)."""


@dataclass(frozen=True)
class CloudLocalizationConfig:
    target_keyframes: int = 12
    """The tracking target holds this many saved keyframe clouds, the nearest to the estimate …"""
    target_max_distance: float = 40.0
    """… within this distance of it (m)."""
    retarget_distance: float = 3.0
    """The target is rebuilt once the estimate is this far (m) from where it was built."""
    min_inlier_fraction: float = 0.5
    """A tracking fit needs this share of the cloud's points near the map …"""
    max_rms: float = 0.15
    """… an inlier residual (point to plane, m) below this …"""
    max_correction_linear: float = 1.0
    max_correction_angular: float = np.radians(5.0)
    """… and to move the prediction less than this (m, rad): farther is a slip onto another surface."""
    max_dead_reckoning: float = 30.0
    """Without a match for this many metres the run is lost: global localization again."""
    global_every: float = 2.0
    """A global localization is tried at every this many metres driven while not localized."""
    global_candidates: int = 3
    """Saved keyframes (the nearest descriptors, apart from each other) verified per attempt."""
    descriptor_max_distance: float = 0.5


@dataclass(frozen=True, eq=False)
class LocalizedCloud(LocalizedMeasurement):
    """A cloud's `LocalizedMeasurement`: `pose` is the base's 4×4 pose; `score` is the fit's inlier fraction
    (3D has no correlative score); `rms` the inlier residual of the fit."""

    global_fix: bool = False
    anchor: int = -1
    """With a global fix: the saved keyframe it matched, `relative` the cloud's pose in its frame and
    `information` (6×6) that of the match (the constraint a resumed SLAM adds)."""
    relative: FloatArray = field(default_factory=lambda: np.eye(4))
    information: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))
    recovered_indices: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """Clouds processed while not localized whose map poses this global fix gives back …"""
    recovered_poses: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """… and those poses (M, 4, 4)."""


class EmptyCloudMapError(EmptySavedMapError):
    """A saved map to localize in has no keyframe cloud."""


def require_clouds(keyframe_clouds: Sequence[NDArray[np.floating]]) -> None:
    """Raise `EmptyCloudMapError` unless some keyframe cloud holds a point."""
    if not any(len(cloud) for cloud in keyframe_clouds):
        raise EmptyCloudMapError("the saved map has no keyframe cloud to localize in")


class CloudLocalizer:
    """Feed the new run's clouds in order with `localize`; see the module docstring.

    `keyframe_clouds` (points in each keyframe's base frame) at 4×4 `keyframe_poses` are the saved map;
    `initial_pose` (x, y, yaw) where the run's first cloud is, else found by global localization."""

    def __init__(self, keyframe_clouds: Sequence[NDArray[np.floating]], keyframe_poses: FloatArray,
                 config: Slam3DConfig, settings: CloudLocalizationConfig | None = None, *,
                 initial_pose: Sequence[float] | None = None) -> None:
        require_clouds(keyframe_clouds)
        self.config = config
        self.settings = settings or CloudLocalizationConfig()
        self._clouds = [np.asarray(cloud, dtype=np.float64) for cloud in keyframe_clouds]
        self._poses = np.asarray(keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
        loop = config.loop_closure
        self._descriptors = np.array([keyframe_descriptor(pose, cloud, loop)
                                      for pose, cloud in zip(self._poses, self._clouds, strict=True)])
        self._initial_pose = None if initial_pose is None else np.asarray(initial_pose, dtype=np.float64)
        self._map_from_odometry: FloatArray | None = None
        self._target: RegistrationTarget | None = None
        self._target_centre = np.full(2, np.inf)
        self._last_match_odometry: FloatArray | None = None
        self._lost: list[tuple[int, FloatArray]] = []
        """(index, odometry pose) of clouds processed since the run was last localized."""
        self._last_attempt: FloatArray | None = None
        self._submaps: dict[int, RegistrationTarget] = {}

    @property
    def localized(self) -> bool:
        return self._map_from_odometry is not None

    def localize(self, index: int, stamp_ns: int, odometry_pose: FloatArray | None,
                 points: FloatArray) -> LocalizedCloud:
        """One cloud: its base pose in the run's odometry frame (None: the odometry could not register it)
        and its points in the base frame."""
        if odometry_pose is None:
            return self._unmatched(index, stamp_ns, None)
        if self._map_from_odometry is None and self._initial_pose is not None:
            self._map_from_odometry = self._start(odometry_pose)
            self._last_match_odometry = odometry_pose
        if self._map_from_odometry is None:
            return self._search(index, stamp_ns, odometry_pose, points)
        found = self._track(index, stamp_ns, odometry_pose, points)
        if found is not None:
            return found
        assert self._last_match_odometry is not None
        driven = float(np.linalg.norm(odometry_pose[:2, 3] - self._last_match_odometry[:2, 3]))
        if driven > self.settings.max_dead_reckoning:
            self._map_from_odometry = None
            self._lost = []
            self._last_attempt = None
            return self._search(index, stamp_ns, odometry_pose, points)
        return self._unmatched(index, stamp_ns, odometry_pose)

    def _start(self, odometry_pose: FloatArray) -> FloatArray:
        """The map ← odometry transform of the initial pose: its height that of the nearest keyframe."""
        assert self._initial_pose is not None
        nearest = int(np.argmin(np.hypot(*(self._poses[:, :2, 3] - self._initial_pose[:2]).T)))
        start = planar.lift(self._initial_pose, planar.level(self._poses[nearest]))
        return start @ se3.inverse(planar.level(odometry_pose))

    def _unmatched(self, index: int, stamp_ns: int, odometry_pose: FloatArray | None) -> LocalizedCloud:
        if self._map_from_odometry is None or odometry_pose is None:
            if odometry_pose is not None:
                self._lost.append((index, odometry_pose))
            return LocalizedCloud(index, stamp_ns, np.full((4, 4), np.nan), False, False, np.nan, 0.0, np.inf)
        pose = self._map_from_odometry @ odometry_pose
        return LocalizedCloud(index, stamp_ns, pose, True, False, np.nan, 0.0, np.inf)

    # ------------------------------------------------------------------------------------------ tracking

    def _track(self, index: int, stamp_ns: int, odometry_pose: FloatArray,
               points: FloatArray) -> LocalizedCloud | None:
        assert self._map_from_odometry is not None
        settings = self.settings
        prediction = self._map_from_odometry @ odometry_pose
        target = self._target_near(prediction[:2, 3])
        if target is None:
            return None
        if len(points) == 0:
            return None
        source = prepare_source(points, self.config.loop_closure)
        if source.size() == 0:
            return None
        fit = target.register(source, prediction)
        correction = se3.relative(prediction, fit.transform)
        if (fit.inlier_fraction < settings.min_inlier_fraction or fit.rms > settings.max_rms
                or np.linalg.norm(correction[:3, 3]) > settings.max_correction_linear
                or se3.rotation_angle(correction) > settings.max_correction_angular):
            return None
        self._map_from_odometry = fit.transform @ se3.inverse(odometry_pose)
        self._last_match_odometry = odometry_pose
        return LocalizedCloud(index, stamp_ns, fit.transform, True, True, fit.inlier_fraction,
                              fit.inlier_fraction, fit.rms)

    def _target_near(self, position: FloatArray) -> RegistrationTarget | None:
        settings = self.settings
        moved = float(np.hypot(*(position - self._target_centre)))
        if self._target is not None and moved < settings.retarget_distance:
            return self._target
        distance = np.hypot(*(self._poses[:, :2, 3] - position).T)
        nearest = np.argsort(distance)[: settings.target_keyframes]
        nearest = nearest[distance[nearest] <= settings.target_max_distance]
        self._target_centre = position.copy()
        placed = [se3.transform_points(self._poses[k], self._clouds[k])
                  for k in nearest if len(self._clouds[k])]
        self._target = None if not placed else RegistrationTarget(np.concatenate(placed),
                                                                  self.config.loop_closure)
        return self._target

    # ------------------------------------------------------------------------------- global localization

    def _search(self, index: int, stamp_ns: int, odometry_pose: FloatArray,
                points: FloatArray) -> LocalizedCloud:
        settings = self.settings
        if self._last_attempt is not None and np.linalg.norm(
                odometry_pose[:2, 3] - self._last_attempt[:2, 3]) < settings.global_every:
            return self._unmatched(index, stamp_ns, odometry_pose)
        if len(points) == 0:
            return self._unmatched(index, stamp_ns, odometry_pose)
        self._last_attempt = odometry_pose
        loop = self.config.loop_closure
        query = keyframe_descriptor(odometry_pose, points, loop)
        distances, headings = descriptor_distances(query, self._descriptors)
        candidates: list[tuple[int, float]] = []
        for k in np.argsort(distances):
            if (distances[k] > settings.descriptor_max_distance
                    or len(candidates) >= settings.global_candidates):
                break
            if all(abs(int(k) - c) > loop.submap_keyframes for c, _ in candidates):
                candidates.append((int(k), float(headings[k])))
        best = None
        for anchor, heading in candidates:
            verdict = verify_loop(self._submap_target(anchor), points,
                                  [self._heading_guess(anchor, odometry_pose, heading)], loop)
            if verdict.match is not None and (best is None
                                              or verdict.match.inlier_fraction > best[1].inlier_fraction):
                best = (anchor, verdict.match)
        if best is None:
            return self._unmatched(index, stamp_ns, odometry_pose)
        anchor, match = best
        pose = self._poses[anchor] @ match.relative
        self._map_from_odometry = pose @ se3.inverse(odometry_pose)
        self._last_match_odometry = odometry_pose
        self._target = None
        lost, self._lost = self._lost, []
        recovered = np.array([self._map_from_odometry @ p for _, p in lost]).reshape(-1, 4, 4)
        return LocalizedCloud(index, stamp_ns, pose, True, True, match.inlier_fraction, match.inlier_fraction,
                              match.rms, global_fix=True, anchor=anchor, relative=match.relative,
                              information=match.information,
                              recovered_indices=np.array([i for i, _ in lost], dtype=np.int64),
                              recovered_poses=recovered)

    def _submap_target(self, anchor: int) -> RegistrationTarget:
        """The saved keyframes around `anchor` (by index, as the SLAM's loop closures), in its frame, made
        once: a run outside the map tries the same few look-alike places again and again."""
        target = self._submaps.pop(anchor, None)
        if target is None:
            reach = self.config.loop_closure.submap_keyframes
            around = range(max(0, anchor - reach), min(len(self._poses) - 1, anchor + reach) + 1)
            points = np.concatenate([se3.transform_points(se3.relative(self._poses[anchor], self._poses[k]),
                                                          self._clouds[k]) for k in around])
            target = RegistrationTarget(points, self.config.loop_closure)
        self._submaps[anchor] = target  # the most recently used last
        while len(self._submaps) > SUBMAP_CACHE:
            del self._submaps[next(iter(self._submaps))]
        return target

    def _heading_guess(self, anchor: int, odometry_pose: FloatArray, heading: float) -> FloatArray:
        """The cloud's pose in the anchor's frame at the anchor's position, turned by the descriptor's
        heading (between the levelled frames), the two tilts kept."""
        anchor_pose = self._poses[anchor]
        turned = planar.lift(np.array([0.0, 0.0, se2.wrap_angle(heading)]), np.eye(4))
        tilt_anchor = se3.relative(planar.level(anchor_pose), anchor_pose)
        tilt_here = se3.relative(planar.level(odometry_pose), odometry_pose)
        return se3.inverse(tilt_anchor) @ turned @ tilt_here
