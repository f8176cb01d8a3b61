"""The Python API of `replay`: one call that does what the command does, for scripts.

    from pipeline import replay
    result = replay("run.mcap", ReplayConfig(optimizer={"method": "sgd"}), out_dir="results")
    result.poses, result.graph, result.stats.chi2_final, result.outputs["rrd"]

    # sessions (laser or cloud logs): localize in a saved map, or continue mapping it
    replay("second.mcap", map="recordings/first.session")            # second.{tum,json,rrd}
    replay("second.mcap", map="recordings/first.session", initial_pose=(3.5, -1.2, 1.57))
    replay("second.mcap", continue_from="recordings/first.session")  # both runs, a new second.session

`replay` picks the replay from the input (a pose-graph file or a log, `input_kind`) the way the command
does, and raises `OptimizerError`, `FrontendError` or `PipelineError` (`KNOWN_ERRORS`) on bad input;
it never prints or exits. The heavy modules (rerun, numba) are imported on the first call only.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError
from optimizer.errors import OptimizerError
from pipeline.config import ReplayConfig, config_from_mapping, load_config
from pipeline.errors import PipelineError

if TYPE_CHECKING:
    from frontends.protocol import Estimate
    from optimizer.graph import PoseGraph
    from optimizer.iteration import Iteration
    from pipeline.replay_graph import GraphReplayResult
    from pipeline.replay_log import LogReplayResult, SessionStart

KNOWN_ERRORS: tuple[type[Exception], ...] = (OptimizerError, FrontendError, PipelineError)
"""What a replay raises on purpose (bad input, unwritable outputs); anything else is a bug."""
_KNOWN_OR_SYSTEM_ERRORS: tuple[type[Exception], ...] = (*KNOWN_ERRORS, OSError)

DEFAULT_OUT_DIR = Path("recordings")

GRAPH_SUFFIXES = frozenset({".g2o", ".graph"})
_LOG_SUFFIXES = frozenset({".mcap", ".bag", ".db3", ".yaml"})

InputKind = Literal["log", "graph"]


def input_kind(path: str | Path) -> InputKind:
    """"graph" for a pose-graph file (by its suffix, or a text file whose first data line starts with a graph
    tag), "log" for anything else (a log, or a folder holding a ROS 2 bag)."""
    path = Path(path)
    if path.suffix.lower() in GRAPH_SUFFIXES:
        return "graph"
    if not path.is_file() or path.suffix.lower() in _LOG_SUFFIXES:
        return "log"
    try:
        with path.open("rb") as file:
            head = file.read(4096).decode("utf-8", errors="replace")
    except OSError:
        return "log"
    from optimizer.graph_files import is_graph_tag  # with pyarrow: not for every start of the command

    lines = (fields for fields in map(str.split, head.splitlines())
             if fields and not fields[0].startswith("#"))
    return "graph" if is_graph_tag(next(lines, [""])[0]) else "log"


@dataclass(frozen=True)
class ReplayStats:
    """The numbers of a replay (all of them, and more, are in `ReplayResult.summary`)."""

    poses: int
    """Poses of the optimized graph (a log's keyframes)."""
    constraints: int
    loop_closures: int
    """Loop-closure constraints in the graph (a log's accepted loop closures)."""
    loop_closures_rejected: int | None
    """Loop closures the frontend rejected (None for a pose-graph file)."""
    scans: int | None
    """Scans read from a log (None for a pose-graph file)."""
    iterations: Mapping[str, int]
    """Iterations per optimizer stage, in the order they ran."""
    chi2_initial: float
    chi2_final: float
    """χ² of the final poses (the recorded last iteration)."""
    wall_time_s: Mapping[str, float]
    """Seconds per pipeline stage, and "total"."""
    converged: bool = False
    """Whether the optimizer's convergence test held (methods without a polish never converge)."""
    stop_reason: str = ""
    """Why the optimizer stopped, in a few words."""


@dataclass(frozen=True, eq=False)
class ReplayResult:
    """What `replay` did and wrote."""

    input_path: Path
    kind: InputKind
    graph: PoseGraph
    """The pose graph with its optimized poses (for a log: the frontend's keyframe graph; localizing in a
    saved map: that map's graph, unchanged)."""
    poses: NDArray[np.float64]
    """(N, 3) final poses (x, y, θ): one per scan for a log (at `stamps_ns`; continuing a session: every
    scan of it, old ones first; localizing in a saved map: every scan placed in it), one per graph pose
    otherwise."""
    stamps_ns: NDArray[np.int64] | None
    """Sensor stamp of each scan of a log; None for a pose-graph file."""
    stats: ReplayStats
    outputs: Mapping[str, Path]
    """The files written, by kind: "g2o", "json", "rrd", and for a log also "tum" and "map_png" (scans)
    or "ply" (clouds)."""
    summary: Mapping[str, Any]
    """The machine-readable summary, as written to `<stem>.json`."""
    detail: LogReplayResult | GraphReplayResult
    """The replay's own result, with everything else it knows."""


_GRAPH_STATS = ("poses", "constraints", "loop_closures", "iterations", "chi2_initial", "chi2_final",
                "wall_time_s", "converged", "stop_reason")
"""The `ReplayStats` that a pose-graph file's summary holds under the same names."""

ScanCallback = Callable[["Estimate"], None]
IterationCallback = Callable[["Iteration"], None]


def replay(
    path: str | Path,
    config: ReplayConfig | Mapping[str, Any] | str | Path | None = None,
    *,
    out_dir: str | Path = DEFAULT_OUT_DIR,
    on_scan: ScanCallback | None = None,
    on_iteration: IterationCallback | None = None,
    map: str | Path | None = None,
    continue_from: str | Path | None = None,
    initial_pose: Sequence[float] | None = None,
) -> ReplayResult:
    """Replay a log (2D laser or 3D LiDAR SLAM, then the optimizer) or optimize a pose-graph file,
    recording every iteration, and write `<stem>.{g2o,json,rrd}` to `out_dir` (for a log also `.tum` and
    the map, `_map.png` or `.ply`).

    `config` is a `ReplayConfig`, a mapping of sections as the TOML file holds them (`{"optimizer":
    {"method": "sgd"}}`), the path of a TOML configuration file, or None for the defaults.
    `on_scan` is called with every scan's or cloud's estimate (`frontends.protocol.Estimate`) as the
    frontend processes it (logs only); `on_iteration` with every optimizer `Iteration`, the initial
    estimate first. A log's warnings are raised as `LogWarning`s once the replay is done.

    Sessions (a `<stem>.session` a log replay wrote; laser or cloud logs): `map` localizes the log in the
    session's map without changing it (`initial_pose` (x, y, yaw) where the log starts in it, else found
    by global localization) and writes `<stem>.{tum,json,rrd}`: the scans placed in the map, in its frame,
    and per-scan match quality; `continue_from` continues mapping it with the log: one joint optimization,
    every output of a log replay for both runs (the TUM holds every scan of the session, old ones first)
    and a new session. Raises `SessionError` (a `PipelineError`) for a damaged or newer session file,
    `MapPlacementError` (a `FrontendError`) when the log never matches the saved map.
    """
    path = Path(path)
    if config is None or isinstance(config, Mapping):
        config = config_from_mapping(config or {})
    elif not isinstance(config, ReplayConfig):
        config = load_config(config)
    if map is not None and continue_from is not None:
        raise PipelineError("localize in a saved map (map) or continue mapping it (continue_from), not both")
    if initial_pose is not None and map is None:
        raise PipelineError("an initial pose applies to localization in a saved map (map) only")
    session = map if map is not None else continue_from
    if input_kind(path) == "graph":
        if session is not None:
            raise PipelineError(f"{path} is a pose graph: a session localizes or continues with logs only")
        return _replay_graph_file(path, config, Path(out_dir), on_iteration)
    start = None
    if session is not None:
        from pipeline.replay_log import SessionStart

        start = SessionStart.load(session, "map" if map is not None else "continue", initial_pose)
    return _replay_log_file(path, config, Path(out_dir), on_scan, on_iteration, start)


def _replay_graph_file(path: Path, config: ReplayConfig, out_dir: Path,
                       on_iteration: IterationCallback | None) -> ReplayResult:
    from pipeline import replay_graph as module

    detail = module.replay_graph(path, out_dir=out_dir, method=config.optimizer.method,
                                 robust=config.optimizer.robust_kernel,
                                 iterations=config.optimizer.iterations,
                                 repair_information=config.input.repair_information, progress=on_iteration)
    summary = module.summary(detail)
    stats = ReplayStats(**{key: summary[key] for key in _GRAPH_STATS}, loop_closures_rejected=None,
                        scans=None)
    return ReplayResult(path, "graph", detail.graph.with_poses(detail.poses), detail.poses, None, stats,
                        detail.outputs.paths(), summary, detail)


def _replay_log_file(path: Path, config: ReplayConfig, out_dir: Path, on_scan: ScanCallback | None,
                     on_iteration: IterationCallback | None,
                     session: SessionStart | None = None) -> ReplayResult:
    from optimizer.cost import chi2
    from pipeline import replay_log as module
    from pipeline.replay_graph import iterations_per_stage

    detail = module.replay_log(path, out_dir=out_dir, topic=config.input.scan_topic,
                               odometry_topic=config.input.odom_topic, base_frame=config.input.base_frame,
                               method=config.optimizer.method, robust=config.optimizer.robust_kernel,
                               iterations=config.optimizer.iterations, slam2d=config.to_slam2d(),
                               slam3d=config.to_slam3d(), on_measurement=on_scan, on_iteration=on_iteration,
                               session=session)
    graph = detail.frontend.keyframe_graph(detail.keyframe_poses)
    optimization = detail.optimization  # None: localized in a saved map, its graph unchanged
    chi2_final = float(chi2(graph))
    stats = ReplayStats(
        poses=graph.num_poses,
        constraints=graph.num_edges,
        loop_closures=(int((~graph.is_odometry).sum()) if optimization is None
                       else detail.loop_closures["accepted"]),
        loop_closures_rejected=0 if optimization is None else detail.loop_closures["rejected"],
        scans=detail.measurements,
        iterations=iterations_per_stage(stage for stage, _, _ in detail.chi2_per_iteration),
        chi2_initial=chi2_final if optimization is None else detail.chi2_per_iteration[0][2],
        chi2_final=chi2_final,
        wall_time_s=dict(detail.wall_time),
        converged=True if optimization is None else optimization.converged,
        stop_reason=("localization in a saved map: nothing optimized" if optimization is None
                     else optimization.reason),
    )
    return ReplayResult(path, "log", graph, detail.planar_poses, detail.stamps_ns, stats,
                        detail.outputs.paths(), module.summary(detail), detail)


def expected_scans(path: str | Path, scan_topic: str | None = None) -> int | None:
    """How many scans a replay of the log at `path` will read, from the log's summary (for a progress
    bar); None when that cannot be told (the replay itself then reports why)."""
    from frontends.logs import open_log

    try:
        with open_log(path) as log:
            topic, _ = log.sensor_topic(scan_topic)
            return sum(info.count for info in log.info().topics if info.name == topic) or None
    except _KNOWN_OR_SYSTEM_ERRORS:
        return None
