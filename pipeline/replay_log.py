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

A replay may start from a saved session (`SessionStart`, `pipeline.session_file`; 2D laser and 3D
point-cloud sessions):
- `continue`: the frontend table's session factory gives a frontend that continues the saved keyframe graph
  (`frontends.slam2d.session_frontends.ContinuingLaserFrontend`, `frontends.slam3d.session_frontends.
  ContinuingLidarFrontend`); everything else is as above, and the trajectory, the graph, the map and the
  new session hold both runs;
- `map`: localization only (`LocalizingLaserFrontend`, `LocalizingLidarFrontend`): the measurements
  stream through the localizer and the recording as in step 2; the saved map's keyframes are not optimized
  (of scans, the run's own keyframe graph is, with them held: `frontends.slam2d.held_map`, recorded as in
  step 3 by `held_map_solver`), and the outputs are
  `<stem>.tum` (and `<stem>.kitti` for clouds: the measurements placed in the saved map, in its frame),
  `<stem>.json` (per-measurement match quality, `localization_summary`) and `<stem>.rrd` (the saved map
  with the new run on it); the saved map is not changed or written again.

Warnings raised on the way are counted (`pipeline.warning_tally`), written to the summary and raised once
each afterwards. Library code: raises `FrontendError`, `OptimizerError` or `PipelineError`, never prints.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeAlias, cast

import numpy as np
from numpy.typing import NDArray

from frontends.errors import EmptySavedMapError, LogWarning, MapExtentError
from frontends.logs import LogReader, open_log
from frontends.protocol import ContinuingFrontend, Estimate, FrontendOptions, LogFrontend, StreamedFrontend
from optimizer.graph_files import write_g2o
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, METHODS, OptimizationResult
from pipeline import recording
from pipeline.errors import PipelineError
from pipeline.keyframe_optimization import (
    KeyframeOptimization,
    held_map_solver,
    optimize_keyframes,
    wheel_odometry_start,
)
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
from pipeline.ply import write_map_pcd, write_ply
from pipeline.recording import IterationSink
from pipeline.session_file import (
    SENSOR_WORDS,
    SessionContent,
    SessionError,
    read_session,
    saved_map_2d,
    saved_map_3d,
    session_sensor_kind,
    source_description,
    write_session_file,
)
from pipeline.trajectory_io import write_kitti_poses, write_tum
from pipeline.warning_tally import WHILE_READING, WarningTally, reissue, tallied_warnings

if TYPE_CHECKING:  # loaded by the first log of their sensor kind only (`_scan_sensor`, `_cloud_sensor`)
    from frontends.slam2d import Slam2DConfig
    from frontends.slam2d.session_frontends import LocalizingLaserFrontend
    from frontends.slam3d import Slam3DConfig
    from frontends.slam3d.session_frontends import LocalizingLidarFrontend
    from pipeline.recording.clouds import CloudLocalizationRecording, CloudReplayRecording
    from pipeline.recording.scans import MapLocalizationRecording, ScanReplayRecording

FloatArray = NDArray[np.float64]
EstimateCallback = Callable[[Estimate], None]
IterationCallback = Callable[[Iteration], None]

SUMMARY_SCHEMA = "sgdslam.replay-log/3"


class FrontendRecording(Protocol):
    """A frontend's part of the recording, beside the optimization's (`pipeline.recording`): its
    measurements, its final map and what it adds to the optimization's iterations. A localization's
    recording (the saved keyframes are not optimized) is only told of the measurements and the final map
    (a laser run's own graph, solved in the frontend with the saved map held, records through
    `held_map_solver`)."""

    def measurement(self, measurement: Any, estimate: Any) -> None: ...

    def frontend_done(self) -> None: ...

    def final(self, planar_poses: FloatArray, estimates: FloatArray, map_export: Any) -> None: ...

    def iteration_sink(self) -> IterationSink | None: ...

    def keyframe_scans(self) -> Sequence[FloatArray] | None:
        """Each keyframe's 2D points in its own frame, to record the walls moving (None: not drawn)."""
        ...


@dataclass(frozen=True)
class _MapFile:
    """One map output: its `ReplayOutputs` field, its name after the stem, and how it is written."""

    output: str
    suffix: str
    write: Callable[[Path, Any], None]
    """(staged path, the frontend's map export)."""


LocalizingFrontend: TypeAlias = "LocalizingLaserFrontend | LocalizingLidarFrontend"
"""The frontend of a localization in a saved map, of scans or of clouds."""

ReplayMode = Literal["slam", "continue", "map"]
"""A plain log replay, mapping continued from a session, or localization in a session's map."""


@dataclass(frozen=True, eq=False)
class SessionStart:
    """A saved session a log replay starts from (`replay LOG --continue SESSION`, `--map SESSION`)."""

    path: Path
    mode: Literal["continue", "map"]
    content: SessionContent
    initial_pose: tuple[float, float, float] | None = None
    """With "map": where the new run starts in the map (x, y, yaw); None: found by global localization."""

    @classmethod
    def load(cls, path: str | Path, mode: Literal["continue", "map"],
             initial_pose: Sequence[float] | None = None) -> SessionStart:
        """Read the session file (`SessionError` naming it when it is damaged or from a newer version)."""
        # `pipeline.api.replay`, the one caller, has refused an initial pose without "map" already.
        pose = None if initial_pose is None else _three_finite_numbers(initial_pose)
        return cls(Path(path), mode, read_session(Path(path)), pose)

    def frontend_for(self, sensor: _Sensor, kind: str, log: LogReader, topic: str, config: Any,
                     options: FrontendOptions) -> Any:
        """The session's frontend on the log; `PipelineError` when the session's sensor is not the log's."""
        saved_kind = session_sensor_kind(self.path, self.content)
        if saved_kind != kind:
            raise PipelineError(f"{self.path} is a map of {SENSOR_WORDS[saved_kind]} and {log.path} has "
                                f"{SENSOR_WORDS[kind]} ({topic}): a session continues or localizes logs of "
                                "its own kind")
        saved = sensor.saved_map(self.path, self.content)
        saved_base = self.content.header.get("base_frame")
        if options.base_frame is None and isinstance(saved_base, str) and saved_base:
            # The saved poses are of that frame: a log tf does not tie to it is refused (one line naming the
            # frames), not placed with its sensor's poses beside the saved map's base poses.
            options = dataclasses.replace(options, base_frame=saved_base, base_frame_origin=(
                f"the frame {self.path.name}'s poses are of; --base-frame names another"))
        try:
            if self.mode == "continue":
                return sensor.continuing(log, topic, saved, config, options)
            return sensor.localizing(log, topic, saved, config, options, initial_pose=self.initial_pose)
        except MapExtentError as error:
            # The localizer matches against one grid of the whole saved map, on cells up to 20 cm where the
            # map is large (`localization.whole_map_resolution`): 1.6 km² at most.
            verb = "continue" if self.mode == "continue" else "localize in"
            raise MapExtentError(f"{self.path}: this saved map is too large to {verb}: {error} (maps beyond "
                                 "that are not supported yet)") from error
        except EmptySavedMapError as error:
            raise SessionError(f"{self.path}: {error}") from error


def _three_finite_numbers(values: object) -> tuple[float, float, float]:
    """(x, y, yaw) of a sequence of three finite numbers (a string is not one: "123" would read as 1, 2,
    3); `PipelineError` otherwise."""
    with contextlib.suppress(TypeError, ValueError):  # not a sequence, or not of numbers
        if not isinstance(values, str | bytes) and len(values) == 3:  # type: ignore[arg-type]
            x, y, yaw = (float(value) for value in values)  # type: ignore[attr-defined]
            if np.all(np.isfinite((x, y, yaw))):
                return x, y, yaw
    raise PipelineError(f"the initial pose must be three finite numbers x, y, yaw; got {values!r}")


@dataclass(frozen=True)
class _Sensor:
    """What a sensor kind chooses: its frontend, its recording, its map files."""

    frontend: Callable[[LogReader, str, Any, FrontendOptions], LogFrontend]
    recording: type[ScanReplayRecording] | type[CloudReplayRecording]
    """A `FrontendRecording` of the frontend (`recording(stream, frontend)`); its `with_map`: whether the
    recording's layout has the 2D map view."""
    map_files: tuple[_MapFile, ...]
    saved_map: Callable[[Path, SessionContent], Any]
    """The saved map of a session (`SessionError` when it is damaged), which the two frontends below
    start from: continuing it (a `LogFrontend`) or localizing in it (a `LocalizingFrontend`)."""
    continuing: Callable[..., ContinuingFrontend]
    localizing: Callable[..., LocalizingFrontend]
    localization_recording: type[MapLocalizationRecording] | type[CloudLocalizationRecording]
    """The recording of a localization in a saved map (`recording(stream, frontend)`)."""
    kitti_poses: bool = False
    """Also write the trajectory as KITTI poses (`<stem>.kitti`: 3×4 matrices, one line per measurement)."""
    held_map: bool = False
    """Its localization solves the run's own keyframe graph with the saved map held (`held_map_solver`):
    that optimization is recorded."""


@functools.cache
def _scan_sensor() -> _Sensor:
    # Each frontend is imported by the first log of its sensor kind: a replay of clouds never loads the laser
    # frontend's compiled kernels (0.3 s of start-up), nor a laser replay the 3D one.
    from frontends.slam2d import LaserFrontend
    from frontends.slam2d.session_frontends import ContinuingLaserFrontend, LocalizingLaserFrontend
    from pipeline.recording.scans import MapLocalizationRecording, ScanReplayRecording

    return _Sensor(LaserFrontend, ScanReplayRecording, (
        _MapFile("map_png", "_map.png", lambda path, grid: write_png(path, picture_with_scale_bar(grid))),
        _MapFile("map_pgm", "_map.pgm", lambda path, grid: write_bytes(path, map_server_pgm(grid))),
        # The YAML names the PGM beside it, which only its suffix tells apart.
        _MapFile("map_yaml", "_map.yaml",
                 lambda path, grid: write_text(path, map_server_yaml(grid, path.with_suffix(".pgm").name))),
    ), saved_map_2d, ContinuingLaserFrontend, LocalizingLaserFrontend, MapLocalizationRecording,
        held_map=True)


@functools.cache
def _cloud_sensor() -> _Sensor:
    from frontends.slam3d import LidarFrontend
    from frontends.slam3d.session_frontends import ContinuingLidarFrontend, LocalizingLidarFrontend
    from pipeline.recording.clouds import CloudLocalizationRecording, CloudReplayRecording

    return _Sensor(LidarFrontend, CloudReplayRecording, (_MapFile("ply", ".ply", write_ply),
                                                         _MapFile("pcd", ".pcd", write_map_pcd)),
                   saved_map_3d, ContinuingLidarFrontend, LocalizingLidarFrontend, CloudLocalizationRecording,
                   kitti_poses=True)


_SENSORS: dict[str, Callable[[], _Sensor]] = {"scan": _scan_sensor, "cloud": _cloud_sensor}
"""Sensor kind → its `_Sensor`."""


@dataclass(frozen=True)
class ReplayOutputs:
    tum: Path
    json: Path
    rrd: Path
    g2o: Path | None = None
    """The keyframe graph (not written by a localization in a saved map)."""
    map_png: Path | None = None
    """The occupancy grid (scans), north up, with a scale bar."""
    map_pgm: Path | None = None
    """The occupancy grid for ROS map_server (scans), with `map_yaml`."""
    map_yaml: Path | None = None
    ply: Path | None = None
    """The point map (clouds)."""
    pcd: Path | None = None
    """The same point map as a binary PCD (clouds)."""
    kitti: Path | None = None
    """The trajectory as KITTI poses (clouds)."""
    session: Path | None = None
    """Everything needed to localize in the map or continue it (`pipeline.session_file`)."""

    @classmethod
    def for_input(cls, out_dir: Path, input_path: Path, sensor: str = "scan",
                  mode: ReplayMode = "slam") -> ReplayOutputs:
        """The outputs of a replay of `input_path`; localization in a saved map ("map") writes only the
        trajectory, the summary and the recording."""
        stem = output_stem(input_path)
        chosen = _SENSORS[sensor]()
        kinds = ["tum", "json", "rrd"] + ["kitti"] * chosen.kitti_poses + ["g2o", "session"] * (mode != "map")
        map_files = () if mode == "map" else chosen.map_files
        return cls(**{kind: out_dir / f"{stem}.{kind}" for kind in kinds},
                   **{map_file.output: out_dir / f"{stem}{map_file.suffix}" for map_file in map_files})

    def paths(self) -> dict[str, Path]:
        """Kind → path of every output written ("tum", "g2o", "json", "rrd" and the map's)."""
        return {kind: path for kind, path in dataclasses.asdict(self).items() if path is not None}


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
    """(K, 3) optimized planar keyframe poses (localizing in a saved map: the map's, unchanged)."""
    chi2_per_iteration: tuple[tuple[str, int, float], ...]
    optimization: OptimizationResult | None
    """How the keyframe optimization ended (converged, why, every start and the winner); None when
    localizing in a saved map (its keyframes are not optimized; the held map's solve is in `counts`)."""
    wall_time: dict[str, float]
    outputs: ReplayOutputs
    counts: dict[str, int]
    loop_closures: dict[str, Any]
    warnings: list[dict[str, Any]]
    """[{"message", "count"}]: what was skipped or lost on the way, each distinct message once."""
    settings: dict[str, Any]
    mode: ReplayMode = "slam"
    session: Path | None = None
    """The session the replay started from (continue, map)."""

    @property
    def planar_poses(self) -> FloatArray:
        """(S, 3) every measurement's pose in the plane."""
        if self.poses.ndim == 2:
            return self.poses
        from frontends.slam3d import planar  # clouds only: see `_cloud_sensor`

        return planar.planar(self.poses)


def _warn_if_stamps_go_back(path: Path, kind: str, stamps: NDArray[np.int64], saved: int,
                            tum_name: str) -> None:
    """A continued session's trajectory is the saved run's `saved` measurements, then the log's: warn when
    the log's first stamp is not after the saved run's last (the same log again, or clocks that restart at
    0, as a simulator's do), since the TUM file's stamps then go back where the runs join."""
    if 0 < saved < len(stamps) and stamps[saved] <= stamps[saved - 1]:
        what = "scans" if kind == "scan" else "clouds"
        warnings.warn(f"{path}: its {what} (from {stamps[saved] / 1e9:.3f} s) do not come after the "
                      f"session's (to {stamps[saved - 1] / 1e9:.3f} s): {tum_name} holds the session's "
                      "first, then this log's, and its stamps go back where the two join (tools that want "
                      "rising stamps, such as evo, read the two parts apart)", LogWarning, stacklevel=2)


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
    session: SessionStart | None = None,
) -> LogReplayResult:
    """Run the SLAM of the log's sensor (`topic`, found by type unless given) on the log at `path` and
    write its outputs to `out_dir`. `slam2d` / `slam3d` configure the frontend of scans / clouds.
    `session`: continue a saved session's map, or localize in it (see the module docstring)."""
    path = Path(path)
    if method not in METHODS:
        raise PipelineError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    run = _Run(path, method, iterations, robust, on_measurement, on_iteration, session)
    options = FrontendOptions(base_frame=base_frame, odometry_topic=odometry_topic)
    tally = WarningTally(path)
    try:
        with tallied_warnings(tally), open_log(path) as log:
            return run.replay(log, Path(out_dir), topic, options, {"scan": slam2d, "cloud": slam3d}, tally)
    except Exception as error:
        # What went wrong before may be the cause (a truncated log has no topics left): said with it.
        for item in tally.as_json():
            error.add_note(f"{WHILE_READING}{item['message']}")
        raise
    finally:
        reissue(path, tally.as_json())


class _WrittenBeside(ThreadPoolExecutor):
    """A thread of its own for the map while the replay goes on: the map is made there from the final
    poses on, while the replay sends the recorded iterations (`make_map`), and its files are written there
    from the moment it is made, while the replay records it, closes the recording and writes the other
    files. Encoding the map's PNG (zlib, which releases the GIL) is most of their time: 0.13 s of the UAL
    log's 0.2 s, as long as all the rest after the map. Leaving the `with` waits for the thread (the files
    not started yet are dropped: the run failed)."""

    def __init__(self) -> None:
        super().__init__(max_workers=1, thread_name_prefix="map-files")
        self.made_map: Future[Any] | None = None
        """The map `make_map` started, of the final keyframe poses."""

    def __exit__(self, *exc_info: object) -> None:
        self.shutdown(wait=True, cancel_futures=True)

    def make_map(self, map_export: Callable[[FloatArray], Any], keyframe_poses: FloatArray) -> None:
        """Start making the map of the final `keyframe_poses` (`map_export`), while the main thread sends
        the recorded iterations: the 2D occupancy grid's rays are traced without the GIL (0.14 s on UAL)."""
        self.made_map = self.submit(map_export, keyframe_poses)


@dataclass(frozen=True)
class _Run:
    path: Path
    method: str
    iterations: int | None
    robust: str | None
    on_measurement: EstimateCallback | None
    on_iteration: IterationCallback | None
    session: SessionStart | None = None

    @property
    def mode(self) -> ReplayMode:
        return "slam" if self.session is None else self.session.mode

    def replay(self, log: LogReader, out_dir: Path, topic: str | None, options: FrontendOptions,
               configs: dict[str, Any], tally: WarningTally) -> LogReplayResult:
        """Stream the measurements through the frontend and the recording, optimize its keyframe graph
        (localizing in a saved map: the map's keyframe poses stand), make the map (`beside`, from the final
        poses on) and record all of it, then write the outputs, timing each stage (`timings`)."""
        started = time.perf_counter()
        topic, kind = log.sensor_topic(topic)
        sensor = _SENSORS[kind]()
        localizing = self.mode == "map"
        outputs = ReplayOutputs.for_input(out_dir, self.path, kind, self.mode)
        paths = outputs.paths()
        inputs = (self.path,) if self.session is None else (self.path, self.session.path)
        with (staged_outputs_in(out_dir, *paths.values(), inputs=inputs) as staged_paths,
              _WrittenBeside() as beside):
            staged = dict(zip(paths, staged_paths, strict=True))
            if self.session is None:
                frontend = sensor.frontend(log, topic, configs[kind], options)
            else:
                frontend = self.session.frontend_for(sensor, kind, log, topic, configs[kind], options)
            timings = {"read_odometry_tf": time.perf_counter() - started}
            stream = recording.create_recording(staged["rrd"], name=self.path.name,
                                                with_map=sensor.recording.with_map)
            try:
                if localizing and sensor.held_map:
                    cast("LocalizingLaserFrontend", frontend).held_map_solver = held_map_solver(
                        stream, self.on_iteration)
                recorder = (sensor.localization_recording if localizing else sensor.recording)(
                    stream, frontend)  # type: ignore[arg-type]
                count = self.stream(frontend, recorder, timings)
                trace: tuple[tuple[str, int, float], ...]
                localizer = cast(LocalizingFrontend, frontend)  # when localizing
                if localizing:
                    assert self.session is not None
                    keyframe_poses, trace, optimization = localizer.saved.keyframe_poses, (), None
                    recording.log_run_properties(stream, {
                        "input": str(self.path), "topic": topic, "mode": "map",
                        "session": str(self.session.path), "measurements": count,
                        "map_keyframes": len(keyframe_poses)})
                else:
                    optimized = self.optimize(frontend, topic, count, recorder, stream, timings,
                                              functools.partial(beside.make_map, frontend.map_export))
                    keyframe_poses, trace, optimization = optimized.poses, optimized.trace, optimized.result
                map_started = time.perf_counter()
                map_export = (frontend.map_export(keyframe_poses) if beside.made_map is None
                              else beside.made_map.result())
                # Localizing in a saved map writes no map files (`ReplayOutputs.for_input`).
                written = [beside.submit(map_file.write, staged[map_file.output], map_export)
                           for map_file in sensor.map_files if map_file.output in staged]
                poses = localizer.localized_poses() if localizing else frontend.estimates(keyframe_poses)
                timings["map"] = time.perf_counter() - map_started
                record_started = time.perf_counter()
                recorder.final(keyframe_poses, poses, map_export)
                timings["record_maps"] = time.perf_counter() - record_started
            finally:
                close_started = time.perf_counter()
                recording.close_recording(stream)
                timings["record_close"] = time.perf_counter() - close_started
            counts = frontend.counts()
            if self.mode == "continue":
                _warn_if_stamps_go_back(self.path, kind, frontend.stamps_ns, counts["session_scans"],
                                        outputs.tum.name)
            write_started = time.perf_counter()
            write_tum(staged["tum"], frontend.stamps_ns, poses)
            if outputs.kitti is not None:
                write_kitti_poses(staged["kitti"], poses)
            if not localizing:
                self.write_graph_and_session(frontend, log, kind, topic, keyframe_poses, staged)
            for map_file_written in written:
                map_file_written.result()  # raises what writing it raised
            timings["write"] = time.perf_counter() - write_started
            timings["total"] = time.perf_counter() - started
            replayed = LogReplayResult(
                input_path=self.path, sensor=kind, topic=topic, odometry_topic=frontend.odometry_topic,
                sensor_frame=frontend.sensor_frame, base_frame=frontend.base_frame, frontend=frontend,
                measurements=count, stamps_ns=frontend.stamps_ns, poses=poses,
                keyframe_poses=keyframe_poses, chi2_per_iteration=trace,
                optimization=optimization, wall_time=timings, outputs=outputs,
                counts=counts, loop_closures=frontend.loop_closures(), warnings=tally.as_json(),
                settings=frontend.settings(), mode=self.mode,
                session=None if self.session is None else self.session.path,
            )
            text = localization_summary_text(replayed) if localizing else json_text(summary(replayed))
            write_text(staged["json"], text)
        return replayed

    def write_graph_and_session(self, frontend: LogFrontend, log: LogReader, kind: str, topic: str,
                                keyframe_poses: FloatArray, staged: dict[str, Path]) -> None:
        """The keyframe graph and the session of a mapping replay (plain or continued); its map files are
        written beside."""
        write_g2o(staged["g2o"], frontend.keyframe_graph(), keyframe_poses)
        arrays, keyframe_points = frontend.session_content(keyframe_poses)
        header = {
            "sensor_kind": kind, "topic": topic, "sensor_frame": frontend.sensor_frame,
            "base_frame": frontend.base_frame, "settings": frontend.settings(),
            "source": source_description(log.info().files),
        }
        if self.session is not None:  # the map holds the earlier sessions' logs too
            earlier = self.session.content.header
            header["continued_from"] = {"path": str(self.session.path.resolve()),
                                        "source": earlier.get("source"),
                                        "continued_from": earlier.get("continued_from")}
        write_session_file(staged["session"], header, arrays, keyframe_points)

    def stream(self, frontend: StreamedFrontend, recorder: FrontendRecording,
               timings: dict[str, float]) -> int:
        """Stream the measurements through the frontend and the recording; how many there were."""
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
        return count

    def optimize(self, frontend: LogFrontend, topic: str, count: int, recorder: FrontendRecording,
                 stream: Any, timings: dict[str, float],
                 on_final: Callable[[FloatArray], None]) -> KeyframeOptimization:
        """Optimize the frontend's keyframe graph from its starts, recording every iteration; `on_final`
        gets the final poses before the recording is flushed."""
        optimize_started = time.perf_counter()
        graph = frontend.keyframe_graph()
        session = {} if self.session is None else {"mode": self.mode, "session": str(self.session.path)}
        recording.log_run_properties(stream, {"input": str(self.path), "topic": topic, "method": self.method,
                                              "measurements": count, "keyframes": graph.num_poses, **session})
        optimized = optimize_keyframes(
            stream, frontend.keyframe_graph(frontend.odometry_chain), graph, self.method, self.iterations,
            self.on_iteration, recorder.iteration_sink(), robust=self.robust,
            keyframe_scans=recorder.keyframe_scans(), wheel_odometry=wheel_odometry_start(
                frontend.keyframe_wheel_odometry(), frontend.odometry_chain[0]), on_final=on_final)
        timings["record_iterations"] = optimized.record_seconds
        timings["optimize_and_record"] = time.perf_counter() - optimize_started
        return optimized


def summary(result: LogReplayResult) -> dict[str, Any]:
    """The JSON summary of a mapping replay (plain or continued)."""
    if result.optimization is None:
        return localization_summary(result)
    continued = {}
    if result.session is not None and result.mode == "continue":
        continued = {"session": {"continued_from": str(result.session),
                                 "placement": cast(ContinuingFrontend, result.frontend).placement()}}
    return {
        "schema": SUMMARY_SCHEMA,
        "mode": result.mode,
        **continued,
        **_source_fields(result),
        "counts": result.counts,
        "loop_closures": result.loop_closures,
        **optimization_summary(result.optimization),
        "chi2_per_iteration": [{"stage": s, "index": i, "chi2": c} for s, i, c in result.chi2_per_iteration],
        **_run_fields(result),
    }


def _source_fields(result: LogReplayResult) -> dict[str, Any]:
    """What was read: the summary's fields naming the input, its topics and frames."""
    return {"input": str(result.input_path), "sensor": result.sensor, "topic": result.topic,
            "odometry_topic": result.odometry_topic, "sensor_frame": result.sensor_frame,
            "base_frame": result.base_frame}


def _run_fields(result: LogReplayResult) -> dict[str, Any]:
    """How the run went: the summary's closing fields (times, warnings, settings, outputs)."""
    return {"wall_time_s": result.wall_time, "warnings": result.warnings, "config": result.settings,
            "outputs": {kind: str(path) for kind, path in result.outputs.paths().items()}}


MAX_PER_SCAN_ROWS = 20_000
"""A localization summary lists at most this many scans one by one (every k-th of a longer log)."""
SCAN_STATES = {"matched": "m", "tracked": "t", "predicted": "p", "between": "b", "recovered": "r",
               "never": "-"}
"""One character per scan in a localization summary's `per_scan.state`."""


def localization_summary(result: LogReplayResult) -> dict[str, Any]:
    """The JSON summary of a localization in a saved map, without its per-scan table (`per_scan`, see
    `localization_summary_text`)."""
    assert result.mode == "map"
    frontend = cast(LocalizingFrontend, result.frontend)
    found = frontend.localizations
    stamps = found.stamps_ns
    fixes = [{"scan": int(k), "stamp_ns": int(stamps[k]), "score": float(found.score[k])}
             for k in found.global_fixes]
    first_fix = (stamps[found.global_fixes[0]] - stamps[0]) * 1e-9 if len(fixes) else None
    return {
        "schema": SUMMARY_SCHEMA,
        "mode": "map",
        "session": str(result.session),
        **_source_fields(result),
        "initial_pose": None if frontend.initial_pose is None else list(frontend.initial_pose),
        "counts": result.counts,
        "localization": {
            "scans": len(stamps),
            "with_pose": int(found.has_pose.sum()),
            "localized_when_processed": int(found.localized.sum()),
            "matched": int(found.matched.sum()),
            "tracked_outside_map": int(found.tracked_outside.sum()),
            "between_localized_scans": int(found.posed_between.sum()),
            "recovered_by_a_global_fix": int(found.recovered.sum()),
            "never_localized": int((~found.has_pose).sum()),
            "never_localized_note": "scans never placed in the map have no pose and are not in the TUM file",
            "first_fix_after_s": first_fix,
            "global_fixes": fixes,
            "score": _percentiles(found.score[found.matched]),
            "inlier_fraction": _percentiles(found.inlier_fraction[found.matched]),
            "rms_m": _percentiles(found.rms[found.matched]),
        },
        **_run_fields(result),
    }


def localization_summary_text(result: LogReplayResult) -> str:
    """`localization_summary` as JSON text, with `per_scan`: one row of compact arrays per quantity
    (the scan's stamp, state — m matched, t tracked outside the saved map on the rolling local map of the
    recent scans, p predicted by odometry (the wheels', else the scans' own) without a match, b a fast
    laser's scan posed between two localized ones, r pose recovered by a later global fix, - never
    localized — score, inlier fraction, ICP rms), each on one line."""
    assert result.mode == "map"
    found = cast(LocalizingFrontend, result.frontend).localizations
    stride = -(-len(found.stamps_ns) // MAX_PER_SCAN_ROWS)
    rows = np.arange(0, len(found.stamps_ns), stride)
    state = np.full(len(found.stamps_ns), SCAN_STATES["never"])
    state[found.recovered] = SCAN_STATES["recovered"]
    state[found.localized] = SCAN_STATES["predicted"]
    state[found.tracked_outside] = SCAN_STATES["tracked"]
    state[found.posed_between] = SCAN_STATES["between"]
    state[found.matched] = SCAN_STATES["matched"]
    per_scan = {
        "stride": int(stride),
        "stamp_ns": found.stamps_ns[rows].tolist(),
        "state": "".join(state[rows]),
        "score": _rounded(found.score[rows], 3),
        "inlier_fraction": _rounded(found.inlier_fraction[rows], 3),
        "rms_m": _rounded(found.rms[rows], 4),
    }
    lines = ",\n".join(f'    "{name}": {json.dumps(values, separators=(",", ":"))}'
                        for name, values in per_scan.items())
    text = json_text(localization_summary(result))
    assert text.endswith("\n}\n")
    return text[:-3] + ',\n  "per_scan": {\n' + lines + "\n  }\n}\n"


def _rounded(values: FloatArray, digits: int) -> list[float | None]:
    return [round(value, digits) if np.isfinite(value) else None for value in values.tolist()]


def _percentiles(values: FloatArray) -> dict[str, float | None]:
    finite = values[np.isfinite(values)]
    quantiles = np.percentile(finite, [5, 50, 95]).tolist() if len(finite) else [None, None, None]
    return dict(zip(("p5", "median", "p95"), quantiles, strict=True))
