"""The optimizer's kernels compiled ahead of need, in a process of its own (`optimizer.warmup`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from optimizer import warmup

REPO = Path(__file__).resolve().parents[1]

COUNT_OPTIMIZER_COMPILES = """
import sys
from numba.core import event
compiled = []
class Listener(event.Listener):
    def on_start(self, data): pass
    def on_end(self, data):
        function = data.data["dispatcher"].py_func
        compiled.append(function.__module__ + "." + function.__qualname__)
event.register("numba:compile", Listener())
from optimizer.solve import optimize
from optimizer.warmup import square_laps
# As `pipeline.keyframe_optimization` optimizes a keyframe graph: the default method from three starts, on
# a graph of another size than the warm-up's.
graph = square_laps(96, seed=5)
for _ in optimize(graph, starts={"a": graph.poses, "b": square_laps(96, seed=6).poses,
                                 "c": square_laps(96, seed=7).poses}):
    pass
print(" ".join(name for name in compiled if name.startswith("optimizer.")))
"""


def test_the_warm_up_caches_every_kernel_a_keyframe_graph_optimization_compiles(tmp_path: Path) -> None:
    """In a fresh cache, the warm-up process compiles what an optimization of another graph then only
    loads: not one optimizer kernel is compiled again (a new kernel on that path, missing from the warm-up,
    fails this)."""
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    marker = tmp_path / "warm"
    subprocess.run([sys.executable, "-m", "optimizer.warmup", str(marker)], cwd=REPO, env=environment,
                   check=True, timeout=900)
    assert marker.exists()
    again = subprocess.run([sys.executable, "-c", COUNT_OPTIMIZER_COMPILES], cwd=REPO, env=environment,
                           check=True, timeout=900, capture_output=True, text=True)
    assert again.stdout.split() == []


def test_the_marker_lies_in_numbas_cache_folder_and_names_the_sources(monkeypatch: pytest.MonkeyPatch,
                                                                       tmp_path: Path) -> None:
    package = tmp_path / "optimizer"
    package.mkdir()
    for source in warmup.PACKAGE.glob("*.py"):
        (package / source.name).write_bytes(source.read_bytes())
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    marker = warmup.marker_path(package)
    assert marker.parent == tmp_path / "cache"
    assert marker.name.startswith("sgdslam-optimizer-warm-")
    assert warmup.marker_path(package) == marker
    # Another version of a source (numba keys its cache on the sources' size and time) is another marker.
    stat = (package / "sgd_kernels.py").stat()
    os.utime(package / "sgd_kernels.py", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    assert warmup.marker_path(package) != marker
    # Without a cache folder chosen, numba caches beside the sources.
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert warmup.marker_path(package).parent == package / "__pycache__"


def test_no_warm_up_where_the_marker_says_it_is_done_or_the_machine_has_one_core(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    started: list[list[str]] = []
    monkeypatch.setattr(warmup.subprocess, "Popen", lambda command, **_: started.append(command))
    monkeypatch.setattr(warmup, "marker_path", lambda: tmp_path / "warm")
    monkeypatch.setattr(warmup.os, "cpu_count", lambda: 1)
    assert warmup.start_in_background() is None
    monkeypatch.setattr(warmup.os, "cpu_count", lambda: 2)
    (tmp_path / "warm").touch()
    assert warmup.start_in_background() is None
    with warmup.warming_up(False):
        pass
    assert started == []
    (tmp_path / "warm").unlink()
    warmup.start_in_background()
    assert started == [[sys.executable, "-m", "optimizer.warmup", str(tmp_path / "warm")]]


def test_a_warm_up_still_running_when_the_replay_ends_is_stopped(monkeypatch: pytest.MonkeyPatch,
                                                                 tmp_path: Path) -> None:
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    monkeypatch.setattr(warmup, "start_in_background", lambda: sleeper)
    with warmup.warming_up(True):
        assert sleeper.poll() is None
    assert sleeper.poll() is not None  # stopped and reaped, not left behind
