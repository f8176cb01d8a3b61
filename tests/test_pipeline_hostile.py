"""Hostile inputs to the command: absurd option values, endless or special files. Each ends in exit 2 with
one line on stderr naming the option or file, quickly, with nothing written."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.cli import app


def _replay_process(*args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """The console script's own entry point, which formats usage errors."""
    return subprocess.run([sys.executable, "-m", "pipeline.launcher", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.parametrize(("args", "named"), [
    (["--iterations", "2147483648"], "--iterations"),
    (["--iterations", "-1"], "--iterations"),
    (["--jobs", "100000"], "--jobs"),
    (["--method", "newton"], "--method"),
])
def test_option_values_out_of_range_are_one_line_errors(tmp_path: Path, args: list[str], named: str) -> None:
    result = _replay_process(tmp_path / "graph.g2o", *args, "--out", tmp_path / "out")
    assert result.returncode == 2
    assert len(result.stderr.splitlines()) == 1 and result.stderr.startswith("replay: error: ")
    assert named in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("setting", "bound"), [
    ("[slam2d.matching]\nresolution = 1e-9\n", "greater than or equal to 0.005"),
    ("[slam2d.matching]\nmax_range = 1e300\n", "less than or equal to 1000"),
    ("[slam2d.keyframes]\nlocal_map_keyframes = 2000000000\n", "less than or equal to 10000"),
    ("[optimizer]\niterations = 1000000000\n", "less than or equal to 1000000"),
])
def test_config_values_that_would_overflow_are_rejected(tmp_path: Path, setting: str, bound: str) -> None:
    config = tmp_path / "replay.toml"
    config.write_text(setting)
    result = CliRunner().invoke(app, ["--config", str(config), "--dump-config"])
    assert result.exit_code == 2
    assert result.stderr.startswith(f"replay: error: {config}:2: ") and bound in result.stderr
    assert len(result.stderr.splitlines()) == 1


@pytest.mark.parametrize("command", [
    ["--config", "{special}", "--dump-config"],
    ["evaluate", "{special}", "{special}"],
])
def test_endless_files_are_refused_without_reading_them_whole(command: list[str]) -> None:
    arguments = [part.format(special="/dev/zero") for part in command]
    result = CliRunner().invoke(app, arguments)
    assert result.exit_code == 2
    assert "/dev/zero" in result.stderr and "larger than" in result.stderr
    assert len(result.stderr.splitlines()) == 1


def test_a_fifo_without_a_writer_does_not_block(tmp_path: Path) -> None:
    fifo = tmp_path / "relations"
    os.mkfifo(fifo)
    finished = threading.Event()
    outcome: list[object] = []

    def run() -> None:
        outcome.append(CliRunner().invoke(app, ["evaluate", str(fifo), str(fifo)]))
        finished.set()

    threading.Thread(target=run, daemon=True).start()
    assert finished.wait(timeout=30), "reading a FIFO blocked"
    result = outcome[0]
    assert result.exit_code == 2 and str(fifo) in result.stderr  # type: ignore[attr-defined]


def test_a_tf_cycle_is_one_line_naming_the_log(tmp_path: Path) -> None:
    """/tf_static says base_link hangs off mount and mount off base_link: no base frame can be found."""
    from tests.hostile_fixtures import scan_log, walls

    cycle = [("mount", "base_link"), ("base_link", "mount")]
    path = scan_log(tmp_path / "cycle.mcap", walls, tf_static=cycle)
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"replay: error: {path}: the transform tree has a cycle through 'base_link'"]


@pytest.mark.parametrize(("time_increment", "timed"), [
    (float("nan"), False), (float("inf"), False), (-float("inf"), False), (1.0, False), (-1.0, False),
    (1e-30, True), (-1e-4, True), (1e-4, True),
])
def test_any_time_increment_replays(tmp_path: Path, time_increment: float, timed: bool) -> None:
    """Beam times a laser could not have (NaN, infinite, 1 s per beam) are read as none; tiny, negative
    (the stamp at the last beam) or plausible ones are used. Either way the replay runs."""
    from tests.hostile_fixtures import scan_log, walls

    path = scan_log(tmp_path / "timed.mcap", walls, time_increment=time_increment,
                    odometry=lambda i: (0.05 * i, 0.0, 0.0))
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out"), "--json", "--quiet"])
    assert result.exit_code == 0, result.output
    counts = json.loads(result.stdout)["counts"]
    assert counts["scans_with_beam_times"] == (counts["scans"] if timed else 0)


def test_beam_times_longer_than_the_time_between_scans_are_ignored_with_a_warning(tmp_path: Path) -> None:
    """Scans 0.1 s apart whose time_increment says 360 beams take 0.18 s: no laser sweeps longer than it
    takes to scan again (a driver's wrong value): read as instant, counted, and said once."""
    from tests.hostile_fixtures import scan_log, walls

    path = scan_log(tmp_path / "slow_beams.mcap", walls, time_increment=0.0005,
                    odometry=lambda i: (0.05 * i, 0.0, 0.0))
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    counts = summary["counts"]
    assert counts["scans_with_beam_times"] == counts["scans"] == 40
    assert counts["scans_beam_times_ignored"] == 39  # all but the first, which has no interval to judge by
    assert summary["warnings"] == [{"message": "39 scans on /scan said their beams took up to 0.18 s "
                                                "(time_increment), longer than the time between scans: they "
                                                "were read as if every beam were taken at the stamp",
                                    "count": 1}]
    lines = result.stderr.splitlines()
    assert [line for line in lines if line.startswith("replay: warning: ")] == [
        f"replay: warning: {path}: {summary['warnings'][0]['message']}"]
    assert "  40 scans with beam times (time_increment): 1 deskewed, 39 read as instant (see the warning)" \
        in lines
