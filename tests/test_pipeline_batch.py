"""Several inputs: a process pool, one failing input not stopping the others, the summary table, --json."""

from __future__ import annotations

import json
import socket
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline import api
from pipeline.batch import run_batch, run_one
from pipeline.batch_inputs import batch_inputs
from pipeline.batch_summary import BATCH_SUMMARY_NAME
from pipeline.cli import _with_ray_address, app
from pipeline.config import ReplayConfig
from pipeline.errors import PipelineError
from tests.pipeline_fixtures import BROKEN_GRAPH, LOOP_POSES, write_drive, write_loop_graph

DRIVE_SCANS = 10
def run_replay(*args: object) -> object:
    return CliRunner().invoke(app, [str(arg) for arg in args])


@pytest.fixture
def three_inputs(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A log, a pose graph and a broken pose graph (line 3)."""
    log = tmp_path / "drive.mcap"
    write_drive(log, scans=DRIVE_SCANS)
    graph = write_loop_graph(tmp_path / "loop.g2o")
    broken = tmp_path / "broken.g2o"
    broken.write_text(BROKEN_GRAPH)
    return log, broken, graph


def test_parallel_jobs_keep_going_past_a_failure(
    tmp_path: Path, three_inputs: tuple[Path, Path, Path]
) -> None:
    log, broken, graph = three_inputs
    out = tmp_path / "out"
    result = run_replay(log, broken, graph, "--jobs", 2, "--out", out, "--json", "--method", "sgd",
                        "--iterations", 3)
    assert result.exit_code == 2, result.output

    # the other two wrote their outputs, the broken one nothing
    names = {path.name for path in out.iterdir()}
    assert {"drive.tum", "drive.g2o", "drive.json", "drive.rrd", "loop.g2o", "loop.json", "loop.rrd"} <= names
    assert not any(name.startswith("broken") for name in names)

    # --json: a list in input order with the counts, and the failure with its one-line reason
    entries = json.loads(result.stdout)
    assert [(Path(entry["input"]), entry["ok"]) for entry in entries] == [(log, True), (broken, False),
                                                                          (graph, True)]
    assert entries[0]["counts"]["scans"] == DRIVE_SCANS
    assert entries[0]["counts"]["keyframes"] >= 2
    graph_entry = entries[2]
    counts = (graph_entry["poses"], graph_entry["constraints"], graph_entry["loop_closures"])
    assert counts == (LOOP_POSES, LOOP_POSES + 1, 2)
    assert graph_entry["iterations"] == {"sgd": 3}
    assert entries[1]["error"].startswith(f"{broken}:3: ")
    assert json.loads((out / "loop.json").read_text())["poses"] == LOOP_POSES

    # the summary table on stderr lists every input and the failure, then the error line
    assert "3 inputs, 2 done, 1 failed" in result.stderr
    for path in (log, broken, graph):
        assert str(path) in result.stderr
    assert "FAILED" in result.stderr
    assert result.stderr.rstrip().splitlines()[-1] == f"replay: error: {entries[1]['error']}"
    assert {entry["host"] for entry in entries} == {socket.gethostname()}

    # the same rows, queryable afterwards: batch_summary.parquet in the output folder
    import pyarrow.parquet as pq

    rows = pq.read_table(out / BATCH_SUMMARY_NAME).to_pylist()
    assert [(row["input"], row["kind"], row["status"]) for row in rows] == [
        (str(log), "log", "ok"), (str(broken), "graph", "failed"), (str(graph), "graph", "ok")]
    assert rows[0]["scans"] == DRIVE_SCANS and rows[0]["poses"] == entries[0]["counts"]["keyframes"]
    assert (rows[2]["poses"], rows[2]["constraints"], rows[2]["loop_closures"]) == counts
    assert dict(rows[2]["iterations"]) == {"sgd": 3}
    assert rows[2]["chi2_final"] == graph_entry["chi2_final"] <= rows[2]["chi2_initial"]
    assert rows[2]["time_total_s"] == dict(rows[2]["wall_time_s"])["total"] > 0
    # sgd alone runs a fixed number of iterations: the table says it did not converge, as the JSON does
    assert rows[2]["converged"] is graph_entry["converged"] is False
    assert rows[2]["stop_reason"] == graph_entry["stop_reason"]
    assert rows[1]["error"] == entries[1]["error"]
    assert rows[1]["poses"] is None and rows[1]["wall_time_s"] is None
    assert {row["host"] for row in rows} == {socket.gethostname()}


def test_sequential_inputs_keep_going_and_quiet_keeps_only_the_error(
    tmp_path: Path, three_inputs: tuple[Path, Path, Path]
) -> None:
    _, broken, graph = three_inputs
    out = tmp_path / "out"
    result = run_replay(broken, graph, "--out", out, "--quiet", "--method", "gn")
    assert result.exit_code == 2
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"replay: error: {broken}:3: ")
    assert (out / "loop.rrd").is_file()


def test_all_good_inputs_exit_0(tmp_path: Path) -> None:
    first = write_loop_graph(tmp_path / "a.g2o")
    second = write_loop_graph(tmp_path / "b.g2o")
    result = run_replay(first, second, "--out", tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert "2 inputs, 2 done, 0 failed" in result.stderr


def test_inputs_with_the_same_stem_are_refused_before_running(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = write_loop_graph(tmp_path / "a" / "loop.g2o")
    second = write_loop_graph(tmp_path / "b" / "loop.g2o")
    result = run_replay(first, second, "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert len(result.stderr.splitlines()) == 1
    assert str(first) in result.stderr and str(second) in result.stderr
    assert not (tmp_path / "out").exists()
    with pytest.raises(PipelineError, match="same outputs"):
        run_batch([first, second], out_dir=tmp_path / "out")
    # The same file twice: not "replay them into different folders"
    with pytest.raises(PipelineError, match=r"is listed twice .*: name each input once"):
        run_batch([first, tmp_path / "a" / ".." / "a" / "loop.g2o"], out_dir=tmp_path / "out")


def test_a_bug_in_one_input_is_reported_with_its_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    good = write_loop_graph(tmp_path / "good.g2o")
    buggy = write_loop_graph(tmp_path / "buggy.g2o")
    real_replay = api.replay

    def replay_with_a_bug(path, *args, **kwargs):  # type: ignore[no-untyped-def]
        if Path(path).name == "buggy.g2o":
            raise ZeroDivisionError("a bug")
        return real_replay(path, *args, **kwargs)

    monkeypatch.setattr("pipeline.batch.replay", replay_with_a_bug)
    outcomes = run_batch([buggy, good], ReplayConfig(optimizer={"method": "gn"}), out_dir=tmp_path / "out")
    assert [outcome.ok for outcome in outcomes] == [False, True]
    assert outcomes[0].error == "internal error: ZeroDivisionError: a bug"
    assert outcomes[0].traceback is not None and "ZeroDivisionError" in outcomes[0].traceback

    # alone on the command line, a bug keeps its traceback (it is not turned into an input error)
    with pytest.raises(ZeroDivisionError):
        run_one(buggy, out_dir=tmp_path / "out", catch_unexpected=False)
    result = run_replay(buggy, good, "--out", tmp_path / "cli", "--quiet", "--method", "gn")
    assert result.exit_code == 2
    assert "Traceback" in result.stderr
    assert "replay: error: internal error: ZeroDivisionError" in result.stderr


def test_json_for_one_input_is_one_object(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    result = run_replay(graph, "--out", tmp_path / "out", "--json", "--quiet", "--method", "gn")
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    entry = json.loads(result.stdout)
    assert (entry["ok"], entry["kind"], entry["poses"], entry["method"]) == (True, "graph", LOOP_POSES, "gn")
    assert entry == {"ok": True, "kind": "graph", **json.loads((tmp_path / "out" / "loop.json").read_text())}


def test_inputs_from_a_list_or_a_folder(tmp_path: Path) -> None:
    listing = tmp_path / "inputs.txt"
    listing.write_text("# tonight\n/data/a.mcap\n\n  relative/b.g2o  \n#/data/skipped.bag\n")
    assert batch_inputs(listing) == [Path("/data/a.mcap"), Path("relative/b.g2o")]

    fleet = tmp_path / "fleet"
    for name in ("robot2/run.bag", "robot1/run.MCAP", "robot1/loop.g2o", "robot1/notes.txt",
                 "robot1/.run.1a2b3c4d.partial.g2o", ".hidden/x.mcap", "results/run.g2o",
                 "robot3/ros2/metadata.yaml", "robot3/ros2/ros2_0.db3"):
        (fleet / name).parent.mkdir(parents=True, exist_ok=True)
        (fleet / name).write_text("")
    found = batch_inputs(fleet, exclude=fleet / "results")
    assert found == [fleet / "robot1/loop.g2o", fleet / "robot1/run.MCAP", fleet / "robot2/run.bag",
                     fleet / "robot3/ros2"]
    assert batch_inputs(fleet / "robot3" / "ros2") == [fleet / "robot3" / "ros2"]

    with pytest.raises(PipelineError, match="cannot read the input list"):
        batch_inputs(tmp_path / "missing.txt")


def test_input_lists_and_folders_as_users_have_them(tmp_path: Path) -> None:
    # A list saved with a byte-order mark (Windows editors): the first name is not '\ufeff/data/a.mcap'.
    listing = tmp_path / "inputs.txt"
    listing.write_bytes("\ufeff/data/a.mcap\n".encode())
    assert batch_inputs(listing) == [Path("/data/a.mcap")]
    # A pose graph given as the list (its 440 lines were 440 missing inputs).
    graph = write_loop_graph(tmp_path / "loop.graph")
    with pytest.raises(PipelineError, match="a log or pose graph, not a list of inputs"):
        batch_inputs(graph)
    # A folder symlinked into the searched one is searched (once, a link back up is not followed).
    fleet, elsewhere = tmp_path / "fleet", tmp_path / "elsewhere"
    (fleet / "robot1").mkdir(parents=True)
    elsewhere.mkdir()
    (fleet / "robot1" / "a.mcap").write_text("")
    (elsewhere / "b.mcap").write_text("")
    (fleet / "robot2").symlink_to(elsewhere)
    (elsewhere / "up").symlink_to(fleet)
    assert batch_inputs(fleet) == [fleet / "robot1" / "a.mcap", fleet / "robot2" / "b.mcap"]
    # The searched folder is the output folder too: a replay's own graphs (a summary beside) are results.
    (fleet / "robot1" / "a.g2o").write_text("")
    (fleet / "robot1" / "a.json").write_text("{}")
    (fleet / "robot1" / "c.g2o").write_text("")
    assert batch_inputs(fleet / "robot1", exclude=fleet / "robot1") == [fleet / "robot1" / "a.mcap",
                                                                          fleet / "robot1" / "c.g2o"]


def test_command_reads_inputs_from_a_folder_and_refuses_an_empty_one(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    write_loop_graph(fleet / "loop.g2o")
    out = fleet / "out"  # inside the searched folder: its results are not inputs
    out.mkdir()
    (out / "old.g2o").write_text(BROKEN_GRAPH)
    result = run_replay("--inputs", fleet, "--out", out, "--method", "sgd", "--iterations", 1, "--json",
                        "--allow-unconverged")
    assert result.exit_code == 0, result.output
    entry = json.loads(result.stdout)  # one input: one object
    assert (entry["input"], entry["host"]) == (str(fleet / "loop.g2o"), socket.gethostname())
    assert (out / BATCH_SUMMARY_NAME).is_file()

    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing tonight\n")
    result = run_replay("--inputs", empty, "--out", tmp_path / "out2")
    assert result.exit_code == 2
    assert result.stderr == f"replay: error: {empty}: the list names no input\n"


def test_ray_takes_an_optional_address() -> None:
    assert _with_ray_address(["run", "--ray", "a.mcap"]) == ["run", "--ray=local", "a.mcap"]
    assert _with_ray_address(["run", "a.mcap", "--ray"]) == ["run", "a.mcap", "--ray=local"]
    assert _with_ray_address(["run", "--ray", "--jobs", "2"]) == ["run", "--ray=local", "--jobs", "2"]
    assert _with_ray_address(["run", "--ray", "auto", "a.mcap"]) == ["run", "--ray=auto", "a.mcap"]
    assert _with_ray_address(["run", "--ray", "head.lan:6379"]) == ["run", "--ray=head.lan:6379"]
    assert _with_ray_address(["run", "--ray", "ray://10.0.0.2:10001"]) == ["run", "--ray=ray://10.0.0.2:10001"]
    assert _with_ray_address(["run", "--ray=auto"]) == ["run", "--ray=auto"]
    assert _with_ray_address(["run", "--", "--ray"]) == ["run", "--", "--ray"]


def test_ray_options_need_ray(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    result = run_replay(graph, "--retries", 2, "--out", tmp_path / "out")
    assert result.exit_code == 2 and "--retries" in result.stderr and "--ray" in result.stderr
    result = run_replay(graph, "--ray", "--jobs", 2, "--out", tmp_path / "out")
    assert result.exit_code == 2 and "choose one" in result.stderr

    monkeypatch.setitem(sys.modules, "ray", None)  # as if the ray extra were not installed
    result = run_replay(graph, "--ray", "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.startswith("replay: error: running on Ray needs the ray package: pip install")
    assert not (tmp_path / "out").exists()


KILLED_MID_WRITE = """
import os, sys
from pathlib import Path
from pipeline.outputs import staged_outputs
from tests.pipeline_fixtures import BROKEN_GRAPH
folder = Path(sys.argv[1])
with staged_outputs(folder / f"{sys.argv[2]}.g2o", folder / f"{sys.argv[2]}.json") as temporaries:
    for temporary in temporaries:
        temporary.write_text("half")
    os._exit(1)  # as a worker killed mid-write: nothing of staged_outputs' cleanup runs
"""


def test_what_killed_replays_left_is_cleaned_up_for_the_batch_stems_only(tmp_path: Path) -> None:
    import subprocess

    from pipeline.ray_batch import remove_partial_outputs

    for stem in ("run", "run.x", "other"):
        subprocess.run([sys.executable, "-c", KILLED_MID_WRITE, str(tmp_path), stem], check=False,
                       cwd=Path(__file__).resolve().parents[1])
    (tmp_path / "run.g2o").write_text("a finished output")
    left = sorted(path.name for path in tmp_path.iterdir() if path.name.startswith("."))
    assert len(left) >= 3 and any(".other" in name for name in left)

    assert remove_partial_outputs(tmp_path, {"run", "run.x"}) == ["run", "run.x"]
    remaining = sorted(path.name for path in tmp_path.iterdir())
    assert "run.g2o" in remaining and (tmp_path / "run.g2o").read_text() == "a finished output"
    hidden = [name for name in remaining if name.startswith(".")]
    assert hidden and all(name.startswith(".other") for name in hidden)


def test_a_stopped_pool_cleans_up_after_workers_that_exited_on_their_own(tmp_path: Path) -> None:
    """A worker that died mid-write without being killed here (the OS's OOM killer, or a clean-up cut
    short) left its staging folder and lock: stopping the pool removes them, not only the killed ones'."""
    from pipeline import batch

    class StoppedPool:  # its workers are gone already
        def __init__(self) -> None:
            self._processes: dict[int, object] = {}

        def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
            pass

    staging = tmp_path / ".run.staging-123-abcd"
    staging.mkdir()
    (staging / "run.json").write_text("half")
    (tmp_path / ".run.lock").write_text("")
    (tmp_path / "run.g2o").write_text("the previous run's output")
    batch._stop_pool(StoppedPool(), [tmp_path / "run.g2o"], tmp_path)  # type: ignore[arg-type]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["run.g2o"]
    assert (tmp_path / "run.g2o").read_text() == "the previous run's output"


def test_a_worker_that_dies_loses_its_pool_s_inputs_once_not_the_batch(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker killed (out of memory) breaks the process pool, and every input not finished with it: they
    go to a fresh pool once more (before: all six of a batch failed); lost twice, an input failed."""
    import concurrent.futures
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from pipeline import batch

    rounds: list[list[str]] = []

    class OnePoolDies:
        """In place of ProcessPoolExecutor: the first pool breaks with every input; later ones run them."""

        def __init__(self, *_args: object, **_kwargs: object) -> None:
            rounds.append([])

        def submit(self, _function: object, path: Path, *_args: object) -> Future[object]:
            rounds[-1].append(path.name)
            future: Future[object] = Future()
            if len(rounds) == 1 or path.name == "killer.g2o":
                future.set_exception(BrokenProcessPool("A process in the process pool was terminated"))
            else:
                future.set_result(batch.BatchOutcome(path, "graph"))
            return future

        def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
            pass

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", OnePoolDies)
    monkeypatch.setattr(batch, "_pool_processes", lambda pool: [])
    names = ["a.g2o", "killer.g2o", "b.g2o"]
    outcomes = batch._run_in_pool([tmp_path / name for name in names], ReplayConfig(), tmp_path, 2, None)
    assert rounds == [names, names]
    died = "worker process failed: A process in the process pool was terminated"
    assert [(outcome.input_path.name, outcome.error) for outcome in outcomes] == [
        ("a.g2o", None), ("killer.g2o", died), ("b.g2o", None)]


def test_a_local_ray_runtime_refuses_tasks_larger_than_the_machine() -> None:
    """`--ray --cpus-per-task 4` on a 2-CPU machine waited forever, printing nothing."""
    from types import SimpleNamespace

    from pipeline.ray_batch import _refuse_tasks_larger_than_this_machine

    two_cpus = SimpleNamespace(cluster_resources=lambda: {"CPU": 2.0, "memory": 1e9})
    _refuse_tasks_larger_than_this_machine(two_cpus, 2.0)  # type: ignore[arg-type]
    with pytest.raises(PipelineError, match=r"--cpus-per-task 4: the local Ray runtime has 2 CPUs"):
        _refuse_tasks_larger_than_this_machine(two_cpus, 4.0)  # type: ignore[arg-type]


def test_a_ray_address_where_nothing_listens_is_one_line_at_once(tmp_path: Path) -> None:
    """`ray.init` retried such an address for minutes (killed after 400 s), printing Ray's own lines."""
    pytest.importorskip("ray", reason="needs the ray extra: pip install '.[ray]'")
    import socket as sockets

    with sockets.socket() as probe:  # a port nothing listens on: bound, then closed
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    graph = write_loop_graph(tmp_path / "loop.g2o")
    result = run_replay(graph, "--ray", f"127.0.0.1:{port}", "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"replay: error: cannot connect to the Ray cluster at 127.0.0.1:{port}: Connection refused"]
    # "auto" with RAY_ADDRESS naming that address hung as long (killed after 60 s)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
        result = run_replay(graph, "--ray", "auto", "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [f"replay: error: cannot connect to the Ray cluster at auto "
                                          f"(RAY_ADDRESS=127.0.0.1:{port}): Connection refused"]
