"""2D laser SLAM: scans (and wheel odometry) in, a keyframe pose graph with verified loop closures out.

1. Each scan is matched against a local map of recent keyframes: correlative search around the
   prediction (wheel odometry, or constant velocity without it), then point-to-line ICP with the
   prediction as a prior.
2. A scan that moved far enough from the last keyframe becomes a keyframe, tied to the previous one by
   its match; every scan is tied to its keyframe by its own match.
3. At keyframes, older keyframes near the current estimate (a radius growing with the distance since the
   last loop closure) are loop-closure candidates: branch-and-bound over a wide window on the candidate's
   submap, then ICP; accepted on score, inliers and residual.
4. Every few loop closures the graph is re-optimized; a loop closure whose error stays large at the
   optimum is inconsistent with the rest and is removed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.growing_rows import GrowingRows
from frontends.loop_closing import Constraints, HypothesisPool, is_small, optimize_and_prune, path_lengths
from frontends.slam2d.cadence import MatchCadence
from frontends.slam2d.config import (
    HYPOTHESIS_KEYFRAMES,
    LOOP_CANDIDATES_PER_KEYFRAME,
    LOOP_QUERY_KEYFRAMES,
    LOOP_QUERY_THINNING,
    LOOP_SEARCH_EVERY_KEYFRAMES,
    OPTIMIZE_EVERY_LOOP_CLOSURES,
    RELIABLE_ODOMETRY_INTERVAL,
    SMALL_CORRECTION_ANGULAR,
    SMALL_CORRECTION_LINEAR,
    UNRELIABLE_ODOMETRY_SCALE,
    MatchingConfig,
    OdometryConfig,
    Slam2DConfig,
)
from frontends.slam2d.correlative import (
    Match,
    SearchWindow,
    branch_and_bound_levels,
    match_branch_and_bound,
    match_exhaustive,
)
from frontends.slam2d.deskew import ScanDeskewer, along_motion, interpolated
from frontends.slam2d.global_match import match_beyond, match_unambiguous
from frontends.slam2d.grid import LikelihoodGrid
from frontends.slam2d.held_odometry import OdometryHold
from frontends.slam2d.icp import IcpResult, refine_point_to_line, scan_normals
from frontends.slam2d.local_map import Keyframe, Submap, one_per_cell, place
from frontends.slam2d.match_covariance import heading_coupling, score_plateau, slide_to_prior, widened
from frontends.slam2d.motion_prior import after_gap, carried_motion, gap_widening
from frontends.slam2d.stage_times import StageTimes
from optimizer import se2
from optimizer.graph import PoseGraph

if TYPE_CHECKING:
    from frontends.slam2d.resume import ResumedSlam2D, SavedConstraints, SavedScans

FloatArray = NDArray[np.float64]

REOPTIMIZE_ITERATIONS = 15
ODOMETRY_BRANCH_AND_BOUND_LEVELS = 3
COARSE_THINNING = 0.05
"""Without odometry the correlative search reads one scan point per cell of this size (m)."""
NARROW_WINDOW_LINEAR = 0.2
NARROW_WINDOW_ANGULAR = math.radians(10.0)
"""Without odometry the window searched first around the constant-velocity prediction (± m, ± rad)."""
BRANCH_AND_BOUND_LEVELS = 4
"""Coarsest candidates span 2⁴ cells (0.8 m at 5 cm) at least; a wider window gets more levels
(`branch_and_bound_levels`). The optimum does not depend on it; the work does: a 3.2 m block bounds every
pose inside it by nearly the best score anywhere (some wall is always that close), so little is pruned, and
on CSAIL 6 levels cost ~1.4× the verification time of 4."""
FINE_SEARCH_CELLS = 200
"""A loop closure's window is searched on the submap's own grid up to this many cells from its centre (10 m
at 5 cm; 0.08 s a search on a 30 m-range outdoor log). Where the drift allows more (a long path since the
candidate) and that search finds nothing, the whole window is searched on a grid coarse enough to hold it
in as many cells, for a match beyond the fine window (`global_match.match_beyond`). The UAL outdoor log
came back to its start 14 m off after 570 m, beyond any 10 m window, and its map held the street twice,
7 m apart."""
LOCAL_MAP_GROWTH = 4
"""A new keyframe is stamped into the local map in place until the map holds this many keyframes more than
`local_map_keyframes`; the next one builds it again from the last `local_map_keyframes`. Building it
stamps every point of every keyframe (a quarter of the 2D replay's time when built at every keyframe);
adding one stamps that keyframe's alone."""
FAST_TURN_SHARE = 0.5
"""Without odometry, a predicted turn of more than this share of the angular window is a fast turn, where
the turn may stop or swing back within a scan: the last pose's window is searched too (`_match`)."""
LOCAL_MAP_SLACK = 2.0
"""The local map's grid reaches this much (m) beyond its margin, room for the keyframes added in place."""
LOOP_SUBMAPS_KEPT_CELLS = 4_000_000
"""The submaps of the last loop search's candidates are kept, with their pyramids, for the next search when
their grids hold at most this many cells: 32 MB each, and at most 96 MB more for a fine search's six pyramid
levels (the UAL vehicle's, 30 m scans: 1.4–1.8 M cells; its replay peaked 100 MB higher). A robot coming back
along an old path searches the same candidates from keyframe after keyframe while their poses stay put (UAL:
keyframes 0 and 13, 40 times each), and building their grid and pyramid was most of each search."""


@dataclass(frozen=True, eq=False)
class ScanEstimate:
    """What the frontend concluded about one scan when it processed it."""

    index: int
    stamp_ns: int
    pose: FloatArray
    """(x, y, θ) in the map frame at processing time."""
    matched: bool
    """False when the scan could not be matched and its pose is the prediction."""
    keyframe: int
    new_loop_closures: tuple[tuple[int, int], ...]
    """Loop closures (older keyframe, this keyframe) accepted while processing this scan."""
    points: FloatArray | None = None
    """The scan's points (N, 2) in the base frame, deskewed (`LaserFrontend.add`); None: as measured."""
    between: bool = False
    """Not matched by design: a fast laser's scan between two matched ones (`frontends.slam2d.cadence`).
    Its `pose` is predicted from the last matched scan; the graph's is interpolated once the next one is
    matched."""


@dataclass(frozen=True, eq=False)
class Slam2DGraph:
    """The frontend's result: the keyframe graph and how every scan hangs off its keyframe."""

    graph: PoseGraph
    """Keyframe poses as estimated online (loop closures applied); constraints odometry then loops."""
    scan_stamps_ns: NDArray[np.int64]
    scan_keyframes: NDArray[np.int64]
    scan_offsets: FloatArray
    """(S, 3) pose of each scan in the frame of its keyframe."""
    keyframe_scans: tuple[FloatArray, ...]
    """Each keyframe's points in its own frame (for maps)."""
    odometry_chain: FloatArray
    """(K, 3) keyframe poses from the odometry constraints alone (no loop closures): a poor start."""
    loop_closures_accepted: int
    loop_closures_rejected: int
    scans_unmatched: int
    loop_closures_unconfirmed: int = 0
    """Loop closures that waited for a second, agreeing one in vain (expired, or void after the map moved)."""
    scans_between: int = 0
    """Scans not matched by design, posed between matched ones (`ScanEstimate.between`)."""
    stage_times: StageTimes = field(default_factory=StageTimes)
    """Where the frontend spent its time (matching, keyframes, loop search, verification, online
    optimization)."""

    def scan_poses(self, keyframe_poses: FloatArray) -> FloatArray:
        """Every scan's pose given (optimized) keyframe poses."""
        return se2.compose(keyframe_poses[self.scan_keyframes], self.scan_offsets)


@dataclass(frozen=True, eq=False)
class _LoopHypothesis:
    candidate: int
    current: int
    measurement: FloatArray
    information: FloatArray
    correction: FloatArray
    """Matched pose ∘ estimated pose⁻¹ of the current keyframe: how far the match moves the map."""


def predicted_motion(settings: OdometryConfig, last_odometry: FloatArray | None, odometry: FloatArray | None,
                     reliable: bool, last_motion: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The motion since the last scan and its information: from wheel odometry when both scans have it
    (uncertainty growing with the distance and turn, scaled up when the odometry is `reliable` no more),
    else the last motion again (constant velocity, loosely)."""
    if odometry is not None and last_odometry is not None:
        motion = se2.relative(last_odometry, np.asarray(odometry, dtype=np.float64))
        distance = float(np.hypot(motion[0], motion[1]))
        sigma_linear = settings.odometry_sigma_linear + settings.odometry_sigma_per_metre * distance
        sigma_angular = settings.odometry_sigma_angular + settings.odometry_sigma_per_radian * abs(motion[2])
        if not reliable:
            sigma_linear *= UNRELIABLE_ODOMETRY_SCALE
            sigma_angular *= UNRELIABLE_ODOMETRY_SCALE
    else:
        motion = last_motion
        sigma_linear = settings.constant_velocity_sigma_linear
        sigma_angular = settings.constant_velocity_sigma_angular
    return motion, np.diag([sigma_linear**-2, sigma_linear**-2, sigma_angular**-2])


def points_to_match(points: ArrayLike, point_times: ArrayLike | None,
                    matching: MatchingConfig) -> tuple[FloatArray, FloatArray | None]:
    """A scan's points (N, 2) as the trackers match them, with their times (None without, or when not
    deskewing): those within `max_range`, one per half cell of the matching grid (as the local map keeps
    them). A dense laser's extra points near the robot would otherwise outweigh the rest of the scan in
    every match, and its matches claim an information that grows with the beam count: a simulated drive
    of 4 000 beams a scan erred by 0.026 m median against 0.013 at 1 440; thinned, 0.013."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    kept = np.flatnonzero(np.einsum("ij,ij->i", points, points) <= matching.max_range**2)
    kept = kept[one_per_cell(points[kept], 0.5 * matching.resolution)]
    times = None if point_times is None or not matching.deskew else np.asarray(point_times)[kept]
    return np.ascontiguousarray(points[kept]), times


def match_without_odometry(
    points: FloatArray, grid: LikelihoodGrid, prior: FloatArray, window: SearchWindow, *,
    narrow_first: bool = True
) -> tuple[Match | None, SearchWindow]:
    """The correlative start for ICP when only constant velocity predicts the motion, and the window it
    lies in: `window`, or that window turning twice as far past an optimum on its angular edge.

    An optimum on the window's angular edge may be the edge of a better one beyond: the robot turned more
    than the window allows for beyond the prediction (a scan dropped during a turn, a swing), and the track
    is lost if it is taken (simulated turns outrunning a ±35° window by 2–18°: the heading ended 36–58°
    off). The window is then searched turning twice as far (`SearchWindow.turned_past`), and an optimum
    scoring better beyond the edge taken. The Intel Research Lab log without odometry and 15 % of its scans
    dropped turned 42° in one scan where 5° were predicted.

    The search reads one point per `COARSE_THINNING` cell (dense returns near the robot count once; ICP
    then uses them all). The narrow window around the prediction is searched first, exhaustively: the
    prediction is usually close, and an optimum inside the narrow window is taken (the wide window's
    optimum may lie elsewhere: a look-alike pose farther from the prediction, which the old search would
    have taken). Only an optimum in the narrow window's outer half (the motion changed more than usual) calls
    for the wide window, by branch and bound, which then only has to beat the narrow optimum. Without
    `narrow_first` (after a gap, `GAP_WIDENING`) the wide window is searched at once."""
    coarse_points = np.ascontiguousarray(points[one_per_cell(points, COARSE_THINNING)])
    found = _match_in_window(coarse_points, grid, prior, window, narrow_first)
    wider = None if found is None else window.turned_past(found.pose, prior)
    if found is None or wider is None:
        return found, window
    beyond = match_branch_and_bound(coarse_points, grid, prior, wider, found.score * (1.0 + 1e-12),
                                    levels=ODOMETRY_BRANCH_AND_BOUND_LEVELS)
    return (found, window) if beyond is None else (beyond, wider)


def _match_in_window(coarse_points: FloatArray, grid: LikelihoodGrid, prior: FloatArray,
                     window: SearchWindow, narrow_first: bool) -> Match | None:
    """`match_without_odometry` within `window`, of the thinned points."""
    if not narrow_first:
        return match_branch_and_bound(coarse_points, grid, prior, window, 0.0,
                                      levels=ODOMETRY_BRANCH_AND_BOUND_LEVELS)
    narrow_window = SearchWindow(min(NARROW_WINDOW_LINEAR, window.linear),
                                 min(NARROW_WINDOW_ANGULAR, window.angular), window.angular_step)
    narrow = match_exhaustive(coarse_points, grid, prior, narrow_window)
    cells = round(float(np.max(np.abs(narrow.pose[:2] - prior[:2]))) / grid.resolution)
    steps = round(abs(float(narrow.pose[2] - prior[2])) / window.angular_step)
    # Beyond half the narrow window the prediction was off by more than it usually is (a quick turn, a
    # jolt), and the narrow window may have cut the true optimum off.
    far = (2 * cells >= math.ceil(narrow_window.linear / grid.resolution - 1e-9)
           or 2 * steps >= math.floor(narrow_window.angular / window.angular_step))
    if far and narrow_window != window:
        # Anything better than the narrow optimum: the wide optimum itself, with far less to explore.
        wide = match_branch_and_bound(coarse_points, grid, prior, window, narrow.score * (1.0 - 1e-12),
                                      levels=ODOMETRY_BRANCH_AND_BOUND_LEVELS)
        if wide is not None:
            return wide
    return narrow if narrow.score > 0.0 else None  # nothing scores: as the branch and bound says


class LaserSlam2D:
    """Feed scans in time order with `add_scan`; `finish` returns the keyframe graph."""

    def __init__(self, config: Slam2DConfig | None = None) -> None:
        self.config = config or Slam2DConfig()
        self._keyframe_poses: list[FloatArray] = []
        self._keyframe_rows = GrowingRows((3,), np.float64)
        """`_keyframe_poses` as one array (`_set_keyframe_poses`, `_add_keyframe_untimed` keep both)."""
        self._keyframes: list[Keyframe] = []
        self._edges = Constraints(measurement_shape=(3,), information_size=3)
        self._scan_stamps: list[int] = []
        self._scan_keyframes: list[int] = []
        self._scan_offsets: list[FloatArray] = []
        self._last_pose = np.zeros(3)
        self._last_odometry: FloatArray | None = None
        self._keyframe_odometry: FloatArray | None = None
        """The wheel odometry at the last keyframe (None: that scan had none)."""
        self._last_motion = np.zeros(3)
        self._cadence = MatchCadence(self.config.matching.min_match_interval)
        self._last_matched: tuple[int, int] | None = None
        """The index and stamp of the last matched scan (or of the first scan)."""
        self._matched_interval_ns = 0
        """The time between the last two matched scans: the span of `_last_motion`."""
        self._between: list[int] = []
        """The scans since the last matched one, posed by interpolation when the next one is matched."""
        self._scans_between = 0
        self._odometry_hold = OdometryHold()
        """While the wheel odometry repeats its last value: the motion tracked since it last changed."""
        self._deskewer = ScanDeskewer()
        self._local_map: Submap | None = None
        self._loop_submaps: dict[tuple[int, ...], tuple[FloatArray, float, Submap]] = {}
        """The last loop searches' submaps by their keyframes, with those keyframes' poses and the margin
        they were built with (`_loop_submap`)."""
        self._failed_wide_searches: dict[int, int] = {}
        """Candidates searched beyond the fine window in vain, each with the keyframe that searched them
        (`_searched_wide_in_vain`); forgotten when the poses move."""
        self._local_map_first = 0
        """The oldest keyframe in the local map (the map holds it and every later one)."""
        self._pending_loops = 0
        self._travel = 0.0
        """How far the keyframes have travelled (m), step by step."""
        self._last_closure_travel = -math.inf
        """`_travel` at the last keyframe that closed a loop."""
        self._hypotheses: HypothesisPool[_LoopHypothesis] = HypothesisPool(SMALL_CORRECTION_LINEAR,
                                                                           SMALL_CORRECTION_ANGULAR)
        self._rejected = 0
        self._unmatched = 0
        self.stage_times = StageTimes()

    @classmethod
    def resume(
        cls,
        keyframe_scans: Sequence[FloatArray],
        keyframe_poses: FloatArray,
        constraints: SavedConstraints,
        config: Slam2DConfig | None = None,
        *,
        scans: SavedScans | None = None,
        placed_by_caller: bool = False,
    ) -> ResumedSlam2D:
        """Continue mapping from a saved keyframe graph (`frontends.slam2d.resume`): the new run is placed
        in the old map by global localization (the caller's, when `placed_by_caller`), its keyframes get
        indices after the old ones, loop closures search old and new keyframes alike, and `finish` returns
        the joint graph."""
        from frontends.slam2d.resume import ResumedSlam2D  # the subclass imports this module

        return ResumedSlam2D(keyframe_scans, keyframe_poses, constraints, config, scans=scans,
                             placed_by_caller=placed_by_caller)

    # ------------------------------------------------------------------------------------------ scans

    def add_scan(
        self,
        stamp_ns: int,
        points: FloatArray,
        odometry: FloatArray | None = None,
        odometry_interval: float = 0.0,
        point_times: FloatArray | None = None,
    ) -> ScanEstimate:
        """Process one scan: `points` (N, 2) in the robot base frame, `odometry` its wheel-odometry pose,
        interpolated between messages `odometry_interval` seconds apart (0: a message at the scan's stamp),
        `point_times` (N,) when each point was taken (s after `stamp_ns`; None: all at the stamp)."""
        due = self._cadence.due(int(stamp_ns))
        if not due and self._local_map is not None and self._last_matched is not None:
            return self._add_scan_between(int(stamp_ns), self._motion_since_matched(int(stamp_ns), odometry))
        matching = self.config.matching
        points, times = points_to_match(points, point_times, matching)
        index = len(self._scan_stamps)
        new_loops: tuple[tuple[int, int], ...] = ()
        if not self._keyframe_poses:
            pose, matched, information = np.zeros(3), True, np.eye(3)
            self._add_keyframe(pose, points, None, information)
            self._keyframe_odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        else:
            reliable = odometry_interval <= RELIABLE_ODOMETRY_INTERVAL
            with self.stage_times.stage("matching"):
                prior, prior_information = self._predict(int(stamp_ns), odometry, reliable)
                odometry_motion = (None if odometry is None or self._last_odometry is None
                                   else se2.relative(self._last_pose, prior))
                window_scale = 1.0 if reliable else UNRELIABLE_ODOMETRY_SCALE
                deskewed = self._deskewer.deskewed(points, times, int(stamp_ns), odometry_motion)
                pose, matched, information = self._match(int(stamp_ns), deskewed, prior, prior_information,
                                                         window_scale)
                if matched and times is not None and odometry_motion is None:
                    # Deskewed under the motions before the scan, a scan period late at every change of
                    # pace; matched, the scan's own motion is known: deskewed again with it, and matched.
                    own_motion = se2.relative(self._last_pose, pose)
                    deskewed = self._deskewer.deskewed(points, times, int(stamp_ns), None, own_motion)
                    pose, matched, information = self._match(int(stamp_ns), deskewed, prior,
                                                             prior_information, window_scale)
                points = deskewed
                self._last_motion = se2.relative(self._last_pose, pose)
                self._last_pose = pose
            last_keyframe = self._keyframe_poses[-1]
            step = se2.relative(last_keyframe, pose)
            keyframes = self.config.keyframes
            elapsed = (int(stamp_ns) - self._last_matched[1]) * 1e-9 if self._last_matched else 0.0
            turning_fast = abs(self._last_motion[2]) > keyframes.max_turn_rate * max(elapsed, 1e-3)
            moved = np.hypot(step[0], step[1]) >= keyframes.distance or abs(step[2]) >= keyframes.angle
            # Without a usable local map (the first scans were empty) any scan with points starts one.
            if (moved and not turning_fast) or (
                self._local_map is None and len(points) >= matching.min_points
            ):
                information = self._step_information(information, odometry, reliable)
                self._add_keyframe(pose, points, step, information)
                self._keyframe_odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
                with self.stage_times.stage("loop_search"):
                    new_loops = self._close_loops()
                pose = self._last_pose  # the loop closures may have moved it
        self._last_odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        self._deskewer.moved(int(stamp_ns), self._last_motion if index else None)
        self._append_scan(int(stamp_ns), len(self._keyframe_poses) - 1, pose)
        self._pose_between(pose)
        keyframe = len(self._keyframe_poses) - 1
        self._unmatched += not matched
        return ScanEstimate(index, int(stamp_ns), pose.copy(), matched, keyframe, new_loops)

    def _append_scan(self, stamp_ns: int, keyframe: int, pose: FloatArray) -> None:
        """A scan at `pose`, hung off `keyframe`."""
        self._scan_stamps.append(stamp_ns)
        self._scan_keyframes.append(keyframe)
        self._scan_offsets.append(se2.relative(self._keyframe_poses[keyframe], pose))

    def odometry_restarts(self) -> None:
        """The next scan's odometry is in another frame (its source changed, e.g. the wheels' taking over
        from the scans' own): no motion is measured across the change, to the last scan nor to the last
        keyframe, as at the first scan."""
        self._last_odometry = None
        self._keyframe_odometry = None
        self._odometry_hold.reset()

    def _motion_since_matched(self, stamp_ns: int, odometry: FloatArray | None) -> FloatArray:
        """The motion predicted from the last matched scan to the scan at `stamp_ns`: the odometry's, or the
        last matched motion at constant velocity."""
        assert self._last_matched is not None
        if odometry is not None and self._last_odometry is not None:
            return se2.relative(self._last_odometry, np.asarray(odometry, dtype=np.float64))
        elapsed = stamp_ns - self._last_matched[1]
        fraction = elapsed / self._matched_interval_ns if self._matched_interval_ns > 0 else 0.0
        return along_motion(self._last_motion, np.array([fraction]))[0]

    def _add_scan_between(self, stamp_ns: int, motion: FloatArray) -> ScanEstimate:
        """A scan the cadence skips, posed for now by the `motion` predicted since the last matched scan."""
        pose = se2.compose(self._last_pose, motion)
        index, keyframe = len(self._scan_stamps), len(self._keyframe_poses) - 1
        self._append_scan(stamp_ns, keyframe, pose)
        self._between.append(index)
        self._scans_between += 1
        return ScanEstimate(index, stamp_ns, pose.copy(), False, keyframe, (), between=True)

    def _pose_between(self, pose: FloatArray) -> None:
        """The newest scan was matched at `pose` (or is the first, or starts a run in a saved map): the scans
        since the one matched before are placed between the two at constant velocity (they are at most a
        `min_match_interval` apart). Then it is the last matched scan."""
        index = len(self._scan_stamps) - 1
        stamp = self._scan_stamps[index]
        self._cadence.matched(stamp)
        if self._between and self._last_matched is not None:
            last_index, last_stamp = self._last_matched
            last_keyframe = self._scan_keyframes[last_index]
            start = se2.compose(self._keyframe_poses[last_keyframe], self._scan_offsets[last_index])
            stamps = np.array([self._scan_stamps[k] for k in self._between], dtype=np.int64)
            span = stamp - last_stamp
            fractions = (stamps - last_stamp) / span if span > 0 else np.zeros(len(stamps))
            poses = interpolated(start, pose, fractions)
            # No keyframe is made between matched scans: they all hang off the one the last matched did.
            keyframe = self._keyframe_poses[self._scan_keyframes[self._between[0]]]
            for k, offset in zip(self._between, se2.relative(keyframe, poses), strict=True):
                self._scan_offsets[k] = offset
        self._between.clear()
        self._matched_interval_ns = 0 if self._last_matched is None else stamp - self._last_matched[1]
        self._last_matched = (index, stamp)

    def _predict(self, stamp_ns: int, odometry: FloatArray | None,
                 reliable: bool) -> tuple[FloatArray, FloatArray]:
        """The prior of the scan's match: the last pose moved by the odometry (`predicted_motion`), or
        without it by the last matched motion carried over the time since (`_carried_motion`), its σ
        widened after a gap (`_gap_widening`).

        A jump that ends a hold of the odometry is applied from where the hold began (`OdometryHold`):
        else the match lands on a wrong wall around a prior a whole turn off, and the keyframe step
        carries it into the graph."""
        settings = self.config.odometry
        constant_velocity = odometry is None or self._last_odometry is None  # `predicted_motion`'s branch
        last_motion = self._carried_motion(stamp_ns) if constant_velocity else self._last_motion
        motion, information = predicted_motion(settings, self._last_odometry, odometry, reliable, last_motion)
        if constant_velocity:
            linear, angular = self._gap_widening(stamp_ns)
            information = information / np.array([linear, linear, angular]) ** 2
        motion = self._odometry_hold.corrected(motion, self._last_odometry, odometry, self._last_motion,
                                               settings.window_linear, settings.window_angular)
        return se2.compose(self._last_pose, motion), information

    def _carried_motion(self, stamp_ns: int) -> FloatArray:
        """The last matched motion carried over the time since the last matched scan (`carried_motion`)."""
        if self._last_matched is None:
            return self._last_motion
        rate = self._cadence.rate
        return carried_motion(self._last_motion, rate.scan_time(self._matched_interval_ns),
                              self._scan_time(stamp_ns))

    def _gap_widening(self, stamp_ns: int) -> tuple[float, float]:
        """`gap_widening` over the time since the last matched scan."""
        if self._last_matched is None:
            return 1.0, 1.0
        return gap_widening(self.config.odometry, self._scan_time(stamp_ns))

    def _scan_time(self, stamp_ns: int) -> int:
        """The time since the last matched scan, as the stamps tell it (`ScanRate.scan_time`); 0 before it."""
        if self._last_matched is None:
            return 0
        return self._cadence.rate.scan_time(stamp_ns - self._last_matched[1])

    def _match(
        self, stamp_ns: int, points: FloatArray, prior: FloatArray, prior_information: FloatArray,
        window_scale: float
    ) -> tuple[FloatArray, bool, FloatArray]:
        """The scan's pose, whether a match gave it (else the prior's), and its information.

        Without odometry a match that fails around the constant-velocity prior is tried again around the
        last pose (no motion): constant velocity overshoots where the motion reverses. On the Intel Research
        Lab log the robot swings in place, 30° one way then 5° back within a scan; predicted another 30°, the
        scan fell outside the window, the pose followed the prior, the prior's motion became the velocity,
        and the next scans ran away with it, metres per scan. During a fast turn (the prediction turns by more
        than half the window) the last pose's window is searched even when the prediction's matched: a
        laser seeing 180° matched a scan that swung back 35° after turning 24° to a wrong pose 24° off inside
        the prediction's window. The better-scoring of two different optima is taken (the same optimum
        found twice: the prediction's). A match is still refused where ICP slid beyond the window searched
        around either (`_match_around`)."""
        result = self._match_around(stamp_ns, points, prior, prior, prior_information, window_scale)
        if self._last_odometry is not None:
            return result[:3]
        moved = se2.relative(self._last_pose, prior)
        if not np.any(moved):
            return result[:3]
        turning = abs(moved[2]) > FAST_TURN_SHARE * self.config.odometry.window_angular_without_odometry
        if result[1] and not turning:
            return result[:3]
        still = self._match_around(stamp_ns, points, self._last_pose, prior, prior_information, window_scale)
        better = still[3] > result[3] and not self._same_pose(still[0], result[0])
        return still[:3] if still[1] and (not result[1] or better) else result[:3]

    def _same_pose(self, a: FloatArray, b: FloatArray) -> bool:
        """Whether two matches found the same optimum: within a cell and an angular step."""
        return is_small(se2.relative(a, b), self.config.matching.resolution,
                        self.config.odometry.angular_step)

    def _match_around(
        self, stamp_ns: int, points: FloatArray, center: FloatArray, prior: FloatArray,
        prior_information: FloatArray, window_scale: float
    ) -> tuple[FloatArray, bool, FloatArray, float]:
        """`_match` searching the window around `center`; the prior weighs in ICP and along look-alike
        stretches all the same (where a corridor leaves the motion along it open, the prediction's is the
        better guess than none)."""
        matching = self.config.matching
        settings = self.config.odometry
        has_odometry = self._last_odometry is not None
        matched, score = False, -1.0
        pose, information = prior, prior_information
        if len(points) >= matching.min_points and self._local_map is not None:
            coarse: Match | None
            if has_odometry:
                window = SearchWindow(settings.window_linear * window_scale,
                                      settings.window_angular * window_scale, settings.angular_step)
                coarse = match_exhaustive(points, self._local_map.grid, center, window)
            else:
                linear, angular = self._gap_widening(stamp_ns)
                window = SearchWindow(settings.window_linear_without_odometry * linear,
                                      settings.window_angular_without_odometry * angular,
                                      settings.angular_step)
                elapsed = self._scan_time(stamp_ns)
                gap = after_gap((linear, angular), elapsed, self._cadence.rate.typical_ns)
                coarse, window = match_without_odometry(points, self._local_map.grid, center, window,
                                                        narrow_first=not gap)
            local = self._local_map
            start = center if coarse is None else coarse.pose
            score = -1.0 if coarse is None else coarse.score
            refined = refine_point_to_line(
                points,
                local.grid,
                local.points,
                local.normals,
                start,
                max_distance=matching.icp_max_distance,
                sigma=matching.point_sigma,
                prior=prior,
                prior_information=prior_information,
            )
            # Without odometry the window spans any plausible motion: ICP ending beyond it slid along a
            # corridor (Intel lidar-only: 2.5 m in one scan). The odometry's window is tight, and ICP rightly
            # leaves it where the wheels slipped (CSAIL's turns: its map bent when such matches were refused).
            slid = not has_odometry and not window.holds(refined.pose, center, local.grid.resolution)
            if coarse is not None and refined.inlier_fraction >= settings.min_inlier_fraction and not slid:
                pose, matched = refined.pose, True
                information = matching.information_scale * refined.information
                # Along a look-alike stretch the prediction decides (`match_covariance`).
                # The scan's own information (the prior taken out) says how a slide turns (an arc's wall).
                coupling = heading_coupling(refined.information - prior_information)
                pose, information = slide_to_prior(pose, information, prior, prior_information,
                                                   score_plateau(points, local.grid, pose,
                                                                 heading_per_metre=coupling))
        return pose, matched, information, score

    def _step_information(self, information: FloatArray, odometry: FloatArray | None,
                          reliable: bool) -> FloatArray:
        """The information of the constraint from the last keyframe to a new one: the match's, and the
        wheel odometry's over the whole step.

        Along a direction the scan does not pin (a featureless corridor, a hall seen across), the match
        follows the odometry prior of its last scan, weighed by `information_scale` like the ICP Hessian
        it sits in: a σ of a quarter metre per keyframe there. The optimizer then bends such stretches
        freely, by metres, to absorb the misfit of loop closures elsewhere, while the wheels measured the
        step to centimetres. Fused with the odometry's own information over the step, the constraint is
        weak along such a direction only as far as the odometry is."""
        if odometry is None or self._keyframe_odometry is None:
            return information
        _, odometry_information = predicted_motion(self.config.odometry, self._keyframe_odometry, odometry,
                                                   reliable, self._last_motion)
        return information + odometry_information

    # -------------------------------------------------------------------------------------- keyframes

    def _add_keyframe(
        self, pose: FloatArray, points: FloatArray, step: FloatArray | None, information: FloatArray
    ) -> None:
        with self.stage_times.stage("keyframes"):
            self._add_keyframe_untimed(pose, points, step, information)

    def _add_keyframe_untimed(
        self, pose: FloatArray, points: FloatArray, step: FloatArray | None, information: FloatArray
    ) -> None:
        self._keyframe_poses.append(np.array(pose, dtype=np.float64))
        self._keyframe_rows.append(pose)
        self._keyframes.append(Keyframe(points, scan_normals(points)))
        self._last_pose = np.array(pose, dtype=np.float64)
        count = len(self._keyframe_poses)
        if step is not None:
            self._edges.add(count - 2, count - 1, step, information, is_loop=False)
            self._travel += math.hypot(step[0], step[1])
        self._extend_local_map()

    def _local_map_margin(self) -> float:
        """How far beyond its points the local map's grid reaches: the widest odometry search window."""
        return self.config.odometry.window_linear_without_odometry + 1.0

    def _extend_local_map(self) -> None:
        """Add the newest keyframe to the local map in place (`Submap.extended`), or build the map again
        from the last `local_map_keyframes` when it holds `LOCAL_MAP_GROWTH` keyframes more than that, or
        the keyframe reaches past its grid."""
        matching = self.config.matching
        local = self._local_map
        held = len(self._keyframe_poses) - 1 - self._local_map_first
        if local is not None and held < self.config.keyframes.local_map_keyframes + LOCAL_MAP_GROWTH:
            extended = local.extended(self._keyframes[-1], self._keyframe_poses[-1],
                                      likelihood_sigma=matching.likelihood_sigma,
                                      margin=self._local_map_margin(),
                                      pairing_distance=matching.icp_max_distance)
            if extended is not None:
                self._local_map = extended
                return
        self._rebuild_local_map()

    def _rebuild_local_map(self) -> None:
        self._local_map_first = max(0, len(self._keyframe_poses) - self.config.keyframes.local_map_keyframes)
        recent = slice(self._local_map_first, None)
        matching = self.config.matching
        keyframes = self._keyframes[recent]
        if sum(len(k.points) for k in keyframes) < matching.min_points:
            self._local_map = None
            return
        margin = self._local_map_margin()
        self._local_map = Submap.of(
            keyframes,
            self._keyframe_poses[recent],
            resolution=matching.resolution,
            likelihood_sigma=matching.likelihood_sigma,
            margin=margin + LOCAL_MAP_SLACK,
            pairing_distance=matching.icp_max_distance,
            reach=2.0 * matching.max_range + margin,
        )

    # ---------------------------------------------------------------------------------- loop closures

    def _close_loops(self) -> tuple[tuple[int, int], ...]:
        settings = self.config.loop_closure
        current = len(self._keyframe_poses) - 1
        if not settings.enabled or current % LOOP_SEARCH_EVERY_KEYFRAMES:
            return ()
        if self._travel - self._last_closure_travel < settings.travel_between_closures:
            return ()
        scan = self._keyframes[current].points
        if len(scan) < self.config.matching.min_points:
            return ()
        older = current - settings.min_separation_keyframes
        if older < 0:
            return ()
        positions = self._keyframe_rows.rows()[: older + 1, :2]
        here = self._keyframe_poses[current]
        distance = np.hypot(*(positions - here[:2]).T)
        # The drift between two keyframes grows with the path joining them in the graph (through the
        # loop closures already made), not with the time since the last loop closure anywhere; no
        # keyframe within the largest radius needs no path lengths.
        radius = np.full(older + 1, settings.max_search_radius)
        if np.any(distance <= settings.max_search_radius):
            radius = settings.search_radii(self._path_lengths_to(current)[: older + 1])
        fine = np.minimum(radius, FINE_SEARCH_CELLS * self.config.matching.resolution)
        candidates = self._loop_candidates(distance, fine) or self._loop_candidates(distance, radius)
        in_vain = self._searched_wide_in_vain(candidates, current)
        found = []
        accepted_now: list[_LoopHypothesis] = []
        self._hypotheses.expire(current, HYPOTHESIS_KEYFRAMES)
        for candidate, wide_in_vain in zip(candidates, in_vain, strict=True):
            fine_first = bool(distance[candidate] <= fine[candidate])
            searched_radius = float(fine[candidate] if wide_in_vain else radius[candidate])
            if not fine_first and searched_radius <= fine[candidate]:
                continue  # nothing to search: neither window
            with self.stage_times.stage("verification"):
                hypothesis = self._verify_loop(candidate, current, float(fine[candidate]), searched_radius,
                                               fine_first)
            if hypothesis is None:
                if searched_radius > fine[candidate]:
                    self._failed_wide_searches[candidate] = current
                continue
            for accepted in self._hypotheses.confirm(hypothesis):
                self._edges.add(accepted.candidate, accepted.current, accepted.measurement,
                                accepted.information, is_loop=True)
                found.append((accepted.candidate, accepted.current))
                accepted_now.append(accepted)
        if found:
            self._last_closure_travel = self._travel
            self._pending_loops += len(found)
            if self._optimization_due(accepted_now):
                self.optimize_online()
        return tuple(found)

    def _optimization_due(self, accepted: Sequence[_LoopHypothesis]) -> bool:
        """Whether the loop closures just `accepted` call for an online optimization now (a hook: the
        resumed SLAM also optimizes when they move the map far)."""
        return self._pending_loops >= OPTIMIZE_EVERY_LOOP_CLOSURES

    def _path_lengths_to(self, keyframe: int) -> FloatArray:
        """Shortest path length (m) through the graph's constraints from `keyframe` to every keyframe."""
        first, second, lengths = self._edges.path_columns()
        return path_lengths(len(self._keyframe_poses), first, second, lengths, keyframe)

    def _loop_candidates(self, distance: FloatArray, radius: FloatArray) -> list[int]:
        """Up to `LOOP_CANDIDATES_PER_KEYFRAME` keyframes within `radius` of the current one (`distance`
        away), the nearest for its radius first, each a submap away from the others."""
        spacing = self.config.loop_closure.submap_keyframes
        candidates: list[int] = []
        for candidate in np.argsort(distance / radius):
            if distance[candidate] > radius[candidate] or len(candidates) >= LOOP_CANDIDATES_PER_KEYFRAME:
                break
            if all(abs(int(candidate) - c) > spacing for c in candidates):
                candidates.append(int(candidate))
        return candidates

    def _searched_wide_in_vain(self, candidates: list[int], current: int) -> list[bool]:
        """For each of the `candidates`: whether a recent query searched its submap beyond the fine window in
        vain (`match_beyond`) — a query sharing a keyframe with the current one (`LOOP_QUERY_KEYFRAMES`),
        against a candidate a submap apart or less, since the poses last moved. Such a candidate's fine
        window is still searched, its wide one is not: a wide search seeing nearly the same points on
        nearly the same submap fails again. The UAL vehicle, 14 m off when it drove 44 m back along its
        start, searched wide 116 times in vain before its 3 matches (0.65 s of its 4 s replay): 23 now,
        with the same matches and trajectory. On every other log we have, no wide search skipped would have
        matched (their trajectories are unchanged to the 0.1 mm). Skipping fine searches after a failure
        too skipped matches: as the query grows, a fine search fails and then matches, and two agreeing
        matches confirm a loop closure. Without wheel odometry ACES's map broke (0.06 → 1.95 m from its
        run with odometry), and so did Intel's with 15 % of its scans dropped (0.04 → 6.1 m)."""
        self._failed_wide_searches = {
            candidate: searched for candidate, searched in self._failed_wide_searches.items()
            if current - searched <= LOOP_QUERY_KEYFRAMES
        }
        spacing = self.config.loop_closure.submap_keyframes
        failed = self._failed_wide_searches
        return [any(abs(candidate - f) <= spacing for f in failed) for candidate in candidates]

    def _verify_loop(self, candidate: int, current: int, fine_radius: float, radius: float,
                     fine_first: bool) -> _LoopHypothesis | None:
        """The loop closure from `candidate`'s submap to the current keyframe, or None: searched within
        `fine_radius` on the submap's grid (`fine_first`: the candidate is that near), and where that finds
        none, within the drift's whole `radius` on a coarser grid for a match beyond the fine window
        (`match_beyond`)."""
        settings = self.config.loop_closure
        matching = self.config.matching
        submap = self._loop_submap(self._loop_submap_members(candidate, current, fine_radius + 1.0),
                                   fine_radius + 1.0)
        here = self._keyframe_poses[current]
        query = self._query_points(current)
        window = SearchWindow(fine_radius, settings.angular_window, settings.angular_step)
        verified = None
        if fine_first:
            levels = branch_and_bound_levels(fine_radius, matching.resolution,
                                             minimum=BRANCH_AND_BOUND_LEVELS)
            verified = match_unambiguous(query, submap, here, window, matching=matching, acceptance=settings,
                                         levels=levels, crop_pyramid=True)
        if verified is None and radius > fine_radius:
            verified = match_beyond(query, submap, here, window, radius, matching=matching,
                                    acceptance=settings, cells=FINE_SEARCH_CELLS,
                                    min_levels=BRANCH_AND_BOUND_LEVELS)
        if verified is None:
            return None
        refined = verified.icp
        z = se2.relative(self._keyframe_poses[candidate], refined.pose)
        correction = se2.compose(refined.pose, se2.inverse(here))
        information = self._loop_information(query, submap, refined)
        return _LoopHypothesis(candidate, current, z, information, correction)

    def _loop_submap_members(self, candidate: int, current: int, margin: float) -> tuple[int, ...]:
        """The keyframes of `candidate`'s submap for a search from `current`: its neighbours by index, not
        too recent, within reach of it (a submap with `margin`)."""
        settings = self.config.loop_closure
        around = range(
            max(0, candidate - settings.submap_keyframes),
            min(current - settings.min_separation_keyframes, candidate + settings.submap_keyframes) + 1,
        )
        # Neighbours by index are neighbours in space within one run, not across the seam of a resumed
        # session (the saved map's last keyframe, the new run's first): those out of the candidate's reach
        # share no wall with it and would only stretch the grid between two places.
        reach = 2.0 * self.config.matching.max_range + margin
        centre = self._keyframe_poses[candidate][:2]
        return tuple(k for k in around if math.hypot(*(self._keyframe_poses[k][:2] - centre)) <= reach)

    def _loop_submap(self, members: tuple[int, ...], margin: float) -> Submap:
        """The submap of these keyframes with `margin`: the one a recent search built while none of them
        moved (`LOOP_SUBMAPS_KEPT_CELLS`), else built now."""
        matching = self.config.matching
        poses = np.array([self._keyframe_poses[k] for k in members])
        key = members
        kept = self._loop_submaps.pop(key, None)
        if kept is not None and kept[1] == margin and np.array_equal(kept[0], poses):
            submap = kept[2]
        else:
            submap = Submap.of([self._keyframes[k] for k in members], list(poses),
                               resolution=matching.resolution, likelihood_sigma=matching.likelihood_sigma,
                               margin=margin, pairing_distance=matching.icp_max_distance)
        if submap.grid.values.size <= LOOP_SUBMAPS_KEPT_CELLS:
            self._loop_submaps[key] = (poses, margin, submap)  # the newest last
            while len(self._loop_submaps) > LOOP_CANDIDATES_PER_KEYFRAME:
                del self._loop_submaps[next(iter(self._loop_submaps))]
        return submap

    def _loop_information(self, query: FloatArray, submap: Submap, refined: IcpResult) -> FloatArray:
        """The loop closure's information: the ICP Hessian's, widened along a score plateau (a stretch of
        corridor the query fits anywhere along, `match_covariance`): in the submap's frame, as the match."""
        information = self.config.matching.information_scale * refined.information
        plateau = score_plateau(query, submap.grid, refined.pose)
        if not plateau.is_slide:
            return information
        return widened(information, plateau)

    def _query_points(self, current: int) -> FloatArray:
        """The current keyframe's scan with the previous few, in its frame, thinned."""
        here = self._keyframe_poses[current]
        recent = range(max(0, current - LOOP_QUERY_KEYFRAMES), current + 1)
        points = np.concatenate(
            [place(self._keyframes[k].points, se2.relative(here, self._keyframe_poses[k])) for k in recent]
        )
        return np.ascontiguousarray(points[one_per_cell(points, LOOP_QUERY_THINNING)])

    # ------------------------------------------------------------------------------------ optimization

    def _graph(self, poses: FloatArray | None = None) -> PoseGraph:
        first, second, measurements, informations, _ = self._edges.arrays()
        return PoseGraph.build(
            np.arange(len(self._keyframe_poses)),
            self._keyframe_rows.rows() if poses is None else poses,
            first,
            second,
            measurements,
            informations,
        )

    def optimize_online(self) -> None:
        """Re-optimize the keyframe graph from the current estimate, dropping inconsistent loop closures."""
        with self.stage_times.stage("online_optimization"):
            self._optimize_online_untimed()

    def _optimize_online_untimed(self) -> None:
        new_loops, self._pending_loops = self._pending_loops, 0
        settings = self.config.loop_closure
        self._hypotheses.clear()  # a hypothesis' correction is relative to the estimate it was found on
        if len(self._keyframe_poses) < 2 or not any(self._edges.is_loop):
            return
        poses, removed = optimize_and_prune(self._edges, self._graph, self._keyframe_rows.rows(),
                                            settings.chi2_threshold, REOPTIMIZE_ITERATIONS, new_loops)
        self._rejected += removed
        self._move_keyframes(poses)

    def _move_keyframes(self, poses: FloatArray) -> None:
        offset = se2.relative(self._keyframe_poses[-1], self._last_pose)
        self._set_keyframe_poses(poses)
        self._last_pose = se2.compose(self._keyframe_poses[-1], offset)
        self._rebuild_local_map()

    def _set_keyframe_poses(self, poses: Sequence[FloatArray] | FloatArray) -> None:
        """Every keyframe's pose anew (an optimization moved them, or a saved map's)."""
        self._keyframe_poses = [np.array(p, dtype=np.float64) for p in poses]
        self._keyframe_rows.reset(self._keyframe_poses)
        self._failed_wide_searches = {}

    def keyframe_poses(self) -> FloatArray:
        """(K, 3) the current estimate of every keyframe's pose in the map frame."""
        return self._keyframe_rows.rows().copy()

    def keyframe_scans(self) -> list[FloatArray]:
        """Every keyframe's points (N, 2) in its own frame."""
        return [k.points for k in self._keyframes]

    def keyframe_position(self, keyframe: int) -> FloatArray:
        """The current estimate of a keyframe's position (x, y) in the map frame."""
        return self._keyframe_poses[keyframe][:2].copy()

    # ------------------------------------------------------------------------------------------ result

    def finish(self) -> Slam2DGraph:
        """Final online optimization, and the keyframe graph with every scan's offset from its keyframe."""
        if self._pending_loops:
            self.optimize_online()
        self._hypotheses.clear()
        graph = self._graph()
        _, _, measurements, _, is_loop = self._edges.arrays()
        chain = se2.compose_chain(measurements[~is_loop])
        return Slam2DGraph(
            graph=graph,
            scan_stamps_ns=np.array(self._scan_stamps, dtype=np.int64),
            scan_keyframes=np.array(self._scan_keyframes, dtype=np.int64),
            scan_offsets=np.array(self._scan_offsets).reshape(-1, 3),
            keyframe_scans=tuple(k.points for k in self._keyframes),
            odometry_chain=chain,
            loop_closures_accepted=int(sum(self._edges.is_loop)),
            loop_closures_rejected=self._rejected,
            scans_unmatched=self._unmatched,
            loop_closures_unconfirmed=self._hypotheses.dropped,
            scans_between=self._scans_between,
            stage_times=self.stage_times,
        )

