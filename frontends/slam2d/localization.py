"""Localization in a saved 2D map: the new run's scans are matched against a map that never changes.

The map is built once from the saved keyframe scans at their poses: one likelihood grid (correlative
matching) with the points and normals ICP pairs with.

- Tracking: each scan is matched around its prediction (wheel odometry, else constant velocity), then
  refined by point-to-line ICP with the prediction as a prior, exactly as the SLAM matches its local map.
- Global localization (no start pose, or tracking lost for `lost_after_unmatched` scans in a row): a
  loop-closure-free `LaserSlam2D` tracks the scans in a frame of their own; at each of its new keyframes
  its last few keyframes, seen from the newest one, are searched over the whole map (all headings) by
  branch and bound, and the match is accepted only when it passes the loop closures' ambiguity and ICP
  tests. The scans tracked meanwhile get their map poses back through the same transform (`recovered_*`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError
from frontends.slam2d.config import LoopClosureConfig, Slam2DConfig
from frontends.slam2d.correlative import SearchWindow, match_branch_and_bound, match_exhaustive
from frontends.slam2d.global_match import VerifiedMatch, match_unambiguous, thinned_query
from frontends.slam2d.grid import build_likelihood_grid
from frontends.slam2d.icp import refine_point_to_line, scan_normals
from frontends.slam2d.local_map import Keyframe, Submap
from frontends.slam2d.slam import (
    BRANCH_AND_BOUND_LEVELS,
    ODOMETRY_BRANCH_AND_BOUND_LEVELS,
    LaserSlam2D,
    predicted_motion,
)
from optimizer import se2

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class EmptyMapError(FrontendError):
    """A saved map to localize in has no keyframe with enough points to match against."""


@dataclass(frozen=True)
class LocalizationConfig:
    global_levels: int = BRANCH_AND_BOUND_LEVELS
    """Branch-and-bound pyramid levels of the whole-map search (the loop closures': one compiled kernel)."""
    global_resolution: float = 0.15
    """Cell size (m) of the grid the whole-map search runs on (its likelihood σ at least this): a building
    at 5 cm cells and 0.75° steps takes seconds per attempt, at 15 cm and 1° a fraction of one; ICP on the
    full-resolution map then refines the match."""
    global_angular_step: float = math.radians(1.0)
    global_margin: float = 2.0
    """The search covers the saved keyframes' bounding box plus this (m): the robot is where the mapping
    robot was, give or take a corridor's width."""
    min_query_keyframes: int = 4
    """Global localization waits until the scans since it started span this many keyframes (~1 m)."""
    retry_every_keyframes: int = 3
    """After a failed attempt, the next one waits this many keyframes: an attempt over a whole building
    costs tenths of a second to seconds, and the next keyframe mostly sees the same place."""
    lost_after_unmatched: int = 5
    """Tracking is lost after this many scans in a row matched nothing, or matched with a score below
    `min_tracking_score`: localize globally again."""
    max_dead_reckoning: float = 30.0
    """With wheel odometry, scans that match nothing (the robot drove out of the saved map, or people hide
    the walls) keep the odometry's pose; tracking is declared lost only once it moved this far (m) since
    the last match: back in the map, the tracking window finds the walls again, which a global search in a
    place the map does not show never would (and it costs seconds)."""
    min_tracking_score: float = 0.5
    """A well-tracked scan scores 0.8–1 on its map; a robot carried elsewhere without its odometry saying so
    can still match a look-alike corridor at 0.55–0.7 (simulated building): the lost test catches only
    scans that fit the map worse than that."""
    max_lost_keyframes: int = 300
    """While lost, the scans are tracked in their own frame; that track restarts after this many keyframes
    (only the last few make a query; the rest would only cost memory)."""
    acceptance: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    """Score, ambiguity and ICP tests of a global match, and the query's keyframes and thinning: the loop
    closures' own settings."""


@dataclass(frozen=True, eq=False)
class LocalizedScan:
    index: int
    stamp_ns: int
    pose: FloatArray
    """(x, y, θ) in the map frame; NaN while the robot is not localized."""
    localized: bool
    matched: bool
    """This scan matched the map (False: the pose is the prediction, or unknown)."""
    score: float
    """Correlative score of the match (mean likelihood of the points on the map, in [0, 1]); NaN if none."""
    inlier_fraction: float
    """Share of the scan's points ICP paired with the map (0 when not matched)."""
    rms: float
    """ICP residual of the paired points (m); inf when none."""
    information: FloatArray
    """(3, 3) information of the pose, as the SLAM weighs its constraints (zeros when not matched)."""
    global_fix: bool = False
    """The pose comes from a global localization accepted at this scan."""
    recovered_indices: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """Scans processed while not localized whose map poses this global localization gives back …"""
    recovered_poses: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """… and those poses (M, 3)."""


class MapLocalizer:
    """Feed a new run's scans in time order with `localize`; the saved map is never changed."""

    def __init__(
        self,
        map_keyframe_scans: Sequence[FloatArray],
        map_keyframe_poses: FloatArray,
        config: Slam2DConfig | None = None,
        *,
        settings: LocalizationConfig | None = None,
        initial_pose: Sequence[float] | None = None,
    ) -> None:
        self.config = config or Slam2DConfig()
        self.settings = settings or LocalizationConfig()
        matching = self.config.matching
        poses = np.asarray(map_keyframe_poses, dtype=np.float64).reshape(-1, 3)
        usable = [len(s) >= matching.min_points for s in map_keyframe_scans]
        if len(map_keyframe_scans) != len(poses) or not any(usable):
            raise EmptyMapError(
                f"{len(map_keyframe_scans)} keyframe scans for {len(poses)} poses, "
                f"{sum(usable)} with {matching.min_points} or more points: nothing to localize in"
            )
        keyframes = [Keyframe(np.ascontiguousarray(s, dtype=np.float64),
                              scan_normals(np.ascontiguousarray(s, dtype=np.float64)))
                     for s, u in zip(map_keyframe_scans, usable, strict=True) if u]
        kept = poses[np.array(usable)]
        self.map = Submap.of(
            keyframes,
            list(kept),
            resolution=matching.resolution,
            likelihood_sigma=matching.likelihood_sigma,
            margin=self.settings.global_margin + 1.0,
            pairing_distance=matching.icp_max_distance,
        )
        resolution = max(self.settings.global_resolution, matching.resolution)
        self._search_grid = build_likelihood_grid(self.map.points, resolution,
                                                  max(matching.likelihood_sigma, resolution),
                                                  self.settings.global_margin + 1.0)
        low, high = kept[:, :2].min(axis=0), kept[:, :2].max(axis=0)
        self._search_center = np.array([*(0.5 * (low + high)), 0.0])
        self._search_window = SearchWindow(
            float(0.5 * (high - low).max()) + self.settings.global_margin,
            math.pi,
            self.settings.global_angular_step,
        )
        self._count = 0
        self._pose: FloatArray | None = None if initial_pose is None else np.array(initial_pose, dtype=float)
        self._last_odometry: FloatArray | None = None
        self._last_motion = np.zeros(3)
        self._misses = 0
        self._unmatched_distance = 0.0
        self._tracker: LaserSlam2D | None = None
        self._tracked: list[int] = []
        self._last_tracker_keyframe = -1

    @property
    def localized(self) -> bool:
        return self._pose is not None

    # ------------------------------------------------------------------------------------------ scans

    def localize(
        self,
        stamp_ns: int,
        points: FloatArray,
        odometry: FloatArray | None = None,
        odometry_interval: float = 0.0,
    ) -> LocalizedScan:
        """Place one scan (`points` (N, 2) in the robot base frame) in the map; `odometry` is its wheel
        odometry pose (any origin: only the motion between scans is used), interpolated between messages
        `odometry_interval` seconds apart."""
        matching = self.config.matching
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        points = np.ascontiguousarray(points[np.einsum("ij,ij->i", points, points) <= matching.max_range**2])
        index = self._count
        self._count += 1
        odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        if self._pose is None:
            return self._search(index, int(stamp_ns), points, odometry, odometry_interval)
        result = self._track(index, int(stamp_ns), points, odometry, odometry_interval)
        self._last_odometry = odometry
        fits = result.matched and result.score >= self.settings.min_tracking_score
        if fits:
            self._misses = 0
            self._unmatched_distance = 0.0
            return result
        self._unmatched_distance += float(np.hypot(self._last_motion[0], self._last_motion[1]))
        if len(points) < matching.min_points:
            return result
        self._misses += 1
        dead_reckoning = odometry is not None and self._unmatched_distance <= self.settings.max_dead_reckoning
        if self._misses >= self.settings.lost_after_unmatched and not dead_reckoning:
            self._lose()
        return result

    def _track(self, index: int, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
               odometry_interval: float) -> LocalizedScan:
        assert self._pose is not None
        matching = self.config.matching
        settings = self.config.odometry
        reliable = odometry_interval <= settings.reliable_interval
        has_odometry = odometry is not None and self._last_odometry is not None
        prior, prior_information = self._predict(odometry, reliable)
        pose, matched, score = prior, False, math.nan
        information = np.zeros((3, 3))
        inliers, rms = 0.0, math.inf
        if len(points) >= matching.min_points:
            scale = 1.0 if reliable else settings.unreliable_scale
            if has_odometry:
                window = SearchWindow(settings.window_linear * scale, settings.window_angular * scale,
                                      settings.angular_step)
                coarse = match_exhaustive(points, self.map.grid, prior, window)
            else:
                window = SearchWindow(settings.window_linear_without_odometry,
                                      settings.window_angular_without_odometry, settings.angular_step)
                coarse = match_branch_and_bound(points, self.map.grid, prior, window, 0.0,
                                                levels=ODOMETRY_BRANCH_AND_BOUND_LEVELS)
            start = prior if coarse is None else coarse.pose
            refined = refine_point_to_line(
                points, self.map.grid, self.map.points, self.map.normals, start,
                max_distance=matching.icp_max_distance, sigma=matching.point_sigma,
                prior=prior, prior_information=prior_information,
            )
            inliers, rms = refined.inlier_fraction, refined.rms
            if coarse is not None and refined.inlier_fraction >= settings.min_inlier_fraction:
                pose, matched, score = refined.pose, True, coarse.score
                information = matching.information_scale * refined.information
        self._last_motion = se2.relative(self._pose, pose)
        self._pose = np.array(pose)
        return LocalizedScan(index, stamp_ns, self._pose.copy(), True, matched, score, inliers, rms,
                             information)

    def _predict(self, odometry: FloatArray | None, reliable: bool) -> tuple[FloatArray, FloatArray]:
        assert self._pose is not None
        motion, information = predicted_motion(self.config.odometry, self._last_odometry, odometry, reliable,
                                               self._last_motion)
        return se2.compose(self._pose, motion), information

    # ---------------------------------------------------------------------------- global localization

    def _lose(self) -> None:
        self._pose = None
        self._misses = 0
        self._unmatched_distance = 0.0
        self._tracker = None

    def _search(self, index: int, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
                odometry_interval: float) -> LocalizedScan:
        """Track the scan in the lost stretch's own frame; at a new keyframe, look for it in the map."""
        if self._tracker is None or len(self._tracker.keyframe_poses()) > self.settings.max_lost_keyframes:
            disabled = replace(self.config.loop_closure, enabled=False)
            self._tracker = LaserSlam2D(replace(self.config, loop_closure=disabled))
            self._tracked = []
            self._last_tracker_keyframe = -1
        estimate = self._tracker.add_scan(stamp_ns, points, odometry, odometry_interval)
        self._tracked.append(index)
        nothing = LocalizedScan(index, stamp_ns, np.full(3, np.nan), False, False, math.nan, 0.0, math.inf,
                                np.zeros((3, 3)))
        if estimate.keyframe == self._last_tracker_keyframe:
            return nothing
        self._last_tracker_keyframe = estimate.keyframe
        keyframe_poses = self._tracker.keyframe_poses()
        due = len(keyframe_poses) - self.settings.min_query_keyframes
        if due < 0 or due % self.settings.retry_every_keyframes:
            return nothing
        found = self._global_match(keyframe_poses)
        if found is None:
            return nothing
        local_frame = keyframe_poses[-1]
        map_from_local = se2.compose(found.pose, se2.inverse(local_frame))
        tracked = self._tracker.finish()
        recovered = se2.compose(map_from_local, tracked.scan_poses(tracked.graph.poses))
        pose = recovered[-1]
        self._pose = pose.copy()
        self._last_odometry = odometry
        self._last_motion = np.zeros(3)
        self._tracker = None
        return LocalizedScan(
            index, stamp_ns, pose.copy(), True, True, found.score, found.icp.inlier_fraction, found.icp.rms,
            self.config.matching.information_scale * found.icp.information, global_fix=True,
            recovered_indices=np.array(self._tracked[:-1], dtype=np.int64),
            recovered_poses=recovered[:-1].copy(),
        )

    def _global_match(self, keyframe_poses: FloatArray) -> VerifiedMatch | None:
        assert self._tracker is not None
        acceptance = self.settings.acceptance
        recent = slice(max(0, len(keyframe_poses) - 1 - acceptance.query_keyframes), None)
        thinning = max(acceptance.query_thinning, self._search_grid.resolution)
        query = thinned_query(self._tracker.keyframe_scans()[recent], keyframe_poses[recent],
                              keyframe_poses[-1], thinning)
        if len(query) < self.config.matching.min_points:
            return None
        return match_unambiguous(query, self.map, self._search_center, self._search_window,
                                 matching=self.config.matching, acceptance=acceptance,
                                 levels=self.settings.global_levels, search_grid=self._search_grid)
