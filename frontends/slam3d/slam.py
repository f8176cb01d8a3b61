"""3D LiDAR SLAM: point clouds in, a keyframe pose graph with verified loop closures out.

1. Each cloud is registered by KISS-ICP (`frontends.slam3d.odometry`), deskewed when it carries per-point
   times. Poses are those of the vehicle's base (the sensor's mount from tf, identity without one) in the
   odometry frame (the base at the first cloud).
2. A cloud that moved far enough from the last keyframe becomes a keyframe: its cloud, downsampled, is kept
   in the keyframe's frame with a Scan Context descriptor, and the KISS-ICP motion since the previous
   keyframe is a constraint between the two. Every cloud is tied to its keyframe by a fixed offset.
3. At keyframes, older keyframes near the current estimate (a radius growing with the path joining them in
   the graph) whose descriptor looks alike are verified by GICP with an ambiguity test
   (`frontends.slam3d.loop_closure`). A loop closure that moves the current estimate more than a little is
   a hypothesis until a second one agrees with it, as in 2D.
4. Every few loop closures the planar graph is re-optimized (Gauss–Newton) and loop closures whose χ²
   stays large at the optimum are removed; the map ← odometry correction follows the last keyframe.

Ground-vehicle assumption online. The graph is kept in 3D (4×4 keyframe poses, relative 4×4 constraints
with 6×6 information) but optimized online in SE(2): x, y and yaw, through `frontends.slam3d.planar`;
height, roll and pitch of every keyframe stay those of the odometry. After the final planar (SGD)
optimization, `Slam3DGraph.polish_se3` runs Levenberg–Marquardt on SE(3) over the same constraints
(`frontends.slam3d.pose_graph3d`), so loop closures correct height drift too (ramps, several storeys).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.errors import FrontendError
from frontends.logs.types import Cloud3D
from frontends.loop_closing import Constraints, HypothesisPool, optimize_and_prune, path_lengths
from frontends.protocol import FloatArray, IntArray
from frontends.slam3d import planar, pose_graph3d, se3
from frontends.slam3d.config import LoopClosureConfig, Slam3DConfig
from frontends.slam3d.degeneracy import UNDERCONSTRAINED_SHARE, weakest_horizontal_share
from frontends.slam3d.loop_closure import (
    LoopMatch,
    RegistrationTarget,
    descriptor_distances,
    scan_context,
    verify_loop,
)
from frontends.slam3d.odometry import KissOdometry, Odometry, OdometryStep, downsample
from frontends.slam3d.pose_graph3d import PolishResult
from frontends.slam3d.voxel_map import place_one_per_voxel
from optimizer import se2
from optimizer.graph import PoseGraph

REOPTIMIZE_ITERATIONS = 15
DESCRIPTOR_GUESS_MIN_ANGLE = np.radians(5.0)
"""The descriptor's heading is tried as a second registration start when it differs this much from the
estimate's (otherwise the two starts are the same)."""


def keyframe_descriptor(pose: FloatArray, points: FloatArray, settings: LoopClosureConfig) -> FloatArray:
    """The Scan Context descriptor of a cloud (points in the base frame) seen levelled: its roll and pitch
    in `pose` (4×4) taken out."""
    levelled = se3.transform_points(se3.relative(planar.level(pose), pose), points)
    return scan_context(
        levelled, settings.descriptor_rings, settings.descriptor_sectors, settings.descriptor_radius
    )


@dataclass(frozen=True, eq=False)
class CloudEstimate:
    """What the frontend concluded about one cloud when it processed it."""

    index: int
    stamp_ns: int
    pose: FloatArray
    """4×4 pose of the base in the map frame at processing time (identity before the first keyframe)."""
    tracked: bool
    """False when the cloud had too few points to register: its pose is the previous one."""
    keyframe: int
    """Its keyframe; −1 for a cloud before the first keyframe (not part of the trajectory)."""
    new_loop_closures: tuple[tuple[int, int], ...]
    """Loop closures (older keyframe, this keyframe) accepted while processing this cloud."""


@dataclass(frozen=True, eq=False)
class Slam3DGraph:
    """The frontend's result: the 3D keyframe graph and how every cloud hangs off its keyframe."""

    keyframe_poses: FloatArray
    """(K, 4, 4) keyframe poses as estimated online (loop closures applied)."""
    keyframe_odometry: FloatArray
    """(K, 4, 4) keyframe poses from KISS-ICP alone: a poorer start, and the source of height, roll, pitch."""
    keyframe_stamps_ns: IntArray
    edge_from: IntArray
    edge_to: IntArray
    """(M,) constraints, odometry then loop closures in the order they were made; from < to."""
    relative: FloatArray
    """(M, 4, 4) measured pose of `edge_to` in the frame of `edge_from`."""
    information: FloatArray
    """(M, 6, 6) in (tx, ty, tz, rx, ry, rz) order."""
    is_loop: NDArray[np.bool_]
    cloud_stamps_ns: IntArray
    cloud_keyframes: IntArray
    cloud_offsets: FloatArray
    """(S, 4, 4) pose of each cloud's base in the frame of its keyframe."""
    keyframe_clouds: tuple[NDArray[np.float32], ...]
    """Each keyframe's cloud, downsampled and deskewed, in the keyframe's base frame (for maps)."""
    loop_closures_accepted: int
    loop_closures_rejected: int
    """Accepted online, then removed by the χ² test after an optimization."""
    loop_candidates: dict[str, int]
    """How candidate verifications ended: "accepted", "poor fit", "ambiguous", "unconfirmed"."""
    clouds_untracked: int
    clouds_dropped: int
    """Clouds before the first keyframe that had too few points: not in the trajectory."""
    odometry_guesses_overruled: int = 0
    """Clouds registered from the LiDAR's own prediction because the odometry's motion fit far worse."""
    keyframes_underconstrained: int = 0
    """Keyframes whose cloud cannot measure horizontal motion in some direction (`degeneracy`)."""
    underconstrained_travel: float = 0.0
    """Metres driven into those keyframes from the ones before them."""

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframe_poses)

    @property
    def odometry_chain(self) -> FloatArray:
        """(K, 3) planar keyframe poses from the odometry alone: where the recorded optimization starts."""
        return planar.planar(self.keyframe_odometry)

    def planar_graph(self, planar_poses: ArrayLike | None = None) -> PoseGraph:
        """The SE(2) graph the backend optimizes, at the online estimate unless `planar_poses` (K, 3)."""
        return planar.project_graph(
            self.keyframe_poses, self.edge_from, self.edge_to, self.relative, self.information, planar_poses
        )

    def lift(self, planar_poses: ArrayLike) -> FloatArray:
        """(K, 4, 4) keyframe poses from optimized planar ones, height, roll and pitch from odometry."""
        return planar.lift(planar_poses, self.keyframe_odometry)

    def polish_se3(self, keyframe_poses: ArrayLike, max_iterations: int = 20) -> PolishResult:
        """Full SE(3) polish of (K, 4, 4) keyframe poses (the lifted planar optimum) over this graph's
        constraints: loop closures then correct height, roll and pitch as well."""
        return pose_graph3d.polish(
            keyframe_poses,
            self.edge_from,
            self.edge_to,
            self.relative,
            self.information,
            max_iterations=max_iterations,
        )

    def cloud_poses(self, keyframe_poses: ArrayLike) -> FloatArray:
        """(S, 4, 4) every cloud's pose given (optimized) 4×4 keyframe poses."""
        return np.asarray(keyframe_poses, dtype=np.float64)[self.cloud_keyframes] @ self.cloud_offsets

    def map_points(self, keyframe_poses: ArrayLike, voxel: float) -> NDArray[np.float32]:
        """(P, 3) the keyframe clouds placed at 4×4 `keyframe_poses`, one point per voxel of this size."""
        poses = np.asarray(keyframe_poses)
        if len(poses) != len(self.keyframe_clouds):
            raise ValueError(f"{len(poses)} poses for {len(self.keyframe_clouds)} keyframe clouds")
        return place_one_per_voxel(poses, self.keyframe_clouds, voxel)


@dataclass(frozen=True, eq=False)
class _LoopHypothesis:
    candidate: int
    current: int
    match: LoopMatch
    correction: FloatArray
    """Planar: matched pose ∘ estimated pose⁻¹ of the current keyframe (how far the match moves the map)."""


class NothingRegisteredError(FrontendError):
    """No cloud of the run could be registered (too few points, or all in one spot)."""


class LidarSlam3D:
    """Feed clouds in time order with `add_cloud`; `finish` returns the keyframe graph.

    `sensor_to_base` is the 4×4 pose of the sensor in the vehicle's base frame (its mount); poses and
    keyframe clouds are the base's. Identity: the sensor frame is the base frame. `odometry` replaces
    KISS-ICP (built from `config.odometry` by default) by another source of registered clouds.
    """

    def __init__(
        self,
        config: Slam3DConfig | None = None,
        *,
        sensor_to_base: ArrayLike | None = None,
        odometry: Odometry | None = None,
    ) -> None:
        self.config = config or Slam3DConfig()
        self._mount = np.eye(4) if sensor_to_base is None else np.array(sensor_to_base, dtype=np.float64)
        if self._mount.shape != (4, 4):
            raise ValueError(f"sensor_to_base must be 4×4, got {self._mount.shape}")
        self._mount_inverse = se3.inverse(self._mount)
        self._odometry = odometry or KissOdometry(self.config.odometry)
        self._odometry_origin = np.eye(4)
        """Pose of the odometry frame in the frame keyframe odometry poses are kept in: identity, but for a
        SLAM resumed on a saved map (`frontends.slam3d.resume`), where it places the new run in the map."""
        self._map_from_odometry = np.eye(4)
        self._keyframe_odometry: list[FloatArray] = []
        self._keyframe_poses: list[FloatArray] = []
        self._keyframe_stamps: list[int] = []
        self._keyframe_clouds: list[NDArray[np.float32]] = []
        self._keyframe_descriptors: list[FloatArray] = []
        self._keyframe_travel: list[float] = []
        self._edges = Constraints(measurement_shape=(4, 4), information_size=6)
        self._cloud_stamps: list[int] = []
        self._cloud_keyframes: list[int] = []
        self._cloud_offsets: list[FloatArray] = []
        self._last_base = np.eye(4)
        self._last_odometry_pose: FloatArray | None = None
        self._clouds_seen = 0
        self._untracked = 0
        self._dropped = 0
        self._guesses_overruled = 0
        self._underconstrained = 0
        self._underconstrained_travel = 0.0
        self._pending_loops = 0
        self._last_closure_travel = -np.inf
        """Path length (m) at the keyframe that last closed a loop."""
        self._hypotheses: HypothesisPool[_LoopHypothesis] = HypothesisPool(
            self.config.loop_closure.small_correction_linear,
            self.config.loop_closure.small_correction_angular,
        )
        self._rejected = 0
        self._candidates = {"accepted": 0, "poor fit": 0, "ambiguous": 0, "unconfirmed": 0}

    # ------------------------------------------------------------------------------------------ clouds

    def add_cloud(self, cloud: Cloud3D, odometry_pose: ArrayLike | None = None) -> CloudEstimate:
        """Process one cloud (points in the sensor frame). `odometry_pose` (4×4, optional) is the base's
        pose at the cloud's stamp from the vehicle's own odometry (`vehicle.OdometryPrior.at`): its motion
        since the previous registered cloud is the registration's starting guess."""
        index = self._clouds_seen
        self._clouds_seen += 1
        odometry = None if odometry_pose is None else np.asarray(odometry_pose, dtype=np.float64)
        motion_guess = None
        if odometry is not None and self._last_odometry_pose is not None:
            base_motion = se3.relative(self._last_odometry_pose, odometry)
            motion_guess = self._mount_inverse @ base_motion @ self._mount
        step = self._odometry.register(cloud.points, cloud.point_times, motion_guess)
        if step is not None:
            # the guess is relative to the last registered cloud: no odometry there, no guess next time
            self._last_odometry_pose = odometry
            self._guesses_overruled += step.guess_overruled
        return self._add_step(index, int(cloud.stamp_ns), step)

    def _base_pose(self, step: OdometryStep) -> FloatArray:
        """4×4 pose of the base at a registered cloud, in the frame keyframe odometry poses are kept in."""
        return self._odometry_origin @ self._mount @ step.pose @ self._mount_inverse

    def _keyframe_points(self, step: OdometryStep) -> FloatArray:
        """The registered cloud as a keyframe keeps it: downsampled, in the base frame at its stamp."""
        points = downsample(step.points, self.config.keyframes.cloud_voxel)
        # deskewed points are in the sensor frame at the sweep's end: bring them to the base at the stamp
        to_base = self._mount @ se3.relative(step.pose, step.points_pose)
        return se3.transform_points(to_base, points)

    def _add_step(self, index: int, stamp_ns: int, step: OdometryStep | None) -> CloudEstimate:
        """The cloud `index` registered by the odometry (None: too few points): keyframe, loop closures,
        its offset from its keyframe."""
        if step is None:
            self._untracked += 1
            if not self._keyframe_poses:
                self._dropped += 1
                return CloudEstimate(index, stamp_ns, np.eye(4), False, -1, ())
            base = self._last_base
        else:
            base = self._base_pose(step)
        new_loops: tuple[tuple[int, int], ...] = ()
        if step is not None and self._is_new_keyframe(base):
            self._add_keyframe(base, stamp_ns, self._keyframe_points(step))
            new_loops = self._close_loops()
        self._last_base = base
        keyframe = self._hang_cloud(stamp_ns, base)
        pose = self._keyframe_poses[keyframe] @ self._cloud_offsets[-1]
        return CloudEstimate(index, stamp_ns, pose, step is not None, keyframe, new_loops)

    def _hang_cloud(self, stamp_ns: int, base: FloatArray) -> int:
        """Tie the cloud at odometry pose `base` to the newest keyframe by its offset; that keyframe."""
        keyframe = len(self._keyframe_poses) - 1
        self._cloud_stamps.append(int(stamp_ns))
        self._cloud_keyframes.append(keyframe)
        self._cloud_offsets.append(se3.relative(self._keyframe_odometry[keyframe], base))
        return keyframe

    def _is_new_keyframe(self, base: FloatArray, previous: FloatArray | None = None) -> bool:
        """Whether `base` is far enough from the previous keyframe's odometry pose (default: the last
        keyframe's) to be a keyframe."""
        if previous is None and not self._keyframe_odometry:
            return True
        settings = self.config.keyframes
        step = se3.relative(self._keyframe_odometry[-1] if previous is None else previous, base)
        return bool(
            np.linalg.norm(step[:3, 3]) >= settings.distance or se3.rotation_angle(step) >= settings.angle
        )

    # -------------------------------------------------------------------------------------- keyframes

    def _add_keyframe(self, base: FloatArray, stamp_ns: int, points: FloatArray,
                      information: FloatArray | None = None) -> None:
        """`information`: of the constraint from the previous keyframe (default: the odometry's)."""
        settings = self.config.loop_closure
        count = len(self._keyframe_odometry)
        travel = length = 0.0
        if count:
            step = se3.relative(self._keyframe_odometry[-1], base)
            length = float(np.linalg.norm(step[:3, 3]))
            if information is None:
                information = self._odometry_information(step)
            self._edges.add(count - 1, count, step, information, is_loop=False)
            travel = self._keyframe_travel[-1] + length
        self._keyframe_odometry.append(base.copy())
        self._keyframe_poses.append(self._map_from_odometry @ base)
        self._keyframe_stamps.append(int(stamp_ns))
        self._keyframe_clouds.append(points.astype(np.float32))
        self._keyframe_travel.append(travel)
        if weakest_horizontal_share(points) < UNDERCONSTRAINED_SHARE:
            self._underconstrained += 1
            self._underconstrained_travel += length
        self._keyframe_descriptors.append(keyframe_descriptor(base, points, settings))

    def _odometry_information(self, step: FloatArray) -> FloatArray:
        settings = self.config.keyframes
        length = float(np.linalg.norm(step[:3, 3]))
        sigma_linear = settings.odometry_sigma_linear + settings.odometry_sigma_per_metre * length
        sigma_angular = (
            settings.odometry_sigma_angular
            + settings.odometry_sigma_per_radian * float(se3.rotation_angle(step))
            + settings.odometry_sigma_per_metre_angular * length
        )
        return np.diag([sigma_linear**-2] * 3 + [sigma_angular**-2] * 3)

    # ---------------------------------------------------------------------------------- loop closures

    def _close_loops(self, current: int | None = None) -> tuple[tuple[int, int], ...]:
        """Loop closures of keyframe `current` (default: the newest) to keyframes far enough back along
        the path."""
        settings = self.config.loop_closure
        if current is None:
            current = len(self._keyframe_poses) - 1
        if not settings.enabled or current % settings.every_keyframes:
            return ()
        if self._keyframe_travel[current] - self._last_closure_travel < settings.travel_between_closures:
            return ()
        travel = np.array(self._keyframe_travel)
        older = int(np.searchsorted(travel, travel[current] - settings.min_travel, side="right"))
        if older == 0:
            return ()
        self._hypotheses.expire(current, settings.hypothesis_keyframes)
        poses = planar.planar(np.array(self._keyframe_poses[:older]))
        here = planar.planar(self._keyframe_poses[current])
        distance = np.hypot(*(poses[:, :2] - here[:2]).T)
        if not np.any(distance <= settings.max_search_radius):  # nothing near: skip the graph search
            return ()
        radius = settings.search_radii(self._path_lengths_to(current)[:older])
        near = np.flatnonzero(distance <= radius)
        if len(near) == 0:
            return ()
        distances, headings = descriptor_distances(
            self._keyframe_descriptors[current], np.array([self._keyframe_descriptors[k] for k in near])
        )
        candidates: list[tuple[int, float]] = []
        for i in np.argsort(distances):
            if distances[i] > settings.descriptor_max_distance:
                break
            if len(candidates) >= settings.candidates_per_keyframe:
                break
            if all(abs(int(near[i]) - c) > settings.submap_keyframes for c, _ in candidates):
                candidates.append((int(near[i]), float(headings[i])))
        found: list[tuple[int, int]] = []
        for candidate, heading in candidates:
            hypothesis = self._verify_loop(candidate, current, heading, older - 1)
            if hypothesis is None:
                continue
            for accepted in self._hypotheses.confirm(hypothesis):
                self._edges.add(
                    accepted.candidate,
                    accepted.current,
                    accepted.match.relative,
                    accepted.match.information,
                    is_loop=True,
                )
                found.append((accepted.candidate, accepted.current))
        if found:
            self._last_closure_travel = float(travel[current])
            self._candidates["accepted"] += len(found)
            self._pending_loops += len(found)
            if self._pending_loops >= settings.optimize_every_loop_closures:
                self.optimize_online()
        return tuple(found)

    def _path_lengths_to(self, keyframe: int) -> FloatArray:
        """Shortest path length (m) through the graph's constraints from `keyframe` to every keyframe."""
        first, second, relative, _, _ = self._edges.arrays()
        return path_lengths(
            len(self._keyframe_poses), first, second, np.linalg.norm(relative[:, :3, 3], axis=1), keyframe
        )

    def _verify_loop(
        self, candidate: int, current: int, heading: float, last_old: int
    ) -> _LoopHypothesis | None:
        settings = self.config.loop_closure
        anchor = self._keyframe_poses[candidate]
        around = self._submap_keyframes(candidate, last_old)
        target_points = np.concatenate(
            [
                se3.transform_points(se3.relative(anchor, self._keyframe_poses[k]), self._keyframe_clouds[k])
                for k in around
            ]
        )
        here = self._keyframe_poses[current]
        estimate = se3.relative(anchor, here)
        guesses = [estimate]
        # The descriptor's heading is between the levelled frames: keep the estimate's position and tilts.
        levelled = se3.relative(planar.level(anchor), planar.level(here))
        if abs(se2.wrap_angle(heading - planar.yaw(levelled))) > DESCRIPTOR_GUESS_MIN_ANGLE:
            turned = planar.lift(np.array([*levelled[:2, 3], heading]), levelled)
            tilt_anchor = se3.relative(planar.level(anchor), anchor)
            tilt_here = se3.relative(planar.level(here), here)
            guesses.append(se3.inverse(tilt_anchor) @ turned @ tilt_here)
        verdict = verify_loop(
            RegistrationTarget(target_points, settings), self._keyframe_clouds[current], guesses, settings
        )
        if verdict.match is None:
            self._candidates[verdict.reason] += 1
            return None
        matched = planar.planar(anchor @ verdict.match.relative)
        correction = se2.compose(matched, se2.inverse(planar.planar(here)))
        return _LoopHypothesis(candidate, current, verdict.match, correction)

    def _submap_keyframes(self, candidate: int, last: int) -> range:
        """The keyframes whose clouds make the registration target of a loop closure to `candidate`: its
        neighbours along the path, none after `last`."""
        reach = self.config.loop_closure.submap_keyframes
        return range(max(0, candidate - reach), min(last, candidate + reach) + 1)

    # ------------------------------------------------------------------------------------ optimization

    def _planar_graph(self, planar_poses: FloatArray) -> PoseGraph:
        first, second, relative, information, _ = self._edges.arrays()
        return planar.project_graph(
            np.array(self._keyframe_poses), first, second, relative, information, planar_poses
        )

    def optimize_online(self) -> None:
        """Re-optimize the planar keyframe graph from the current estimate, dropping inconsistent loop
        closures, and move the keyframes (and the map ← odometry correction) accordingly."""
        new_loops, self._pending_loops = self._pending_loops, 0
        # a hypothesis' correction is relative to the estimate it was found on: void once that moves
        self._hypotheses.clear()
        if len(self._keyframe_poses) < 2 or not any(self._edges.is_loop):
            return
        poses, removed = optimize_and_prune(
            self._edges, self._planar_graph, planar.planar(np.array(self._keyframe_poses)),
            self.config.loop_closure.chi2_threshold, REOPTIMIZE_ITERATIONS, new_loops,
        )
        self._rejected += removed
        lifted = planar.lift(poses, np.array(self._keyframe_odometry))
        self._keyframe_poses = list(lifted)
        self._map_from_odometry = lifted[-1] @ se3.inverse(self._keyframe_odometry[-1])

    # ------------------------------------------------------------------------------------------ result

    def finish(self) -> Slam3DGraph:
        """Final online optimization, and the keyframe graph with every cloud's offset from its keyframe.
        Raises `FrontendError` when no cloud could be registered."""
        if not self._keyframe_poses:
            raise NothingRegisteredError(
                f"none of the {self._clouds_seen} clouds had the {self.config.odometry.min_points} points "
                "spread over more than a voxel needed to register it"
            )
        if self._pending_loops:
            self.optimize_online()
        self._hypotheses.clear()
        first, second, relative, information, is_loop = self._edges.arrays()
        return Slam3DGraph(
            keyframe_poses=np.array(self._keyframe_poses),
            keyframe_odometry=np.array(self._keyframe_odometry),
            keyframe_stamps_ns=np.array(self._keyframe_stamps, dtype=np.int64),
            edge_from=first,
            edge_to=second,
            relative=relative,
            information=information,
            is_loop=is_loop,
            cloud_stamps_ns=np.array(self._cloud_stamps, dtype=np.int64),
            cloud_keyframes=np.array(self._cloud_keyframes, dtype=np.int64),
            cloud_offsets=np.array(self._cloud_offsets).reshape(-1, 4, 4),
            keyframe_clouds=tuple(self._keyframe_clouds),
            loop_closures_accepted=int(is_loop.sum()),
            loop_closures_rejected=self._rejected,
            loop_candidates={**self._candidates, "unconfirmed": self._hypotheses.dropped},
            clouds_untracked=self._untracked,
            clouds_dropped=self._dropped,
            odometry_guesses_overruled=self._guesses_overruled,
            keyframes_underconstrained=self._underconstrained,
            underconstrained_travel=self._underconstrained_travel,
        )
