"""Replay a 3D LiDAR log: KISS-ICP odometry and loop closures, the SGD backend, a recording, a map.

1. Read the log's transform tree (small) for the sensor's mount on the base, then stream the clouds in
   sensor-time order through the 3D frontend (`frontends.slam3d`).
2. The keyframe graph, projected to SE(2) (ground-vehicle assumption, see `frontends.slam3d.planar`), is
   optimized from its odometry-only estimate, so the recording shows the map straightening out; the
   online estimate is polished as well and the lower χ² wins. Height, roll and pitch come from odometry.
3. Outputs: `<stem>.tum` (the 3D pose of every cloud at its stamp), `<stem>.ply` (the map: keyframe
   clouds at their optimized poses, one point per voxel), `<stem>.g2o` (the planar keyframe graph with
   optimized poses), `<stem>.json` (counts, timings, χ² per iteration) and `<stem>.rrd`, written under
   temporary names and renamed on success.

Library code: raises `FrontendError`, `OptimizerError` or `PipelineError`, never prints or exits.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.logs import open_log
from frontends.slam3d import CloudEstimate, LidarSlam3D, Slam3DConfig, Slam3DGraph, downsample
from optimizer.graph_files import write_g2o
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, METHODS, OptimizationResult
from pipeline import recording
from pipeline.errors import PipelineError
from pipeline.keyframe_optimization import optimize_keyframes
from pipeline.outputs import json_text, optimization_summary, output_stem, staged_outputs_in, write_text
from pipeline.ply import write_ply
from pipeline.recording import clouds as cloud_recording
from pipeline.trajectory_io import write_tum

FloatArray = NDArray[np.float64]
CloudCallback = Callable[[CloudEstimate], None]
IterationCallback = Callable[[Iteration], None]

SUMMARY_SCHEMA = "sgdslam.replay-cloud/2"
DEFAULT_BASE_FRAME = "base_link"
MAP_VOXEL = 0.2
"""The map (PLY and recording) keeps one point per voxel of this size (m)."""
RECORDING_KEYFRAME_VOXEL = 0.5
"""Keyframe clouds in the recording are thinned to this voxel (m): hundreds of them stay light to view."""


@dataclass(frozen=True)
class CloudReplayOutputs:
    tum: Path
    ply: Path
    g2o: Path
    json: Path
    rrd: Path

    @classmethod
    def for_input(cls, out_dir: Path, input_path: Path) -> CloudReplayOutputs:
        stem = output_stem(input_path)
        return cls(*(out_dir / f"{stem}.{suffix}" for suffix in ("tum", "ply", "g2o", "json", "rrd")))

    def as_tuple(self) -> tuple[Path, Path, Path, Path, Path]:
        return self.tum, self.ply, self.g2o, self.json, self.rrd


@dataclass(frozen=True, eq=False)
class CloudReplayResult:
    input_path: Path
    cloud_topic: str
    sensor_frame: str
    base_frame: str | None
    """The base frame the poses are of; None when tf does not mount the sensor (poses of the sensor)."""
    frontend: Slam3DGraph
    stamps_ns: NDArray[np.int64]
    poses: FloatArray
    """(S, 4, 4) final pose of every cloud."""
    keyframe_poses: FloatArray
    """(K, 4, 4) final keyframe poses."""
    planar_keyframe_poses: FloatArray
    """(K, 3) the optimized planar poses they were lifted from."""
    map_points: int
    chi2_per_iteration: tuple[tuple[str, int, float], ...]
    optimization: OptimizationResult
    """How the keyframe optimization ended (converged, why, every start and the winner)."""
    wall_time: dict[str, float]
    outputs: CloudReplayOutputs
    counts: dict[str, int] = field(default_factory=dict)


def replay_cloud(
    path: str | Path,
    *,
    out_dir: str | Path,
    cloud_topic: str | None = None,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    robust: str | None = None,
    config: Slam3DConfig | None = None,
    on_iteration: IterationCallback | None = None,
    on_cloud: CloudCallback | None = None,
    base_frame: str = DEFAULT_BASE_FRAME,
) -> CloudReplayResult:
    """Run the 3D SLAM on the PointCloud log at `path` and write its outputs to `out_dir`."""
    started = time.perf_counter()
    path = Path(path)
    out_dir = Path(out_dir)
    if method not in METHODS:
        raise PipelineError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    config = config or Slam3DConfig()
    outputs = CloudReplayOutputs.for_input(out_dir, path)
    timings: dict[str, float] = {}
    with open_log(path) as log:
        topic, kind = log.sensor_topic(cloud_topic)
        if kind != "cloud":
            raise PipelineError(f"{path}: topic {topic} holds 2D laser scans, not point clouds")
        tree = log.transform_tree()
        timings["read_tf"] = time.perf_counter() - started
        frontend_started = time.perf_counter()
        slam: LidarSlam3D | None = None
        sensor_frame = ""
        mounted_on: str | None = None
        clouds = 0
        points = 0
        for cloud in log.clouds(topic):
            if slam is None:
                sensor_frame = cloud.frame_id
                mount = tree.sensor_mount(base_frame, cloud.frame_id, cloud.stamp_ns)
                mounted_on = base_frame if mount is not None or cloud.frame_id == base_frame else None
                slam = LidarSlam3D(config, sensor_to_base=None if mount is None else mount.matrix())
            estimate = slam.add_cloud(cloud)
            clouds += 1
            points += len(cloud.points)
            if on_cloud is not None:
                on_cloud(estimate)
        if slam is None:
            raise PipelineError(f"{path}: topic {topic} has no point clouds")
        frontend = slam.finish()
        timings["frontend"] = time.perf_counter() - frontend_started

    with staged_outputs_in(out_dir, *outputs.as_tuple()) as (tum_tmp, ply_tmp, g2o_tmp, json_tmp, rrd_tmp):
        optimize_started = time.perf_counter()
        stream = recording.create_recording(rrd_tmp, name=path.name)
        try:
            recording.log_run_properties(
                stream,
                {"input": str(path), "topic": topic, "method": method, "clouds": clouds,
                 "keyframes": frontend.num_keyframes},
            )  # fmt: skip
            cloud_recording.send_cloud_blueprint(stream)
            cloud_recording.log_keyframe_clouds(
                stream,
                [downsample(cloud, RECORDING_KEYFRAME_VOXEL) for cloud in frontend.keyframe_clouds],
            )
            cloud_recording.log_initial_trajectory3d(stream, frontend.keyframe_odometry)
            optimized = optimize_keyframes(
                stream,
                frontend.planar_graph(frontend.odometry_chain),
                frontend.planar_graph(),
                method,
                iterations,
                on_iteration,
                _LiftedPoses(frontend, cloud_recording.KeyframePoseRecorder(stream)),
                robust=robust,
            )
            trace, planar_poses = optimized.trace, optimized.poses
            timings["optimize_and_record"] = time.perf_counter() - optimize_started
            keyframe_poses = frontend.lift(planar_poses)
            map_started = time.perf_counter()
            map_points = frontend.map_points(keyframe_poses, MAP_VOXEL)
            timings["map"] = time.perf_counter() - map_started
            cloud_recording.log_map(stream, map_points)
        finally:
            recording.close_recording(stream)
        write_started = time.perf_counter()
        poses = frontend.cloud_poses(keyframe_poses)
        write_tum(tum_tmp, frontend.cloud_stamps_ns, poses)
        write_ply(ply_tmp, map_points)
        write_g2o(g2o_tmp, frontend.planar_graph(), planar_poses)
        timings["write"] = time.perf_counter() - write_started
        timings["total"] = time.perf_counter() - started
        result = CloudReplayResult(
            input_path=path,
            cloud_topic=topic,
            sensor_frame=sensor_frame,
            base_frame=mounted_on,
            frontend=frontend,
            stamps_ns=frontend.cloud_stamps_ns,
            poses=poses,
            keyframe_poses=keyframe_poses,
            planar_keyframe_poses=planar_poses,
            map_points=len(map_points),
            chi2_per_iteration=tuple(trace),
            optimization=optimized.result,
            wall_time=timings,
            outputs=outputs,
            counts={
                "clouds": clouds,
                "points_per_cloud": round(points / clouds),
                "clouds_in_trajectory": len(frontend.cloud_stamps_ns),
                "clouds_untracked": frontend.clouds_untracked,
            },
        )
        write_text(json_tmp, json_text(summary(result, config)))
    return result


class _LiftedPoses:
    """Records every iteration's keyframe poses in 3D (height, roll and pitch from odometry)."""

    def __init__(self, frontend: Slam3DGraph, recorder: cloud_recording.KeyframePoseRecorder) -> None:
        self._frontend = frontend
        self._recorder = recorder

    def add(self, step: int, iteration: Iteration) -> None:
        self._recorder.add(step, self._frontend.lift(iteration.poses))

    def flush(self) -> None:
        self._recorder.flush()


def summary(result: CloudReplayResult, config: Slam3DConfig | None = None) -> dict[str, Any]:
    frontend = result.frontend
    clouds = result.counts.get("clouds", 0)
    frontend_seconds = result.wall_time.get("frontend", 0.0)
    return {
        "schema": SUMMARY_SCHEMA,
        "input": str(result.input_path),
        "cloud_topic": result.cloud_topic,
        "sensor_frame": result.sensor_frame,
        "base_frame": result.base_frame,
        "counts": {
            **result.counts,
            "keyframes": frontend.num_keyframes,
            "constraints": len(frontend.edge_from),
            "map_points": result.map_points,
        },
        "loop_closures": {
            "accepted": frontend.loop_closures_accepted,
            "rejected": frontend.loop_closures_rejected,
            "candidates": frontend.loop_candidates,
        },
        **optimization_summary(result.optimization),
        "chi2_per_iteration": [{"stage": s, "index": i, "chi2": c} for s, i, c in result.chi2_per_iteration],
        "wall_time_s": result.wall_time,
        "frontend_clouds_per_second": clouds / frontend_seconds if frontend_seconds > 0 else None,
        "config": dataclasses.asdict(config) if config is not None else None,
        "outputs": {
            kind: str(getattr(result.outputs, kind)) for kind in ("tum", "ply", "g2o", "json", "rrd")
        },
    }
