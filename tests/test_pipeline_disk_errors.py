"""A full or read-only output disk: one line on stderr naming the output and the OS's reason, exit 2, the
old outputs untouched and no staging folder or lock left. On a real small tmpfs where this process may
mount one (root), else through the API with the OS call failing."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from optimizer.graph_files import write_g2o
from optimizer.gridworld import generate_grid_world
from pipeline import api
from pipeline.errors import OutputError
from tests.pipeline_fixtures import write_loop_graph

OUTPUTS = ("city.g2o", "city.json", "city.rrd")


def _replay(graph: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pipeline.launcher", str(graph), "--out", str(out), "--quiet",
         "--method", "sgd", "--iterations", "1", "--allow-unconverged"],
        capture_output=True, text=True, timeout=120, env={**os.environ, "NUMBA_NUM_THREADS": "1"})


def _snapshot(out: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(out.iterdir())}


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 4 MB tmpfs, unmounted afterwards; skips where mounting is not allowed."""
    mount_point = tmp_path / "disk"
    mount_point.mkdir()
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mount_point)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", "-l", str(mount_point)], capture_output=True)


@pytest.fixture(scope="module")
def city(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("graph") / "city.g2o"
    write_g2o(path, generate_grid_world(1500, seed=3).graph)
    return path


def _fill(disk: Path, leave: int) -> None:
    """Fill the file system of `disk` until `leave` bytes are free."""
    stats = os.statvfs(disk)
    free = stats.f_bavail * stats.f_frsize
    with (disk / "filler").open("wb") as filler:
        filler.truncate(0)
        filler.write(bytes(max(free - leave, 0)))


FREE_SPACE_LEFT = {
    "recording-start": lambda recording_size: 16 << 10,  # not even the recording's first bytes fit
    "recording": lambda recording_size: 96 << 10,  # the recording fails half-way
    "graph file": lambda recording_size: recording_size + (64 << 10),  # the graph file does not fit after it
}


@pytest.mark.parametrize("fails", FREE_SPACE_LEFT)
def test_a_full_disk_is_one_line_and_keeps_the_old_outputs(city: Path, small_disk: Path, fails: str) -> None:
    out = small_disk / "out"
    assert _replay(city, out).returncode == 0
    before = _snapshot(out)
    assert sorted(before) == sorted(OUTPUTS)
    # The recording is written first (during the optimization), then the graph file, then the summary.
    recording_size = len(before["city.rrd"])
    _fill(small_disk, leave=FREE_SPACE_LEFT[fails](recording_size))

    result = _replay(city, out)
    assert result.returncode == 2, result.stderr
    named = out / ("city.g2o" if fails == "graph file" else "city.rrd")
    assert result.stderr.splitlines() == [result.stderr.rstrip("\n")]
    assert result.stderr.startswith(f"replay: error: {named}: ")
    assert result.stderr.rstrip().endswith("No space left on device")
    assert _snapshot(out) == before  # old outputs untouched, no staging folder, no lock


def test_a_read_only_disk_is_one_line_and_keeps_the_old_outputs(city: Path, small_disk: Path) -> None:
    out = small_disk / "out"
    assert _replay(city, out).returncode == 0
    before = _snapshot(out)
    remounted = subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], capture_output=True, text=True)
    if remounted.returncode != 0:
        pytest.skip(f"cannot remount read-only: {remounted.stderr.strip()}")

    result = _replay(city, out)
    assert result.returncode == 2, result.stderr
    assert result.stderr == f"replay: error: {out}: cannot write in the folder: Read-only file system\n"
    assert _snapshot(out) == before


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes in any folder")
def test_a_folder_without_write_permission_is_one_line(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    out = tmp_path / "out"
    api.replay(graph, out_dir=out)
    before = _snapshot(out)
    out.chmod(0o555)
    try:
        with pytest.raises(OutputError, match=f"^{out}: cannot write in the folder: Permission denied$"):
            api.replay(graph, out_dir=out)
    finally:
        out.chmod(0o755)
    assert _snapshot(out) == before


def test_the_disk_filling_while_outputs_are_flushed_keeps_the_old_ones(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    out = tmp_path / "out"
    api.replay(graph, out_dir=out)
    before = _snapshot(out)

    def disk_full(_descriptor: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OutputError) as raised:
        api.replay(graph, out_dir=out)
    assert str(raised.value) == f"{out}: cannot write in the folder: No space left on device"
    assert _snapshot(out) == before
