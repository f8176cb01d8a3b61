"""The 2D laser frontends of a log replay that starts from a saved map (`replay LOG --map SESSION`,
`replay LOG --continue SESSION`), both reading the new log as `LaserFrontend` does.

- `ContinuingLaserFrontend`: `LaserFrontend` whose SLAM is `LaserSlam2D.resume` on the saved keyframe
  graph; the replay then optimizes the joint graph like any other, and every scan of the session, old and
  new, gets its pose (`stamps_ns`, `estimates`).
- `LocalizingLaserFrontend`: every scan goes to a `MapLocalizer` over the saved keyframes; the saved map
  is never changed. Scans never placed in the map have no pose: they are counted (`ScanLocalizations`),
  never given a made-up one. Every scan also goes to the run's own SLAM, resumed on the saved keyframe
  graph and placed where the localizer first placed the run. Once the log is read, that SLAM's joint graph
  is solved with the saved keyframes held (`frontends.slam2d.held_map`), and its poses are the trajectory
  given, where it agrees with the localizer's map matches (`HELD_MAP_AGREEMENT`); otherwise the
  stretches tracked or predicted between map matches are smoothed (`frontends.slam2d.
  localization_smoothing`) and the smoothed trajectory is given. The per-scan states and match quality
  stay as measured online. A fast laser's scans are localized at the mapping's cadence
  (`frontends.slam2d.cadence`) while the run is placed; the scans between are posed between the localized
  ones around them, after the smoothing.

In both, the new log's wheel odometry starts anywhere: it is used for the motion between scans only.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError, LogWarning, MapPlacementError
from frontends.logs import LogReader
from frontends.protocol import (
    ON_PATH_MIN_MEASUREMENTS,
    ON_SAVED_PATH,
    BoolArray,
    FloatArray,
    FrontendOptions,
    IntArray,
    SavedMapLocalization,
    ScanLocalizations,
    checked_on_saved_path,
    on_saved_path,
)
from frontends.saved_arrays import checked, checked_edges, checked_graph, checked_keyframes, checked_members
from frontends.slam2d.cadence import MatchCadence
from frontends.slam2d.config import Slam2DConfig
from frontends.slam2d.deskew import along_motion, interpolated
from frontends.slam2d.frontend import LaserFrontend
from frontends.slam2d.held_map import (
    HELD_MAP_AGREEMENT,
    HeldMapScans,
    HeldMapSolver,
    HeldOdometry,
    held_map_scans,
    held_map_trajectory,
    solve_held_map,
)
from frontends.slam2d.localization import LocalizedScan, MapLocalizer
from frontends.slam2d.localization_smoothing import SmoothedTrajectory, smooth_scans
from frontends.slam2d.occupancy import OccupancyGrid, occupancy_grid
from frontends.slam2d.resume import ResumedSlam2D, SavedConstraints, SavedScans
from frontends.slam2d.slam import LaserSlam2D, ScanEstimate
from frontends.slam2d.wall_crossings import WallCrossings, checked_wall_crossings
from frontends.threads import InOrderWorker
from optimizer import se2
from optimizer.graph import PoseGraph

SCAN_SESSION_ARRAYS = ("keyframe_poses", "edge_from", "edge_to", "measurements", "information", "is_loop",
                       "scan_stamps_ns", "scan_keyframes", "scan_offsets")
"""The arrays a 2D laser session holds (`LaserFrontend.session_content`)."""


@dataclass(frozen=True, eq=False)
class SavedMap2D:
    """A saved 2D keyframe map: what a session file gives the frontends."""

    keyframe_scans: tuple[FloatArray, ...]
    """Each keyframe's points (N, 2) in its own frame."""
    keyframe_poses: FloatArray
    """(K, 3) the keyframes' optimized poses in the map frame."""
    constraints: SavedConstraints
    scans: SavedScans | None = None
    """How the saved run's scans hang off its keyframes (to continue with every scan of the session)."""

    def graph(self) -> PoseGraph:
        """The saved keyframe graph at the saved poses."""
        c = self.constraints
        return PoseGraph.build(np.arange(len(self.keyframe_poses)), self.keyframe_poses, c.edge_from,
                               c.edge_to, c.measurements, c.information)

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, NDArray[Any]],
                    keyframe_points: Sequence[NDArray[Any]]) -> SavedMap2D:
        """The map a session's arrays hold (`LaserFrontend.session_content`'s), checked for consistency:
        `SavedArraysError` naming the array that is missing or does not fit the others."""
        poses, scans = checked_keyframes(arrays, keyframe_points, SCAN_SESSION_ARRAYS, (3,), 2, "scans")
        keyframes = len(poses)
        edge_from, edge_to = checked_edges(arrays, keyframes)
        edges = len(edge_from)
        stamps, scan_keyframes = checked_members(arrays, "scan", keyframes)
        saved = cls(
            scans, poses,
            SavedConstraints(edge_from.astype(np.int64), edge_to.astype(np.int64),
                             checked("measurements", arrays, (edges, 3), np.floating),
                             checked("information", arrays, (edges, 3, 3), np.floating),
                             checked("is_loop", arrays, (edges,), np.bool_)),
            SavedScans(stamps.astype(np.int64), scan_keyframes.astype(np.int64),
                       checked("scan_offsets", arrays, (len(stamps), 3), np.floating)),
        )
        checked_graph(saved.graph)
        return saved


OLD_NEW_CLOSURES_ON_PATH = 0.05
"""A continued run should close loops with the saved keyframes where it drives their path: one for at most
every 20 of its keyframes there, or its placement is suspect (another building's log, placed by a look-alike
corridor, is mapped over the saved one). The second halves of ACES and CSAIL continued on their first halves
(`benchmarks/cut_log.py`): 26 and 35 loop closures with the old keyframes (the placement's match not counted)
for 127 and 105 new keyframes on their path; ACES continued on CSAIL's session: none for 160."""


class ContinuingLaserFrontend(LaserFrontend):
    """Mapping continued from a saved map: see the module docstring and `frontends.slam2d.resume`."""

    odometry_starts_at_map_origin = False

    def __init__(self, log: LogReader, topic: str, saved: SavedMap2D, config: Slam2DConfig | None = None,
                 options: FrontendOptions | None = None) -> None:
        super().__init__(log, topic, config, options)
        self.saved = saved
        self._resumed: ResumedSlam2D = LaserSlam2D.resume(saved.keyframe_scans, saved.keyframe_poses,
                                                          saved.constraints, self.config, scans=saved.scans)
        self._slam = self._resumed
        self._on_path = 0
        """New keyframes on the saved run's path (within `ON_SAVED_PATH` of a saved keyframe)."""

    def _process(self, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
                 odometry_interval: float, point_times: FloatArray | None) -> ScanEstimate:
        estimate = super()._process(stamp_ns, points, odometry, odometry_interval, point_times)
        # The resumed SLAM counts the session's scans too: the estimate is of this log's next scan.
        return dataclasses.replace(estimate, index=self._counts["scans"])

    def keyframe_wheel_odometry(self) -> FloatArray | None:
        return None  # the saved keyframes were driven with another log's odometry

    def finish(self) -> None:
        """`LaserFrontend.finish`, then a warning when the new keyframes on the saved run's path closed
        (almost) no loop with the saved ones (`OLD_NEW_CLOSURES_ON_PATH`)."""
        super().finish()
        graph, old = self.result.graph, len(self.saved.keyframe_poses)
        on_path = int(on_saved_path(graph.poses[old:, :2], graph.poses[:old, :2]).sum())
        # Loop closures between old and new keyframes, the placement's own match (to the first new one) not.
        closures = int(np.sum(self._crossing() & (np.maximum(graph.edge_from, graph.edge_to) != old)))
        self._on_path = on_path
        if on_path >= ON_PATH_MIN_MEASUREMENTS and closures < OLD_NEW_CLOSURES_ON_PATH * on_path:
            warnings.warn(f"{self._log.path}: {on_path} of its keyframes lie on the saved run's path "
                          f"(within {ON_SAVED_PATH:g} m of a saved keyframe) but closed {closures} loops "
                          "with the saved keyframes: the log may be of another place than the session, or "
                          "the place changed (see the recording)", LogWarning, stacklevel=2)

    def _crossing(self) -> BoolArray:
        """The loop-closure constraints between an old keyframe and a new one."""
        graph, old = self.result.graph, len(self.saved.keyframe_poses)
        return ((graph.edge_from < old) != (graph.edge_to < old)) & ~graph.is_odometry

    def counts(self) -> dict[str, int]:
        """`LaserFrontend.counts` (its keyframes, constraints and loop closures those of the joint graph),
        and what the session added: its keyframes and scans, the new scans left out because they came
        before the stretch placed in the map, and the constraints tying new keyframes to old ones (the
        placement's included)."""
        return {**super().counts(), "session_keyframes": len(self.saved.keyframe_poses),
                "session_scans": 0 if self.saved.scans is None else len(self.saved.scans.stamps_ns),
                "scans_unplaced": self._resumed.scans_unplaced,
                "loop_closures_old_new": int(self._crossing().sum()),
                "keyframes_on_saved_path": self._on_path}

    def placement(self) -> dict[str, Any]:
        """Where the new run joined the saved map: the new log's scan (index, stamp) placed by global
        localization and its match quality."""
        found = self._resumed.placement
        if found is None:
            return {}
        return {"scan": found.index, "stamp_ns": found.stamp_ns, "pose": found.pose.tolist(),
                "score": found.score, "inlier_fraction": found.inlier_fraction, "rms_m": found.rms}


class LocalizingLaserFrontend(SavedMapLocalization[ScanLocalizations], LaserFrontend):
    """Localization only in a saved map: see the module docstring and `frontends.slam2d.localization`.

    After `finish`, `localizations` says how every scan ended, `stamps_ns` / `localized_poses` are the
    scans with a pose, and `keyframe_graph` / `map_export` are the saved map's, unchanged."""

    odometry_starts_at_map_origin = False

    def __init__(self, log: LogReader, topic: str, saved: SavedMap2D, config: Slam2DConfig | None = None,
                 options: FrontendOptions | None = None, *,
                 initial_pose: Sequence[float] | None = None) -> None:
        super().__init__(log, topic, config, options)
        self.saved = saved
        self.initial_pose = None if initial_pose is None else tuple(float(v) for v in initial_pose)
        self._localizer = MapLocalizer(saved.keyframe_scans, saved.keyframe_poses, self.config,
                                       initial_pose=self.initial_pose)
        self._found: list[LocalizedScan] = []
        """What the localizer said of each scan it was given (every scan but those between)."""
        self._localized_scans: list[int] = []
        """The scan index of each of `_found` (the localizer counts the scans it was given)."""
        self._odometry: list[FloatArray | None] = []
        """The wheel odometry at each of `_found`."""
        self._cadence = MatchCadence(self.config.matching.min_match_interval)
        self._between: list[int] = []
        """The scans a fast laser took between two given to the localizer (`frontends.slam2d.cadence`)."""
        self._stamps: list[int] = []
        self._poses: list[FloatArray] = []
        """Each scan's pose as given when processed, or as a later global fix recovered it."""
        self._recovered: list[int] = []
        self._fixes: list[int] = []
        self._localizations: ScanLocalizations | None = None
        self._on_path = (0, 0)
        """Scans placed on the saved run's path, and how many of them did not match the saved map."""
        self._crossings = WallCrossings(0, 0.0)
        self._saved_grid: OccupancyGrid | None = None
        """The saved map's occupancy grid, at its own keyframe poses (`map_export`)."""
        self._smoothing: SmoothedTrajectory | None = None
        self._held = LaserSlam2D.resume(saved.keyframe_scans, saved.keyframe_poses, saved.constraints,
                                        self.config, placed_by_caller=True)
        """The run's own SLAM on the saved keyframe graph, placed by `_localizer` (`frontends.slam2d.
        held_map`)."""
        self._held_worker = InOrderWorker("held-map")
        """Adds each scan to `_held` beside the localizer's work on the next one (`frontends.threads`)."""
        self.held_map_solver: HeldMapSolver = solve_held_map
        """What optimizes the held map's graph in `finish` (a replay's also records its iterations)."""
        self._held_map: HeldMapScans | None = None
        self._held_map_apart = float("nan")
        """The median distance (m) between the held-map poses and the localizer's matched ones."""
        self._held_map_used = False
        self._held_odometry = HeldOdometry()

    def _process(self, stamp_ns: int, points: FloatArray, odometry: FloatArray | None,
                 odometry_interval: float, point_times: FloatArray | None) -> ScanEstimate:
        index = len(self._stamps)
        self._stamps.append(stamp_ns)
        due = self._cadence.due(stamp_ns)
        last = self._found[-1] if self._found else None
        if not due and last is not None and last.localized and (last.matched or last.tracked):
            self._held_worker.submit(partial(self._held.add_scan, stamp_ns, points, odometry,
                                             odometry_interval, point_times))
            pose = self._predicted(stamp_ns, odometry)
            self._poses.append(pose)
            self._between.append(index)
            return ScanEstimate(index, stamp_ns, pose.copy(), False, -1, (), between=True)
        found = self._localizer.localize(stamp_ns, points, odometry, odometry_interval, point_times)
        held_odometry, held_interval, restart = self._held_odometry.of(odometry, odometry_interval, found)
        if restart:
            self._held_worker.submit(self._held.odometry_restarts)
        self._held_worker.submit(partial(self._held.add_scan, stamp_ns, points, held_odometry, held_interval,
                                         point_times, located=found))
        self._cadence.matched(stamp_ns)
        self._found.append(found)
        self._localized_scans.append(index)
        self._odometry.append(None if odometry is None else np.asarray(odometry, dtype=np.float64))
        self._poses.append(found.pose.copy())
        if found.global_fix:
            self._fixes.append(index)
            for given, pose in zip(found.recovered_indices.tolist(), found.recovered_poses, strict=True):
                scan = self._localized_scans[given]
                self._poses[scan] = pose.copy()
                self._recovered.append(scan)
        return ScanEstimate(index, found.stamp_ns, found.pose.copy(), found.matched, -1, ())

    def _predicted(self, stamp_ns: int, odometry: FloatArray | None) -> FloatArray:
        """A scan between: the last localized scan's pose moved by the odometry since, or by the motion
        between the last two localized scans at constant velocity (the localizer's own predictions)."""
        last, last_odometry = self._found[-1], self._odometry[-1]
        if odometry is not None and last_odometry is not None:
            return se2.compose(last.pose, se2.relative(last_odometry, np.asarray(odometry, dtype=np.float64)))
        if len(self._found) < 2 or not self._found[-2].localized:
            return last.pose.copy()
        before = self._found[-2]
        span = last.stamp_ns - before.stamp_ns
        fraction = (stamp_ns - last.stamp_ns) / span if span > 0 else 0.0
        motion = se2.relative(before.pose, last.pose)
        return se2.compose(last.pose, along_motion(motion, np.array([fraction]))[0])

    def finish(self) -> None:
        """Raises `MapPlacementError` when no scan could be placed in the saved map."""
        self._held_worker.drain()
        if self._counts["scans"] == 0:
            raise FrontendError(f"{self._log.path}: topic {self._topic} has no scans")
        self._after_reading()
        count, given = len(self._stamps), np.array(self._localized_scans, dtype=np.int64)
        between = np.zeros(count, dtype=bool)
        between[self._between] = True
        columns = {"localized": between.copy(), "matched": np.zeros(count, dtype=bool),
                   "tracked": np.zeros(count, dtype=bool), "score": np.full(count, np.nan),
                   "inlier_fraction": np.zeros(count), "rms": np.full(count, np.inf)}
        for name, column in columns.items():
            column[given] = [getattr(found, name) for found in self._found]
        recovered = np.zeros(count, dtype=bool)
        recovered[self._recovered] = True
        recovered &= ~columns["localized"]
        online = np.array(self._poses).reshape(-1, 3)
        self._smoothing = smooth_scans(self._found, online[given])
        poses, smoothed = online.copy(), np.zeros(count, dtype=bool)
        poses[given], smoothed[given] = self._smoothing.poses, self._smoothing.smoothed
        self._pose_between(poses, smoothed, given)
        held = self._held_map_poses(online, columns["matched"])
        if held is not None:
            by_held_map = np.isfinite(held[:, 0]) & (columns["localized"] | recovered)
            poses[by_held_map], smoothed[by_held_map] = held[by_held_map], False
        self._localizations = ScanLocalizations(
            np.array(self._stamps, dtype=np.int64), poses, columns["localized"], columns["matched"],
            recovered, columns["score"], columns["inlier_fraction"], columns["rms"],
            np.array(self._fixes, dtype=np.int64), columns["tracked"], online_poses=online,
            smoothed=smoothed, between=between)
        if not self._localizations.has_pose.any():
            raise MapPlacementError(
                f"none of the {count} scans of {self._log.path} could be placed in the saved map of "
                f"{len(self.saved.keyframe_poses)} keyframes: no unambiguous match"
                + ("" if self.initial_pose is not None else " (an --initial-pose x,y,yaw may help)"))
        # Scans given to the localizer and placed then: a scan between was not matched by design, one
        # recovered by a later fix was not placed when it was matched.
        examined = columns["localized"] & ~between
        self._on_path = checked_on_saved_path(self._log.path, "scans", poses[examined, :2],
                                              columns["matched"][examined], self.saved.keyframe_poses[:, :2])
        self._crossings = checked_wall_crossings(self._log.path, "scans", poses[:, :2],
                                                 self.map_export(self.saved.keyframe_poses))

    @property
    def held_map_solved(self) -> bool:
        """Whether `finish` solved the run's own keyframe graph with the saved map held (the run was
        placed), whether or not its trajectory was given."""
        return self._held_map is not None

    def _held_map_poses(self, online: FloatArray, matched: BoolArray) -> FloatArray | None:
        """(S, 3) each scan's pose by the held-map solution (NaN before the run was placed), or None when
        there is none to give: the run never placed, or the solution does not agree with the localizer's
        map matches (`held_map_trajectory`; a warning says when it lies too far from them)."""
        try:
            self._held_map = held_map_scans(self._held, self.saved.keyframe_poses, self.held_map_solver)
        except MapPlacementError:
            return None
        trajectory = held_map_trajectory(self._held_map, np.array(self._stamps, dtype=np.int64), online,
                                         matched)
        self._held_map_apart = trajectory.apart
        if not self._held_map.converged:
            warnings.warn(f"{self._log.path}: the run's own keyframe graph, solved in the saved map, did "
                          "not converge: the trajectory is the one matched scan by scan", LogWarning,
                          stacklevel=2)
        elif trajectory.apart > HELD_MAP_AGREEMENT:
            warnings.warn(f"{self._log.path}: the run's own keyframe graph, solved in the saved map, lies "
                          f"{trajectory.apart:.2f} m (median) from the scans matched to the map one by "
                          "one: the trajectory is the one matched scan by scan", LogWarning, stacklevel=2)
        self._held_map_used = trajectory.agrees
        return trajectory.poses if trajectory.agrees else None

    def _pose_between(self, poses: FloatArray, smoothed: BoolArray, given: IntArray) -> None:
        """The scans between two given to the localizer, in place: between the two (smoothed) poses around
        them at constant velocity; left at their prediction after the last one."""
        stamps = np.array(self._stamps, dtype=np.int64)
        for scan in self._between:
            after = int(np.searchsorted(given, scan))
            if after >= len(given):
                continue
            start, end = given[after - 1], given[after]
            if not np.all(np.isfinite(poses[[start, end]])):
                continue
            fraction = (stamps[scan] - stamps[start]) / (stamps[end] - stamps[start])
            poses[scan] = interpolated(poses[start], poses[end], np.array([fraction]))[0]
            smoothed[scan] = smoothed[start] and smoothed[end]

    def keyframe_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        graph = self.saved.graph()
        return graph if planar_poses is None else graph.with_poses(planar_poses)

    def map_export(self, planar_poses: FloatArray) -> OccupancyGrid:
        if not np.array_equal(planar_poses, self.saved.keyframe_poses):
            return occupancy_grid(self.saved.keyframe_scans, planar_poses)
        if self._saved_grid is None:
            self._saved_grid = occupancy_grid(self.saved.keyframe_scans, self.saved.keyframe_poses)
        return self._saved_grid

    def keyframe_wheel_odometry(self) -> FloatArray | None:
        return None

    def counts(self) -> dict[str, int]:
        """The localization's counts, with the scans the offline smoothing placed and whether it converged
        (1; 0: the poses are the online ones)."""
        found = self.localizations  # raises until `finish` has run (and smoothed)
        assert self._smoothing is not None
        return {**self._counts, **self._input_counts, **self._log.counts,
                "map_keyframes": len(self.saved.keyframe_poses), **found.counts(),
                "scans_smoothed": 0 if found.smoothed is None else int(np.sum(found.smoothed)),
                "scans_on_saved_path": self._on_path[0], "scans_on_saved_path_unmatched": self._on_path[1],
                "saved_map_wall_crossings": self._crossings.crossings,
                "smoothing_converged": int(self._smoothing.converged),
                **self._held_map_counts(found)}

    def _held_map_counts(self, found: ScanLocalizations) -> dict[str, int]:
        """The held-map solution's part of `counts`: whether it gave the trajectory, the scans it posed,
        the new keyframes and their constraints to the saved ones, the distance (mm, median) to the
        localizer's map matches."""
        held = self._held_map
        if held is None:
            return {"held_map_used": 0}
        posed = int(np.sum(found.has_pose[len(found.stamps_ns) - len(held.stamps_ns):]))
        return {"held_map_used": int(self._held_map_used),
                "scans_held_map": posed if self._held_map_used else 0, "held_map_keyframes": held.keyframes,
                "held_map_old_new_constraints": held.old_new_constraints,
                "held_map_converged": int(held.converged),
                "held_map_apart_from_matches_mm": -1 if np.isnan(self._held_map_apart)
                else round(1000 * self._held_map_apart)}

    def loop_closures(self) -> dict[str, Any]:
        return {"accepted": 0, "rejected": 0, "candidates": {"accepted": 0, "unconfirmed": 0}}

