"""Replay a robot log, 2D laser scans or 3D point clouds: its SLAM frontend, the SGD backend, a recording of
every iteration, trajectory and map files.

1. Open the log; its sensor topic's kind chooses the frontend (`frontends.slam2d.LaserFrontend` or
   `frontends.slam3d.LidarFrontend`, both `frontends.protocol.LogFrontend`) and the recording's part for
   it (`pipeline.recording.scans` / `.clouds`). The outputs are staged before the frontend runs, so an
   unwritable `--out` fails at once.
2. Every measurement streams through the frontend (keyframes, loop closures) and into the recording.
3. The keyframe graph (SE(2)) is optimized by the chosen method from two recorded starts, the
   odometry-only estimate and the online one; the lower final χ² wins (`pipeline.keyframe_optimization`).
4. Outputs: `<stem>.tum` (every measurement's pose at its sensor stamp), `<stem>.g2o` (the keyframe graph
   with optimized poses), the map (`<stem>_map.png`, an occupancy grid, for scans; `<stem>.ply`, points,
   for clouds), `<stem>.json` (counts, timings, χ² per iteration, convergence, warnings) and
   `<stem>.rrd`, published together on success (`pipeline.outputs`).

Warnings raised on the way are counted (`pipeline.warning_tally`), written to the summary and raised once
each afterwards. Library code: raises `FrontendError`, `OptimizerError` or `PipelineError`, never prints.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from frontends.logs import LogReader, open_log
from frontends.protocol import Estimate, FrontendOptions, LogFrontend
from frontends.slam2d import LaserFrontend, OccupancyGrid, Slam2DConfig
from frontends.slam3d import LidarFrontend, Slam3DConfig, planar
from optimizer.graph_files import write_g2o
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, METHODS, OptimizationResult
from pipeline import recording
from pipeline.errors import PipelineError
from pipeline.keyframe_optimization import IterationSink, optimize_keyframes
from pipeline.map_files import map_server_pgm, map_server_yaml, picture_with_scale_bar
from pipeline.outputs import (
    json_text,
    optimization_summary,
    output_stem,
    staged_outputs_in,
    write_bytes,
    write_png,
    write_text,
)
from pipeline.ply import write_ply
from pipeline.recording.clouds import CloudReplayRecording
from pipeline.recording.scans import ScanReplayRecording
from pipeline.trajectory_io import write_tum
from pipeline.warning_tally import WarningTally, reissue, tallied_warnings

FloatArray = NDArray[np.float64]
EstimateCallback = Callable[[Estimate], None]
IterationCallback = Callable[[Iteration], None]

SUMMARY_SCHEMA = "sgdslam.replay-log/3"


class FrontendRecording(Protocol):
    """A frontend's part of the recording, beside the optimization's (`pipeline.recording`)."""

    with_map: bool
    """Whether the recording's layout has the 2D map view."""

    def measurement(self, measurement: Any, estimate: Any) -> None: ...

    def frontend_done(self) -> None: ...

    def iteration_sink(self) -> IterationSink | None: ...

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: Any) -> None: ...


@dataclass(frozen=True)
class _MapFile:
    """One map output: its `ReplayOutputs` field, its name after the stem, and how it is written."""

    output: str
    suffix: str
    write: Callable[[Path, Any, ReplayOutputs], None]
    """(staged path, the frontend's map export, the outputs' published paths)."""


@dataclass(frozen=True)
class _Sensor:
    """What a sensor kind chooses: its frontend, its recording, its map files."""

    frontend: Callable[[LogReader, str, Any, FrontendOptions], LogFrontend]
    recording: type[ScanReplayRecording] | type[CloudReplayRecording]
    """A `FrontendRecording` of the frontend (`recording(stream, frontend)`)."""
    map_files: tuple[_MapFile, ...]


def _write_map_yaml(path: Path, grid: OccupancyGrid, outputs: ReplayOutputs) -> None:
    assert outputs.map_pgm is not None
    write_text(path, map_server_yaml(grid, outputs.map_pgm.name))


_SENSORS = {
    "scan": _Sensor(LaserFrontend, ScanReplayRecording, (
        _MapFile("map_png", "_map.png", lambda path, grid, _: write_png(path, picture_with_scale_bar(grid))),
        _MapFile("map_pgm", "_map.pgm", lambda path, grid, _: write_bytes(path, map_server_pgm(grid))),
        _MapFile("map_yaml", "_map.yaml", _write_map_yaml),
    )),
    "cloud": _Sensor(LidarFrontend, CloudReplayRecording, (
        _MapFile("ply", ".ply", lambda path, points, _: write_ply(path, points)),
    )),
}


@dataclass(frozen=True)
class ReplayOutputs:
    tum: Path
    g2o: Path
    json: Path
    rrd: Path
    map_png: Path | None = None
    """The occupancy grid (scans), north up, with a scale bar."""
    map_pgm: Path | None = None
    """The occupancy grid for ROS map_server (scans), with `map_yaml`."""
    map_yaml: Path | None = None
    ply: Path | None = None
    """The point map (clouds)."""

    @classmethod
    def for_input(cls, out_dir: Path, input_path: Path, sensor: str = "scan") -> ReplayOutputs:
        stem = output_stem(input_path)
        chosen = _SENSORS[sensor]
        files = {suffix: out_dir / f"{stem}.{suffix}" for suffix in ("tum", "g2o", "json", "rrd")}
        return cls(**files, **{map_file.output: out_dir / f"{stem}{map_file.suffix}"
                               for map_file in chosen.map_files})

    def paths(self) -> dict[str, Path]:
        """Kind → path of every output written ("tum", "g2o", "json", "rrd" and the map's)."""
        names = ("tum", "g2o", "json", "rrd", "map_png", "map_pgm", "map_yaml", "ply")
        return {name: getattr(self, name) for name in names if getattr(self, name) is not None}


@dataclass(frozen=True, eq=False)
class LogReplayResult:
    input_path: Path
    sensor: str
    """"scan" (2D laser) or "cloud" (3D LiDAR)."""
    topic: str
    odometry_topic: str | None
    sensor_frame: str
    base_frame: str | None
    """The frame the poses are of; None when tf does not mount the sensor on it (poses of the sensor)."""
    frontend: LogFrontend
    measurements: int
    """Scans or clouds processed."""
    stamps_ns: NDArray[np.int64]
    poses: FloatArray
    """Final pose of every measurement at `stamps_ns`: (S, 3), or (S, 4, 4) for clouds."""
    keyframe_poses: FloatArray
    """(K, 3) optimized planar keyframe poses."""
    chi2_per_iteration: tuple[tuple[str, int, float], ...]
    optimization: OptimizationResult
    """How the keyframe optimization ended (converged, why, every start and the winner)."""
    wall_time: dict[str, float]
    outputs: ReplayOutputs
    counts: dict[str, int]
    loop_closures: dict[str, Any]
    warnings: list[dict[str, Any]]
    """[{"message", "count"}]: what was skipped or lost on the way, each distinct message once."""
    settings: dict[str, Any]

    @property
    def planar_poses(self) -> FloatArray:
        """(S, 3) every measurement's pose in the plane."""
        return self.poses if self.poses.ndim == 2 else planar.planar(self.poses)


def replay_log(
    path: str | Path,
    *,
    out_dir: str | Path,
    topic: str | None = None,
    odometry_topic: str | None = None,
    base_frame: str | None = None,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    robust: str | None = None,
    slam2d: Slam2DConfig | None = None,
    slam3d: Slam3DConfig | None = None,
    on_measurement: EstimateCallback | None = None,
    on_iteration: IterationCallback | None = None,
) -> LogReplayResult:
    """Run the SLAM of the log's sensor (`topic`, found by type unless given) on the log at `path` and
    write its outputs to `out_dir`. `slam2d` / `slam3d` configure the frontend of scans / clouds."""
    path = Path(path)
    if method not in METHODS:
        raise PipelineError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    run = _Run(path, method, iterations, robust, on_measurement, on_iteration)
    options = FrontendOptions(base_frame=base_frame, odometry_topic=odometry_topic)
    tally = WarningTally(path)
    try:
        with tallied_warnings(tally), open_log(path) as log:
            return run.replay(log, Path(out_dir), topic, options, {"scan": slam2d, "cloud": slam3d}, tally)
    finally:
        reissue(path, tally.as_json())


@dataclass(frozen=True, eq=False)
class _Optimized:
    measurements: int
    trace: tuple[tuple[str, int, float], ...]
    optimization: OptimizationResult
    keyframe_poses: FloatArray
    poses: FloatArray
    map_export: Any
    """What the frontend's `map_export` gave: an occupancy grid (scans) or points (clouds)."""


@dataclass(frozen=True)
class _Run:
    path: Path
    method: str
    iterations: int | None
    robust: str | None
    on_measurement: EstimateCallback | None
    on_iteration: IterationCallback | None

    def replay(self, log: LogReader, out_dir: Path, topic: str | None, options: FrontendOptions,
               configs: dict[str, Any], tally: WarningTally) -> LogReplayResult:
        started = time.perf_counter()
        topic, kind = log.sensor_topic(topic)
        sensor = _SENSORS[kind]
        outputs = ReplayOutputs.for_input(out_dir, self.path, kind)
        paths = outputs.paths()
        with staged_outputs_in(out_dir, *paths.values()) as staged_paths:
            staged = dict(zip(paths, staged_paths, strict=True))
            frontend = sensor.frontend(log, topic, configs[kind], options)
            timings = {"read_odometry_tf": time.perf_counter() - started}
            stream = recording.create_recording(staged["rrd"], name=self.path.name,
                                                with_map=sensor.recording.with_map)
            try:
                recorder: FrontendRecording = sensor.recording(stream, frontend)  # type: ignore[arg-type]
                result = self.through(frontend, topic, recorder, stream, timings)
            finally:
                close_started = time.perf_counter()
                recording.close_recording(stream)
                timings["record_close"] = time.perf_counter() - close_started
            write_started = time.perf_counter()
            write_tum(staged["tum"], frontend.stamps_ns, result.poses)
            write_g2o(staged["g2o"], frontend.keyframe_graph(), result.keyframe_poses)
            for map_file in sensor.map_files:
                map_file.write(staged[map_file.output], result.map_export, outputs)
            timings["write"] = time.perf_counter() - write_started
            timings["total"] = time.perf_counter() - started
            replayed = LogReplayResult(
                input_path=self.path, sensor=kind, topic=topic, odometry_topic=frontend.odometry_topic,
                sensor_frame=frontend.sensor_frame, base_frame=frontend.base_frame, frontend=frontend,
                measurements=result.measurements, stamps_ns=frontend.stamps_ns, poses=result.poses,
                keyframe_poses=result.keyframe_poses, chi2_per_iteration=result.trace,
                optimization=result.optimization, wall_time=timings, outputs=outputs,
                counts=frontend.counts(), loop_closures=frontend.loop_closures(), warnings=tally.as_json(),
                settings=frontend.settings(),
            )
            write_text(staged["json"], json_text(summary(replayed)))
        return replayed

    def through(self, frontend: LogFrontend, topic: str, recorder: FrontendRecording, stream: Any,
                timings: dict[str, float]) -> _Optimized:
        """Stream the measurements through the frontend, then optimize its keyframe graph and make the map,
        recording all of it; `timings` gets the seconds of each stage."""
        started = time.perf_counter()
        record_seconds = 0.0
        count = 0
        for measurement in frontend.measurements():
            estimate = frontend.add(measurement)
            count += 1
            record_started = time.perf_counter()
            recorder.measurement(measurement, estimate)
            record_seconds += time.perf_counter() - record_started
            if self.on_measurement is not None:
                self.on_measurement(estimate)
        frontend.finish()  # raises when there was nothing to process
        record_started = time.perf_counter()
        recorder.frontend_done()
        record_seconds += time.perf_counter() - record_started
        timings["frontend"] = time.perf_counter() - started - record_seconds
        timings["record_scans"] = record_seconds
        optimize_started = time.perf_counter()
        graph = frontend.keyframe_graph()
        recording.log_run_properties(stream, {"input": str(self.path), "topic": topic,
                                              "method": self.method, "measurements": count,
                                              "keyframes": graph.num_poses})
        optimized = optimize_keyframes(stream, frontend.keyframe_graph(frontend.odometry_chain), graph,
                                       self.method, self.iterations, self.on_iteration,
                                       recorder.iteration_sink(), robust=self.robust)
        timings["record_iterations"] = optimized.record_seconds
        timings["optimize_and_record"] = time.perf_counter() - optimize_started
        map_started = time.perf_counter()
        estimates = frontend.estimates(optimized.poses)
        map_export = frontend.map_export(optimized.poses)
        timings["map"] = time.perf_counter() - map_started
        record_started = time.perf_counter()
        recorder.final(optimized.poses, estimates, map_export)
        timings["record_maps"] = time.perf_counter() - record_started
        return _Optimized(count, optimized.trace, optimized.result, optimized.poses, estimates, map_export)


def summary(result: LogReplayResult) -> dict[str, Any]:
    return {
        "schema": SUMMARY_SCHEMA,
        "input": str(result.input_path),
        "sensor": result.sensor,
        "topic": result.topic,
        "odometry_topic": result.odometry_topic,
        "sensor_frame": result.sensor_frame,
        "base_frame": result.base_frame,
        "counts": result.counts,
        "loop_closures": result.loop_closures,
        **optimization_summary(result.optimization),
        "chi2_per_iteration": [{"stage": s, "index": i, "chi2": c} for s, i, c in result.chi2_per_iteration],
        "wall_time_s": result.wall_time,
        "warnings": result.warnings,
        "config": result.settings,
        "outputs": {kind: str(path) for kind, path in result.outputs.paths().items()},
    }
