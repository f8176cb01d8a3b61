"""End-to-end tests of `replay` on pose-graph files: every method, the outputs, the recording, bad input."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from numpy.typing import NDArray
from typer.testing import CliRunner

from optimizer.cost import chi2
from optimizer.errors import GraphError
from optimizer.graph_files import read_graph
from optimizer.solve import METHODS, optimize
from pipeline import recording
from pipeline.cli import DEFAULT_COMMAND, ReplayGroup, app
from pipeline.replay_graph import replay_graph
from tests.pipeline_fixtures import LOOP_POSES, loop_graph_text, read_recording, write_loop_graph

REPO = Path(__file__).resolve().parents[1]

# ----------------------------------------------------------------------------------------------- helpers

def strip_points(value: object) -> NDArray[np.float64]:
    """The points of the single line strip in one LineStrips2D row, as an (n, 2) array."""
    strips = list(value)  # type: ignore[call-overload]
    assert len(strips) == 1
    return np.asarray(strips[0], dtype=np.float64)


def run_replay(*args: str) -> object:
    return CliRunner().invoke(app, [str(arg) for arg in args])


def output_names(directory: Path) -> set[str]:
    return {path.name for path in directory.iterdir()} if directory.exists() else set()


EXPECTED_STAGES = {
    "sgd": ["sgd"],
    "sgd+gn": ["sgd", "sgd-tree", "gauss-newton"],
    "sgd-tree": ["sgd-tree"],
    "sgd-tree+gn": ["sgd-tree", "gauss-newton"],
    "gn": ["gauss-newton"],
    "gauss-seidel": ["gauss-seidel"],
}
"""The stages of the run from the file's estimate (the default also polishes a chordal start after it)."""

# ------------------------------------------------------------------------------------------------- tests


def test_every_method_is_covered() -> None:
    assert set(EXPECTED_STAGES) == set(METHODS)


@pytest.mark.parametrize("method", sorted(EXPECTED_STAGES))
def test_replay_writes_graph_summary_and_recording(tmp_path: Path, method: str) -> None:
    graph_path = write_loop_graph(tmp_path / "loop.g2o")
    out = tmp_path / "out"
    sweeps = 15
    converges = method.endswith("gn")  # the others run a fixed number of iterations
    result = run_replay(graph_path, "--out", out, "--method", method, "--iterations", sweeps, "--quiet")
    assert result.exit_code == (0 if converges else 3), result.output
    if converges:
        assert result.output == ""  # --quiet
    else:
        assert result.stderr.startswith(f"replay: not converged: {graph_path}: {sweeps} iterations")
        assert len(result.stderr.splitlines()) == 1
    assert output_names(out) == {"loop.g2o", "loop.json", "loop.rrd"}

    # The .g2o: the input's constraints around new poses, which the summary's final χ² describes.
    original = read_graph(graph_path).graph
    written = read_graph(out / "loop.g2o").graph
    np.testing.assert_array_equal(written.vertex_ids, original.vertex_ids)
    np.testing.assert_array_equal(written.edge_from, original.edge_from)
    np.testing.assert_array_equal(written.edge_to, original.edge_to)
    np.testing.assert_array_equal(written.measurements, original.measurements)
    np.testing.assert_array_equal(written.information, original.information)
    assert not np.allclose(written.poses, original.poses)

    summary = json.loads((out / "loop.json").read_text())
    trace = summary["chi2_per_iteration"]
    assert summary["method"] == method
    assert summary["converged"] is converges
    counts = (summary["poses"], summary["constraints"], summary["loop_closures"])
    assert counts == (LOOP_POSES, LOOP_POSES + 1, 2)
    assert trace[0] == {"step": 0, "start": "estimate", "stage": "initial", "index": 0,
                        "chi2": pytest.approx(chi2(original))}
    assert [row["step"] for row in trace] == list(range(len(trace)))
    # (the closing "selected" row repeats whichever candidate won)
    from_estimate = [row for row in trace[1:] if row["start"] == "estimate" and row["stage"] != "selected"]
    stages = [row["stage"] for row in from_estimate]
    assert list(dict.fromkeys(stages)) == EXPECTED_STAGES[method]
    for stage in EXPECTED_STAGES[method]:
        indices = [row["index"] for row in from_estimate if row["stage"] == stage]
        assert indices == list(range(1, len(indices) + 1))
    if method != "gn" and not method.startswith("sgd-tree"):
        assert summary["iterations"][EXPECTED_STAGES[method][0]] == sweeps
    if method == "sgd+gn":  # the chordal start, polished directly, and the winner repeated last
        starts = list(dict.fromkeys(row["start"] for row in trace))
        assert starts[:2] == ["estimate", "chordal"]
        assert [row["stage"] for row in trace if row["start"] == "chordal"][:2] == ["initial", "gauss-newton"]
        assert trace[-1]["stage"] == "selected" and trace[-1]["start"] == summary["start"]
    assert summary["chi2_final"] == trace[-1]["chi2"]
    assert summary["chi2_final"] == pytest.approx(chi2(written), rel=1e-9)
    assert summary["chi2_final"] < 0.1 * summary["chi2_initial"]
    assert set(summary["wall_time_s"]) == {"load", "optimize", "record", "write", "total"}
    assert all(seconds >= 0 for seconds in summary["wall_time_s"].values())
    assert set(summary["optimize_time_s"]) >= {"initial", *EXPECTED_STAGES[method]}
    assert summary["outputs"] == {kind: str(out / f"loop.{kind}") for kind in ("g2o", "json", "rrd")}

    # The recording: one row per iteration the optimizer yields (counted here by running it again).
    yielded = list(optimize(original, method=method, iterations=sweeps))
    assert len(yielded) == len(trace)
    entities = read_recording(out / "loop.rrd")
    assert entities["/" + recording.CHI2_ENTITY].steps == list(range(len(yielded)))
    # Geometry only where some pose moved more than a thousandth of the map's extent since the last drawn
    # row (a pixel of the view), and always the first and the last iteration.
    drawn, last = [], None
    for step, iteration in enumerate(yielded):
        xy = iteration.poses[:, :2]
        if (last is None or step == len(yielded) - 1
                or np.abs(xy - last).max() > 1e-3 * np.ptp(xy, axis=0).max()):
            drawn.append(step)
            last = xy
    for path in (recording.TRAJECTORY_ENTITY, recording.LOOP_CLOSURES_ENTITY, recording.CHI2_ENTITY):
        assert entities["/" + path].timelines == {"iteration"}, path
        if path != recording.CHI2_ENTITY:
            assert entities["/" + path].steps == drawn, path
    stages = entities["/" + recording.STAGE_ENTITY]  # repeats of a converged stage are left out
    assert stages.timelines == {"iteration"} and stages.steps[0] == 0
    assert set(stages.steps) <= set(range(len(yielded)))

    trajectories = entities["/world/trajectory"].columns["LineStrips2D:strips"]
    for row, step in zip(trajectories, drawn, strict=True):
        np.testing.assert_allclose(strip_points(row), yielded[step].poses[:, :2], atol=1e-5)
    np.testing.assert_allclose(strip_points(trajectories[-1]), written.poses[:, :2], atol=1e-5)
    initial = entities["/world/initial_trajectory"]
    assert initial.static_rows == 1
    np.testing.assert_allclose(strip_points(initial.static_columns["LineStrips2D:strips"][0]),
                               original.poses[:, :2], atol=1e-5)

    closures = entities["/world/loop_closures"].columns["LineStrips2D:strips"][-1]
    final = written.poses[:, :2]
    expected_segments = {(LOOP_POSES - 1, 0), (LOOP_POSES // 3, 2 * LOOP_POSES // 3)}  # as stored
    assert len(closures) == len(expected_segments)
    for a, b in expected_segments:
        assert any(np.allclose(segment, [final[a], final[b]], atol=1e-5) for segment in closures)

    scalars = [value[0] for value in entities["/optimizer/chi2"].columns["Scalars:scalars"]]
    np.testing.assert_allclose(scalars, [row["chi2"] for row in trace], rtol=1e-12)
    texts = entities["/optimizer/stage"].columns["TextLog:text"]
    labels = [f"{row['stage']} {row['index']}" if row["start"] == "estimate" else
              f"{row['start']}: {row['stage']} {row['index']}" for row in trace]
    assert [text[0].rsplit(":", 1)[0] for text in texts] == [labels[step] for step in stages.steps]

    rerun_cli = shutil.which("rerun")
    if rerun_cli is not None:  # installed with rerun-sdk
        check = subprocess.run([rerun_cli, "rrd", "verify", str(out / "loop.rrd")], capture_output=True,
                               text=True, timeout=60, stdin=subprocess.DEVNULL)
        assert check.returncode == 0, check.stdout + check.stderr


def test_toro_input_writes_g2o_named_after_the_input(tmp_path: Path) -> None:
    # The same loop as TORO: information order xx xy yy θθ xθ yθ; the output is g2o all the same.
    toro_lines = []
    for line in loop_graph_text().splitlines():
        tag, *values = line.split()
        if tag == "VERTEX_SE2":
            toro_lines.append(" ".join(["VERTEX2", *values]))
        else:
            xx, xy, xt, yy, yt, tt = values[5:]
            toro_lines.append(" ".join(["EDGE2", *values[:5], xx, xy, yy, tt, xt, yt]))
    graph_path = tmp_path / "loop.graph"
    graph_path.write_text("\n".join(toro_lines) + "\n")
    result = run_replay(graph_path, "--out", tmp_path / "out", "--method", "gn", "--quiet")
    assert result.exit_code == 0, result.output
    assert output_names(tmp_path / "out") == {"loop.g2o", "loop.json", "loop.rrd"}
    assert read_graph(tmp_path / "out" / "loop.g2o").format == "g2o"
    summary = json.loads((tmp_path / "out" / "loop.json").read_text())
    assert summary["input_format"] == "toro"


def test_replay_without_input_uses_the_bundled_sample_log(tmp_path: Path) -> None:
    out = tmp_path / "recordings"
    result = run_replay("--out", out)
    assert result.exit_code == 0, result.output
    names = {"csail_sample.tum", "csail_sample.g2o", "csail_sample.json", "csail_sample.rrd",
             "csail_sample_map.png", "csail_sample_map.pgm", "csail_sample_map.yaml", "csail_sample.session"}
    assert output_names(out) == names
    summary = json.loads((out / "csail_sample.json").read_text())
    assert Path(summary["input"]).name == "csail_sample.mcap"
    assert summary["counts"]["scans"] == 1000
    assert summary["loop_closures"]["accepted"] > 0
    # the summary at the end (not --quiet) names the χ² change and every output
    assert "chi2" in result.stderr
    for name in names:
        assert str(out / name) in result.stderr


def test_help_shows_usage_methods_and_examples() -> None:
    result = run_replay("--help")
    assert result.exit_code == 0
    assert "Usage: replay [OPTIONS] [INPUT]" in result.output
    for method in METHODS:
        assert method in result.output
    assert "Examples:" in result.output
    assert "rerun-sdk 0.41" in result.output


BAD_INPUTS = {
    "malformed line": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0\n", ":3: "),
    "not a number": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 x 0 0\n", ":2: "),
    "empty file": ("", ": "),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path: Path, case: str) -> None:
    text, where = BAD_INPUTS[case]
    graph_path = tmp_path / "bad.g2o"
    graph_path.write_text(text)
    out = tmp_path / "out"
    result = run_replay(graph_path, "--out", out)
    assert result.exit_code == 2
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"replay: error: {graph_path}{where}")
    assert not out.exists()


def test_missing_file_exits_2(tmp_path: Path) -> None:
    result = run_replay(tmp_path / "nowhere.g2o", "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [f"replay: error: {tmp_path / 'nowhere.g2o'}: no such file"]
    assert not (tmp_path / "out").exists()


def test_failed_run_does_not_clobber_previous_outputs(tmp_path: Path) -> None:
    out = tmp_path / "out"
    good = write_loop_graph(tmp_path / "loop.g2o")
    assert run_replay(good, "--out", out, "--quiet").exit_code == 0
    before = {name: (out / name).read_bytes() for name in output_names(out)}

    (tmp_path / "bad").mkdir()
    bad = tmp_path / "bad" / "loop.g2o"  # same stem, so the same output names
    bad.write_text(loop_graph_text().replace("EDGE_SE2 3 4", "EDGE_SE2 3 4 oops", 1))
    result = run_replay(bad, "--out", out)
    assert result.exit_code == 2
    assert f"{bad}:" in result.stderr
    assert {name: (out / name).read_bytes() for name in output_names(out)} == before


@pytest.mark.parametrize("reached", ["same path", "hard link"])
def test_a_graph_replayed_into_its_own_folder_is_refused_and_left_as_it_was(tmp_path: Path,
                                                                           reached: str) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    original = graph.read_bytes()
    given = graph
    if reached == "hard link":  # another name for the same file: its output would still replace it
        (tmp_path / "elsewhere").mkdir()
        given = tmp_path / "elsewhere" / "loop.g2o"
        os.link(graph, given)
    result = run_replay(given, "--out", graph.parent)
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"replay: error: {graph}: is an input of this replay, and its output of the same name would replace "
        "it; write the outputs into another folder (--out)"]
    assert graph.read_bytes() == original
    assert sorted(path.name for path in graph.parent.iterdir()) == sorted(
        ["loop.g2o"] + ["elsewhere"] * (reached == "hard link"))  # no outputs, no lock or staging left
    # Into another folder the same graph replays, and its input stays as it was.
    assert run_replay(given, "--out", tmp_path / "out", "--quiet").exit_code == 0
    assert graph.read_bytes() == original


class _StoppedError(GraphError):
    pass


@pytest.mark.parametrize("failure", [_StoppedError, KeyboardInterrupt])
def test_failure_during_optimization_leaves_no_partial_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                             failure: type[BaseException]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "loop.json").write_text("previous run\n")
    graph_path = write_loop_graph(tmp_path / "loop.g2o")

    def failing_optimize(graph, method, iterations, **options):  # type: ignore[no-untyped-def]
        yielded = iter(optimize(graph, method=method, iterations=iterations, **options))
        for _ in range(3):
            yield next(yielded)
        raise failure("stopped")

    monkeypatch.setattr("pipeline.replay_graph.optimize", failing_optimize)
    with pytest.raises(failure):
        replay_graph(graph_path, out_dir=out, method="sgd")
    assert output_names(out) == {"loop.json"}
    assert (out / "loop.json").read_text() == "previous run\n"


def test_failure_removes_an_output_folder_it_created(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def failing_optimize(graph, method, iterations, **options):  # type: ignore[no-untyped-def]
        raise GraphError("stopped")
        yield  # a generator, like the real one

    monkeypatch.setattr("pipeline.replay_graph.optimize", failing_optimize)
    with pytest.raises(GraphError):
        replay_graph(write_loop_graph(tmp_path / "loop.g2o"), out_dir=tmp_path / "new" / "out", method="sgd")
    assert not (tmp_path / "new" / "out").exists()


def test_library_result_and_progress(tmp_path: Path) -> None:
    seen: list[tuple[str, int]] = []
    result = replay_graph(write_loop_graph(tmp_path / "loop.g2o"), out_dir=tmp_path / "out", method="sgd+gn",
                          iterations=5, progress=lambda it: seen.append((it.stage, it.index)))
    assert seen == [(record.stage, record.index) for record in result.iterations]
    assert seen[:2] == [("initial", 0), ("sgd", 1)]
    assert result.iterations_per_stage["sgd"] == 5
    assert result.final_chi2 == pytest.approx(chi2(result.graph, result.poses), rel=1e-9)
    assert result.final_chi2 < result.initial_chi2
    assert result.outputs.rrd == tmp_path / "out" / "loop.rrd"


def test_iteration_recorder_sends_batches_on_one_timeline(tmp_path: Path) -> None:
    # A tiny batch size forces a column batch every two iterations; the timeline must stay continuous.
    graph = read_graph(write_loop_graph(tmp_path / "loop.g2o")).graph
    iterations = list(optimize(graph, method="sgd", iterations=6))
    path = tmp_path / "batched.rrd"
    stream = recording.create_recording(path, name="batched")
    loops = ~graph.is_odometry
    recorder = recording.IterationRecorder(stream, graph.edge_from[loops], graph.edge_to[loops],
                                           batch_bytes=2 * LOOP_POSES * 8)
    steps = [recorder.add(iteration) for iteration in iterations]
    recorder.flush()
    recording.close_recording(stream)
    assert steps == list(range(len(iterations)))
    trajectory = read_recording(path)["/world/trajectory"]
    assert trajectory.steps == steps
    for iteration, row in zip(iterations, trajectory.columns["LineStrips2D:strips"], strict=True):
        np.testing.assert_allclose(strip_points(row), iteration.poses[:, :2], atol=1e-5)


def test_iteration_recorder_thins_huge_graphs_except_the_final_iteration(tmp_path: Path) -> None:
    # With room for 7 points per iteration, the 30-pose loop is drawn through poses 0, 5, …, 25 and the
    # last (stride ceil(29 / 6) = 5); room for 2 points keeps one of the two loop closures.
    graph = read_graph(write_loop_graph(tmp_path / "loop.g2o")).graph
    iterations = list(optimize(graph, method="sgd", iterations=4))
    loops = ~graph.is_odometry
    shown = [0, 5, 10, 15, 20, 25, LOOP_POSES - 1]
    for max_points, loops_shown in ((7, 2), (2, 1)):
        path = tmp_path / f"thinned{max_points}.rrd"
        stream = recording.create_recording(path, name="thinned")
        recorder = recording.IterationRecorder(stream, graph.edge_from[loops], graph.edge_to[loops],
                                               batch_bytes=200, max_points=max_points)
        for iteration in iterations:
            recorder.add(iteration)
        recorder.flush()
        recording.close_recording(stream)
        content = read_recording(path)
        trajectory = content["/world/trajectory"]
        closures = content["/world/loop_closures"]
        assert trajectory.steps == closures.steps == list(range(len(iterations)))
        rows = trajectory.columns["LineStrips2D:strips"]
        for iteration, row, segments in zip(iterations, rows, closures.columns["LineStrips2D:strips"],
                                            strict=True):
            final = iteration is iterations[-1]
            expected = iteration.poses[:, :2] if final else iteration.poses[shown if max_points == 7 else
                                                                            [0, LOOP_POSES - 1], :2]
            np.testing.assert_allclose(strip_points(row), expected, atol=1e-5)
            assert len(list(segments)) == (int(loops.sum()) if final else loops_shown)


def test_module_entry_point_reports_errors_without_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1\n")
    command = [sys.executable, "-m", "pipeline.cli", str(bad), "--out", str(tmp_path / "out")]
    completed = subprocess.run(command, capture_output=True, text=True, cwd=REPO, timeout=120,
                               stdin=subprocess.DEVNULL)
    assert completed.returncode == 2
    assert completed.stdout == ""
    assert completed.stderr.splitlines() == [completed.stderr.strip()]
    assert completed.stderr.startswith(f"replay: error: {bad}:2: ")
    assert "Traceback" not in completed.stderr
    assert not (tmp_path / "out").exists()


def test_singular_information_is_rejected_unless_repair_is_asked(tmp_path: Path) -> None:
    lines = loop_graph_text().splitlines()
    # the first edge (file line LOOP_POSES + 1) loses its θθ information: singular, not positive definite
    fields = lines[LOOP_POSES].split()
    lines[LOOP_POSES] = " ".join([*fields[:-1], "0"])
    graph_path = tmp_path / "singular.g2o"
    graph_path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"

    rejected = run_replay(graph_path, "--out", out, "--quiet")
    assert rejected.exit_code == 2
    assert rejected.stderr.startswith(f"replay: error: {graph_path}:{LOOP_POSES + 1}: ")
    assert not out.exists()

    repaired = run_replay(graph_path, "--out", out, "--quiet", "--repair-information", "--method", "gn")
    assert repaired.exit_code == 0, repaired.output
    summary = json.loads((out / "singular.json").read_text())
    assert summary["repaired_information_lines"] == [LOOP_POSES + 1]


def test_replay_group_routes_to_subcommands_and_defaults_to_run() -> None:
    # How the pipeline issue will grow the command: subcommands beside the default `run`.
    calls: list[tuple[str, object]] = []
    grown = typer.Typer(cls=ReplayGroup)

    @grown.callback()
    def _root() -> None:
        pass

    @grown.command(DEFAULT_COMMAND)
    def _run(graph: str | None = typer.Argument(None), quiet: bool = False) -> None:
        calls.append(("run", (graph, quiet)))

    @grown.command("info")
    def _info(log: str) -> None:
        calls.append(("info", log))

    runner = CliRunner()
    for args in (["a.g2o", "--quiet"], [], ["info", "b.mcap"], ["run", "c.g2o"]):
        assert runner.invoke(grown, args).exit_code == 0, args
    assert calls == [("run", ("a.g2o", True)), ("run", (None, False)), ("info", "b.mcap"),
                     ("run", ("c.g2o", False))]


@pytest.mark.parametrize(("options", "expected"), [((), None), (("--iterations", "7"), 7)])
def test_the_command_leaves_the_iterations_to_the_optimizer_unless_given(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, options: tuple[str, ...],
        expected: int | None) -> None:
    # None lets the default method hand a large graph's SGD over to the polish once it stalls
    # (optimizer.solve.until_stalled): a count passed down would be run to its end.
    import pipeline.replay_graph as module
    from pipeline.errors import PipelineError

    asked: dict[str, object] = {}

    def replay_graph_stand_in(path: Path, **options: object) -> None:
        asked.update(options)
        raise PipelineError("stand-in: stop here")

    monkeypatch.setattr(module, "replay_graph", replay_graph_stand_in)
    graph = write_loop_graph(tmp_path / "loop.g2o")
    result = run_replay(str(graph), "--out", str(tmp_path / "out"), *options)
    assert result.exit_code == 2 and "stand-in" in result.output
    assert asked["iterations"] == expected


def test_rerun_disabled_by_the_environment_is_a_clear_error_not_a_silent_empty_recording(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # RERUN=off makes the SDK drop every log call (and fail on the blueprint with a traceback).
    monkeypatch.setenv("RERUN", "off")
    graph = write_loop_graph(tmp_path / "loop.g2o")
    result = run_replay(str(graph), "--out", str(tmp_path / "out"))
    assert result.exit_code == 2
    assert "Rerun logging is disabled by the environment (RERUN=off)" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "out").exists()  # a folder this run created is removed again
