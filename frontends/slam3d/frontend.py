"""The 3D LiDAR SLAM as a `frontends.protocol.LogFrontend`: a log's point clouds in, the planar keyframe
graph, every cloud's 3D pose and a point map out."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError
from frontends.logs import Cloud3D, LogReader
from frontends.protocol import FloatArray, FrontendOptions, IntArray, LogFrontendBase, default_base_frame
from frontends.slam3d.config import Slam3DConfig
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph
from optimizer.graph import PoseGraph

MAP_VOXEL = 0.2
"""The map keeps one point per voxel of this size (m)."""


class LidarFrontend(LogFrontendBase[Slam3DConfig, Slam3DGraph]):
    """`LidarSlam3D` on the clouds of `topic` in an open log; see `frontends.protocol.LogFrontend`.

    The odometry topic is chosen here (`odometry_topic`) for the odometry prior of the 3D frontend; the
    clouds alone drive it today."""

    def __init__(self, log: LogReader, topic: str, config: Slam3DConfig | None = None,
                 options: FrontendOptions | None = None) -> None:
        super().__init__(log, topic, config or Slam3DConfig(), options)
        self._slam: LidarSlam3D | None = None
        self._clouds = 0
        self._points = 0
        self._map_points: int | None = None

    def measurements(self) -> Iterator[Cloud3D]:
        return self._log.clouds(self._topic)

    def add(self, measurement: Cloud3D) -> CloudEstimate:
        if self._slam is None:
            self.sensor_frame = measurement.frame_id
            base = self.base_frame or default_base_frame(self._tree, measurement.frame_id)
            mount = self._tree.sensor_mount(base, measurement.frame_id, measurement.stamp_ns)
            self.base_frame = base if mount is not None or measurement.frame_id == base else None
            self._slam = LidarSlam3D(self.config, sensor_to_base=None if mount is None else mount.matrix())
        self._clouds += 1
        self._points += len(measurement.points)
        return self._slam.add_cloud(measurement)

    def finish(self) -> None:
        if self._slam is None:
            raise FrontendError(f"{self._log.path}: topic {self._topic} has no point clouds")
        self._result = self._slam.finish()

    def keyframe_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        return self.result.planar_graph(planar_poses)

    @property
    def stamps_ns(self) -> IntArray:
        return self.result.cloud_stamps_ns

    def estimates(self, planar_poses: FloatArray) -> FloatArray:
        return self.result.cloud_poses(self.result.lift(planar_poses))

    def map_export(self, planar_poses: FloatArray) -> NDArray[np.float32]:
        points = self.result.map_points(self.result.lift(planar_poses), MAP_VOXEL)
        self._map_points = len(points)
        return points

    def counts(self) -> dict[str, int]:
        result = self.result
        counts = {"clouds": self._clouds, "points_per_cloud": round(self._points / max(self._clouds, 1)),
                  "clouds_in_trajectory": len(result.cloud_stamps_ns),
                  "clouds_untracked": result.clouds_untracked,
                  **self._log.counts, "keyframes": result.num_keyframes, "constraints": len(result.edge_from)}
        if self._map_points is not None:
            counts["map_points"] = self._map_points
        return counts

    def loop_closures(self) -> dict[str, Any]:
        result = self.result
        return {"accepted": result.loop_closures_accepted, "rejected": result.loop_closures_rejected,
                "candidates": dict(result.loop_candidates)}
