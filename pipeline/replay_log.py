"""Replay a 2D laser log: SLAM frontend, the SGD backend, a recording of every iteration, trajectory files.

1. Read the log's wheel odometry and transform tree (small), then stream the scans in sensor-time order.
2. The frontend matches each scan, makes keyframes and loop closures (`frontends.slam2d`).
3. The keyframe graph is optimized by the chosen method from two recorded starts: the odometry-only
   estimate (what the robot believed before any loop closure), so the recording shows the map
   straightening out, and the online estimate; the lower final χ² wins and is the recorded last iteration.
4. Outputs: `<stem>.tum` (one pose per scan at its sensor stamp), `<stem>.g2o` (keyframe graph with
   optimized poses), `<stem>.json` (counts, timings, χ² per iteration, convergence) and `<stem>.rrd`,
   staged and published together on success (`pipeline.outputs`).

Library code: raises `FrontendError`, `OptimizerError` or `PipelineError`, never prints or exits.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.logs import LogReader, TransformTree, open_log
from frontends.slam2d import (
    LaserSlam2D,
    OdometryTrack,
    ScanEstimate,
    Slam2DConfig,
    Slam2DGraph,
    occupancy_grid,
    place,
    read_odometry,
    scans_in_base_frame,
)
from optimizer import se2
from optimizer.graph_files import write_g2o
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, METHODS, OptimizationResult
from pipeline import recording
from pipeline.errors import PipelineError
from pipeline.keyframe_optimization import optimize_keyframes, wheel_odometry_start
from pipeline.outputs import (
    json_text,
    optimization_summary,
    output_stem,
    staged_outputs_in,
    write_png,
    write_text,
)
from pipeline.recording import map2d
from pipeline.recording import scans as scan_recording
from pipeline.trajectory_io import write_tum

FloatArray = NDArray[np.float64]
ScanCallback = Callable[[ScanEstimate], None]
IterationCallback = Callable[[Iteration], None]

SUMMARY_SCHEMA = "sgdslam.replay-log/2"


@dataclass(frozen=True)
class LogReplayOutputs:
    tum: Path
    g2o: Path
    json: Path
    rrd: Path
    map_png: Path

    @classmethod
    def for_input(cls, out_dir: Path, input_path: Path) -> LogReplayOutputs:
        stem = output_stem(input_path)
        files = [out_dir / f"{stem}.{suffix}" for suffix in ("tum", "g2o", "json", "rrd")]
        return cls(*files, out_dir / f"{stem}_map.png")

    def as_tuple(self) -> tuple[Path, Path, Path, Path, Path]:
        return self.tum, self.g2o, self.json, self.rrd, self.map_png


@dataclass(frozen=True, eq=False)
class LogReplayResult:
    input_path: Path
    scan_topic: str
    odometry_topic: str | None
    frontend: Slam2DGraph
    stamps_ns: NDArray[np.int64]
    poses: FloatArray
    """(S, 3) final pose of every scan."""
    keyframe_poses: FloatArray
    chi2_per_iteration: tuple[tuple[str, int, float], ...]
    optimization: OptimizationResult
    """How the keyframe optimization ended (converged, why, every start and the winner)."""
    wall_time: dict[str, float]
    outputs: LogReplayOutputs
    counts: dict[str, int] = field(default_factory=dict)


def replay_log(
    path: str | Path,
    *,
    out_dir: str | Path,
    scan_topic: str | None = None,
    odometry_topic: str | None = None,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    robust: str | None = None,
    config: Slam2DConfig | None = None,
    on_scan: ScanCallback | None = None,
    on_iteration: IterationCallback | None = None,
) -> LogReplayResult:
    """Run the 2D SLAM on the log at `path` and write its outputs to `out_dir`."""
    started = time.perf_counter()
    path = Path(path)
    out_dir = Path(out_dir)
    if method not in METHODS:
        raise PipelineError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    outputs = LogReplayOutputs.for_input(out_dir, path)
    timings: dict[str, float] = {}
    with open_log(path) as log:
        topic, kind = log.sensor_topic(scan_topic)
        if kind != "scan":
            raise PipelineError(
                f"{path}: topic {topic} holds 3D point clouds: replay it with "
                "pipeline.replay_cloud (the replay command chooses it by itself)"
            )
        chosen_odometry = log.odometry_topic(odometry_topic)
        data_counts: dict[str, int] = {}  # what the input checks dropped, skipped or reordered
        odometry = read_odometry(log, odometry_topic, counts=data_counts)
        tree = log.transform_tree()
        timings["read_odometry_tf"] = time.perf_counter() - started
        staged = staged_outputs_in(out_dir, *outputs.as_tuple())
        with staged as (tum_tmp, g2o_tmp, json_tmp, rrd_tmp, png_tmp):
            stream = recording.create_recording(rrd_tmp, name=path.name, with_map=True)
            recording.log_run_properties(stream, {"input": str(path), "scan_topic": topic,
                                                  "odometry_topic": chosen_odometry or "", "method": method})
            run: _FrontendRun | None = None
            try:
                run = _run_frontend(log, topic, odometry, tree, config, stream, on_scan, data_counts)
                timings["frontend"] = run.seconds - run.record_seconds
                frontend = run.frontend
                optimize_started = time.perf_counter()
                first_scans = np.unique(frontend.scan_keyframes, return_index=True)[1]
                optimized = optimize_keyframes(
                    stream,
                    frontend.graph.with_poses(frontend.odometry_chain),
                    frontend.graph,
                    method,
                    iterations,
                    on_iteration,
                    robust=robust,
                    keyframe_scans=frontend.keyframe_scans,
                    wheel_odometry=None if odometry is None else wheel_odometry_start(
                        odometry.interpolate(frontend.scan_stamps_ns[first_scans])[0],
                        frontend.odometry_chain[0]),
                )
                trace, keyframe_poses = optimized.trace, optimized.poses
                timings["record_iterations"] = optimized.record_seconds
                timings["optimize_and_record"] = time.perf_counter() - optimize_started
                poses = frontend.scan_poses(keyframe_poses)
                map_started = time.perf_counter()
                grid = occupancy_grid(frontend.keyframe_scans, keyframe_poses)
                picture = grid.image()
                timings["occupancy_grid"] = time.perf_counter() - map_started
                record_started = time.perf_counter()
                scan_recording.log_final_trajectory(stream, poses)
                map2d.log_occupancy(stream, picture, grid.origin, grid.resolution)
                timings["record_maps"] = time.perf_counter() - record_started
            finally:
                close_started = time.perf_counter()
                recording.close_recording(stream)
                timings["record_scans"] = run.record_seconds if run is not None else 0.0
                timings["record_close"] = time.perf_counter() - close_started
            write_started = time.perf_counter()
            write_tum(tum_tmp, frontend.scan_stamps_ns, poses)
            write_g2o(g2o_tmp, frontend.graph, keyframe_poses)
            write_png(png_tmp, picture)
            timings["write"] = time.perf_counter() - write_started
            timings["total"] = time.perf_counter() - started
            result = LogReplayResult(
                input_path=path,
                scan_topic=topic,
                odometry_topic=chosen_odometry,
                frontend=frontend,
                stamps_ns=frontend.scan_stamps_ns,
                poses=poses,
                keyframe_poses=keyframe_poses,
                chi2_per_iteration=tuple(trace),
                optimization=optimized.result,
                wall_time=timings,
                outputs=outputs,
                counts=run.counts,
            )
            write_text(json_tmp, json_text(summary(result)))
    return result


@dataclass(frozen=True, eq=False)
class _FrontendRun:
    frontend: Slam2DGraph
    counts: dict[str, int]
    seconds: float
    record_seconds: float
    """Of `seconds`, the time spent logging scans to the recording."""


def _run_frontend(
    log: LogReader,
    topic: str,
    odometry: OdometryTrack | None,
    tree: TransformTree,
    config: Slam2DConfig | None,
    stream: Any,
    on_scan: ScanCallback | None,
    data_counts: dict[str, int],
) -> _FrontendRun:
    """Stream the scans through the SLAM frontend, recording each one as it is processed; the counts of
    the input checks (scans without returns, odometry dropped, messages late) join `data_counts`."""
    started = time.perf_counter()
    base_frame = odometry.child_frame if odometry is not None else "base_link"
    slam = LaserSlam2D(config)
    scans_recorder = scan_recording.ScanRecorder(stream)
    scan_recording.log_scan_styles(stream)
    record_seconds = 0.0
    counts = {"scans": 0, "scans_with_tf_mount": 0, "scans_with_odometry": 0}
    odometry_poses: list[FloatArray] = []
    min_points = (config or Slam2DConfig()).matching.min_points
    for scan, has_mount in scans_in_base_frame(log, topic, tree, base_frame, min_points=min_points,
                                               counts=data_counts):
        prediction, interval = None, 0.0
        if odometry is not None:
            at, intervals = odometry.interpolate(np.array([scan.stamp_ns]))
            prediction = None if np.isnan(at[0, 0]) else at[0]
            interval = float(intervals[0]) * 1e-9
        estimate = slam.add_scan(scan.stamp_ns, scan.points, prediction, interval)
        counts["scans"] += 1
        counts["scans_with_tf_mount"] += has_mount
        if prediction is not None:
            counts["scans_with_odometry"] += 1
            odometry_poses.append(prediction)
        record_started = time.perf_counter()
        scans_recorder.add(
            estimate.index, estimate.stamp_ns, place(scan.points, estimate.pose), estimate.pose
        )
        if estimate.new_loop_closures:
            segments = np.array(
                [
                    [slam.keyframe_position(a), slam.keyframe_position(b)]
                    for a, b in estimate.new_loop_closures
                ]
            )
            scan_recording.log_loop_closures_found(stream, estimate.index, estimate.stamp_ns, segments)
        record_seconds += time.perf_counter() - record_started
        if on_scan is not None:
            on_scan(estimate)
    if counts["scans"] == 0:
        raise PipelineError(f"{log.path}: topic {topic} has no scans")
    record_started = time.perf_counter()
    scans_recorder.flush()
    if odometry_poses:
        # In the map frame, which starts at the first scan: the odometry seen from its own first pose.
        track = np.array(odometry_poses)
        scan_recording.log_odometry_trajectory(stream, se2.relative(track[0], track))
    record_seconds += time.perf_counter() - record_started
    counts.update(data_counts)
    counts.update(log.counts)
    return _FrontendRun(slam.finish(), counts, time.perf_counter() - started, record_seconds)


def summary(result: LogReplayResult) -> dict[str, Any]:
    frontend = result.frontend
    return {
        "schema": SUMMARY_SCHEMA,
        "input": str(result.input_path),
        "scan_topic": result.scan_topic,
        "odometry_topic": result.odometry_topic,
        "counts": {
            **result.counts,
            "keyframes": frontend.graph.num_poses,
            "constraints": frontend.graph.num_edges,
            "scans_unmatched": frontend.scans_unmatched,
        },
        "loop_closures": {
            "accepted": frontend.loop_closures_accepted,
            "rejected": frontend.loop_closures_rejected,
        },
        **optimization_summary(result.optimization),
        "chi2_per_iteration": [{"stage": s, "index": i, "chi2": c} for s, i, c in result.chi2_per_iteration],
        "wall_time_s": result.wall_time,
        "outputs": {
            kind: str(getattr(result.outputs, kind)) for kind in ("tum", "g2o", "json", "rrd", "map_png")
        },
    }
