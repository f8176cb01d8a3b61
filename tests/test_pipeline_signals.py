"""A replay stopped by SIGTERM or SIGKILL at any point leaves the old outputs or the new ones, complete, and
nothing else (after SIGKILL: once the next run into the folder has cleaned up)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from optimizer.cost import chi2
from optimizer.graph_files import read_graph, write_g2o
from optimizer.gridworld import generate_grid_world

OUTPUTS = {"city.g2o", "city.json", "city.rrd"}


def _replay(graph: Path, out: Path, iterations: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "pipeline.launcher", str(graph), "--out", str(out), "--quiet",
         "--iterations", str(iterations)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
    )


def _state(graph: Path, out: Path) -> str:
    """'old' or 'new' when the folder holds exactly one complete, consistent set of outputs."""
    assert {path.name for path in out.iterdir()} == OUTPUTS
    summary = json.loads((out / "city.json").read_text())
    written = read_graph(out / "city.g2o").graph
    original = read_graph(graph).graph
    assert summary["chi2_final"] == pytest.approx(chi2(original, written.poses), rel=1e-9)
    assert (out / "city.rrd").stat().st_size > 0
    return "old" if summary["iterations"]["sgd"] == 1 else "new"


@pytest.fixture(scope="module")
def city(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("graph") / "city.g2o"
    world = generate_grid_world(4000, seed=3)
    write_g2o(path, world.graph)
    return path


@pytest.mark.parametrize("delay", [0.2, 3.0, 6.0])
@pytest.mark.parametrize("signal_number", [signal.SIGTERM, signal.SIGKILL])
def test_a_stopped_replay_leaves_old_or_new_outputs(city: Path, tmp_path: Path, delay: float,
                                                     signal_number: int) -> None:
    out = tmp_path / "out"
    first = _replay(city, out, iterations=1)
    assert first.wait(timeout=120) == 0, first.stderr.read() if first.stderr else ""
    assert _state(city, out) == "old"

    second = _replay(city, out, iterations=60)
    time.sleep(delay)
    second.send_signal(signal_number)
    code = second.wait(timeout=120)
    stderr = second.stderr.read() if second.stderr else ""
    if signal_number == signal.SIGTERM:
        assert code in (0, 128 + signal.SIGTERM), stderr  # 0: it had finished before the signal came
        assert "Traceback" not in stderr
    else:
        # Whatever a killed run left (its staging folder, its lock) goes with the next run into the folder.
        third = _replay(city, out, iterations=1)
        assert third.wait(timeout=120) == 0
    assert _state(city, out) in ("old", "new")
