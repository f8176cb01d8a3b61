"""The 3D LiDAR SLAM as a `frontends.protocol.LogFrontend`: a log's point clouds in, the planar keyframe
graph, every cloud's 3D pose and a point map out."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError, LogFileError, LogWarning, UnusableLogError
from frontends.logs import ODOMETRY_FRAME, Cloud3D, LogReader, TransformTree
from frontends.protocol import FloatArray, FrontendOptions, IntArray, LogFrontendBase, SessionArrays
from frontends.slam3d.config import Slam3DConfig
from frontends.slam3d.pose_graph3d import PolishResult
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, NothingRegisteredError, Slam3DGraph
from frontends.slam3d.vehicle import LidarMount, OdometryPrior, lidar_mount
from optimizer.graph import PoseGraph

MAP_VOXEL = 0.2
"""The map keeps one point per voxel of this size (m)."""


def _odometry_prior(log: LogReader, topic: str | None, tree: TransformTree) -> OdometryPrior | None:
    """The log's odometry (its odometry topic, else tf's dynamic odom edge) as a prior. Without an
    odometry topic, the tf already read says whether there is a dynamic edge at all: a log with none
    (static mounts only) is not read a second time to find no odometry in it."""
    if topic is None and all(tree.is_static(frame) or tree.parent(frame) is None for frame in tree.frames):
        return None
    return OdometryPrior.from_poses(log.odometry(topic))


class LidarFrontend(LogFrontendBase[Slam3DConfig, Slam3DGraph]):
    """`LidarSlam3D` on the clouds of `topic` in an open log; see `frontends.protocol.LogFrontend`.

    The base frame and the LiDAR's mount come from tf (`vehicle.lidar_mount`: the requested base frame,
    else the frame that moves). The log's odometry (its odometry topic, else tf's odom edge), when it
    has one, is read before the clouds and gives KISS-ICP its motion guess (`vehicle.OdometryPrior`).
    Final poses: the planar optimum lifted to 3D, then polished in SE(3) when `config.se3_polish.enabled`
    (`polish` holds how that went)."""

    def __init__(self, log: LogReader, topic: str, config: Slam3DConfig | None = None,
                 options: FrontendOptions | None = None) -> None:
        super().__init__(log, topic, config or Slam3DConfig(), options)
        self._slam: LidarSlam3D | None = None
        self._clouds = 0
        self._clouds_with_odometry = 0
        self._points = 0
        self._map_points: int | None = None
        self._prior = _odometry_prior(log, self.odometry_topic, self._tree)
        if self._prior is not None:
            self._odometry_read(ODOMETRY_FRAME, self._prior.child_frame)
        self.sensor_to_base = np.eye(4)
        """The LiDAR's mount on the base (from tf at the first cloud; identity without one)."""
        self.polish: PolishResult | None = None
        self._polished_for: bytes | None = None

    def measurements(self) -> Iterator[Cloud3D]:
        return self._log.clouds(self._topic)

    def add(self, measurement: Cloud3D) -> CloudEstimate:
        if self._slam is None:
            self.sensor_frame = measurement.frame_id
            requested = self.base_frame
            try:
                mount = lidar_mount(self._tree, measurement.frame_id, measurement.stamp_ns, requested)
            except FrontendError as error:  # a cycle in tf
                raise LogFileError(self._log.path, str(error)) from None
            if mount is None:
                raise self._unlinked_base_frame(measurement.frame_id, "LiDAR")
            self.base_frame = mount.base_frame if mount.from_tf or requested is not None else None
            self.sensor_to_base = np.asarray(mount.sensor_to_base, dtype=np.float64)
            self._slam = self._make_slam(self.sensor_to_base)
            self._prior = self._prior_of_base(mount, measurement.stamp_ns)
        self._clouds += 1
        self._points += len(measurement.points)
        odometry_pose = None if self._prior is None else self._prior.at(measurement.stamp_ns)
        self._clouds_with_odometry += odometry_pose is not None
        return self._slam.add_cloud(measurement, odometry_pose)

    def _make_slam(self, sensor_to_base: FloatArray) -> LidarSlam3D:
        """The SLAM the clouds go to (a session's frontends start it from a saved map)."""
        return LidarSlam3D(self.config, sensor_to_base=sensor_to_base)

    def _prior_of_base(self, mount: LidarMount, stamp_ns: int) -> OdometryPrior | None:
        """The odometry as poses of the mount's base frame; None, and a warning, when tf cannot relate the
        two (the odometry is then not used)."""
        prior = self._prior
        if prior is None or not prior.child_frame or prior.child_frame == mount.base_frame:
            return prior
        link = self._tree.sensor_mount(prior.child_frame, mount.base_frame, stamp_ns)
        if link is None:
            warnings.warn(f"{self._log.path}: tf gives no path from the poses' frame {mount.base_frame} "
                          f"(the LiDAR's base) to the odometry's {prior.child_frame}: the odometry was not "
                          "used", LogWarning, stacklevel=2)
            return None
        return prior.rebase(link.matrix())

    def _keyframe_poses(self, planar_poses: FloatArray) -> FloatArray:
        """3D keyframe poses of a planar optimum: lifted, then polished in SE(3) (computed once)."""
        lifted = self.result.lift(planar_poses)
        settings = self.config.se3_polish
        if not settings.enabled:
            return lifted
        key = np.ascontiguousarray(planar_poses, dtype=np.float64).tobytes()
        if self.polish is None or self._polished_for != key:
            self.polish = self.result.polish_se3(lifted, settings.max_iterations)
            self._polished_for = key
        return self.polish.poses

    def finish(self) -> None:
        if self._slam is None:
            raise FrontendError(f"{self._log.path}: topic {self._topic} has no point clouds")
        try:
            self._result = self._finished(self._slam.finish)
        except NothingRegisteredError as error:
            raise UnusableLogError(self._log.path, str(error)) from None
        result = self._result
        untracked = result.clouds_untracked
        if untracked:
            needed = self.config.odometry.min_points
            warnings.warn(f"{self._log.path}: {untracked} of the {self._clouds} clouds on {self._topic} had "
                          f"fewer than {needed} points spread over more than a voxel to register: each was "
                          "given the pose of the last registered cloud", LogWarning, stacklevel=2)
        overruled = result.odometry_guesses_overruled
        if overruled:
            warnings.warn(f"{self._log.path}: at {overruled} of the {self._clouds} clouds the odometry's "
                          f"motion ({self.odometry_topic or 'tf'}) was far from the LiDAR's and fit the map "
                          "much worse (a jump in the odometry?): those clouds were registered without it",
                          LogWarning, stacklevel=2)
        if result.keyframes_underconstrained:
            warnings.warn(f"{self._log.path}: {result.keyframes_underconstrained} of the "
                          f"{result.num_keyframes} keyframes ({result.underconstrained_travel:.0f} m of the "
                          "path) saw surfaces facing almost only one horizontal direction (a featureless "
                          "road or tunnel): the LiDAR cannot measure motion along them there, which the "
                          "odometry or, without it, constant velocity carried; distances there may be short",
                          LogWarning, stacklevel=2)
        if self._prior is not None:
            self._warn_if_odometry_covered_nothing(self._prior.stamps_ns, result.cloud_stamps_ns,
                                                   self._clouds_with_odometry, "clouds", "registered")
        if not any(len(cloud) for cloud in result.keyframe_clouds):
            odometry = self.config.odometry
            raise UnusableLogError(
                self._log.path, f"no cloud on {self._topic} kept a point between min_range "
                f"({odometry.min_range:g} m) and max_range ({odometry.max_range:g} m) of [slam3d.odometry]: "
                "nothing to map")

    def keyframe_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        return self.result.planar_graph(planar_poses)

    @property
    def stamps_ns(self) -> IntArray:
        return self.result.cloud_stamps_ns

    def estimates(self, planar_poses: FloatArray) -> FloatArray:
        return self.result.cloud_poses(self._keyframe_poses(planar_poses))

    def session_content(self, planar_poses: FloatArray) -> SessionArrays:
        result = self.result
        arrays = {"keyframe_poses": self._keyframe_poses(planar_poses), "keyframe_planar_poses": planar_poses,
                  "keyframe_stamps_ns": result.keyframe_stamps_ns, "edge_from": result.edge_from,
                  "edge_to": result.edge_to, "relative": result.relative, "information": result.information,
                  "is_loop": result.is_loop, "cloud_stamps_ns": result.cloud_stamps_ns,
                  "cloud_keyframes": result.cloud_keyframes, "cloud_offsets": result.cloud_offsets,
                  "sensor_to_base": self.sensor_to_base}
        return arrays, result.keyframe_clouds

    def map_export(self, planar_poses: FloatArray) -> NDArray[np.float32]:
        points = self.result.map_points(self._keyframe_poses(planar_poses), MAP_VOXEL)
        self._map_points = len(points)
        return points

    def counts(self) -> dict[str, int]:
        result = self.result
        counts = {"clouds": self._clouds, "points_per_cloud": round(self._points / max(self._clouds, 1)),
                  "clouds_in_trajectory": len(result.cloud_stamps_ns),
                  "clouds_untracked": result.clouds_untracked,
                  "clouds_odometry_overruled": result.odometry_guesses_overruled,
                  "keyframes_underconstrained": result.keyframes_underconstrained,
                  **self._log.counts, "keyframes": result.num_keyframes, "constraints": len(result.edge_from)}
        if self._map_points is not None:
            counts["map_points"] = self._map_points
        return counts

    def loop_closures(self) -> dict[str, Any]:
        result = self.result
        return {"accepted": result.loop_closures_accepted, "rejected": result.loop_closures_rejected,
                "candidates": dict(result.loop_candidates)}
