"""Localization in a saved 2D map: the new run's scans are matched against a map that never changes.

The map is built once from the saved keyframe scans at their poses: one likelihood grid (correlative
matching) with the points and normals ICP pairs with.

- Tracking: each scan is matched around its prediction (wheel odometry, else the scans' own odometry,
  `ScanOdometry`, used as wheel odometry is; constant velocity only where neither measured the motion from the
  last scan: the first scan, a change of source), then refined by point-to-line ICP, exactly as the SLAM
  matches its local map, with one difference: the prior is the prediction with the pose's own covariance
  (carried along the odometry, shrunk by every match), so the pose is the covariance-weighted mean of
  prediction and match, and a weak match (scoring below `min_tracking_score`: most of the scan falls where the
  map saw nothing) weighs only `weak_match_weight`. Wheels that slip or misreport are overruled: where the
  match scores as a loop closure must and the prediction lies off its score plateau, the prediction weighs
  only `weak_match_weight` against it, and a later jump of the wheels that pays back the motion they missed
  meanwhile is taken off (`held_odometry.OverruledOdometry`). The match is not used when it scores below
  `min_match_score`, pairs too few points, or ICP left the search window (it slid along a corridor the search
  never scored): the scan keeps the prediction and counts as predicted (`LocalizedScan.predicted`).
- Rolling local map (slam_toolbox's localization mode keeps one too): the scans of the last
  `rolling_map_length` metres at their tracked poses, with the saved keyframes nearest to them, never
  written into the saved map. A scan the saved map places only weakly or not at all is matched on it too,
  as the SLAM matches its recent keyframes: that match measures the motion from the last scan, far better
  than wheel odometry (CSAIL's turns by 5° a scan more or less than its wheels tell). A weak match of the
  saved map is then weighed against that motion instead of the odometry's; where the saved map cannot
  place the scan, the robot stays tracked in its frame (`LocalizedScan.tracked`), drifting slowly, and a
  weak match of the saved map does not take over from such a track (one scoring 0.2 pulled CSAIL's pose
  0.1 m off the track at its re-entry, and back the next scan): a strong one does, or the local
  re-acquisition. A pose tracked there is not dead reckoning: it is never declared lost for it (near the
  saved keyframes too, unless `count_rolling_tracks_near_map`).
- Local re-acquisition: after a few misses, at every `relocalize_every` metres, the last few scans
  (placed by their tracked poses, which odometry keeps consistent with each other) are searched around
  the prediction by branch and bound, in a window growing with the distance driven since the last good
  match, and the match is accepted only when unambiguous and verified by ICP (the loop closures' tests).
  Once that window outgrows `max_relocalize_window` (a long stretch off the map), the saved map's
  matches near the track are not taken; the region is searched on the global search's coarse grid, and
  its match is taken when it lands where the track is or a second one, metres on, agrees with it.
- Global localization (no start pose, or no good match for `max_dead_reckoning` metres, or no match for
  `lost_after_unmatched` scans without odometry): a loop-closure-free `LaserSlam2D` tracks the scans in a
  frame of their own; at its new keyframes its last few keyframes, seen from the newest one, are searched
  over the whole map (all headings) by branch and bound, and the match is accepted only when it passes
  the loop closures' ambiguity and ICP tests. Failed attempts back off (a robot outside the map would pay
  a whole-map search every metre). The scans tracked meanwhile get their map poses back through the same
  transform (`recovered_*`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np

from frontends.errors import EmptySavedMapError, MapExtentError
from frontends.protocol import FloatArray, IntArray, LocalizedMeasurement
from frontends.slam2d.cadence import ScanRate
from frontends.slam2d.config import (
    LOOP_QUERY_KEYFRAMES,
    LOOP_QUERY_THINNING,
    RELIABLE_ODOMETRY_INTERVAL,
    UNRELIABLE_ODOMETRY_SCALE,
    Slam2DConfig,
)
from frontends.slam2d.correlative import Match, SearchWindow, match_branch_and_bound, match_exhaustive
from frontends.slam2d.deskew import ScanDeskewer
from frontends.slam2d.global_match import VerifiedMatch, match_unambiguous, thinned_query
from frontends.slam2d.grid import MAX_LIKELIHOOD_CELLS, build_likelihood_grid
from frontends.slam2d.held_odometry import OdometryHold, OverruledOdometry
from frontends.slam2d.icp import IcpResult, refine_point_to_line, scan_normals
from frontends.slam2d.local_map import Keyframe, Submap
from frontends.slam2d.localization_config import LocalizationConfig
from frontends.slam2d.match_covariance import score_plateau
from frontends.slam2d.motion_prior import after_gap, carried_motion, gap_widening
from frontends.slam2d.scan_odometry import ScanOdometry
from frontends.slam2d.slam import (
    ODOMETRY_BRANCH_AND_BOUND_LEVELS,
    LaserSlam2D,
    match_without_odometry,
    points_to_match,
    predicted_motion,
)
from frontends.slam2d.stage_times import StageTimes
from optimizer import se2

__all__ = ["EmptyMapError", "LocalizationConfig", "LocalizedScan", "MapLocalizer"]

LOCAL_SEARCH_LEVELS = 5
"""Branch-and-bound levels of a local re-acquisition: coarsest candidates span 1.6 m at 5 cm, about the
windows searched; the whole map's pyramid is built once and shared by every attempt."""
RECENT_TURN = math.radians(12.0)
"""A scan turned this much from the last one kept for re-acquisition queries is kept too (new walls)."""
CONFIRMATION_SPAN = 4.0
"""A wide re-acquisition waits for another to agree over at most this many `relocalize_every_outside`."""
AGREEING_HEADING = math.radians(5.0)
"""Two wide re-acquisitions agree when they turn the track within this of each other (and move it within
half the ambiguity distance)."""


def whole_map_resolution(keyframes: Sequence[Keyframe], poses: FloatArray, resolution: float,
                         margin: float) -> float:
    """The cell size of the saved map's one grid: `resolution`, or the smallest multiple of it, up to
    `MAX_MAP_COARSENING` times, that fits the map with `margin` in `MAX_LIKELIHOOD_CELLS` (bounds from
    each keyframe's pose and farthest point); `MapExtentError` beyond."""
    reach = np.array([float(np.sqrt((k.points ** 2).sum(axis=1).max())) for k in keyframes])
    low = (poses[:, :2] - reach[:, None]).min(axis=0) - margin
    high = (poses[:, :2] + reach[:, None]).max(axis=0) + margin
    cells = float(np.prod(np.ceil((high - low) / resolution) + 1))
    coarsening = max(1, math.ceil(math.sqrt(cells / MAX_LIKELIHOOD_CELLS)))
    if coarsening > MAX_MAP_COARSENING:
        width, height = high - low
        raise MapExtentError(f"a map of {width:.4g} × {height:.4g} m would need cells of "
                             f"{coarsening * resolution:.2g} m to fit in one grid of {MAX_LIKELIHOOD_CELLS} "
                             f"cells (at most {MAX_MAP_COARSENING * resolution:.2g} m)")
    return resolution * coarsening


MAX_MAP_COARSENING = 4
"""A saved map too large for one grid at the matching's resolution is localized in on cells up to this
many times coarser (`whole_map_resolution`): 1.6 km² at 20 cm. The Freiburg clinic's map (439 × 246 m, 3 502
keyframes; 43 M cells at 5 cm) is localized in at 10 cm: its own log 0.021 / 0.090 m (median / 95 %) from
the single run. Coarser cells would blur what a match can tell."""


def _propagate(covariance: FloatArray, pose: FloatArray, motion: FloatArray, noise: FloatArray) -> FloatArray:
    """The covariance (map frame) of pose ⊕ motion, `noise` being the motion's (robot frame)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    jacobian = np.eye(3)
    jacobian[0, 2] = -s * motion[0] - c * motion[1]
    jacobian[1, 2] = c * motion[0] - s * motion[1]
    return jacobian @ covariance @ jacobian.T + rotation @ noise @ rotation.T


def _in_frame(information: FloatArray, heading: float) -> FloatArray:
    """A map-frame (x, y, θ) information expressed in the frame of a pose heading `heading`."""
    c, s = math.cos(heading), math.sin(heading)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rotation.T @ information @ rotation


class EmptyMapError(EmptySavedMapError):
    """A saved map to localize in has no keyframe with enough points to match against."""


@dataclass(frozen=True, eq=False)
class LocalizedScan(LocalizedMeasurement):
    """A scan's `LocalizedMeasurement`: `score` is the correlative score (mean likelihood of the points on
    the map), `inlier_fraction` the share ICP paired, `rms` ICP's residual."""

    information: FloatArray
    """(3, 3) information of the pose, as the SLAM weighs its constraints (zeros when not matched)."""
    global_fix: bool = False
    """The pose comes from a global localization accepted at this scan."""
    recovered_indices: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """Scans processed while not localized whose map poses this global localization gives back …"""
    recovered_poses: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """… and those poses (M, 3)."""
    relocalized: bool = False
    """The pose comes from a local re-acquisition accepted at this scan (a windowed search around the
    prediction after a stretch of weak or missing matches)."""
    tracked: bool = False
    """Not matched to the saved map (`matched` is False) but to the rolling local map: the recent scans
    at their tracked poses with the saved keyframes nearby. Where the saved map cannot place the scan
    (outside it, mostly) the pose is tracked in the map's frame, drifting slowly from it; `score`,
    `inlier_fraction`, `rms` and `information` are then that match's."""
    motion: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    """The motion from the previous scan's pose to this one as measured locally, before the saved map
    corrected it: the odometry's (or constant velocity's) prediction, or the rolling local map's match
    when the saved map's was weak or failed. NaN when the previous scan gave no pose to measure from (the
    first scan, a global fix)."""
    motion_information: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """(3, 3) information of `motion`, in the previous pose's frame."""
    map_information: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """(3, 3) information the saved map's match alone gives the pose (map frame; the prediction it was
    fused with left out, a weak match's weighed by `weak_match_weight`); zeros when not map-matched."""

    @property
    def predicted(self) -> bool:
        """Localized, but the pose is the odometry (or constant-velocity) prediction: no match was good
        enough, on the saved map or on the rolling local map."""
        return self.localized and not self.matched and not self.tracked


@dataclass(frozen=True, eq=False)
class _TrackingMatch:
    score: float
    """Correlative score of the search (NaN when it found nothing)."""
    refined: IcpResult
    accepted: bool
    """The match may place the scan (see `MapLocalizer._match`)."""
    prior_information: FloatArray
    """The prediction's information ICP fused the match with (part of `refined.information`)."""
    overruled: bool = False
    """The search's optimum overruled the prediction (the wheels', or the rolling map's where `_track` matches
    the saved map again around it): the prediction weighed as a weak match would (`_match`)."""

    def own_information(self, information_scale: float) -> FloatArray:
        """The match's information without the prediction's (on the SLAM's constraint scale)."""
        return information_scale * (self.refined.information - self.prior_information)

    def strong(self, min_score: float) -> bool:
        return self.accepted and self.score >= min_score


@dataclass(frozen=True, eq=False)
class _RollingScan:
    keyframe: Keyframe
    pose: FloatArray
    travelled: float
    """Distance driven (m) from the start of the rolling map's track to this scan."""


def _off_the_plateau(points: FloatArray, submap: Submap, optimum: FloatArray, prior: FloatArray) -> bool:
    """Whether `prior` lies off the score plateau of `points` on the submap around `optimum` (both poses):
    the scan tells the two apart (`match_covariance.score_plateau`). A prior within a cell of the optimum
    is on it."""
    offset = np.asarray(prior[:2]) - np.asarray(optimum[:2])
    if math.hypot(float(offset[0]), float(offset[1])) <= submap.grid.resolution:
        return False
    return not score_plateau(points, submap.grid, optimum).holds(offset)


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
        first_scan_alone: bool = True,
    ) -> None:
        """`first_scan_alone`: a global localization tries the first scan of its search alone before the
        scans of about a metre (`LocalizationConfig.min_query_keyframes`). A continued map is placed only
        by the longer query: its whole new run hangs off that placement, and a single scan places it less
        exactly (Intel continued in two halves: 0.010 → 0.018 m median from its single run; ACES without
        odometry: 0.055 → 0.097 m on the relations)."""
        self.config = config or Slam2DConfig()
        self.settings = settings or LocalizationConfig()
        self._first_scan_alone = first_scan_alone
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
        self._map_keyframes = keyframes
        self._map_keyframe_poses = kept
        map_resolution = whole_map_resolution(keyframes, kept, matching.resolution,
                                              self.settings.global_margin + 1.0)
        self.map = Submap.of(
            keyframes,
            list(kept),
            resolution=map_resolution,
            likelihood_sigma=max(matching.likelihood_sigma, map_resolution),
            margin=self.settings.global_margin + 1.0,
            pairing_distance=matching.icp_max_distance,
        )
        resolution = max(self.settings.global_resolution, map_resolution)
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
        self._deskewer = ScanDeskewer()
        self._pose: FloatArray | None = None if initial_pose is None else np.array(initial_pose, dtype=float)
        self._covariance = self._fix_covariance()
        self._last_odometry: FloatArray | None = None
        self._last_motion = np.zeros(3)
        self._last_stamp: int | None = None
        """The stamp of the last scan tracked or placed (the end of `_last_motion`)."""
        self._motion_span_ns = 0
        """The time `_last_motion` took (0: unknown)."""
        self._rate = ScanRate()
        self._odometry_hold = OdometryHold()
        self._overruled = OverruledOdometry()
        self._last_overruled = False
        """Whether the pose `_track` gave last came from a match of the saved map that overruled the
        prediction (`_TrackingMatch.overruled`)."""
        self._misses = 0
        self._since_good = 0.0
        self._since_attempt = 0.0
        self._fits_map_while_drifted = False
        """The last scan matched the saved map well near a pose drifted beyond `max_relocalize_window`."""
        self._wide_failures = 0
        """Wide re-acquisitions in a row that placed nothing while the saved map fitted near the track or a
        match waited for its confirmation (after `attempts_before_backoff` of them their spacing doubles
        with each, up to `relocalize_every_outside`)."""
        self._pending_correction: tuple[FloatArray, float] | None = None
        """The correction of the track a wide re-acquisition found, and `_travelled` then: waiting for one
        metres on to agree."""
        self._recent: deque[tuple[FloatArray, FloatArray]] = deque(maxlen=self.settings.relocalize_keyframes)
        self._tracker: LaserSlam2D | None = None
        self._scan_odometry: ScanOdometry | None = None
        """Without wheel odometry, the scans' own (`ScanOdometry`), used as the wheel odometry would be."""
        self._map_matched = True
        """The last scan was placed by the saved map (else tracked or predicted: a weak match of the saved
        map does not take over from the rolling local map's track)."""
        self._tracked: list[int] = []
        self._last_tracker_keyframe = -1
        self._next_attempt = self.settings.min_query_keyframes
        self._failed_attempts = 0
        self._rolling: deque[_RollingScan] = deque()
        self._travelled = 0.0
        self._rolling_submap: Submap | None = None
        """Built from `_rolling` when a scan needs it, kept until `rolling_map_rebuild` metres later."""
        self._rolling_built_at = 0.0
        self._dead_reckoned = 0.0
        """Distance driven since the last good match on the saved map, outside the stretches tracked on the
        rolling local map (see `LocalizationConfig.count_rolling_tracks_near_map`)."""
        self.stage_times = StageTimes()
        """Where `localize` spent its time: tracking, local re-acquisition, global localization."""

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
        point_times: FloatArray | None = None,
    ) -> LocalizedScan:
        """Place one scan (`points` (N, 2) in the robot base frame, taken at `point_times` (N,) s after
        `stamp_ns`, None: at the stamp) in the map; `odometry` is its wheel odometry pose (any origin: only
        the motion between scans is used), interpolated between messages `odometry_interval` seconds
        apart."""
        matching = self.config.matching
        points, times = points_to_match(points, point_times, matching)
        index = self._count
        self._count += 1
        self._rate.add(int(stamp_ns))
        odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        if (odometry is None) != (self._scan_odometry is not None):
            # The odometry's source changes (or the first scan): no motion measured across the change.
            self._last_odometry = None
            self._overruled.reset()
            self._scan_odometry = None if odometry is not None else ScanOdometry(
                self.config, self.settings.max_lost_keyframes)
            if self._tracker is not None:  # the lost stretch's tracker too, else it takes the jump as motion
                self._tracker.odometry_restarts()
        if self._scan_odometry is not None:
            with self.stage_times.stage("scan odometry"):
                odometry = self._scan_odometry.pose(int(stamp_ns), points, times)
            odometry_interval = 0.0
        if self._pose is None:
            self._deskewer.moved(int(stamp_ns), None)  # the lost stretch's tracker deskews its scans
            with self.stage_times.stage("global"):
                return self._search(index, int(stamp_ns), points, odometry, odometry_interval, times)
        has_odometry = odometry is not None and self._last_odometry is not None
        with self.stage_times.stage("tracking"):
            reliable = odometry_interval <= RELIABLE_ODOMETRY_INTERVAL
            prediction = self._predict(odometry, reliable, int(stamp_ns))
            odometry_motion = se2.relative(self._pose, prediction[0]) if has_odometry else None
            deskewed = self._deskewer.deskewed(points, times, int(stamp_ns), odometry_motion)
            before = (self._pose, self._covariance, self._map_matched)
            result = self._track(index, int(stamp_ns), deskewed, odometry, prediction)
            if times is not None and odometry_motion is None and (result.matched or result.tracked):
                # As the SLAM does (`LaserSlam2D.add_scan`): again under the scan's own motion, now known.
                deskewed = self._deskewer.deskewed(points, times, int(stamp_ns), None, self._last_motion)
                self._pose, self._covariance, self._map_matched = before
                result = self._track(index, int(stamp_ns), deskewed, odometry, prediction)
            if odometry_motion is None and not (result.matched or result.tracked) and np.any(
                    prediction[0] != before[0]):
                result = self._track_still(index, int(stamp_ns), deskewed, odometry, before, prediction,
                                           result)
            if odometry_motion is not None:
                matched_motion = se2.relative(before[0], self._pose)
                self._overruled.note(self._last_overruled, odometry_motion, matched_motion)
            points = deskewed
            self._deskewer.moved(int(stamp_ns), self._last_motion)
            self._motion_span_ns = 0 if self._last_stamp is None else int(stamp_ns) - self._last_stamp
            self._last_stamp = int(stamp_ns)
        self._last_odometry = odometry
        moved = float(np.hypot(self._last_motion[0], self._last_motion[1]))
        self._since_attempt += moved
        self._travelled += moved
        if len(points) < matching.min_points:  # nothing to judge the pose by: it follows the prediction
            self._since_good += moved
            self._dead_reckoned += moved
            return result
        self._remember(points)
        self._remember_rolling(points)
        settings = self.settings
        if result.matched and result.score >= settings.min_tracking_score:
            self._misses = 0
            self._since_good = 0.0
            self._dead_reckoned = 0.0
            self._pending_correction = None
            self._wide_failures = 0
            return result
        self._since_good += moved
        self._misses += 1
        # A pose tracked on the rolling local map is what slam_toolbox's localization gives: the scan is
        # explained (by the recent scans and the saved keyframes nearby), so it is not dead reckoning, also
        # near the saved keyframes, where the first run may have seen the place only from afar (CSAIL: 40 m
        # along walls its map glimpsed, declared lost, then placed 5 m off by a look-alike room). Opt-in
        # (`count_rolling_tracks_near_map`): near them, a track only on its own recent scans counts, so a
        # robot carried elsewhere inside the map (its scans fit themselves anywhere) is found again.
        outside = result.tracked and not self._near_map(result.pose)
        explained = result.tracked and (outside or not settings.count_rolling_tracks_near_map)
        if not explained:
            self._dead_reckoned += moved
        reach = self._relocalize_reach()
        if reach > settings.max_relocalize_window:
            # Drifted further than the fine window reaches: the wide search thins out as the region grows,
            # unless the saved map fits the scan near the track or a candidate waits for its confirmation.
            every = max(settings.relocalize_every_outside, settings.wide_retry_share * reach)
            if self._fits_map_while_drifted or self._pending_correction is not None:
                # Sooner, backing off as these attempts fail (each up to 0.25 s on a 250 m building).
                backoff = max(0, self._wide_failures - settings.attempts_before_backoff)
                every = min(settings.relocalize_every * 2.0**backoff, settings.relocalize_every_outside)
            else:
                self._wide_failures = 0
            attempt = self._misses > settings.relocalize_after and self._since_attempt >= every
        else:
            every = settings.relocalize_every_outside if outside else settings.relocalize_every
            attempt = self._misses == settings.relocalize_after or (
                self._misses > settings.relocalize_after and self._since_attempt >= every)
        if attempt:
            self._since_attempt = 0.0
            with self.stage_times.stage("relocalization"):
                found = self._relocalize(result)
            if found is not None:
                return found
        lost = (self._dead_reckoned > settings.max_dead_reckoning if has_odometry
                else self._misses >= settings.lost_after_unmatched and not explained)
        if lost:
            self._lose()
        return result

    def _track(self, index: int, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
               prediction: tuple[FloatArray, FloatArray, FloatArray, SearchWindow, bool]) -> LocalizedScan:
        """Match a scan around `prediction` (`_predict`'s)."""
        assert self._pose is not None
        matching = self.config.matching
        has_odometry = odometry is not None and self._last_odometry is not None
        previous = self._pose
        self._fits_map_while_drifted = False
        prior, covariance, noise, window, gap = prediction
        motion, motion_information = se2.relative(previous, prior), cast(FloatArray, np.linalg.inv(noise))
        map_information = np.zeros((3, 3))
        # ICP weighs its points as independent, which the match's information undoes by
        # `information_scale`: the prior is weighed on the same (inflated) scale, so the fusion below is
        # the covariance-weighted mean of prediction and match.
        prior_information = cast(FloatArray, np.linalg.inv(covariance)) / matching.information_scale
        pose, matched, tracked, score = prior, False, False, math.nan
        self._last_overruled = False
        information = np.zeros((3, 3))
        inliers, rms = 0.0, math.inf
        if len(points) >= matching.min_points:
            found = self._match(points, self.map, prior, prior_information, window, has_odometry,
                                weigh_weak=True, gap=gap)
            # Off the saved map for longer than a re-acquisition's fine window allows for, the pose may be
            # metres off along a corridor, where the map's walls fit a look-alike stretch inside the
            # tracking window as well as the true one (Killian Court: 9 m off, then matched there for 900
            # scans): the track goes on, and only a re-acquisition searching as far as the drift allows
            # may bring the pose back onto the map.
            drifted = not self._map_matched and self._relocalize_reach() > self.settings.max_relocalize_window
            strong = found.strong(self.settings.min_tracking_score)
            self._fits_map_while_drifted = drifted and strong
            if (drifted or not strong) and self._rolling:
                # The saved map places the scan poorly or not at all: the rolling local map (the recent
                # scans at their tracked poses, with the saved keyframes nearby) measures the motion, as
                # the SLAM's own matching on its recent keyframes does. (The odometry's motion instead:
                # ACES, the map at the full run's poses, 0.047 m median, 0.115 m where the map's matches
                # are weak; CSAIL's heading 5–9° off there.)
                rolling = self._match(points, self._rolling_map(), prior, prior_information, window,
                                      has_odometry, weigh_weak=False, gap=gap)
                if rolling.strong(self.settings.min_tracking_score):
                    own = rolling.own_information(matching.information_scale)
                    motion = se2.relative(previous, rolling.refined.pose)
                    motion_information = motion_information + _in_frame(own, float(previous[2]))
                    if found.accepted and self._map_matched:
                        # A weak match of the saved map, weighed against the motion the recent scans
                        # measured instead of the odometry's.
                        found = self._match(points, self.map, rolling.refined.pose, prior_information,
                                            window, has_odometry, weigh_weak=True)
                    else:
                        found = replace(found, accepted=False)
                    if not found.accepted:
                        found, tracked = rolling, True
            inliers, rms = found.refined.inlier_fraction, found.refined.rms
            self._last_overruled = found.accepted and found.overruled
            if found.accepted:
                pose, matched, score = found.refined.pose, not tracked, found.score
                information = matching.information_scale * found.refined.information
                own = found.own_information(matching.information_scale)
                if not tracked:
                    weak = score < self.settings.min_tracking_score
                    map_information = (self.settings.weak_match_weight if weak else 1.0) * own
                    covariance = cast(FloatArray, np.linalg.inv(information + 1e-12 * np.eye(3)))
                # A tracked pose keeps the prediction's covariance: matched against scans placed by the
                # tracking itself, it drifts from the saved map (as odometry does, only slower), and the
                # map's match must outweigh it as soon as the robot is back in the map.
        self._last_motion = se2.relative(self._pose, pose)
        self._pose = np.array(pose)
        self._covariance = covariance
        self._map_matched = matched
        return LocalizedScan(index, stamp_ns, self._pose.copy(), True, matched, score, inliers, rms,
                             information, tracked=tracked, motion=motion,
                             motion_information=motion_information, map_information=map_information)

    def _track_still(self, index: int, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
                     before: tuple[FloatArray, FloatArray, bool],
                     prediction: tuple[FloatArray, FloatArray, FloatArray, SearchWindow, bool],
                     failed: LocalizedScan) -> LocalizedScan:
        """Without odometry, a scan `_track` could place neither on the map nor on the recent scans around
        the constant-velocity prediction, tracked again around the last pose (`before`: the state before
        the first attempt), as the SLAM does (`LaserSlam2D._match`): constant velocity overshoots where a
        turn stops or swings back. The first attempt's result and state stand if this one fails too."""
        first = (self._pose, self._covariance, self._map_matched, self._last_motion)
        drifted_fit = self._fits_map_while_drifted
        self._pose, self._covariance, self._map_matched = before
        still = self._track(index, stamp_ns, points, odometry, (before[0], *prediction[1:]))
        if still.matched or still.tracked:
            return still
        self._pose, self._covariance, self._map_matched, self._last_motion = first
        self._fits_map_while_drifted = drifted_fit
        return failed

    def _tracking_window(self, has_odometry: bool, reliable: bool,
                         widening: tuple[float, float] = (1.0, 1.0)) -> SearchWindow:
        settings = self.config.odometry
        if has_odometry:
            scale = 1.0 if reliable else UNRELIABLE_ODOMETRY_SCALE
            return SearchWindow(settings.window_linear * scale, settings.window_angular * scale,
                                settings.angular_step)
        return SearchWindow(settings.window_linear_without_odometry * widening[0],
                            settings.window_angular_without_odometry * widening[1], settings.angular_step)

    def _match(self, points: FloatArray, submap: Submap, prior: FloatArray, prior_information: FloatArray,
               window: SearchWindow, has_odometry: bool, *, weigh_weak: bool, gap: bool = False,
               whole_window: bool = False) -> _TrackingMatch:
        """The scan matched on `submap` around the prior: correlative search (exhaustive in the odometry's
        small window; without odometry as the SLAM searches, `match_without_odometry`: the narrow window
        around the constant-velocity prediction first, unless after a `gap`; the `whole_window` by branch
        and bound), then ICP fused with the prior. With `weigh_weak`, a match scoring below
        `min_tracking_score` weighs only `weak_match_weight` against the prior."""
        matching = self.config.matching
        coarse: Match | None
        if has_odometry:
            coarse = match_exhaustive(points, submap.grid, prior, window)
        elif whole_window:
            coarse = match_branch_and_bound(points, submap.grid, prior, window, 0.0,
                                            levels=ODOMETRY_BRANCH_AND_BOUND_LEVELS)
        else:  # as the SLAM searches: after a gap the wide window at once
            coarse, window = match_without_odometry(points, submap.grid, prior, window,
                                                    narrow_first=not gap)
        start = prior if coarse is None else coarse.pose
        overruled = False
        strong = coarse is not None and coarse.score >= self.settings.min_tracking_score
        if weigh_weak and not strong:
            prior_information = prior_information / self.settings.weak_match_weight
        elif (coarse is not None and coarse.score >= self.settings.acceptance.min_score and has_odometry
              and window.linear <= self.config.odometry.window_linear
              and submap is self.map and _off_the_plateau(points, submap, start, prior)):
            # The wheels, trusted (their narrow window: not interpolated over a long gap), put the scan
            # where it scores well below an optimum the map would accept as a loop closure: they slipped or
            # misreport (the Freiburg 079 log's drive forwards while the robot backs up, 0.1 m a scan).
            # Fused as it weighs, their prediction dragged every match towards it, and the pose off the
            # map, 5 m within 30 scans: it weighs against the match as a weak match weighs against it. (A
            # weaker optimum does not overrule them: where the map saw a place from afar, matches scoring
            # 0.50–0.52 lay 0.3–0.7 m off.)
            prior_information = prior_information * self.settings.weak_match_weight
            overruled = True
        refined = refine_point_to_line(
            points, submap.grid, submap.points, submap.normals, start,
            max_distance=matching.icp_max_distance, sigma=matching.point_sigma,
            prior=prior, prior_information=prior_information,
        )
        # Not used below `min_match_score` (too few points on the map), with too few points paired, or
        # when ICP left the window (it slid along a corridor the search never scored).
        scored = coarse is not None and coarse.score >= self.settings.min_match_score
        inside = window.holds(refined.pose, prior, submap.grid.resolution)
        if scored and has_odometry and not inside:
            # ICP found the walls beyond the odometry's window: the wheels slipped, or the robot turned
            # faster than they tell (CSAIL's turn 7–10° more than its odometry between two scans). Search
            # the window a match without odometry would (branch and bound, so it costs a few matches).
            return self._match(points, submap, prior, prior_information,
                               self._tracking_window(False, False), False, weigh_weak=weigh_weak,
                               whole_window=True)
        accepted = (scored and refined.inlier_fraction >= self.config.odometry.min_inlier_fraction and inside)
        return _TrackingMatch(math.nan if coarse is None else float(coarse.score), refined, accepted,
                              prior_information, overruled)

    def _remember(self, points: FloatArray) -> None:
        """Keep the scan for local re-acquisition queries when it is `relocalize_every` from the last kept."""
        assert self._pose is not None
        if self._recent:
            step = se2.relative(self._recent[-1][1], self._pose)
            if np.hypot(step[0], step[1]) < self.settings.relocalize_every and abs(step[2]) < RECENT_TURN:
                return
        self._recent.append((points, self._pose.copy()))

    def _remember_rolling(self, points: FloatArray) -> None:
        """The scan joins the rolling local map when `rolling_map_spacing` from the last one that joined (or
        turned `RECENT_TURN`); scans more than `rolling_map_length` behind it leave."""
        assert self._pose is not None
        settings = self.settings
        if self._rolling:
            step = se2.relative(self._rolling[-1].pose, self._pose)
            if np.hypot(step[0], step[1]) < settings.rolling_map_spacing and abs(step[2]) < RECENT_TURN:
                return
        self._rolling.append(_RollingScan(Keyframe(points, scan_normals(points)), self._pose.copy(),
                                          self._travelled))
        while (len(self._rolling) > 1
               and self._travelled - self._rolling[0].travelled > settings.rolling_map_length):
            self._rolling.popleft()
        if self._travelled - self._rolling_built_at >= settings.rolling_map_rebuild:
            self._rolling_submap = None

    def _rolling_map(self) -> Submap:
        """The rolling local map: the recent scans at their tracked poses, and the saved keyframes nearest
        to the newest of them (never written into the saved map)."""
        if self._rolling_submap is None:
            settings = self.settings
            matching = self.config.matching
            newest = self._rolling[-1].pose
            offsets = self._map_keyframe_poses[:, :2] - newest[:2]
            distances = np.hypot(offsets[:, 0], offsets[:, 1])
            nearest = np.argsort(distances)[: settings.rolling_map_saved_keyframes]
            nearest = nearest[distances[nearest] <= settings.rolling_map_reach]
            keyframes = [self._map_keyframes[k] for k in nearest] + [r.keyframe for r in self._rolling]
            poses = [self._map_keyframe_poses[k] for k in nearest] + [r.pose for r in self._rolling]
            window = self.config.odometry.window_linear_without_odometry
            self._rolling_submap = Submap.of(keyframes, poses, resolution=matching.resolution,
                                             likelihood_sigma=matching.likelihood_sigma, margin=window + 1.0,
                                             pairing_distance=matching.icp_max_distance)
            self._rolling_built_at = self._travelled
        return self._rolling_submap

    def _near_map(self, pose: FloatArray) -> bool:
        offsets = self._map_keyframe_poses[:, :2] - pose[:2]
        return bool(np.min(np.einsum("ij,ij->i", offsets, offsets)) <= self.settings.map_reach**2)

    def _relocalize(self, tracked: LocalizedScan) -> LocalizedScan | None:
        """The recent scans searched around the current pose in a window widening with the distance driven
        since the last good match; the scan's new pose when unambiguous and verified."""
        assert self._pose is not None
        settings = self.settings
        acceptance = settings.acceptance
        scans = [s for s, _ in self._recent]
        poses = [p for _, p in self._recent]
        linear = self._relocalize_reach()
        if linear > settings.max_relocalize_window:
            if self._fits_map_while_drifted:  # the scans before it may lie where the map never was
                scans, poses = scans[-1:], poses[-1:]
            found = self._confirmed(self._wide_match(scans, poses, linear))
            self._wide_failures = 0 if found is not None else self._wide_failures + 1
        else:
            query = thinned_query(scans, poses, self._pose, LOOP_QUERY_THINNING)
            if len(query) < self.config.matching.min_points:
                return None
            window = SearchWindow(linear, settings.relocalize_angular, acceptance.angular_step)
            found = match_unambiguous(query, self.map, self._pose, window, matching=self.config.matching,
                                      acceptance=acceptance, levels=LOCAL_SEARCH_LEVELS)
        if found is None:
            return None
        correction = se2.compose(found.pose, se2.inverse(self._pose))
        self._recent = deque(((s, se2.compose(correction, p)) for s, p in self._recent),
                             maxlen=settings.relocalize_keyframes)
        self._rolling = deque(replace(r, pose=se2.compose(correction, r.pose)) for r in self._rolling)
        self._rolling_submap = None
        self._pose = found.pose.copy()
        self._covariance = self._fix_covariance()
        self._map_matched = True
        self._misses = 0
        self._since_good = 0.0
        self._dead_reckoned = 0.0
        information = self.config.matching.information_scale * found.icp.information
        return LocalizedScan(
            tracked.index, tracked.stamp_ns, self._pose.copy(), True, True, found.score,
            found.icp.inlier_fraction, found.icp.rms, information, relocalized=True, motion=tracked.motion,
            motion_information=tracked.motion_information, map_information=information,
        )

    def _confirmed(self, found: VerifiedMatch | None) -> VerifiedMatch | None:
        """A wide match that lands where the track is, or moves it as one found at least
        `relocalize_every_outside` metres before did (else None: it waits for such a one). One wide match can
        be a look-alike of a place outside the map, which the map cannot show (CSAIL: 9.4 m off, scoring
        0.61 with 71 % of the query paired; true ones there and at Killian Court 0.67–0.94 and 84–100 %); the
        track, or a match metres on with other scans, lands on the same place only where it is the place."""
        assert self._pose is not None
        settings = self.settings
        pending = self._pending_correction
        if (pending is not None
                and self._travelled - pending[1] > CONFIRMATION_SPAN * settings.relocalize_every_outside):
            pending = self._pending_correction = None  # too old to vouch for the track's drift since
        if found is None:
            return None
        for correction, since in [(np.zeros(3), -math.inf)] + ([] if pending is None else [pending]):
            offset = se2.relative(se2.compose(correction, self._pose), found.pose)
            if (math.hypot(offset[0], offset[1]) < 0.5 * settings.acceptance.ambiguity_distance
                    and abs(offset[2]) < AGREEING_HEADING):
                if self._travelled - since >= settings.relocalize_every_outside:
                    self._pending_correction = None
                    return found
                return None  # the same scans, mostly: not a second opinion yet
        self._pending_correction = (se2.compose(found.pose, se2.inverse(self._pose)), self._travelled)
        return None

    def _relocalize_reach(self) -> float:
        """Half-width (m) of the region a re-acquisition searches: the drift since the last good match."""
        settings = self.settings
        return settings.relocalize_window + settings.relocalize_window_per_metre * self._since_good

    def _wide_match(self, scans: list[FloatArray], poses: list[FloatArray],
                    reach: float) -> VerifiedMatch | None:
        """The recent scans searched on the global localization's coarse grid within `reach` of the current
        pose (headings within `relocalize_angular`), or over the whole map once that lies within reach (a
        region hours of driving wide would cost time and memory as its area grows, for nothing)."""
        assert self._pose is not None
        query = self._global_query(scans, poses, self._pose)
        if query is None:
            return None
        center, linear = self._pose, reach
        whole = self._search_window.linear
        if reach >= np.hypot(*(np.abs(self._pose[:2] - self._search_center[:2]) + whole)):
            center, linear = np.array([*self._search_center[:2], self._pose[2]]), whole
        window = SearchWindow(linear, self.settings.relocalize_angular, self.settings.global_angular_step)
        return match_unambiguous(query, self.map, center, window, matching=self.config.matching,
                                 acceptance=self.settings.acceptance, levels=self.settings.global_levels,
                                 search_grid=self._search_grid)

    def _predict(self, odometry: FloatArray | None, reliable: bool,
                 stamp_ns: int) -> tuple[FloatArray, FloatArray, FloatArray, SearchWindow, bool]:
        """The predicted pose, its covariance (the pose's own, carried along the motion, plus the motion's
        noise), that noise (robot frame), the window to search and whether the scan comes after a gap
        (`after_gap`): wheel odometry's as `LocalizationConfig` models it; without odometry, the SLAM's
        loose constant-velocity prior, the last motion carried over the time since (`motion_prior`), its σ
        and window widened after a gap."""
        assert self._pose is not None
        has_odometry = odometry is not None and self._last_odometry is not None
        elapsed = 0 if self._last_stamp is None else self._rate.scan_time(stamp_ns - self._last_stamp)
        span = self._rate.scan_time(self._motion_span_ns)
        last_motion = self._last_motion if has_odometry else carried_motion(self._last_motion, span, elapsed)
        motion, information = predicted_motion(self.config.odometry, self._last_odometry, odometry, reliable,
                                               last_motion)
        widening = (1.0, 1.0) if has_odometry else gap_widening(self.config.odometry, elapsed)
        window = self._tracking_window(has_odometry, reliable, widening)
        motion = self._odometry_hold.corrected(motion, self._last_odometry, odometry, self._last_motion,
                                               window.linear, window.angular)
        if has_odometry:
            motion = self._overruled.corrected(motion, self._last_motion, window.linear)
        if self._odometry_hold.holding:
            # The odometry's value is stale, not a robot standing still: the motion the scans tracked last
            # goes on (a turn in place at 14°/scan would otherwise leave the window at its first scan).
            motion = self._last_motion
        if has_odometry:
            settings = self.settings
            distance = float(np.hypot(motion[0], motion[1]))
            linear = settings.odometry_noise_linear + settings.odometry_noise_per_metre * distance
            angular = (settings.odometry_noise_angular + settings.odometry_noise_angular_per_metre * distance
                       + settings.odometry_noise_per_radian * abs(float(motion[2])))
            scale = 1.0 if reliable else UNRELIABLE_ODOMETRY_SCALE
            noise = np.diag([(scale * linear) ** 2, (scale * linear) ** 2, (scale * angular) ** 2])
        else:
            noise = np.linalg.inv(information / np.array([widening[0], widening[0], widening[1]]) ** 2)
        covariance = _propagate(self._covariance, self._pose, motion, noise)
        gap = not has_odometry and after_gap(widening, elapsed, self._rate.typical_ns)
        return se2.compose(self._pose, motion), covariance, noise, window, gap

    def _fix_covariance(self) -> FloatArray:
        settings = self.settings
        return np.diag([settings.fix_sigma_linear**2, settings.fix_sigma_linear**2,
                        settings.fix_sigma_angular**2])

    # ---------------------------------------------------------------------------- global localization

    def _lose(self) -> None:
        self._pose = None
        self._overruled.reset()
        self._pending_correction = None
        self._wide_failures = 0
        self._misses = 0
        self._since_good = 0.0
        self._dead_reckoned = 0.0
        self._recent.clear()
        self._rolling.clear()
        self._rolling_submap = None
        self._tracker = None

    def _search(self, index: int, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
                odometry_interval: float, times: FloatArray | None) -> LocalizedScan:
        """Track the scan in the lost stretch's own frame; at a new keyframe, look for it in the map."""
        if self._tracker is None or len(self._tracker.keyframe_poses()) > self.settings.max_lost_keyframes:
            self._tracker = LaserSlam2D(self.config.without_loop_closures())
            self._tracked = []
            self._last_tracker_keyframe = -1
            # The first scan alone is tried at once: a robot standing still makes no keyframe to wait for.
            self._next_attempt = 1 if self._first_scan_alone else self.settings.min_query_keyframes
        estimate = self._tracker.add_scan(stamp_ns, points, odometry, odometry_interval, times)
        self._tracked.append(index)
        nothing = LocalizedScan(index, stamp_ns, np.full(3, np.nan), False, False, math.nan, 0.0, math.inf,
                                np.zeros((3, 3)))
        if estimate.keyframe == self._last_tracker_keyframe:
            return nothing
        self._last_tracker_keyframe = estimate.keyframe
        keyframe_poses = self._tracker.keyframe_poses()
        if len(keyframe_poses) < self._next_attempt:
            return nothing
        found = self._global_match(keyframe_poses)
        if found is None and len(keyframe_poses) < self.settings.min_query_keyframes:
            self._next_attempt = self.settings.min_query_keyframes  # one scan is often ambiguous: wait
            return nothing
        if found is None:
            settings = self.settings
            self._failed_attempts += 1
            backoff = max(0, self._failed_attempts - settings.attempts_before_backoff)
            self._next_attempt = len(keyframe_poses) + min(settings.retry_every_keyframes << min(backoff, 8),
                                                           settings.max_retry_keyframes)
            return nothing
        self._failed_attempts = 0
        local_frame = keyframe_poses[-1]
        map_from_local = se2.compose(found.pose, se2.inverse(local_frame))
        tracked = self._tracker.finish()
        recovered = se2.compose(map_from_local, tracked.scan_poses(tracked.graph.poses))
        pose = recovered[-1]
        self._pose = pose.copy()
        self._covariance = self._fix_covariance()
        self._map_matched = True
        self._last_odometry = odometry
        self._last_motion = np.zeros(3)
        self._last_stamp, self._motion_span_ns = stamp_ns, 0
        self._odometry_hold.reset()
        self._tracker = None
        self._recent.clear()
        information = self.config.matching.information_scale * found.icp.information
        return LocalizedScan(
            index, stamp_ns, pose.copy(), True, True, found.score, found.icp.inlier_fraction, found.icp.rms,
            information, global_fix=True, map_information=information,
            recovered_indices=np.array(self._tracked[:-1], dtype=np.int64),
            recovered_poses=recovered[:-1].copy(),
        )

    def _global_match(self, keyframe_poses: FloatArray) -> VerifiedMatch | None:
        assert self._tracker is not None
        acceptance = self.settings.acceptance
        recent = slice(max(0, len(keyframe_poses) - 1 - LOOP_QUERY_KEYFRAMES), None)
        query = self._global_query(list(self._tracker.keyframe_scans()[recent]), list(keyframe_poses[recent]),
                                   keyframe_poses[-1])
        if query is None:
            return None
        return match_unambiguous(query, self.map, self._search_center, self._search_window,
                                 matching=self.config.matching, acceptance=acceptance,
                                 levels=self.settings.global_levels, search_grid=self._search_grid)

    def _global_query(self, scans: list[FloatArray], poses: list[FloatArray],
                      frame: FloatArray) -> FloatArray | None:
        """The query of a search on the coarse grid: the scans seen from `frame`, one point per coarse cell,
        at most `global_max_points` (None: too few points)."""
        query = thinned_query(scans, poses, frame, max(LOOP_QUERY_THINNING, self._search_grid.resolution))
        if len(query) < self.config.matching.min_points:
            return None
        # Every candidate of the search scores every query point: an evenly spread share of them bounds
        # and ranks the candidates as well, for a fraction of the work.
        return np.ascontiguousarray(query[:: -(-len(query) // self.settings.global_max_points)])
