"""The `replay` command line.

`replay [INPUT] [options]` runs the default command on a log (MCAP, ROS 1 bag, ROS 2 bag directory) or a
2D pose graph (g2o, TORO), told apart by the path and its content; a first argument naming a subcommand
(`evaluate`) runs that one instead.

Errors the program raises on purpose (`OptimizerError`, `FrontendError`, `PipelineError`) end in one line
on stderr, `replay: error: <message>`, and exit code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import enum
import json
import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer
from typer.core import TyperCommand, TyperGroup

from frontends.errors import FrontendError
from optimizer.errors import OptimizerError
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, METHODS
from pipeline.errors import PipelineError
from pipeline.evaluation import DEFAULT_TOLERANCE_NS, RelationsResult, evaluate_files

if TYPE_CHECKING:
    from pipeline.replay_graph import GraphReplayResult
    from pipeline.replay_log import LogReplayResult

KNOWN_ERRORS = (OptimizerError, FrontendError, PipelineError)
GRAPH_SUFFIXES = frozenset({".g2o", ".graph"})
GRAPH_TAGS = frozenset({"VERTEX_SE2", "EDGE_SE2", "VERTEX2", "EDGE2", "VERTEX_SE3:QUAT", "EDGE_SE3:QUAT",
                        "VERTEX3", "EDGE3"})

PROGRAM = "replay"
DEFAULT_COMMAND = "run"
DEFAULT_OUT_DIR = Path("recordings")
EXIT_ERROR = 2
"""Exit code of a run that failed on bad input or unwritable outputs (the same as usage errors)."""

_IMPLICIT_DEFAULT = "pipeline.cli.implicit_default"

Method = enum.StrEnum("Method", [(name, name) for name in METHODS])  # type: ignore[misc]
"""The optimizer's methods as a choice (the names come from `optimizer.solve.METHODS`)."""
_DEFAULT_METHOD_CHOICE = Method(DEFAULT_METHOD)


class ReplayGroup(TyperGroup):
    """Runs the default command unless the first argument names a subcommand.

    This keeps `replay`, `replay GRAPH` and `replay --help` working the way a single command would, while
    leaving room for subcommands (`replay info`, …): a group's own positional argument would swallow them.
    """

    def parse_args(self, ctx: typer.Context, args: list[str]) -> list[str]:
        if not args or args[0] not in self.commands:
            ctx.meta[_IMPLICIT_DEFAULT] = True
            args = [DEFAULT_COMMAND, *args]
        return super().parse_args(ctx, args)


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
    """Replay a robot log (2D laser) or a pose graph through the SGD backend into a Rerun recording."""


_EPILOG = f"""\b
Examples:
  replay                                 # the bundled M3500 sample -> recordings/M3500.{{g2o,json,rrd}}
  replay run.mcap                        # 2D laser SLAM -> recordings/run.{{tum,g2o,json,rrd}}
  replay run.bag --scan-topic /front/scan --odom-topic /wheel_odom
  replay rosbag2_dir/                    # a ROS 2 bag (sqlite3 or MCAP storage)
  replay graph.g2o                       # SGD then Gauss-Newton (the default method)
  replay graph.graph --method sgd --iterations 30 --out results
  replay graph.g2o --method gauss-seidel --quiet

\b
Outputs, in DIR: <stem>.g2o (optimised poses), <stem>.json (counts, chi2 per iteration, wall time per
stage), <stem>.rrd (every iteration on the timeline `iteration`) and, for logs, <stem>.tum (one pose per
scan at its sensor stamp). Open the recording with the Rerun viewer of rerun-sdk 0.41:
rerun recordings/M3500.rrd. Other commands: replay evaluate TRAJECTORY.tum RELATIONS.
Exit code {EXIT_ERROR} on bad input: one line naming the file (and line or message), nothing written."""


@app.command(DEFAULT_COMMAND, cls=_DefaultCommand, epilog=_EPILOG)
def run(
    source: Annotated[Path | None, typer.Argument(
        metavar="INPUT", show_default=False,
        help="A log with 2D laser scans (MCAP, ROS 1 .bag, ROS 2 bag directory) or a 2D pose graph (g2o "
             "VERTEX_SE2/EDGE_SE2, TORO VERTEX2/EDGE2). Default: the bundled M3500 sample (Olson 2006)."),
    ] = None,
    out: Annotated[Path, typer.Option(
        "--out", "-o", metavar="DIR", help="Folder for the outputs (created if missing).")] = DEFAULT_OUT_DIR,
    method: Annotated[Method, typer.Option(
        "--method", "-m", help="sgd+gn: the paper's SGD, then Gauss-Newton to the exact minimum; "
                               "sgd: SGD only; gn: Gauss-Newton only; gauss-seidel: the paper's baseline."),
    ] = _DEFAULT_METHOD_CHOICE,
    iterations: Annotated[int | None, typer.Option(
        "--iterations", "-n", min=0, show_default=False,
        help="SGD (or Gauss-Seidel) iterations; default 100. With gn: the Gauss-Newton cap.")] = None,
    repair_information: Annotated[bool, typer.Option(
        "--repair-information", help="Clamp the eigenvalues of information matrices that are not positive "
                                     "definite, instead of rejecting the file.")] = False,
    scan_topic: Annotated[str | None, typer.Option(
        "--scan-topic", metavar="TOPIC", help="The LaserScan topic, when the log has several.")] = None,
    odom_topic: Annotated[str | None, typer.Option(
        "--odom-topic", metavar="TOPIC", help="The odometry topic, when the log has several.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress and no summary.")] = False,
) -> None:
    """Replay a log (or optimise a pose graph), recording every iteration, and write the results to DIR."""
    # Imported here so that `replay --help` does not pay for importing rerun.
    from pipeline.bundled import sample_graph
    from pipeline.replay_graph import replay_graph
    from pipeline.replay_log import replay_log

    if source is not None and not is_graph_file(source):
        try:
            with _progress(enabled=not quiet) as progress:
                log_result = replay_log(source, out_dir=out, scan_topic=scan_topic, odometry_topic=odom_topic,
                                        method=str(method.value), iterations=iterations,
                                        on_iteration=progress)
        except KNOWN_ERRORS as error:
            _fail(error)
        if not quiet:
            _print_log_summary(log_result)
        return
    graph_source = nullcontext(source) if source is not None else sample_graph()
    try:
        with graph_source as path, _progress(enabled=not quiet) as progress:
            result = replay_graph(path, out_dir=out, method=str(method.value), iterations=iterations,
                                  repair_information=repair_information, progress=progress)
    except KNOWN_ERRORS as error:
        _fail(error)
    if not quiet:
        _print_summary(result)


def is_graph_file(path: Path) -> bool:
    """A pose-graph file by its suffix, or a text file whose first data line starts with a graph tag."""
    if path.suffix.lower() in GRAPH_SUFFIXES:
        return True
    if not path.is_file() or path.suffix.lower() in {".mcap", ".bag", ".db3", ".yaml"}:
        return False
    try:
        with path.open("rb") as file:
            head = file.read(4096).decode("utf-8", errors="replace")
    except OSError:
        return False
    for line in head.splitlines():
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            return fields[0] in GRAPH_TAGS
    return False


def _fail(error: Exception) -> NoReturn:
    message = " ".join(str(error).split())  # always one line
    typer.echo(f"{PROGRAM}: error: {message}", err=True)
    raise typer.Exit(EXIT_ERROR)


@contextmanager
def _progress(*, enabled: bool) -> Iterator[Callable[[Iteration], None] | None]:
    """A live status line on stderr while optimizing, only when stderr is a terminal."""
    if not enabled or not sys.stderr.isatty():
        yield None
        return
    from rich.console import Console

    with Console(stderr=True).status("reading") as status:

        def show(iteration: Iteration) -> None:
            status.update(f"{iteration.stage} {iteration.index}  chi2 {iteration.chi2:.6g}")

        yield show


def _print_log_summary(result: LogReplayResult) -> None:
    frontend = result.frontend
    times = result.wall_time
    chi2 = result.chi2_per_iteration
    lines = [
        f"{result.input_path.name}: {result.counts['scans']} scans on {result.scan_topic}, odometry "
        f"{result.odometry_topic or 'none'}; {frontend.graph.num_poses} keyframes, "
        f"{frontend.loop_closures_accepted} loop closures ({frontend.loop_closures_rejected} rejected)",
        f"  chi2 {chi2[0][2]:.6g} -> {chi2[-1][2]:.6g} after {len(chi2) - 1} iterations",
        f"  time {times['total']:.2f} s (frontend {times['frontend']:.2f}, optimize+record "
        f"{times['optimize_and_record']:.2f}, write {times['write']:.2f})",
        f"  wrote {result.outputs.tum}, {result.outputs.g2o}, {result.outputs.json}, {result.outputs.rrd}",
    ]
    typer.echo("\n".join(lines), err=True)


def _print_summary(result: GraphReplayResult) -> None:
    graph = result.graph
    per_stage = ", ".join(f"{stage} {count}" for stage, count in result.iterations_per_stage.items())
    times = result.wall_time
    lines = [
        f"{result.input_path.name}: {graph.num_poses} poses, {graph.num_edges} constraints "
        f"({result.num_loop_closures} loop closures), method {result.method}",
        f"  chi2 {result.initial_chi2:.6g} -> {result.final_chi2:.6g}"
        + (f" after {per_stage} iterations" if per_stage else ""),
        f"  time {times['total']:.2f} s (load {times['load']:.2f}, optimize {times['optimize']:.2f}, "
        f"record {times['record']:.2f}, write {times['write']:.2f})",
        f"  wrote {result.outputs.g2o}, {result.outputs.json}, {result.outputs.rrd}",
    ]
    if result.repaired_lines:
        lines.insert(1, f"  repaired the information of {len(result.repaired_lines)} constraints")
    if result.skipped:
        skipped = ", ".join(f"{count} {tag}" for tag, count in sorted(result.skipped.items()))
        lines.insert(1, f"  skipped lines: {skipped}")
    typer.echo("\n".join(lines), err=True)


_INFO_EPILOG = f"""\b
Examples:
  replay info run.mcap
  replay info rosbag2_dir/ --json

\b
Read from the log's summary or index, not its messages: instant even on gigabyte logs.
--json prints one object:
{{"path", "container", "start_ns", "end_ns", "topics": [{{"name", "type", "count"}}, ...]}}.
Exit code {EXIT_ERROR} on bad input: one line naming the file."""


@app.command("info", epilog=_INFO_EPILOG)
def info(
    log: Annotated[Path, typer.Argument(
        metavar="LOG", show_default=False, help="An MCAP file, a ROS 1 bag or a ROS 2 bag directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout.")] = False,
) -> None:
    """Show a log's topics, message types, counts, rates and time span."""
    from frontends.log import open_log

    try:
        with open_log(log) as reader:
            summary = reader.info()
    except KNOWN_ERRORS as error:
        _fail(error)
    if as_json:
        typer.echo(json.dumps(summary.to_json_dict()))
        return
    duration = summary.duration_s
    lines = [
        f"{summary.path}: {summary.container}, {summary.message_count} messages over {duration:.2f} s "
        f"({summary.start_ns * 1e-9:.3f} to {summary.end_ns * 1e-9:.3f})",
    ]
    width = max((len(topic.name) for topic in summary.topics), default=5)
    type_width = max((len(topic.type) for topic in summary.topics), default=4)
    for topic in summary.topics:
        # n messages span n − 1 intervals; the log's span stands in for the topic's own (the summary has no
        # per-topic span), exact for the topics that run the whole log.
        has_rate = duration > 0 and topic.count > 1
        rate = f"{(topic.count - 1) / duration:8.2f} Hz" if has_rate else "       - Hz"
        lines.append(f"  {topic.name:<{width}}  {topic.type:<{type_width}}  {topic.count:>9}  {rate}")
    typer.echo("\n".join(lines))


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
    try:
        result = evaluate_files(trajectory, relations, tolerance_ns=tolerance_ns)
    except PipelineError as error:
        _fail(error)
    if as_json:
        typer.echo(json.dumps({"trajectory": str(trajectory), "relations": str(relations),
                               "tolerance_ns": tolerance_ns, **result.summary()}))
    else:
        typer.echo(_relations_table(result, f"{trajectory.name} against {relations.name} "
                                            f"(tolerance {tolerance_ms:g} ms)"))


def _relations_table(result: RelationsResult, title: str) -> str:
    return "\n".join([
        title,
        f"  relations     {result.count} scored, {result.unmatched} unmatched",
        f"  translation   {result.translation_mean:.4f} ± {result.translation_std:.4f} m",
        f"  rotation      {result.rotation_mean_deg:.3f} ± {result.rotation_std_deg:.3f} deg",
        f"  translation²  {result.translation_squared_mean:.4g} ± {result.translation_squared_std:.4g} m²",
        f"  rotation²     {result.rotation_squared_mean:.4g} ± {result.rotation_squared_std:.4g} deg²",
    ])


def main() -> None:
    """Console-script entry point."""
    from threadpoolctl import threadpool_limits

    # Our linear algebra is many small vectors and 3×3 blocks: BLAS threads only add hand-off latency,
    # and on a busy machine their spinning made one 10k-element dot product take 8 ms instead of 5 µs.
    with threadpool_limits(limits=1, user_api="blas"):
        app(prog_name=PROGRAM)


if __name__ == "__main__":
    main()
