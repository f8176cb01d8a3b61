"""Warnings of a log replay: one line each on stderr (`replay: warning: FILE: …`), a repeated one counted,
none with --quiet, all in the JSON summary; the Python API raises them as `LogWarning`s and prints nothing;
numpy's RuntimeWarnings never reach the user."""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from frontends.errors import LogWarning
from frontends.slam2d import LaserFrontend
from pipeline import replay
from pipeline.cli import app
from pipeline.warning_tally import WarningTally, tallied_warnings
from tests.pipeline_fixtures import write_drive

SCANS = 10
DROPPED_EVERY = 3
"""The injected reader drops one message every this many scans: the same warning, several times."""


@pytest.fixture(scope="module")
def short_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("warnings") / "short.mcap"
    write_drive(path, scans=SCANS)
    return path


@pytest.fixture
def lossy_reading(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The laser frontend warns as a reader losing data does (naming the log), now and then, and trips a
    numpy floating-point warning on every scan."""
    original = LaserFrontend.add

    def add(self: LaserFrontend, measurement: Any) -> Any:
        estimate = original(self, measurement)
        if estimate.index % DROPPED_EVERY == 0:
            warnings.warn(f"{self._log.path}: 1 messages dropped: out of order", LogWarning, stacklevel=2)
        np.log(np.zeros(1))  # "divide by zero encountered in log"
        return estimate

    monkeypatch.setattr(LaserFrontend, "add", add)
    yield


def _expected_count() -> int:
    return len(range(0, SCANS, DROPPED_EVERY))


def test_a_repeated_warning_is_one_line_with_its_count(short_log: Path, tmp_path: Path,
                                                         lossy_reading: None) -> None:
    result = CliRunner().invoke(app, [str(short_log), "--out", str(tmp_path), "--iterations", "3",
                                      "--allow-unconverged"])
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    assert lines[0] == (
        f"replay: warning: {short_log}: 1 messages dropped: out of order ({_expected_count()} times)")
    assert not any(line.startswith("replay: warning") for line in lines[1:])  # once, before the summary
    for python_format in ("LogWarning", "RuntimeWarning", "divide by zero", "warnings.warn"):
        assert python_format not in result.output
    summary = json.loads((tmp_path / "short.json").read_text())
    expected = [{"message": "1 messages dropped: out of order", "count": _expected_count()}]
    assert summary["warnings"] == expected


def test_quiet_silences_warnings_and_json_lists_them(short_log: Path, tmp_path: Path,
                                                     lossy_reading: None) -> None:
    result = CliRunner().invoke(app, [str(short_log), "--out", str(tmp_path), "--iterations", "3",
                                      "--allow-unconverged", "--quiet", "--json"])
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    assert json.loads(result.stdout)["warnings"] == [
        {"message": "1 messages dropped: out of order", "count": _expected_count()}]


def test_the_api_raises_each_warning_once_and_prints_nothing(short_log: Path, tmp_path: Path,
                                                             lossy_reading: None,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = replay(short_log, out_dir=tmp_path)
    assert [(w.category, str(w.message)) for w in caught] == [
        (LogWarning, f"{short_log}: 1 messages dropped: out of order ({_expected_count()} times)")]
    assert result.summary["warnings"] == [
        {"message": "1 messages dropped: out of order", "count": _expected_count()}]
    captured = capsys.readouterr()
    assert (captured.out, captured.err) == ("", "")


def test_a_clean_log_has_no_warnings(short_log: Path, tmp_path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning reissued by the replay would fail here
        result = replay(short_log, out_dir=tmp_path)
    assert result.summary["warnings"] == []


def test_the_tally_merges_repeats_keeps_order_and_drops_noise(tmp_path: Path) -> None:
    tally = WarningTally(tmp_path / "log.mcap")
    with tallied_warnings(tally):
        for text in ("b happened", "a happened", "b happened"):
            warnings.warn(f"{tmp_path / 'log.mcap'}: {text}", LogWarning, stacklevel=1)
        warnings.warn("a library's own\nmulti-line notice", UserWarning, stacklevel=1)
        warnings.warn("going away", DeprecationWarning, stacklevel=1)
        np.sqrt(-np.ones(1))  # "invalid value encountered in sqrt"
    assert tally.as_json() == [{"message": "b happened", "count": 2}, {"message": "a happened", "count": 1},
                               {"message": "a library's own multi-line notice", "count": 1}]
