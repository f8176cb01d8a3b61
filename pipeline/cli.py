"""The `replay` command line.

`replay [INPUT ...] [options]` runs the default command on logs (MCAP, ROS 1 bag, ROS 2 bag directory) of
2D laser scans or 3D point clouds, or on 2D pose graphs (g2o, TORO), told apart by the path and its
content; a first argument naming a subcommand (`info`, `evaluate`) runs that one instead. Several inputs
run `--jobs` at a time in worker processes; one failing does not stop the others; `--ray` runs them as
tasks on a Ray cluster instead, and `--inputs` reads them from a list or a folder. A batch also writes its
result table, `batch_summary.parquet`.

Errors the program raises on purpose (`OptimizerError`, `FrontendError`, `PipelineError`) end in one line
on stderr, `replay: error: <message>`, and exit code 2; anything else is a bug and keeps its traceback.
Warnings (data skipped or lost while reading) are one line each, `replay: warning: <input>: <message>`,
a repeated one counted, none with --quiet; Python's own warning output is switched off.
"""

from __future__ import annotations

import contextlib
import enum
import json
import math
import os
import re
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer
from typer.core import TyperCommand, TyperGroup

from optimizer.robust import KERNELS
from optimizer.solve import DEFAULT_ITERATIONS, MAX_ITERATIONS, METHODS
from optimizer.warmup import warming_up
from pipeline.api import DEFAULT_OUT_DIR, KNOWN_ERRORS, expected_scans, input_kind
from pipeline.batch import BatchOutcome, RayOptions, refuse_clashing_outputs
from pipeline.batch_inputs import batch_inputs
from pipeline.batch_summary import BATCH_SUMMARY_NAME, write_batch_summary
from pipeline.bundled import SAMPLE_DESCRIPTION, sample_log
from pipeline.config import ReplayConfig, config_from_mapping, load_config
from pipeline.errors import PipelineError
from pipeline.evaluation import DEFAULT_TOLERANCE_NS, evaluate_files
from pipeline.launcher import arrow_without_pandas
from pipeline.outputs import install_stop_signals, json_text, raised_by_interrupt
from pipeline.session_file import SENSOR_WORDS, describe_session, is_session_file
from pipeline.warning_tally import WarningTally, tallied_warnings, warning_lines

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

    from frontends.protocol import Estimate
    from optimizer.iteration import Iteration

PROGRAM = "replay"
DEFAULT_COMMAND = "run"
EXIT_ERROR = 2
"""Exit code of a run that failed on bad input or unwritable outputs (the same as usage errors), and of a
batch in which any input failed."""
MAX_JOBS = 256
"""Worker processes at most (each holds a whole replay in memory)."""
EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (128 + SIGINT); after SIGTERM it is 143."""
EXIT_UNCONVERGED = 3
"""Exit code of a run whose optimization did not reach its convergence test (outputs are written and say
`"converged": false`), unless --allow-unconverged."""

_IMPLICIT_DEFAULT = "pipeline.cli.implicit_default"

Method = enum.StrEnum("Method", [(name, name) for name in METHODS])  # type: ignore[misc]
"""The optimizer's methods as a choice (the names come from `optimizer.solve.METHODS`)."""
Robust = enum.StrEnum("Robust", [(name, name) for name in KERNELS])  # type: ignore[misc]


class ReplayGroup(TyperGroup):
    """Runs the default command unless the first argument names a subcommand.

    This keeps `replay`, `replay GRAPH` and `replay --help` working the way a single command would, while
    leaving room for subcommands (`replay info`, …): a group's own positional argument would swallow them.
    """

    def parse_args(self, ctx: typer.Context, args: list[str]) -> list[str]:  # type: ignore[override]
        # (typer passes its own `Context`, a subclass of the vendored click one the base class names)
        if not args or args[0] not in self.commands:
            ctx.meta[_IMPLICIT_DEFAULT] = True
            args = [DEFAULT_COMMAND, *args]
        if args[0] == DEFAULT_COMMAND:
            args = _with_ray_address(args)
        return super().parse_args(ctx, args)

    def invoke(self, ctx: typer.Context) -> Any:  # type: ignore[override]
        # Every command's own errors (bad input, unwritable outputs) end it in one line, not a traceback.
        try:
            return super().invoke(ctx)
        except KNOWN_ERRORS as error:
            message = " ".join(str(error).split())  # always one line
            typer.echo(f"{PROGRAM}: error: {message}", err=True)
            raise typer.Exit(EXIT_ERROR) from error


_RAY_OPTION = "--ray"
_RAY_ADDRESS = re.compile(r"auto|local|(ray://)?[\w.\-\[\]:]+:\d+")
"""What can follow `--ray` as its address ("auto", "local", "host:port", "ray://host:port")."""


def _with_ray_address(args: list[str]) -> list[str]:
    """`--ray` takes an optional address: make it `--ray=ADDRESS`, or `--ray=local` when what follows is
    not an address (an input, another option), so that `replay --ray a.mcap` replays a.mcap."""
    result: list[str] = []
    position = 0
    while position < len(args) and args[position] != "--":
        arg, position = args[position], position + 1
        if arg == _RAY_OPTION:
            following = args[position] if position < len(args) else ""
            is_address = bool(_RAY_ADDRESS.fullmatch(following)) and not Path(following).exists()
            arg = f"{_RAY_OPTION}={following if is_address else 'local'}"
            position += 1 if is_address else 0
        result.append(arg)
    return result + args[position:]


class _DefaultCommandContext(typer.Context):
    """Shows `replay [OPTIONS] …` rather than `replay run [OPTIONS] …` when `run` was implied."""

    @property
    def command_path(self) -> str:
        if self.parent is not None and self.meta.get(_IMPLICIT_DEFAULT):
            return self.parent.command_path
        return super().command_path


class _DefaultCommand(TyperCommand):
    context_class = _DefaultCommandContext


app = typer.Typer(
    name=PROGRAM,
    cls=ReplayGroup,
    add_completion=False,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


@app.callback()
def _root() -> None:
    """Replay a robot log (2D laser or 3D LiDAR) or a pose graph through the SGD backend into a Rerun
    recording."""


_EPILOG = f"""\b
Examples:
  replay                                 # {SAMPLE_DESCRIPTION} -> recordings/
  replay run.mcap                        # 2D laser SLAM -> recordings/run.{{tum,g2o,json,rrd}}, run_map.png
  replay drive.mcap                      # 3D LiDAR SLAM (PointCloud2) -> ... and drive.ply, the point map
  replay run.bag --scan-topic /front/scan --odom-topic /wheel_odom --base-frame base_footprint
  replay rosbag2_dir/                    # a ROS 2 bag (sqlite3 or MCAP storage)
  replay graph.g2o                       # SGD then Gauss-Newton (the default method)
  replay graph.graph --method sgd --iterations 30 --allow-unconverged --out results
  replay a.mcap b.bag c/ --jobs 3 --json > summary.json
  replay --inputs logs.txt --ray         # each input a task on a local Ray runtime
  replay --inputs /fleet/today/ --ray head:6379 --out /shared/results --retries 2
  replay --dump-config > replay.toml     # then: replay run.mcap --config replay.toml
  replay second.mcap --map recordings/first.session       # localize in first's map -> second.{{tum,json,rrd}}
  replay second.mcap --map recordings/first.session --initial-pose 3.5,-1.2,1.57
  replay second.mcap --continue recordings/first.session  # map on with second: both runs, second.session

\b
Outputs, in DIR: <stem>.g2o (optimised poses), <stem>.json (counts, chi2 per iteration, wall time per
stage), <stem>.rrd (every iteration on the timeline `iteration`) and, for logs, <stem>.tum (one pose per
scan or cloud at its sensor stamp), the map: <stem>_map.png with the map_server pair <stem>_map.pgm
and .yaml (laser scans), or <stem>.ply and .pcd with the poses as KITTI <stem>.kitti (point clouds),
and <stem>.session (what --map and --continue start from). Sessions (scans or clouds, one log
at a time): --map localizes the log in the saved map without changing it and writes <stem>.tum (every scan
placed in the map, in its frame; scans never placed are counted in the JSON, not written), <stem>.json
(per-scan match quality) and <stem>.rrd (the saved map with the new run on it); --continue maps on from
the session: the .tum holds every scan of both runs (the session's first) at its jointly optimised pose,
and <stem>.session the joint map. A batch (several inputs, --inputs, --ray) also writes
batch_summary.parquet: one row per input (status, error, counts, chi2, times, host). Open the
recording with the Rerun viewer of rerun-sdk 0.41: rerun recordings/csail_sample.rrd. Settings: a TOML
file (--config; --dump-config writes the defaults), which the options override. Other commands: replay
info LOG, replay evaluate TRAJECTORY.tum RELATIONS.
Exit code {EXIT_ERROR} on bad input (one line naming the file, nothing written for it) or when any of
several inputs failed; {EXIT_UNCONVERGED} when an optimization stopped before its convergence test held (the
outputs are written and say so), unless --allow-unconverged."""


@app.command(DEFAULT_COMMAND, cls=_DefaultCommand, epilog=_EPILOG)
def run(
    sources: Annotated[list[Path] | None, typer.Argument(
        metavar="INPUT", show_default=False,
        help="Logs with 2D laser scans or 3D point clouds (MCAP, ROS 1 .bag, ROS 2 bag directory) or 2D "
             "pose graphs (g2o VERTEX_SE2/EDGE_SE2, TORO VERTEX2/EDGE2). Default: "
             f"{SAMPLE_DESCRIPTION}."),
    ] = None,
    out: Annotated[Path, typer.Option(
        "--out", "-o", metavar="DIR", help="Folder for the outputs (created if missing).")] = DEFAULT_OUT_DIR,
    config_file: Annotated[Path | None, typer.Option(
        "--config", "-c", metavar="FILE", show_default=False,
        help="Settings (TOML; see --dump-config). The options below override it.")] = None,
    method: Annotated[Method | None, typer.Option(
        "--method", "-m", show_default=False,
        help="sgd+gn (default): the paper's SGD, then SGD on a spanning tree, then Gauss-Newton to the "
             "exact minimum (and a chordal start polished, the lower kept); sgd: the paper's SGD only; "
             "sgd-tree, sgd-tree+gn: the tree SGD alone or polished; gn: Gauss-Newton only; "
             "gauss-seidel: the paper's baseline."),
    ] = None,
    robust: Annotated[Robust | None, typer.Option(
        "--robust", show_default=False,
        help="A robust kernel against false loop closures, in SGD's steps and the polish: cauchy or dcs "
             "(with sgd+gn or sgd; off by default: it changes the objective).")] = None,
    iterations: Annotated[int | None, typer.Option(
        "--iterations", "-n", min=0, max=MAX_ITERATIONS, show_default=False,
        help="SGD (or Gauss-Seidel) iterations; default 100 (over 200 000 poses a cap: the default "
             "method's SGD hands over to the polish once it stalls). With gn: the Gauss-Newton cap.")] = None,
    repair_information: Annotated[bool, typer.Option(
        "--repair-information", help="Clamp the eigenvalues of information matrices that are not positive "
                                     "definite, instead of rejecting the file.")] = False,
    scan_topic: Annotated[str | None, typer.Option(
        "--scan-topic", metavar="TOPIC",
        help="The sensor topic (LaserScan or PointCloud2), when the log has several.")] = None,
    odom_topic: Annotated[str | None, typer.Option(
        "--odom-topic", metavar="TOPIC", help="The odometry topic, when the log has several.")] = None,
    base_frame: Annotated[str | None, typer.Option(
        "--base-frame", metavar="FRAME", show_default=False,
        help="The vehicle frame the poses are of; tf must link it to the sensor. Default: the frame that "
             "moves, up the sensor's tf chain (for laser logs with odometry: the odometry's child "
             "frame).")] = None,
    jobs: Annotated[int, typer.Option(
        "--jobs", "-j", min=1, max=MAX_JOBS, metavar="N",
        help="Inputs replayed at the same time (worker processes).")] = 1,
    allow_unconverged: Annotated[bool, typer.Option(
        "--allow-unconverged", help=f"Exit 0, not {EXIT_UNCONVERGED}, when the optimization stops before "
                                    "its convergence test holds (always so for sgd and gauss-seidel alone, "
                                    "which run a fixed number of iterations).")] = False,
    inputs_from: Annotated[Path | None, typer.Option(
        "--inputs", metavar="FILE|DIR", show_default=False,
        help="More inputs: a file listing them (one path a line, # comments), or a folder searched for "
             "logs and pose graphs (ROS 2 bag folders whole; the --out folder skipped).")] = None,
    ray_address: Annotated[str | None, typer.Option(
        _RAY_OPTION, metavar="[ADDRESS]", show_default=False,
        help="Replay each input as one task on Ray (pip install '.[ray]'): on the cluster at ADDRESS "
             "(auto, host:port, ray://host:port), or on a local Ray runtime without one. --out must be "
             "reachable from every node.")] = None,
    cpus_per_task: Annotated[float | None, typer.Option(
        "--cpus-per-task", min=0.01, metavar="N", show_default=False,
        help="With --ray: the CPUs each task reserves (default 1).")] = None,
    retries: Annotated[int | None, typer.Option(
        "--retries", min=0, metavar="N", show_default=False,
        help="With --ray: how often a task that crashed or lost its worker is run again (default 1).")
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress and no summary.")] = False,
    as_json: Annotated[bool, typer.Option(
        "--json", help="Print the summary on stdout as JSON: one object, or a list for several inputs.")
    ] = False,
    dump_config: Annotated[bool, typer.Option(
        "--dump-config", help="Print the settings as TOML (the defaults, with --config and the options "
                              "applied) and exit.")] = False,
    map_session: Annotated[Path | None, typer.Option(
        "--map", metavar="SESSION", show_default=False,
        help="Localize the one log INPUT in the map of SESSION (a .session a replay wrote): the "
             "map is not changed. Writes <stem>.tum (in the map's frame), .json (match quality per scan) "
             "and .rrd (the saved map with the new run).")] = None,
    continue_session: Annotated[Path | None, typer.Option(
        "--continue", metavar="SESSION", show_default=False,
        help="Continue mapping SESSION with the one log INPUT: new keyframes, loop closures "
             "between the runs, one joint optimization; the outputs hold both runs, and a new session.")
    ] = None,
    initial_pose: Annotated[str | None, typer.Option(
        "--initial-pose", metavar="X,Y,YAW", show_default=False,
        help="With --map: where the log starts in the map (m, m, rad). Default: found by global "
             "localization.")] = None,
) -> None:
    """Replay logs (or optimise pose graphs), recording every iteration, and write the results to DIR."""
    # The options that set configuration keys (named alike: --scan-topic sets [input] scan_topic), given.
    options: dict[str, dict[str, object]] = {
        "optimizer": {"method": method and method.value, "iterations": iterations,
                      "robust": robust and robust.value},
        "input": {"scan_topic": scan_topic, "odom_topic": odom_topic, "base_frame": base_frame,
                  "repair_information": repair_information or None}}
    overrides = {section: {key: value for key, value in values.items() if value is not None}
                 for section, values in options.items()}
    config = config_from_mapping(overrides) if config_file is None else load_config(config_file, overrides)
    if dump_config:
        typer.echo(config.to_toml(), nl=False)
        return

    sources = sources or []
    session_options = _session_options(map_session, continue_session, initial_pose, sources,
                                       several=inputs_from is not None or ray_address is not None)
    ray = _ray_options(ray_address, cpus_per_task, retries, jobs)
    for key in overrides["optimizer"] if map_session is not None else ():
        raise PipelineError(f"{_option(key)} has nothing to optimize with --map (localization only: the "
                            "saved map is not changed)")
    if inputs_from is not None:
        listed = batch_inputs(inputs_from, exclude=out)
        if not listed:
            what = ("no logs or pose graphs in the folder" if inputs_from.is_dir()
                    else "the list names no input")
            raise PipelineError(f"{inputs_from}: {what}")
        sources += listed
    _refuse_options_without_use(sources, overrides["input"])
    with contextlib.ExitStack() as stack:
        inputs = sources or [stack.enter_context(sample_log())]  # no input: the bundled sample
        refuse_clashing_outputs(inputs, out)
        batch = len(inputs) > 1 or inputs_from is not None or ray is not None
        outcomes = _run_inputs(inputs, config, out, jobs=jobs, ray=ray, batch=batch, quiet=quiet,
                               replay_options=session_options)
    summary_path, summary_error = _write_batch_summary(out, outcomes) if batch else (None, None)
    _report(outcomes, quiet=quiet, as_json=as_json, summary_path=summary_path)
    if summary_error is not None:
        raise summary_error  # (after the outcomes: one line, as every error of ours)
    _exit_for(outcomes, quiet=quiet, allow_unconverged=allow_unconverged)


def _exit_for(outcomes: Sequence[BatchOutcome], *, quiet: bool, allow_unconverged: bool) -> None:
    """Exit 2 when an input failed; say which optimizations did not converge, and exit 3 for them unless
    `allow_unconverged`."""
    if not all(outcome.ok for outcome in outcomes):
        raise typer.Exit(EXIT_ERROR)
    unconverged = [(outcome.input_path, outcome.stats.stop_reason) for outcome in outcomes
                   if outcome.stats and not outcome.stats.converged]
    advice = "" if allow_unconverged else "; --allow-unconverged accepts this"
    for path, reason in unconverged if not (quiet and allow_unconverged) else []:
        typer.echo(f"{PROGRAM}: not converged: {path}: {reason} (outputs written with \"converged\": "
                   f"false{advice})", err=True)
    if unconverged and not allow_unconverged:
        raise typer.Exit(EXIT_UNCONVERGED)


def _option(key: str) -> str:
    """The option that sets configuration key `key`."""
    return "--" + key.replace("_", "-")


def _refuse_options_without_use(sources: Sequence[Path], input_options: dict[str, Any]) -> None:
    """Options that apply to none of the inputs (named or listed) are errors, not silently ignored.
    `input_options`: the [input] keys given as options."""
    kinds = {input_kind(path) for path in sources} if sources else {"log"}  # no input: the sample log
    if "graph" not in kinds and "repair_information" in input_options:
        raise PipelineError("--repair-information applies to pose-graph inputs only, and no input is one")
    if "log" not in kinds:
        for key in (key for key in input_options if key != "repair_information"):
            raise PipelineError(f"{_option(key)} applies to logs only, and every input is a pose graph")


_NUMBER = r"\s*[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\s*"
_INITIAL_POSE = re.compile(",".join([f"({_NUMBER})"] * 3))
"""x,y,yaw: three plain decimal numbers (no inf, nan or digit separators)."""


def _session_options(map_session: Path | None, continue_session: Path | None, initial_pose: str | None,
                     sources: Sequence[Path], *, several: bool) -> dict[str, Any]:
    """The `replay` keyword arguments of --map / --continue / --initial-pose (None when not given); raises
    `PipelineError` on a misuse."""
    if map_session is not None and continue_session is not None:
        raise PipelineError("--map (localize in a saved map) and --continue (map on from it) exclude each "
                            "other: choose one")
    if initial_pose is not None and map_session is None:
        raise PipelineError("--initial-pose applies to --map only (where the log starts in the saved map)")
    if map_session is not None or continue_session is not None:
        option = "--map" if map_session is not None else "--continue"
        if several or len(sources) != 1:
            raise PipelineError(f"{option} takes exactly one log (INPUT), not a batch or the bundled sample")
        if input_kind(sources[0]) == "graph":
            raise PipelineError(f"{option} applies to logs; {sources[0]} is a pose graph")
    pose = None
    if initial_pose is not None:
        matched = _INITIAL_POSE.fullmatch(initial_pose)
        pose = tuple(float(value) for value in matched.groups()) if matched else None
        if pose is None or not all(math.isfinite(value) for value in pose):
            raise PipelineError(f"--initial-pose wants x,y,yaw (metres, metres, radians: three numbers "
                                f"separated by commas), not {initial_pose!r}")
    return {"map": map_session, "continue_from": continue_session, "initial_pose": pose}


def _ray_options(address: str | None, cpus_per_task: float | None, retries: int | None,
                 jobs: int) -> RayOptions | None:
    """The Ray settings of the command line, None without --ray (where its options are refused)."""
    if address is None:
        if cpus_per_task is not None or retries is not None:
            option = "--cpus-per-task" if cpus_per_task is not None else "--retries"
            raise typer.BadParameter("applies to --ray only", param_hint=option)
        return None
    if jobs > 1:
        raise typer.BadParameter("--jobs runs worker processes here, --ray tasks on Ray: choose one",
                                 param_hint="--jobs")
    return RayOptions(address=address, cpus_per_task=1.0 if cpus_per_task is None else cpus_per_task,
                      retries=1 if retries is None else retries)


def _write_batch_summary(out: Path, outcomes: Sequence[BatchOutcome]) -> tuple[Path | None, Exception | None]:
    """Write `batch_summary.parquet` in `out`: its path, or None and the error (reported after the
    outcomes)."""
    try:
        return write_batch_summary(out / BATCH_SUMMARY_NAME, outcomes), None
    except KNOWN_ERRORS as error:
        return None, error


# ------------------------------------------------------------------------------------------ running inputs


def _run_inputs(inputs: Sequence[Path], config: ReplayConfig, out: Path, *, jobs: int, ray: RayOptions | None,
                batch: bool, quiet: bool, replay_options: dict[str, Any]) -> list[BatchOutcome]:
    """Worker processes (`jobs`) or Ray tasks (`ray`), else one input after another here with live
    progress: then a single input's bug keeps its traceback; in a `batch`, it becomes that input's
    failure so the others still run. `replay_options`: a session's (`_session_options`)."""
    from pipeline.batch import run_batch, run_one, with_this_host

    arrow_without_pandas()
    pooled = ray is not None or (jobs > 1 and len(inputs) > 1)
    interactive = not quiet and sys.stderr.isatty()
    # Someone watching a log's replay on a fresh install waits for its kernels to compile: the optimizer's
    # compile on the other core meanwhile (`optimizer.warmup`); batches and scripts don't need it.
    warm_up = interactive and not pooled and any(input_kind(path) == "log" for path in inputs)
    bars = len(inputs) if batch else 0  # (a bar counting the finished inputs)
    with _python_warnings_off(), _progress_display(interactive, bars) as display, warming_up(warm_up):
        if pooled:
            return run_batch(inputs, config, out_dir=out, jobs=jobs, ray=ray, on_done=display.finished)
        outcomes = []
        for path in inputs:
            with display.watch(path, config) as (on_scan, on_iteration):
                outcome = run_one(path, config, out_dir=out, on_scan=on_scan, on_iteration=on_iteration,
                                  catch_unexpected=batch, replay_options=replay_options)
            outcomes.append(with_this_host(outcome) if batch else outcome)
            display.finished(outcomes[-1])
    return outcomes


@contextmanager
def _python_warnings_off() -> Iterator[None]:
    """Replays count their warnings into their summaries, which `_report` prints one line each: Python's
    own printing of them (multi-line, here and in worker processes) would only repeat them."""
    previous = os.environ.get("PYTHONWARNINGS")
    os.environ["PYTHONWARNINGS"] = "ignore"  # inherited by the worker processes started meanwhile
    try:
        with warnings.catch_warnings(action="ignore"):
            yield
    finally:
        if previous is None:
            os.environ.pop("PYTHONWARNINGS", None)
        else:
            os.environ["PYTHONWARNINGS"] = previous


@contextmanager
def _progress_display(enabled: bool, inputs: int) -> Iterator[_ProgressDisplay]:
    """Rich progress bars on stderr (only when enabled: not --quiet and stderr a terminal), transient: the
    summary replaces them. `inputs` > 0 adds a bar counting finished inputs."""
    if not enabled:
        yield _ProgressDisplay(None, inputs)
        return
    from rich import progress as bars
    from rich.console import Console

    columns = (bars.SpinnerColumn(), bars.TextColumn("{task.description}"), bars.BarColumn(),
               bars.MofNCompleteColumn(), bars.TimeElapsedColumn(), bars.TextColumn("{task.fields[info]}"))
    with bars.Progress(*columns, console=Console(stderr=True), transient=True) as progress:
        yield _ProgressDisplay(progress, inputs)


_STAGES_WITH_KNOWN_LENGTH = frozenset({"sgd", "gauss-seidel"})
"""Stages that run exactly the configured iterations (the polish stops when it converges)."""


class _ProgressDisplay:
    """Bars for one input at a time (scans read and matched; optimizer iterations) and for the inputs."""

    def __init__(self, progress: Progress | None, inputs: int) -> None:
        self._progress = progress
        self._inputs_task: TaskID | None = None
        if progress is not None and inputs > 0:
            self._inputs_task = progress.add_task("inputs", total=inputs, info="")

    @contextmanager
    def watch(self, path: Path, config: ReplayConfig) -> Iterator[tuple[Callable[[Estimate], None] | None,
                                                                         Callable[[Iteration], None] | None]]:
        """The callbacks to pass to the replay of `path` (None when progress is off)."""
        progress = self._progress
        if progress is None:
            yield None, None
            return
        name = path.name
        log = input_kind(path) == "log"
        first_task = progress.add_task(
            f"{name}: {'frames' if log else 'reading'}",
            total=expected_scans(path, config.input.scan_topic) if log else None, info="")
        loops = 0
        stage_tasks: dict[str, TaskID] = {}
        iterations = config.optimizer.iterations
        known_length = DEFAULT_ITERATIONS if iterations is None else iterations  # of sgd and gauss-seidel

        def on_scan(estimate: Estimate) -> None:
            nonlocal loops
            loops += len(estimate.new_loop_closures)
            progress.update(first_task, completed=estimate.index + 1,
                            info=f"{estimate.keyframe + 1} keyframes, {loops} loop closures")

        def on_iteration(iteration: Iteration) -> None:
            stage = iteration.stage
            if stage == "initial":  # the input is read: a graph's "reading" spinner is done
                progress.update(first_task, visible=log)
                return
            if stage not in stage_tasks:
                total = known_length if stage in _STAGES_WITH_KNOWN_LENGTH else None
                stage_tasks[stage] = progress.add_task(f"{name}: {stage}", info="", total=total)
            progress.update(stage_tasks[stage], completed=iteration.index, info=f"chi2 {iteration.chi2:.6g}")

        try:
            yield (on_scan if log else None), on_iteration
        finally:
            for task in (first_task, *stage_tasks.values()):
                progress.remove_task(task)

    def finished(self, outcome: BatchOutcome) -> None:
        if self._progress is not None and self._inputs_task is not None:
            status = "done" if outcome.ok else "FAILED"
            self._progress.update(self._inputs_task, advance=1, info=f"{outcome.input_path.name} {status}")


# ------------------------------------------------------------------------------------------------ reports


def _report(outcomes: Sequence[BatchOutcome], *, quiet: bool, as_json: bool,
            summary_path: Path | None) -> None:
    """Errors (always), warnings and the summary on stderr (unless --quiet), JSON on stdout (--json)."""
    if not quiet:
        for outcome in outcomes:
            tally = (outcome.summary or {}).get("warnings", [])
            for line in warning_lines(PROGRAM, outcome.input_path, tally):
                typer.echo(line, err=True)
    if as_json:
        data = [outcome.to_json() for outcome in outcomes]
        typer.echo(json_text(data[0] if len(data) == 1 else data), nl=False)
    if len(outcomes) > 1:
        for outcome in outcomes:
            if outcome.traceback is not None:
                typer.echo(outcome.traceback.rstrip(), err=True)
        if not quiet:
            _print_table(outcomes, summary_path)
    elif outcomes[0].ok and not quiet:
        typer.echo(_one_input_summary(outcomes[0]), err=True)
    for outcome in outcomes:
        if not outcome.ok:
            typer.echo(f"{PROGRAM}: error: {outcome.error}", err=True)


def _one_input_summary(outcome: BatchOutcome) -> str:
    stats, summary = outcome.stats, outcome.summary
    assert stats is not None and summary is not None
    name = outcome.input_path.name
    counts = summary.get("counts", {})
    if summary.get("mode") == "map":
        found = summary["localization"]
        first_fix = found["first_fix_after_s"]
        lines = [
            f"{name}: {found['scans']} scans on {summary['topic']} localized in "
            f"{summary['session']} ({stats.poses} keyframes, not changed): {found['with_pose']} with a pose "
            f"({found['matched']} matched, {found['tracked_outside_map']} tracked outside the map, "
            + (f"{found['between_localized_scans']} between localized ones, "
               if found.get("between_localized_scans") else "")
            + f"{found['recovered_by_a_global_fix']} recovered by a global fix), "
            f"{found['never_localized']} never localized (not in the .tum)",
            f"  {len(found['global_fixes'])} global fix{'' if len(found['global_fixes']) == 1 else 'es'}"
            + ("" if first_fix is None else f", the first {first_fix:.1f} s after the first scan")
            + f"; median match score {_or_dash(found['score']['median'])}, "
              f"inliers {_or_dash(found['inlier_fraction']['median'])}",
        ]
        if counts.get("held_map_used"):
            lines.append(f"  trajectory: the run's own keyframe graph ({counts['held_map_keyframes']} "
                         f"keyframes, {counts['held_map_old_new_constraints']} constraints to the saved "
                         f"ones) solved in the saved map, {counts['held_map_apart_from_matches_mm']} mm "
                         "(median) from the scans matched to it")
        elif "held_map_used" in counts:
            lines.append("  trajectory: the scans localized one by one, smoothed")
    elif stats.scans is not None:
        what = "point clouds" if summary["sensor"] == "cloud" else "scans"
        lines = [f"{name}: {stats.scans} {what} on {summary['topic']}, odometry "
                 f"{summary['odometry_topic'] or 'none'}, base frame {summary['base_frame'] or 'none'}; "
                 f"{stats.poses} keyframes, {stats.loop_closures} loop closures "
                 f"({stats.loop_closures_rejected} rejected)"]
    else:
        lines = [f"{name}: {stats.poses} poses, {stats.constraints} constraints ({stats.loop_closures} loop "
                 f"closures), method {summary['method']}"]
        if skipped := summary.get("skipped_lines"):
            tags = ", ".join(f"{count} {tag}" for tag, count in sorted(skipped.items()))
            lines.append(f"  skipped lines: {tags}")
        if repaired := summary.get("repaired_information_lines"):
            lines.append(f"  repaired the information of {len(repaired)} constraints")
    if counts.get("scans_between"):
        interval = summary.get("config", {}).get("matching", {}).get("min_match_interval")
        lines.append(f"  {counts['scans_between']} scans posed between matched ones (the laser scans more "
                     f"often than every {interval:g} s: [slam2d.matching] min_match_interval)")
    timed, ignored = counts.get("scans_with_beam_times", 0), counts.get("scans_beam_times_ignored", 0)
    if timed:
        if not summary.get("config", {}).get("matching", {}).get("deskew", True):
            deskewing = "not deskewed ([slam2d.matching] deskew = false)"
        elif ignored:
            deskewing = f"{timed - ignored} deskewed, {ignored} read as instant (see the warning)"
        else:
            deskewing = "deskewed"
        lines.append(f"  {timed} scans with beam times (time_increment): {deskewing}")
    if summary.get("mode") == "continue":
        placement = summary["session"]["placement"]
        lines.append(f"  continued {summary['session']['continued_from']}: {counts['session_keyframes']} "
                     f"keyframes and {counts['session_scans']} scans of it; placed in it at scan "
                     f"{placement.get('scan')}, {counts['scans_unplaced']} scans before that left out; "
                     f"{counts['loop_closures_old_new']} constraints between its keyframes and the new ones")
    if summary.get("mode") != "map":
        per_stage = ", ".join(f"{stage} {count}" for stage, count in stats.iterations.items())
        lines.append(f"  chi2 {stats.chi2_initial:.6g} -> {stats.chi2_final:.6g}"
                     + (f" after {per_stage} iterations" if per_stage else ""))
    times = dict(stats.wall_time_s)
    total = times.pop("total", math.nan)
    stage_times = ", ".join(f"{stage} {seconds:.2f}" for stage, seconds in times.items())
    lines += [f"  time {total:.2f} s ({stage_times})",
              "  wrote " + ", ".join(str(path) for path in outcome.outputs.values())]
    return "\n".join(lines)


def _or_dash(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _print_table(outcomes: Sequence[BatchOutcome], summary_path: Path | None) -> None:
    from rich.console import Console
    from rich.table import Column, Table

    failed = sum(not outcome.ok for outcome in outcomes)
    # A path cut short ("…") cannot be found again: the input column always holds whole paths, the
    # other columns fold instead.
    numbers = ("poses", "loops", "chi2 initial -> final", "time s")
    columns = [Column("input", no_wrap=True, min_width=max(len(str(o.input_path)) for o in outcomes)),
               Column("result", overflow="fold"), *(Column(name, justify="right") for name in numbers)]
    table = Table(*columns, title=f"{len(outcomes)} inputs, {len(outcomes) - failed} done, {failed} failed",
                  title_justify="left", caption=None if summary_path is None else f"table: {summary_path}",
                  caption_justify="left")
    for outcome in outcomes:
        stats = outcome.stats
        if stats is None:
            table.add_row(str(outcome.input_path), f"FAILED: {outcome.error}", "", "", "", "")
            continue
        table.add_row(str(outcome.input_path), f"{outcome.kind} -> {outcome.outputs['rrd'].parent}",
                      str(stats.poses), str(stats.loop_closures),
                      f"{stats.chi2_initial:.4g} -> {stats.chi2_final:.4g}",
                      f"{stats.wall_time_s.get('total', math.nan):.2f}")
    # Not a terminal (a pipe, a file, a test): wide enough that paths and messages stay on their lines.
    Console(stderr=True, width=None if sys.stderr.isatty() else 200).print(table)


_INFO_EPILOG = f"""\b
Examples:
  replay info run.mcap
  replay info rosbag2_dir/ --json

\b
Read from the log's summary or index, not its messages: instant even on gigabyte logs.
--json prints one object:
{{"path", "container", "start_ns", "end_ns", "topics": [{{"name", "type", "count"}}, ...]}}.
Of a session (`replay info recordings/run.session`): what wrote it, the map's sensor, keyframes, scans or
clouds placed, constraints, loop closures and the logs it was made from; with --json
{{"path", "container": "session", "format", "version", "software_version", "topic", "sensor_frame",
"base_frame", "source", "continued_from", "sensor_kind", "keyframes", "measurements", "constraints",
"loop_closures"}}.
Exit code {EXIT_ERROR} on bad input: one line naming the file."""


@app.command("info", epilog=_INFO_EPILOG)
def info(
    log: Annotated[Path, typer.Argument(
        metavar="LOG", show_default=False,
        help="An MCAP file, a ROS 1 bag or a ROS 2 bag directory, or a .session a replay wrote.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout.")] = False,
) -> None:
    """Show a log's topics, message types, counts, rates and time span, or what a session holds."""
    from frontends.logs import open_log

    if is_session_file(log):
        _session_info(log, as_json)
        return
    with tallied_warnings(WarningTally(log)) as tally, open_log(log) as reader:
        summary = reader.info()
    for line in warning_lines(PROGRAM, log, tally.as_json()):  # (a truncated log: what is left is listed)
        typer.echo(line, err=True)
    if as_json:
        typer.echo(json.dumps(summary.to_json_dict()))
        return
    duration = summary.duration_s
    lines = [f"{summary.path}: {summary.container}, {summary.message_count} messages over {duration:.2f} s "
             f"({summary.start_ns * 1e-9:.3f} to {summary.end_ns * 1e-9:.3f})"]
    width = max((len(topic.name) for topic in summary.topics), default=5)
    type_width = max((len(topic.type) for topic in summary.topics), default=4)
    for topic in summary.topics:
        # n messages span n − 1 intervals; the log's span stands in for the topic's own (the summary has no
        # per-topic span), exact for the topics that run the whole log.
        has_rate = duration > 0 and topic.count > 1
        rate = f"{(topic.count - 1) / duration:8.2f} Hz" if has_rate else "       - Hz"
        lines.append(f"  {topic.name:<{width}}  {topic.type:<{type_width}}  {topic.count:>9}  {rate}")
    typer.echo("\n".join(lines))


def _session_info(path: Path, as_json: bool) -> None:
    described = describe_session(path)
    if as_json:
        typer.echo(json.dumps(described))
        return
    kind = described["sensor_kind"]
    lines = [f"{path}: session (format {described['version']}, written by sgdslam "
             f"{described['software_version']}): a map of {SENSOR_WORDS[kind]} on {described['topic']} "
             f"({described['sensor_frame']} in {described['base_frame'] or 'its own frame'})",
             f"  {described['keyframes']} keyframes and {described['measurements']} {kind}s placed; "
             f"{described['constraints']} constraints ({described['loop_closures']} loop closures)"]
    lines += [f"  from {file.get('path')} ({file.get('bytes')} bytes, sha256 {file.get('sha256')})"
              for file in _source_files(described)]
    earlier = described["continued_from"]
    while isinstance(earlier, dict):  # each continuation names the session it continued, and that one its own
        logs = ", ".join(str(file.get("path")) for file in _source_files(earlier))
        lines.append(f"  continuing {earlier.get('path')} (from {logs or 'a log not recorded'})")
        earlier = earlier.get("continued_from")
    typer.echo("\n".join(lines))


def _source_files(entry: dict[str, Any]) -> list[dict[str, Any]]:
    """The source log files a session header's entry names (a header edited by hand may name them oddly)."""
    source = entry.get("source")
    files = source.get("files") if isinstance(source, dict) else None
    return [file for file in files if isinstance(file, dict)] if isinstance(files, list) else []


_EVALUATE_EPILOG = f"""\b
Examples:
  replay evaluate recordings/aces.tum ../shared/data/logs/aces/aces.relations
  replay evaluate run.tum run.relations --json --tolerance-ms 5

\b
Each relation (t1 t2 x y z roll pitch yaw: the true motion from the pose at t1 to the pose at t2, in the
frame of t1) pairs with the trajectory's poses by stamp: the same stamp, else the nearest within the
tolerance; relations that pair with no pose are counted as unmatched. The error of a relation is
e = true⁻¹·estimated; reported are the mean ± std of |translation| (m), |rotation| (deg) and their squares.
Exit code {EXIT_ERROR} on bad input: one line naming the file and line."""


@app.command("evaluate", epilog=_EVALUATE_EPILOG)
def evaluate(
    trajectory: Annotated[Path, typer.Argument(
        metavar="TRAJECTORY.tum", show_default=False,
        help="The trajectory, TUM format (timestamp tx ty tz qx qy qz qw); its poses are taken as planar.")],
    relations: Annotated[Path, typer.Argument(
        metavar="RELATIONS", show_default=False,
        help="Ground-truth relations, Freiburg format (t1 t2 x y z roll pitch yaw).")],
    as_json: Annotated[bool, typer.Option(
        "--json", help="Print one JSON object on stdout instead of the table.")] = False,
    tolerance_ms: Annotated[float, typer.Option(
        "--tolerance-ms", min=0.0, help="How far a relation stamp may be from a trajectory stamp.")
    ] = DEFAULT_TOLERANCE_NS / 1e6,
) -> None:
    """Score a trajectory with the relations metric of Kümmerle et al. 2009."""
    if not math.isfinite(tolerance_ms):
        raise typer.BadParameter("must be finite", param_hint="--tolerance-ms")
    tolerance_ns = round(tolerance_ms * 1e6)
    result = evaluate_files(trajectory, relations, tolerance_ns=tolerance_ns)
    if as_json:
        typer.echo(json.dumps({"trajectory": str(trajectory), "relations": str(relations),
                               "tolerance_ns": tolerance_ns, **result.summary()}))
        return
    typer.echo("\n".join([
        f"{trajectory.name} against {relations.name} (tolerance {tolerance_ms:g} ms)",
        f"  relations     {result.count} scored, {result.unmatched} unmatched",
        f"  translation   {result.translation_mean:.4f} ± {result.translation_std:.4f} m",
        f"  rotation      {result.rotation_mean_deg:.3f} ± {result.rotation_std_deg:.3f} deg",
        f"  translation²  {result.translation_squared_mean:.4g} ± {result.translation_squared_std:.4g} m²",
        f"  rotation²     {result.rotation_squared_mean:.4g} ± {result.rotation_squared_std:.4g} deg²",
    ]))


def main() -> NoReturn:
    """Console-script entry point."""
    from threadpoolctl import threadpool_limits

    # Our linear algebra is many small vectors and 3×3 blocks: BLAS threads only add hand-off latency,
    # and on a busy machine their spinning made one 10k-element dot product take 8 ms instead of 5 µs.
    terminated: list[int] = []

    def on_signal(signum: int, frame: FrameType | None) -> None:
        # SIGTERM is cleaned up like Ctrl-C (staged outputs removed, workers stopped), then reported as such.
        if signum == signal.SIGTERM:
            terminated.append(signum)
        raise KeyboardInterrupt

    install_stop_signals(on_signal)
    code: int | str | None
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            code = app(prog_name=PROGRAM, standalone_mode=False)
    # Ctrl-C or SIGTERM: typer turns it into Abort, but one that comes before typer runs (while
    # threadpool_limits is entered) is still the bare KeyboardInterrupt.
    except (typer.Abort, KeyboardInterrupt):
        code = EXIT_INTERRUPTED
    except Exception as error:
        # A bad option or value (click's UsageError family, whichever click typer uses): one line naming
        # it, like bad input; a stop signal that a callback from C turned into another error: an
        # interrupt. Anything else is a bug and keeps its traceback.
        if raised_by_interrupt(error):
            code = EXIT_INTERRUPTED
        elif hasattr(error, "format_message") and hasattr(error, "exit_code"):
            message = " ".join(error.format_message().split())
            typer.echo(f"{PROGRAM}: error: {message} (see {PROGRAM} --help)", err=True)
            code = EXIT_ERROR
        else:
            raise
    except SystemExit as exit_:
        code = exit_.code
    if terminated and code == EXIT_INTERRUPTED:
        code = 128 + signal.SIGTERM
    _exit_now(code)


def _exit_now(code: int | str | None) -> NoReturn:
    """End the process without the interpreter's teardown.

    By now every output is written, renamed and closed, recordings flushed and disconnected, process pools
    joined and temporary copies removed (all in `with` blocks); what teardown would still do is unload
    numba's LLVM engines and rerun's threads, 0.4 s of a 2 s replay. Only the standard streams need a flush.
    """
    if isinstance(code, str):
        print(code, file=sys.stderr)
        code = 1
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(0 if code is None else int(code))


if __name__ == "__main__":
    main()
