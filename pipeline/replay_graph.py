"""Replay a pose-graph file: optimise it, record every iteration, write the results.

Library code: it raises `OptimizerError` (bad input) or `PipelineError` (outputs), never prints or exits.
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from optimizer.graph import PoseGraph
from optimizer.graph_files import GraphFile, read_graph, write_g2o
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, METHODS, Optimization, OptimizationResult, optimize
from pipeline import recording
from pipeline.errors import PipelineError
from pipeline.outputs import json_text, optimization_summary, output_stem, staged_outputs_in, write_text

ProgressCallback = Callable[[Iteration], None]
"""Called with every iteration as the optimizer yields it (the initial estimate first)."""

SUMMARY_SCHEMA = "sgdslam.replay-graph/2"
"""Names the layout of `<stem>.json`; bumped when a key changes meaning or disappears."""


@dataclass(frozen=True)
class IterationRecord:
    """χ² after one iteration; `step` is its position on the recording's `iteration` timeline. The fields
    in the order of the summary's `chi2_per_iteration` entries."""

    step: int
    start: str
    """The starting estimate (candidate) the iteration belongs to."""
    stage: str
    index: int
    chi2: float


@dataclass(frozen=True)
class ReplayOutputs:
    """The files a replay wrote."""

    g2o: Path
    json: Path
    rrd: Path

    @classmethod
    def for_input(cls, out_dir: Path, input_path: Path) -> ReplayOutputs:
        stem = output_stem(input_path)
        return cls(out_dir / f"{stem}.g2o", out_dir / f"{stem}.json", out_dir / f"{stem}.rrd")

    def paths(self) -> dict[str, Path]:
        """Kind ("g2o", "json", "rrd") → path, as the log replay's outputs give them."""
        return dataclasses.asdict(self)


@dataclass(frozen=True, eq=False)
class GraphReplayResult:
    """What `replay_graph` did: the optimised poses, the χ² trace, timings and the files written."""

    input_path: Path
    input_format: str
    """"g2o" or "toro"."""
    initialised_from_odometry: bool
    skipped: Mapping[str, int]
    """Tags of the input's lines that were skipped, with their counts."""
    repaired_lines: tuple[int, ...]
    """Input lines whose information matrix was repaired (`repair_information=True`)."""
    method: str
    graph: PoseGraph
    """The graph as read (its `poses` are the initial estimate)."""
    poses: NDArray[np.float64]
    """(N, 3) final optimised poses, in the graph's index order."""
    iterations: tuple[IterationRecord, ...]
    """Every iteration the optimizer yielded, the initial estimate first."""
    wall_time: Mapping[str, float]
    """Seconds per pipeline stage: load, optimize, record (everything between the optimizer's iterations),
    write (the optimised graph) and total."""
    optimize_time: Mapping[str, float]
    """Seconds inside the optimizer per optimizer stage (initial, sgd, gauss-newton, gauss-seidel)."""
    outputs: ReplayOutputs
    optimization: OptimizationResult
    """How the optimization ended: converged or not and why, every candidate start, the winner."""

    @property
    def initial_chi2(self) -> float:
        return self.iterations[0].chi2

    @property
    def final_chi2(self) -> float:
        return self.iterations[-1].chi2

    @property
    def iterations_per_stage(self) -> dict[str, int]:
        """Number of iterations of each optimizer stage over every candidate, in the order they ran (without
        the starting estimates and the selection)."""
        return iterations_per_stage(record.stage for record in self.iterations)

    @property
    def num_loop_closures(self) -> int:
        return int(np.count_nonzero(~self.graph.is_odometry))


def iterations_per_stage(stages: Iterable[str]) -> dict[str, int]:
    """How many of these recorded iterations each optimizer stage ran, in order of appearance: the
    starting estimates ("initial") and the selection of the best candidate are none."""
    return dict(Counter(stage for stage in stages if stage not in ("initial", "selected")))


def replay_graph(
    path: str | Path,
    *,
    out_dir: str | Path,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    robust: str | None = None,
    repair_information: bool = False,
    progress: ProgressCallback | None = None,
) -> GraphReplayResult:
    """Optimise the pose graph in `path` and write `<stem>.g2o`, `<stem>.json` and `<stem>.rrd` to `out_dir`.

    `method` is one of `optimizer.solve.METHODS`; `iterations` the number of SGD (or Gauss–Seidel)
    iterations (None: the optimizer's default). `repair_information` clamps the eigenvalues of information
    matrices that are not positive definite instead of rejecting the file.

    The input is read before anything is created; outputs are written under temporary names and renamed
    only when all are complete, so a failure leaves `out_dir` as it was (a folder created by this call is
    removed again).
    """
    started = time.perf_counter()
    path = Path(path)
    out_dir = Path(out_dir)
    if method not in METHODS:
        raise PipelineError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if iterations is not None and iterations < 0:
        raise PipelineError(f"iterations must be >= 0, got {iterations}")

    graph_file = read_graph(path, repair_information=repair_information)
    loaded = time.perf_counter()
    outputs = ReplayOutputs.for_input(out_dir, path)
    staged = staged_outputs_in(out_dir, *outputs.paths().values(), inputs=(path,))
    with staged as (g2o_temporary, json_temporary, rrd_temporary):
        recording_started = time.perf_counter()
        run = _optimize_and_record(graph_file, rrd_temporary, method, iterations, progress, robust)
        optimized = time.perf_counter()
        write_g2o(g2o_temporary, graph_file.graph, run.final_poses)
        finished = time.perf_counter()
        result = GraphReplayResult(
            input_path=path,
            input_format=graph_file.format,
            initialised_from_odometry=graph_file.initialised_from_odometry,
            skipped=dict(graph_file.skipped),
            repaired_lines=tuple(int(line) for line in graph_file.repaired_lines),
            method=method,
            graph=graph_file.graph,
            poses=run.final_poses,
            iterations=run.trace,
            # "write" is the optimised graph; the JSON, written last, cannot time itself.
            wall_time={
                "load": loaded - started,
                "optimize": sum(run.optimize_time.values()),
                # Creating, framing and closing the recording count as recording too.
                "record": optimized - recording_started - sum(run.optimize_time.values()),
                "write": finished - optimized,
                "total": finished - started,
            },
            optimize_time=run.optimize_time,
            outputs=outputs,
            optimization=run.result,
        )
        write_text(json_temporary, json_text(summary(result)))
    return result


@dataclass(frozen=True, eq=False)
class RecordedOptimization:
    """An optimization run to its end with every iteration recorded (`record_optimization`)."""

    trace: tuple[IterationRecord, ...]
    final_poses: NDArray[np.float64]
    result: OptimizationResult
    optimize_time: dict[str, float]
    """Seconds spent inside the optimizer, per optimizer stage (the rest of the time is the recording's)."""


def optimization_recorder(stream: Any, graph: PoseGraph, initial_poses: NDArray[np.float64], *,
                          legend: Mapping[str, tuple[tuple[int, ...], str]] | None = None,
                          still_move: float | None = None,
                          still_fraction: float | None = None) -> recording.IterationRecorder:
    """Start the optimization part of a recording of `graph` (styles, legend, the starting estimate
    `initial_poses`, a note when it has no loop closure) and the recorder of its iterations."""
    recording.log_styles(stream)
    recording.log_legend(stream, legend)
    recording.log_initial_trajectory(stream, initial_poses)
    loops = ~graph.is_odometry
    if not loops.any():
        recording.log_note(stream, recording.NO_LOOP_CLOSURES_NOTE)
    return recording.IterationRecorder(stream, graph.edge_from[loops], graph.edge_to[loops],
                                       still_move=still_move, still_fraction=still_fraction)


def record_optimization(optimization: Optimization, recorder: recording.IterationRecorder,
                        sinks: Sequence[recording.IterationSink] = (),
                        on_iteration: ProgressCallback | None = None,
                        on_final: Callable[[NDArray[np.float64]], None] | None = None,
                        first_recorded: int = 0) -> RecordedOptimization:
    """Run `optimization`, adding every iteration to `recorder` and `sinks` (flushed at the end) and
    passing it to `on_iteration`, timing the optimizer apart from the rest. `on_final` gets the final
    poses as soon as the last iteration is known, before the recorder and the sinks are flushed. Poses
    before `first_recorded` are left out of all of it (and of the final poses): a held map's origin."""
    trace: list[IterationRecord] = []
    optimize_time: dict[str, float] = {}
    final_poses = None
    step_started = time.perf_counter()
    for iteration in optimization:
        stage_seconds = time.perf_counter() - step_started  # the optimizer's time to yield it
        if first_recorded:
            iteration = dataclasses.replace(iteration, poses=iteration.poses[first_recorded:])
        optimize_time[iteration.stage] = optimize_time.get(iteration.stage, 0.0) + stage_seconds
        step = recorder.add(iteration)
        for sink in sinks:
            sink.add(step, iteration)
        trace.append(IterationRecord(step, iteration.start, iteration.stage, iteration.index,
                                     float(iteration.chi2)))
        final_poses = iteration.poses
        if on_iteration is not None:
            on_iteration(iteration)
        step_started = time.perf_counter()
    final = np.array(final_poses, dtype=np.float64)
    if on_final is not None and final_poses is not None:
        on_final(final)
    recorder.flush()
    for sink in sinks:
        sink.flush()
    return RecordedOptimization(tuple(trace), final, optimization.result, optimize_time)


def _optimize_and_record(
    graph_file: GraphFile,
    rrd_path: Path,
    method: str,
    iterations: int | None,
    progress: ProgressCallback | None,
    robust: str | None = None,
) -> RecordedOptimization:
    """Run the optimizer and log every iteration to a recording saved at `rrd_path`."""
    graph = graph_file.graph
    stream = recording.create_recording(rrd_path, name=graph_file.path.stem)
    try:
        recording.log_run_properties(stream, {
            "input": str(graph_file.path),
            "format": graph_file.format,
            "method": method,
            "poses": graph.num_poses,
            "constraints": graph.num_edges,
        })
        recorder = optimization_recorder(stream, graph, graph.poses, still_fraction=recording.STILL_FRACTION)
        run = record_optimization(optimize(graph, method=method, iterations=iterations, robust=robust),
                                  recorder, on_iteration=progress)
        # The default view frames the final graph (the starting estimate may sprawl far beyond it).
        bounds = recording.world_bounds(run.final_poses)
        recording.send_blueprint(stream, recording.default_blueprint(bounds=bounds))
    finally:
        recording.close_recording(stream)
    return run


def summary(result: GraphReplayResult) -> dict[str, Any]:
    """The machine-readable summary written to `<stem>.json`."""
    graph = result.graph
    return {
        "schema": SUMMARY_SCHEMA,
        "input": str(result.input_path),
        "input_format": result.input_format,
        "method": result.method,
        "poses": graph.num_poses,
        "constraints": graph.num_edges,
        "loop_closures": result.num_loop_closures,
        "skipped_lines": dict(result.skipped),
        "repaired_information_lines": list(result.repaired_lines),
        "initialised_from_odometry": result.initialised_from_odometry,
        "iterations": result.iterations_per_stage,
        "chi2_initial": result.initial_chi2,
        "chi2_final": result.final_chi2,
        **optimization_summary(result.optimization),
        "chi2_per_iteration": [dataclasses.asdict(record) for record in result.iterations],
        "wall_time_s": dict(result.wall_time),
        "optimize_time_s": dict(result.optimize_time),
        "outputs": {kind: str(path) for kind, path in result.outputs.paths().items()},
    }

