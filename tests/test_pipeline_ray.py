"""Batches on a real local Ray runtime: outputs equal to a local replay, retries after a crash or a dead
worker, cancellation on interrupt, the command's table and exit code.

Skipped without the `ray` extra; `python -m pytest -m ray` runs only these. One runtime (2 CPUs, loopback
only, no dashboard) serves the whole module: starting one costs seconds.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.batch import BatchOutcome, RayOptions, run_batch, run_one, run_one_on_this_host
from pipeline.batch_summary import BATCH_SUMMARY_NAME
from pipeline.cli import app
from pipeline.config import ReplayConfig
from pipeline.outputs import staged_outputs
from tests.pipeline_fixtures import BROKEN_GRAPH, LOOP_POSES, write_drive, write_loop_graph

ray = pytest.importorskip("ray", reason="needs the ray extra: pip install '.[ray]'")
pytestmark = pytest.mark.ray

SGD_3 = ReplayConfig(optimizer={"method": "sgd", "iterations": 3})
TIMINGS = ("wall_time_s", "optimize_time_s")
"""The only keys of `<stem>.json` that differ between two runs of the same input."""


@pytest.fixture(scope="module", autouse=True)
def ray_runtime() -> Iterator[None]:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False,
             logging_level="ERROR")
    # The workers cannot import this module by name (pytest imports it from tests/, not as a package):
    # send the task wrappers below by value.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    ray.shutdown()


def partial_files(folder: Path) -> list[str]:
    """Anything hidden: staging folders, locks (`pipeline.outputs`)."""
    return sorted(path.name for path in folder.iterdir() if path.name.startswith("."))


def comparable_outputs(out: Path, stem: str) -> dict[str, object]:
    """The deterministic outputs of one replay: g2o and TUM as bytes, the JSON without its timings."""
    found: dict[str, object] = {}
    for suffix in (".g2o", ".tum"):
        path = out / f"{stem}{suffix}"
        if path.exists():
            found[suffix] = path.read_bytes()
    summary = json.loads((out / f"{stem}.json").read_text())
    found[".json"] = {key: value for key, value in summary.items() if key not in TIMINGS}
    return found


def test_outputs_through_ray_equal_a_local_replay(tmp_path: Path) -> None:
    log = tmp_path / "drive.mcap"
    write_drive(log, scans=10)
    graph = write_loop_graph(tmp_path / "loop.g2o")
    broken = tmp_path / "broken.g2o"
    broken.write_text(BROKEN_GRAPH)
    out = tmp_path / "out"

    local = {}
    for path in (log, graph):
        assert run_one(path, SGD_3, out_dir=out).ok
        local[path.stem] = comparable_outputs(out, path.stem)
        for written in out.glob(f"{path.stem}*"):
            written.unlink()

    outcomes = run_batch([log, broken, graph], SGD_3, out_dir=out, ray=RayOptions())
    assert [outcome.ok for outcome in outcomes] == [True, False, True]
    assert outcomes[1].error is not None and outcomes[1].error.startswith(f"{broken}:3: ")
    assert {outcome.host for outcome in outcomes} == {socket.gethostname()}
    for path in (log, graph):
        assert comparable_outputs(out, path.stem) == local[path.stem]
    assert set(local["drive"]) == {".g2o", ".tum", ".json"}
    assert outcomes[2].stats is not None and outcomes[2].stats.poses == LOOP_POSES
    assert not any(path.name.startswith("broken") for path in out.iterdir())
    assert partial_files(out) == []


def attempts_file(path: Path) -> Path:
    return path.with_suffix(".attempts")


def crash_by_name(path: str | Path, config: ReplayConfig | None = None, *, out_dir: str | Path = ".",
                  catch_unexpected: bool = True) -> BatchOutcome:
    """Runs in the worker: counts its tries beside the input, then, by the input's name, kills its own
    process halfway through writing an output (on the first try, or on every try) or raises on the first
    try; otherwise replays."""
    path = Path(path)
    with attempts_file(path).open("a") as attempts:
        attempts.write("try\n")
    first_try = attempts_file(path).read_text().count("try") == 1
    if path.stem == "always_dies" or (path.stem == "dies_once" and first_try):
        with staged_outputs(Path(out_dir) / f"{path.stem}.g2o") as (temporary,):
            temporary.write_text("half a graph")
            os._exit(1)
    if path.stem == "raises_once" and first_try:
        raise RuntimeError("a transient bug")
    return run_one_on_this_host(path, config, out_dir=out_dir, catch_unexpected=catch_unexpected)


def test_crashed_tasks_and_dead_workers_are_retried_and_failures_do_not_stop_the_others(
    tmp_path: Path
) -> None:
    from pipeline.ray_batch import run_batch_on_ray

    names = ("dies_once", "always_dies", "raises_once", "good")
    inputs = [write_loop_graph(tmp_path / f"{name}.g2o") for name in names]
    out = tmp_path / "out"
    outcomes = run_batch_on_ray(inputs, SGD_3, out_dir=out, options=RayOptions(retries=1),
                                replay_one=crash_by_name)

    assert [outcome.ok for outcome in outcomes] == [True, False, True, True]
    tries = [attempts_file(path).read_text().count("try") for path in inputs]
    assert tries == [2, 2, 2, 1]  # one retry each for the crashes, none for the good input
    assert outcomes[1].error is not None and outcomes[1].error.startswith("Ray task failed")
    assert outcomes[1].host is None
    for name in ("dies_once", "raises_once", "good"):
        assert json.loads((out / f"{name}.json").read_text())["poses"] == LOOP_POSES
    assert not any(path.name.startswith("always_dies") for path in out.iterdir())
    assert partial_files(out) == []  # the dead workers' half-written files are gone

    # without retries, the first crash is final and a bug keeps its remote traceback
    again = tmp_path / "again"
    again.mkdir()
    raising = write_loop_graph(again / "raises_once.g2o")
    (outcome,) = run_batch_on_ray([raising], SGD_3, out_dir=out, options=RayOptions(retries=0),
                                  replay_one=crash_by_name)
    assert outcome.error == "internal error: RuntimeError: a transient bug"
    assert outcome.traceback is not None and "a transient bug" in outcome.traceback


def events_file(path: Path) -> Path:
    return path.with_suffix(".events")


def write_forever(path: str | Path, config: ReplayConfig | None = None, *, out_dir: str | Path = ".",
                  catch_unexpected: bool = True) -> BatchOutcome:
    """Runs in the worker: inputs named slow* stage an output and never finish (noting beside the input
    that they started, and that they were interrupted); others replay."""
    path = Path(path)
    if path.stem.startswith("slow"):
        with events_file(path).open("a") as events:
            events.write("started\n")
        try:
            with staged_outputs(Path(out_dir) / f"{path.stem}.g2o") as (temporary,):
                temporary.write_text("the start of a graph")
                for _ in range(6000):  # Python work: Ray's cancel interrupts it between two bytecodes
                    time.sleep(0.1)
        except KeyboardInterrupt:
            with events_file(path).open("a") as events:
                events.write("interrupted\n")
            raise
    return run_one_on_this_host(path, config, out_dir=out_dir, catch_unexpected=catch_unexpected)


def test_an_interrupt_cancels_the_outstanding_tasks_and_leaves_no_partial_file(tmp_path: Path) -> None:
    from pipeline.ray_batch import run_batch_on_ray

    inputs = [write_loop_graph(tmp_path / f"{name}.g2o") for name in ("good", "slow_a", "slow_b")]
    out = tmp_path / "out"
    finished: list[BatchOutcome] = []

    def interrupt(outcome: BatchOutcome) -> None:
        finished.append(outcome)
        raise KeyboardInterrupt  # as Ctrl-C would, while the slow tasks are running or queued

    with pytest.raises(KeyboardInterrupt):
        run_batch_on_ray(inputs, SGD_3, out_dir=out, options=RayOptions(), on_done=interrupt,
                         replay_one=write_forever)
    assert [outcome.input_path.name for outcome in finished] == ["good.g2o"]
    assert sorted(path.name for path in out.iterdir()) == ["good.g2o", "good.json", "good.rrd"]
    # Whether a slow task had started, was interrupted, cancelled or killed depends on the machine's load;
    # whatever happened, it left nothing behind.
    assert not [path.name for path in out.iterdir() if path.name.startswith(".")]


def test_command_with_ray_reads_an_input_list_and_writes_the_table(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    graph = write_loop_graph(tmp_path / "loop.g2o")
    broken = tmp_path / "broken.g2o"
    broken.write_text(BROKEN_GRAPH)
    listing = tmp_path / "inputs.txt"
    listing.write_text(f"# tonight's graphs\n{graph}\n\n{broken}\n")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["--inputs", str(listing), "--ray", "--out", str(out), "--json",
                                      "--method", "sgd", "--iterations", "2", "--retries", "0"])
    assert result.exit_code == 2, result.output
    entries = json.loads(result.stdout)
    assert [(entry["input"], entry["ok"]) for entry in entries] == [(str(graph), True), (str(broken), False)]
    assert entries[0]["host"] == socket.gethostname()
    assert "2 inputs, 1 done, 1 failed" in result.stderr
    assert result.stderr.rstrip().splitlines()[-1] == f"replay: error: {entries[1]['error']}"

    rows = pq.read_table(out / BATCH_SUMMARY_NAME).to_pylist()
    assert [(row["input"], row["status"]) for row in rows] == [(str(graph), "ok"), (str(broken), "failed")]
    assert (rows[0]["poses"], rows[0]["loop_closures"], dict(rows[0]["iterations"])) == (LOOP_POSES, 2,
                                                                                          {"sgd": 2})
    assert rows[1]["error"] == entries[1]["error"] and rows[1]["poses"] is None
