"""Continue mapping from a saved keyframe graph: the new run's keyframes join the old graph.

The new run's odometry origin says nothing about where it starts in the old map, so its first scans go to
a `MapLocalizer` over the old keyframes (global localization) and wait. Once one is placed, the waiting
scans get their map poses back from it and go through the SLAM as usual:
- the first waiting scan becomes keyframe K (K old keyframes), tied to the old keyframe nearest it by the
  localization match (a loop closure, which the χ² check may reject like any other), and to keyframe K−1
  by a very weak constraint that only keeps the odometry chain K−1 → K whole (its measurement is the
  relative pose the localization implies, so the chain the final optimization starts from is right);
- the local map the new scans are matched against holds the recent new keyframes and, until there are
  enough of those, the old keyframes nearest the robot;
- loop closures search every keyframe, old or new, as in one run; one that moves the map far (the new
  run coming back to the old map from stretches it never saw) is optimized at once, not after a few more;
- `finish` returns the joint graph.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from frontends.errors import MapPlacementError
from frontends.loop_closing import is_small
from frontends.protocol import FloatArray, IntArray
from frontends.slam2d.config import SMALL_CORRECTION_ANGULAR, SMALL_CORRECTION_LINEAR, Slam2DConfig
from frontends.slam2d.icp import scan_normals
from frontends.slam2d.local_map import Keyframe, Submap
from frontends.slam2d.localization import LocalizationConfig, LocalizedScan, MapLocalizer
from frontends.slam2d.slam import LaserSlam2D, ScanEstimate, Slam2DGraph, _LoopHypothesis
from optimizer import se2
from optimizer.graph import PoseGraph

BRIDGE_SIGMA_LINEAR = 100.0
BRIDGE_SIGMA_ANGULAR = 10.0
"""σ (m, rad) of the constraint between the old run's last keyframe and the new run's first: it carries no
information (the runs are unrelated in time), it only keeps the chain of consecutive keyframes whole."""


@dataclass(frozen=True, eq=False)
class SavedConstraints:
    """The saved keyframe graph's constraints, in the order the SLAM added them."""

    edge_from: IntArray
    edge_to: IntArray
    measurements: FloatArray
    """(M, 3) z_ab, the pose of b in a's frame."""
    information: FloatArray
    """(M, 3, 3)."""
    is_loop: NDArray[np.bool_] | None = None
    """Loop closures (removable by the χ² check); default: every constraint not between consecutive
    keyframes."""

    @classmethod
    def of(cls, graph: PoseGraph) -> SavedConstraints:
        return cls(graph.edge_from, graph.edge_to, graph.measurements, graph.information)


@dataclass(frozen=True, eq=False)
class SavedScans:
    """How the saved run's scans hang off its keyframes (`Slam2DGraph`'s scan fields), so that `finish`
    gives every scan of the session, old and new."""

    stamps_ns: IntArray
    keyframes: IntArray
    offsets: FloatArray

    @classmethod
    def of(cls, result: Slam2DGraph) -> SavedScans:
        return cls(result.scan_stamps_ns, result.scan_keyframes, result.scan_offsets)


class _WaitingScan(NamedTuple):
    """A new scan kept until the run is placed: `LaserSlam2D.add_scan`'s arguments."""

    stamp_ns: int
    points: FloatArray
    odometry: FloatArray | None
    odometry_interval: float
    point_times: FloatArray | None


class ResumedSlam2D(LaserSlam2D):
    """`LaserSlam2D` started from a saved keyframe graph (see the module's docstring); use
    `LaserSlam2D.resume` to make one."""

    def __init__(
        self,
        keyframe_scans: Sequence[FloatArray],
        keyframe_poses: FloatArray,
        constraints: SavedConstraints,
        config: Slam2DConfig | None = None,
        *,
        scans: SavedScans | None = None,
        localization: LocalizationConfig | None = None,
        placed_by_caller: bool = False,
    ) -> None:
        """`placed_by_caller`: the caller localizes the new scans in the saved map itself and gives each
        scan's `LocalizedScan` to `add_scan` until the run is placed (no second whole-map localizer)."""
        super().__init__(config)
        poses = np.asarray(keyframe_poses, dtype=np.float64).reshape(-1, 3)
        if len(keyframe_scans) != len(poses):
            raise MapPlacementError(f"{len(keyframe_scans)} keyframe scans for {len(poses)} keyframe poses")
        self._placer: MapLocalizer | None = None if placed_by_caller else MapLocalizer(
            keyframe_scans, poses, self.config, settings=localization, first_scan_alone=False)
        self._placed = False
        self._old_count = len(poses)
        self._set_keyframe_poses(poses)
        self._keyframes = [Keyframe(np.ascontiguousarray(s, dtype=np.float64),
                                    scan_normals(np.ascontiguousarray(s, dtype=np.float64)))
                           for s in keyframe_scans]
        is_loop = constraints.is_loop
        if is_loop is None:
            is_loop = np.abs(np.asarray(constraints.edge_to) - np.asarray(constraints.edge_from)) != 1
        for a, b, z, information, loop in zip(constraints.edge_from, constraints.edge_to,
                                              constraints.measurements, constraints.information, is_loop,
                                              strict=True):
            self._edges.add(int(a), int(b), z, np.asarray(information, dtype=np.float64), bool(loop))
        if scans is not None:
            self._scan_stamps = [int(s) for s in scans.stamps_ns]
            self._scan_keyframes = [int(k) for k in scans.keyframes]
            self._scan_offsets = [np.asarray(o, dtype=np.float64) for o in scans.offsets]
        self._waiting: list[_WaitingScan] = []
        self._local_map = None
        self.scans_unplaced = 0
        """New scans seen before the stretch that was placed, left out of the graph."""
        self.placement: LocalizedScan | None = None
        """The global localization that placed the new run in the old map (None until it happened)."""

    @property
    def placed(self) -> bool:
        return self._placed

    def add_scan(
        self,
        stamp_ns: int,
        points: FloatArray,
        odometry: FloatArray | None = None,
        odometry_interval: float = 0.0,
        point_times: FloatArray | None = None,
        located: LocalizedScan | None = None,
    ) -> ScanEstimate:
        """As `LaserSlam2D.add_scan`. Until the run is placed in the old map the scan waits: its estimate
        has a NaN pose, `matched` False and keyframe −1 (`finish` gives it its pose). `located`: the
        caller's localization of this scan (required until placed when `placed_by_caller`; its indices
        count the scans given since the first waiting one)."""
        if self._placed:
            return super().add_scan(stamp_ns, points, odometry, odometry_interval, point_times)
        odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        points = np.asarray(points, dtype=np.float64)
        self._waiting.append(_WaitingScan(int(stamp_ns), points, odometry, odometry_interval, point_times))
        index = len(self._scan_stamps) + len(self._waiting) - 1
        if self._placer is not None:
            located = self._placer.localize(stamp_ns, points, odometry, odometry_interval, point_times)
        elif located is None:
            raise MapPlacementError("a scan of a run placed by its caller came without its localization")
        if not located.localized:
            return ScanEstimate(index, int(stamp_ns), np.full(3, np.nan), False, -1, ())
        found = self.placement = located
        poses = np.concatenate([found.recovered_poses, found.pose[None, :]])
        # Localizer indices count from the first scan it saw, which was the first waiting one.
        order = np.concatenate([found.recovered_indices, [found.index]])
        placed = dict(zip(order.tolist(), poses, strict=True))
        # The lost-stretch tracker restarts after `max_lost_keyframes`: scans before its last start have
        # no map pose and are left out (`scans_unplaced`).
        first = min(placed)
        waiting, self._waiting, self._placer, self._placed = self._waiting[first:], [], None, True
        self.scans_unplaced = first
        self._start_new_run(waiting[0], placed[first], found.information)
        estimate = None
        for scan in waiting[1:]:
            estimate = super().add_scan(*scan)
        if estimate is None:
            keyframe = len(self._keyframe_poses) - 1
            estimate = ScanEstimate(index, int(stamp_ns), self._last_pose.copy(), True, keyframe, ())
        return estimate

    def _start_new_run(self, scan: _WaitingScan, pose: FloatArray, information: FloatArray) -> None:
        stamp, points, odometry = scan.stamp_ns, scan.points, scan.odometry
        max_range = self.config.matching.max_range
        points = points[np.einsum("ij,ij->i", points, points) <= max_range**2]
        old = self._keyframe_rows.rows()[: self._old_count]
        nearest = int(np.argmin(np.hypot(*(old[:, :2] - pose[:2]).T)))
        bridge = np.diag([BRIDGE_SIGMA_LINEAR**-2, BRIDGE_SIGMA_LINEAR**-2, BRIDGE_SIGMA_ANGULAR**-2])
        if not np.any(information):  # a global fix always has an ICP Hessian; guard an empty one anyway
            information = bridge
        if nearest == self._old_count - 1:  # the match itself ties the chain: one constraint, not a loop
            self._add_keyframe(pose, points, se2.relative(self._keyframe_poses[-1], pose), information)
        else:
            self._add_keyframe(pose, points, se2.relative(self._keyframe_poses[-1], pose), bridge)
            self._edges.add(nearest, self._old_count, se2.relative(self._keyframe_poses[nearest], pose),
                            information, is_loop=True)
        new = self._old_count
        self._last_odometry = odometry
        self._keyframe_odometry = odometry
        self._last_motion = np.zeros(3)
        self._append_scan(stamp, new, pose)
        self._pose_between(pose)

    def _extend_local_map(self) -> None:
        """Built again at every keyframe: which old keyframes it holds changes as the robot moves."""
        self._rebuild_local_map()

    def _rebuild_local_map(self) -> None:
        """Recent new keyframes, topped up with the old keyframes nearest the robot."""
        if len(self._keyframe_poses) <= self._old_count:
            self._local_map = None
            return
        wanted = self.config.keyframes.local_map_keyframes
        count = len(self._keyframe_poses)
        recent = list(range(max(self._old_count, count - wanted), count))
        old = self._keyframe_rows.rows()[: self._old_count]
        distance = np.hypot(*(old[:, :2] - self._keyframe_poses[-1][:2]).T)
        reach = 2.0 * self.config.matching.max_range
        closest = np.argsort(distance)[: max(wanted - len(recent), 0)]
        nearest = [int(k) for k in closest if distance[k] <= reach]
        chosen = sorted(nearest) + recent  # the newest last: `Submap.of` centres its reach on it
        matching = self.config.matching
        keyframes = [self._keyframes[k] for k in chosen]
        if sum(len(k.points) for k in keyframes) < matching.min_points:
            self._local_map = None
            return
        self._local_map = Submap.of(
            keyframes,
            [self._keyframe_poses[k] for k in chosen],
            resolution=matching.resolution,
            likelihood_sigma=matching.likelihood_sigma,
            margin=self._local_map_margin(),
            pairing_distance=matching.icp_max_distance,
            reach=2.0 * matching.max_range + self._local_map_margin(),
        )

    def _optimization_due(self, accepted: Sequence[_LoopHypothesis]) -> bool:
        """Also at once when a loop closure just accepted moves the map beyond a small correction: the
        new run drifts through stretches the saved map never saw and comes back to it far off. Its loop
        closure shortens the graph path to the old keyframes, and so their search radius, right away; left
        uncorrected until `OPTIMIZE_EVERY_LOOP_CLOSURES` more, the estimate stays outside that radius and
        the loop closures that would follow (old keyframes and new) are never searched for."""
        return super()._optimization_due(accepted) or any(
            not is_small(self._keyframe_move(h), SMALL_CORRECTION_LINEAR, SMALL_CORRECTION_ANGULAR)
            for h in accepted)

    def _keyframe_move(self, hypothesis: _LoopHypothesis) -> FloatArray:
        """The matched pose of the loop closure's current keyframe in the frame of its estimate. (The
        hypothesis' correction is the move of the whole map about its origin: far from the origin a
        fraction of a degree there is metres, where the keyframe itself barely moves.)"""
        here = self._keyframe_poses[hypothesis.current]
        return se2.relative(here, se2.compose(hypothesis.correction, here))

    def finish(self) -> Slam2DGraph:
        """The joint keyframe graph, old and new; `MapPlacementError` if the new run never matched the
        saved map (then its scans cannot be placed in it)."""
        if not self._placed and self._waiting:
            raise MapPlacementError(
                f"none of the {len(self._waiting)} new scans could be placed in the saved map of "
                f"{self._old_count} keyframes: no unambiguous match"
            )
        return super().finish()
