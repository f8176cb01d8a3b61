"""Continue 3D mapping from a saved keyframe graph: the new run's keyframes join the old graph.

The new run's odometry (KISS-ICP, from its own first cloud) says nothing about where it starts in the old
map, so its first clouds go to a `CloudLocalizer` over the old keyframes (global localization) and wait:
their odometry poses are kept, and the keyframes they would make (chosen as in one run, by the distance
driven in the odometry frame) keep their clouds. Once one cloud is placed:
- the odometry frame is placed in the map (`LidarSlam3D._odometry_origin`), so every new keyframe's
  odometry pose, and with it the height, roll and pitch the planar optimum is lifted with, is in the
  map's frame;
- the early stretch joins the graph: its keyframes become keyframes K, K+1, … (K old keyframes), chained
  by their odometry constraints, the first tied to keyframe K−1 by a very weak constraint that only keeps
  the chain of consecutive keyframes whole; the placed cloud becomes the next keyframe, tied to the old
  keyframe it matched by the match (a loop closure, which the χ² check may reject like any other);
- loop closures are then searched for the early keyframes, with the placement in the graph (their search
  radius grows with the path through it), and later keyframes may close loops with them as in one run:
  the early stretch is corrected like any other (hung off the placed cloud by its odometry it could not
  be);
- a loop closure's registration target (the candidate's neighbours by index) stays within the
  candidate's run: the old run's last keyframe and the new run's first are neighbours by index only;
- loop closures search every keyframe, old or new, as in one run: the old keyframes are "far back along
  the path" from the start (their descriptors are recomputed from the saved clouds);
- `finish` returns the joint graph, every cloud of both runs in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.errors import MapPlacementError
from frontends.protocol import FloatArray, IntArray
from frontends.slam3d import se3
from frontends.slam3d.config import Slam3DConfig
from frontends.slam3d.localization import CloudLocalizationConfig, CloudLocalizer, LocalizedCloud
from frontends.slam3d.odometry import Odometry, OdometryStep
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph, keyframe_descriptor

BRIDGE_SIGMA_LINEAR = 100.0
BRIDGE_SIGMA_ANGULAR = 10.0
"""σ (m, rad) of the constraint between the old run's last keyframe and the new run's first: it carries no
information (the runs are unrelated in time), it only keeps the chain of consecutive keyframes whole."""


@dataclass(frozen=True, eq=False)
class SavedGraph3D:
    """A saved 3D keyframe graph and how its clouds hang off it (what a session holds)."""

    keyframe_clouds: tuple[NDArray[np.floating], ...]
    """Each keyframe's cloud (N, 3) in its base frame."""
    keyframe_poses: FloatArray
    """(K, 4, 4) optimized keyframe poses in the map frame."""
    keyframe_stamps_ns: IntArray
    edge_from: IntArray
    edge_to: IntArray
    relative: FloatArray
    """(M, 4, 4) pose of `edge_to` in the frame of `edge_from`."""
    information: FloatArray
    """(M, 6, 6)."""
    is_loop: NDArray[np.bool_]
    cloud_stamps_ns: IntArray
    cloud_keyframes: IntArray
    cloud_offsets: FloatArray
    """(S, 4, 4) each cloud's base pose in its keyframe's frame."""


class ResumedLidarSlam3D(LidarSlam3D):
    """`LidarSlam3D` started from a saved keyframe graph (see the module's docstring)."""

    def __init__(self, saved: SavedGraph3D, config: Slam3DConfig | None = None, *,
                 sensor_to_base: ArrayLike | None = None, odometry: Odometry | None = None,
                 localization: CloudLocalizationConfig | None = None) -> None:
        super().__init__(config, sensor_to_base=sensor_to_base, odometry=odometry)
        poses = np.asarray(saved.keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(saved.keyframe_clouds) != len(poses):
            raise MapPlacementError(f"{len(saved.keyframe_clouds)} keyframe clouds for {len(poses)} poses")
        self.saved = saved
        self._placer: CloudLocalizer | None = CloudLocalizer(saved.keyframe_clouds, poses, self.config,
                                                             localization)
        self._old_count = len(poses)
        # The saved (optimized) poses stand for the old keyframes' odometry too: the planar optimum is
        # lifted with their height, roll and pitch, and their clouds' offsets are relative to them.
        self._keyframe_odometry = [p.copy() for p in poses]
        self._keyframe_poses = [p.copy() for p in poses]
        self._keyframe_stamps = [int(s) for s in saved.keyframe_stamps_ns]
        self._keyframe_clouds = [np.asarray(c, dtype=np.float32) for c in saved.keyframe_clouds]
        loop = self.config.loop_closure
        self._keyframe_descriptors = [keyframe_descriptor(p, np.asarray(c, dtype=np.float64), loop)
                                      for p, c in zip(poses, saved.keyframe_clouds, strict=True)]
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        self._keyframe_travel = np.concatenate([[0.0], np.cumsum(steps)]).tolist()
        for a, b, z, information, loop_closure in zip(saved.edge_from, saved.edge_to, saved.relative,
                                                      saved.information, saved.is_loop, strict=True):
            self._edges.add(int(a), int(b), z, np.asarray(information, dtype=np.float64), bool(loop_closure))
        self._cloud_stamps = [int(s) for s in saved.cloud_stamps_ns]
        self._cloud_keyframes = [int(k) for k in saved.cloud_keyframes]
        self._cloud_offsets = [np.asarray(o, dtype=np.float64) for o in saved.cloud_offsets]
        self._waiting: list[_WaitingCloud] = []
        self._early_keyframe: FloatArray | None = None
        """Odometry pose of the newest keyframe of the early stretch (None: no registered cloud yet)."""
        self.clouds_unplaced = 0
        """New clouds before the first one the odometry registered: no pose, left out."""
        self.placement: LocalizedCloud | None = None

    @property
    def placed(self) -> bool:
        return self._placer is None

    def _add_step(self, index: int, stamp_ns: int, step: OdometryStep | None) -> CloudEstimate:
        if self._placer is None:
            return super()._add_step(index, stamp_ns, step)
        waiting = CloudEstimate(index, stamp_ns, np.full((4, 4), np.nan), False, -1, ())
        if step is None:
            self._untracked += 1
            self._waiting.append(_WaitingCloud(stamp_ns, None, None))
            return waiting
        # before the placement, `_base_pose` is in the new run's odometry frame (its origin is identity)
        odometry_pose = self._base_pose(step)
        points = self._keyframe_points(step)
        starts_keyframe = self._early_keyframe is None or self._is_new_keyframe(odometry_pose,
                                                                                self._early_keyframe)
        if starts_keyframe:
            self._early_keyframe = odometry_pose
        kept = points.astype(np.float32) if starts_keyframe else None
        self._waiting.append(_WaitingCloud(stamp_ns, odometry_pose, kept))
        found = self._placer.localize(index, stamp_ns, odometry_pose, points)
        if not found.localized:
            return waiting
        self.placement = found
        self._placer = None
        self._odometry_origin = found.pose @ se3.inverse(odometry_pose)
        placed, loops = self._join(stamp_ns, points, found)
        return CloudEstimate(index, stamp_ns, self._keyframe_poses[placed].copy(), True, placed, loops)

    def _join(self, stamp_ns: int, points: FloatArray,
              found: LocalizedCloud) -> tuple[int, tuple[tuple[int, int], ...]]:
        """Fold the early stretch and the placed cloud into the graph (see the module docstring); the
        placed cloud's keyframe and the loop closures found for the early keyframes."""
        bridge = np.diag([BRIDGE_SIGMA_LINEAR**-2] * 3 + [BRIDGE_SIGMA_ANGULAR**-2] * 3)
        information = found.information if np.any(found.information) else bridge
        early: list[int] = []
        base: FloatArray | None = None
        for cloud in self._waiting[:-1]:
            if cloud.odometry_pose is not None:
                base = self._odometry_origin @ cloud.odometry_pose
            if base is None:
                self.clouds_unplaced += 1  # before any registered cloud: no pose to give it
                continue
            if cloud.keyframe_points is not None:
                self._add_new_run_keyframe(base, cloud.stamp_ns, cloud.keyframe_points.astype(np.float64),
                                           bridge)
                early.append(len(self._keyframe_poses) - 1)
            self._hang_cloud(cloud.stamp_ns, base)
        placed_odometry = self._waiting[-1].odometry_pose
        assert placed_odometry is not None  # a cloud is only localized once registered
        base = self._odometry_origin @ placed_odometry
        self._waiting = []
        placed = len(self._keyframe_poses)
        if not early and found.anchor == placed - 1:  # the match itself ties the chain: not a loop
            self._add_new_run_keyframe(base, stamp_ns, points, information)
        else:
            self._add_new_run_keyframe(base, stamp_ns, points, bridge)
            self._edges.add(found.anchor, placed, found.relative, information, is_loop=True)
        self._hang_cloud(stamp_ns, base)
        self._last_base = base
        loops = tuple(loop for keyframe in early for loop in self._close_loops(keyframe))
        return placed, loops

    def _add_new_run_keyframe(self, base: FloatArray, stamp_ns: int, points: FloatArray,
                              first_information: FloatArray) -> None:
        """A keyframe of the new run, tied to the previous by its odometry; the first is tied to the old
        run's last with `first_information`, and every old keyframe is "far back along the path" from it,
        so that loop closures may reach them."""
        first = len(self._keyframe_poses) == self._old_count
        self._add_keyframe(base, stamp_ns, points, first_information if first else None)
        if first:
            travel = self._keyframe_travel
            travel[-1] = max(travel[-1], travel[-2] + self.config.loop_closure.min_travel)

    def _submap_keyframes(self, candidate: int, last: int) -> range:
        """`LidarSlam3D._submap_keyframes` of the candidate's own run: the old run's last keyframe and the
        new run's first are neighbours by index only (the runs are unrelated in time and place)."""
        around = super()._submap_keyframes(candidate, last)
        if candidate < self._old_count:
            return range(around.start, min(around.stop, self._old_count))
        return range(max(around.start, self._old_count), around.stop)

    def finish(self) -> Slam3DGraph:
        """The joint keyframe graph, old and new; `MapPlacementError` if the new run never matched the
        saved map (then its clouds cannot be placed in it)."""
        if self._placer is not None:
            raise MapPlacementError(
                f"none of the {len(self._waiting)} new clouds could be placed in the saved map of "
                f"{self._old_count} keyframes: no unambiguous match")
        return super().finish()


@dataclass(frozen=True, eq=False)
class _WaitingCloud:
    """A new cloud before the run was placed in the saved map."""

    stamp_ns: int
    odometry_pose: FloatArray | None
    """Its base pose in the new run's odometry frame; None: the odometry could not register it."""
    keyframe_points: NDArray[np.float32] | None
    """Its keyframe cloud when it starts a keyframe of the early stretch (in its base frame)."""
