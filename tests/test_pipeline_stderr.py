"""Nothing but our own lines on stderr: no rerun log lines (coloured WARN/ERROR from its Rust side), no numpy
RuntimeWarnings, no Python warning format, whatever the log's numbers are."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.hostile_fixtures import scan_log, walls
from tests.pipeline_fixtures import write_drive

FOREIGN_MARKS = ("\x1b[", "WARN", "ERROR", "Warning", "Traceback", "warnings.warn", ".py:")


def _messy_log(path: Path) -> Path:
    """A log a third of whose scans have no valid return, the others with inf and NaN beams among the
    walls, and odometry with a NaN and a jump of 10⁶ m: numbers that are invalid on purpose."""
    def ranges(i: int) -> np.ndarray:
        if i % 3 == 0:
            return np.full(360, np.nan)
        values = walls(i)
        values[::5] = np.inf
        values[1::7] = np.nan
        return values

    def odometry(i: int) -> tuple[float, float, float]:
        if i == 5:
            return (math.nan, 0.0, 0.0)
        return (1e6, 0.0, 0.0) if i == 9 else (0.05 * i, 0.0, 0.0)

    return scan_log(path, ranges, count=60, odometry=odometry)


def _replay(log: Path, out: Path, *options: str) -> subprocess.CompletedProcess[str]:
    environment = {key: value for key, value in os.environ.items()
                   if key not in ("RUST_LOG", "PYTHONWARNINGS")}
    return subprocess.run(
        [sys.executable, "-m", "pipeline.launcher", str(log), "--out", str(out), "--method", "sgd",
         "--iterations", "3", "--allow-unconverged", *options],
        capture_output=True, text=True, timeout=300, env={**environment, "NUMBA_NUM_THREADS": "1"})


@pytest.mark.parametrize("log_kind", ["drive", "messy"])
def test_a_replay_prints_only_our_lines(tmp_path: Path, log_kind: str) -> None:
    log = tmp_path / f"{log_kind}.mcap"
    if log_kind == "drive":
        write_drive(log, scans=10)
    else:
        _messy_log(log)
    result = _replay(log, tmp_path / "out")
    assert result.returncode == 0, result.stderr
    lines = result.stderr.splitlines()
    assert lines and lines[0].startswith(f"{log.name}: ")  # the summary, then its indented lines
    for line in lines[1:]:
        assert line.startswith(("  ", "replay: ")), line
    for mark in FOREIGN_MARKS:
        assert mark not in result.stderr, result.stderr

    quiet = _replay(log, tmp_path / "quiet", "--quiet")
    assert quiet.returncode == 0, quiet.stderr
    assert all(line.startswith("replay: ") for line in quiet.stderr.splitlines()), quiet.stderr


@pytest.mark.parametrize(("given", "expected"), [(None, "off"), ("warn", "warn")])
def test_rerun_log_lines_are_off_unless_asked_for(given: str | None, expected: str) -> None:
    environment = {key: value for key, value in os.environ.items() if key != "RUST_LOG"}
    if given is not None:
        environment["RUST_LOG"] = given
    shown = subprocess.run(
        [sys.executable, "-c", "import os, pipeline.recording; print(os.environ['RUST_LOG'])"],
        capture_output=True, text=True, timeout=120, env=environment)
    assert shown.stdout.strip() == expected, shown.stderr
