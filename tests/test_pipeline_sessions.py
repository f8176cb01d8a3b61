"""`replay LOG --map SESSION` and `replay LOG --continue SESSION` end to end (issue 13), and their API.

The simulated building (tests/laser_world.py) is driven once; the drive is cut into logs recorded apart,
each with its own stamps and its wheel odometry starting at its own origin:
- `first`: scans 0–134 (the south, east and north corridors), mapped by a plain replay;
- `inside`: scans 40–129, all inside the first map: localized with `--map`;
- `second`: scans 100–190, from the north corridor (mapped) through the west one (not mapped) back into
  the south one (mapped): continued with `--continue`.
The map's frame is the first log's: its first scan's base pose is the origin, so the simulator's truth
seen from the first log's first pose is what every pose written must match.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import pipeline
from frontends.errors import FrontendError, LogWarning
from frontends.slam2d import session_frontends
from frontends.slam2d.held_map import HELD_MAP_AGREEMENT, HeldMapScans
from frontends.slam2d.resume import MapPlacementError
from pipeline.cli import app
from pipeline.errors import PipelineError
from pipeline.session_file import SESSION_VERSION, SessionError, read_session, write_session
from pipeline.trajectory_io import read_tum
from tests.conftest import shared_file
from tests.laser_world import between, long_corridor
from tests.pipeline_fixtures import (
    SCAN_PERIOD_NS,
    START_NS,
    one_error_line,
    read_recording,
    write_drive,
    write_log_start,
    write_loop_graph,
)

HOUR_NS = 3600 * 10**9
MAP_TOLERANCE = 0.07
"""Position error (m) allowed against the truth: the first map itself is off by up to ~4.6 cm, and a
localized scan adds its own match's error (up to ~2 cm here)."""


@dataclass(frozen=True)
class Logs:
    folder: Path
    first: Path
    first_truth: np.ndarray
    inside: Path
    inside_truth: np.ndarray
    second: Path
    second_truth: np.ndarray
    session: Path
    """The session the plain replay of `first` wrote."""

    def in_map_frame(self, truth: np.ndarray) -> np.ndarray:
        return between(self.first_truth[0], truth)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Logs:
    folder = tmp_path_factory.mktemp("sessions")
    first, inside, second = folder / "first.mcap", folder / "inside.mcap", folder / "second.mcap"
    first_truth = write_drive(first, part=slice(0, 135))
    inside_truth = write_drive(inside, part=slice(40, 130), later_ns=2 * HOUR_NS, seed=9)
    second_truth = write_drive(second, part=slice(100, 191), later_ns=HOUR_NS, seed=8)
    mapped = pipeline.replay(first, out_dir=folder / "first_out")
    return Logs(folder, first, first_truth, inside, inside_truth, second, second_truth,
                mapped.outputs["session"])


def run_replay(*args: object) -> object:
    return CliRunner().invoke(app, [str(arg) for arg in args])


def tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    trajectory = read_tum(path)
    yaw = 2.0 * np.arctan2(trajectory.quaternions[:, 2], trajectory.quaternions[:, 3])
    return trajectory.stamps_ns, np.column_stack([trajectory.positions[:, :2], yaw])


def position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1])


def heading_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.abs((poses[:, 2] - truth[:, 2] + np.pi) % (2.0 * np.pi) - np.pi)


def file_names(folder: Path) -> set[str]:
    return {path.name for path in folder.iterdir()} if folder.exists() else set()


# ------------------------------------------------------------------------------------------- --map


def test_map_localizes_a_log_in_the_saved_map_without_an_initial_pose(logs: Logs, tmp_path: Path) -> None:
    session_bytes = logs.session.read_bytes()
    result = pipeline.replay(logs.inside, out_dir=tmp_path, map=logs.session)

    assert file_names(tmp_path) == {"inside.tum", "inside.json", "inside.rrd"}  # no session, graph or map
    assert logs.session.read_bytes() == session_bytes
    stamps, poses = tum_poses(tmp_path / "inside.tum")
    assert len(stamps) == len(logs.inside_truth), "every scan placed: one pose per scan"
    truth = logs.in_map_frame(logs.inside_truth)
    assert position_errors(poses, truth).max() < MAP_TOLERANCE
    assert heading_errors(poses, truth).max() < math.radians(1.0)
    np.testing.assert_array_equal(result.stamps_ns, stamps)
    np.testing.assert_allclose(result.poses[:, :2], poses[:, :2], atol=1e-9)

    summary = json.loads((tmp_path / "inside.json").read_text())
    assert summary["mode"] == "map" and summary["session"] == str(logs.session)
    found = summary["localization"]
    assert found["scans"] == found["with_pose"] == len(stamps)
    assert found["never_localized"] == 0
    assert len(found["global_fixes"]) == 1, "found once, then tracked"
    per_scan = summary["per_scan"]
    assert len(per_scan["state"]) == len(per_scan["score"]) == len(stamps)
    assert set(per_scan["state"]) <= {"m", "r"}  # matched, or recovered by the global fix
    fix = found["global_fixes"][0]["scan"]
    assert per_scan["state"][:fix] == "r" * fix and per_scan["state"][fix:] == "m" * (len(stamps) - fix)
    assert min(s for s in per_scan["score"] if s is not None) > 0.5
    assert result.stats.poses == summary["counts"]["map_keyframes"]  # the saved map's graph, unchanged

    entities = read_recording(tmp_path / "inside.rrd", timeline="scan")
    assert entities["/world/saved_map"].static_rows == 1
    assert entities["/world/final_trajectory"].static_rows == 1
    assert entities["/world/occupancy/grid"].static_rows == 1
    assert len(entities["/world/robot"].steps) == len(stamps) - fix  # scans placed when processed
    # The match quality plot: the matched scans' scores as the JSON lists them, on `scan`.
    score = entities["/localization/score"]
    matched = [k for k, state in enumerate(per_scan["state"]) if state == "m"]
    assert score.steps == matched
    np.testing.assert_allclose([row[0] for row in score.columns["Scalars:scalars"]],
                               [per_scan["score"][k] for k in matched], atol=1e-3)


def test_map_with_an_initial_pose_tracks_from_the_first_scan(logs: Logs, tmp_path: Path) -> None:
    start = logs.in_map_frame(logs.inside_truth[0]) + np.array([0.15, -0.1, math.radians(3.0)])
    result = run_replay(logs.inside, "--out", tmp_path, "--map", logs.session,
                        "--initial-pose", ",".join(f"{value:.6f}" for value in start))
    assert result.exit_code == 0, result.stderr
    assert "localized in" in result.stderr and "  0 global fixes;" in result.stderr
    assert "trajectory: the run's own keyframe graph (" in result.stderr
    summary = json.loads((tmp_path / "inside.json").read_text())
    assert summary["localization"]["global_fixes"] == []
    assert summary["per_scan"]["state"] == "m" * len(logs.inside_truth)
    assert summary["initial_pose"] == pytest.approx(start.tolist(), abs=1e-6)
    stamps, poses = tum_poses(tmp_path / "inside.tum")
    assert len(stamps) == len(logs.inside_truth)
    assert position_errors(poses, logs.in_map_frame(logs.inside_truth)).max() < MAP_TOLERANCE



@pytest.mark.parametrize("offset", [1000.0, 1e20])
def test_map_warns_when_no_scan_matched_the_saved_map(logs: Logs, tmp_path: Path, offset: float) -> None:
    """An initial pose a kilometre (or absurdly far) off the map: every scan is tracked on the log's own
    scans, none matches the map. The run ends, but says so (before: exit 0, no warning, every scan "with a
    pose"; 1e20 m off, a loop search of the run's own SLAM built a grid from the saved map to the run)."""
    start = logs.in_map_frame(logs.inside_truth[0]) + np.array([offset, offset, 0.0])
    result = run_replay(logs.inside, "--out", tmp_path, "--map", logs.session,
                        "--initial-pose", ",".join(f"{value:.6f}" for value in start))
    assert result.exit_code == 0, result.stderr
    assert "none of the" in result.stderr and "matched it" in result.stderr
    summary = json.loads((tmp_path / "inside.json").read_text())
    assert summary["localization"]["matched"] == 0
    assert any("none of the" in warning["message"] for warning in summary["warnings"])

def test_map_writes_the_held_map_trajectory_and_keeps_the_online_states(logs: Logs, tmp_path: Path) -> None:
    """The TUM file and the recording's final trajectory hold the run's own keyframe graph solved with the
    saved map held (`frontends.slam2d.held_map`); the robot's pose recorded scan by scan stays the one given
    online, and the saved map is not written."""
    start = logs.in_map_frame(logs.second_truth[0])
    pipeline.replay(logs.second, out_dir=tmp_path, map=logs.session, initial_pose=tuple(start))
    _, poses = tum_poses(tmp_path / "second.tum")
    summary = json.loads((tmp_path / "second.json").read_text())
    counts = summary["counts"]
    assert counts["held_map_used"] == 1 and counts["held_map_converged"] == 1
    assert counts["scans_held_map"] == len(poses) and counts["scans_smoothed"] == 0
    assert counts["held_map_old_new_constraints"] >= 2, "the placement and at least one loop closure"
    assert 0 <= counts["held_map_apart_from_matches_mm"] < 1000 * HELD_MAP_AGREEMENT
    assert not (tmp_path / "second.session").exists() and not (tmp_path / "second.g2o").exists()
    entities = read_recording(tmp_path / "second.rrd", timeline="scan")
    final = np.array(entities["/world/final_trajectory"].static_columns["LineStrips2D:strips"][0][0])
    online = np.array([row[0] for row in entities["/world/robot"].columns["Points2D:positions"]])
    np.testing.assert_allclose(final, poses[:, :2], atol=1e-5)
    moved = position_errors(online, poses)
    assert moved.max() > 1e-3, "the held-map solution moved the poses given online …"
    assert np.median(moved) < 0.03, "… by centimetres here (the same base poses, not the laser's)"
    truth = logs.in_map_frame(logs.second_truth)
    worst = position_errors(poses, truth).max()
    assert worst < MAP_TOLERANCE
    assert worst < position_errors(online, truth).max(), "nearer the truth at its worst than the online poses"


def test_map_records_the_held_map_solve_iteration_by_iteration(logs: Logs, tmp_path: Path) -> None:
    """The recording plays the run's own keyframe graph solved with the saved map held on `iteration`, as a
    log replay plays its optimization: the new keyframes' walls and trajectory move from the odometry chain
    to where they end, which is where the written trajectory puts them; the saved map is static."""
    start = logs.in_map_frame(logs.second_truth[0])
    pipeline.replay(logs.second, out_dir=tmp_path, map=logs.session, initial_pose=tuple(start))
    _, poses = tum_poses(tmp_path / "second.tum")
    counts = json.loads((tmp_path / "second.json").read_text())["counts"]
    entities = read_recording(tmp_path / "second.rrd")
    assert entities["/world/saved_map"].static_rows == 1 and not entities["/world/saved_map"].steps
    keyframes = sorted(path for path in entities if re.fullmatch(r"/world/keyframes/k\d{6}", path))
    assert len(keyframes) == counts["held_map_keyframes"] > 1
    assert all(entities[f"{path}/scan"].steps for path in keyframes), "each new keyframe's walls"
    # A keyframe is the scan that made it: its last recorded pose is one of the poses written.
    ends = np.array([entities[path].columns["Transform3D:translation"][-1][0][:2] for path in keyframes])
    nearest = np.hypot(*(ends[:, None, :] - poses[None, :, :2]).transpose(2, 0, 1)).min(axis=1)
    assert nearest.max() < 1e-4
    trajectory = entities["/world/trajectory"]
    first, last = (np.array(trajectory.columns["LineStrips2D:strips"][k][0]) for k in (0, -1))
    assert len(first) == len(last) == len(keyframes)
    assert np.abs(first - last).max() > 0.01, "the odometry chain, then the optimum: the keyframes moved"
    chi2 = [row[0] for row in entities["/optimizer/log10_chi2"].columns["Scalars:scalars"]]
    assert chi2[-1] < chi2[0]


def test_map_keeps_the_scan_by_scan_trajectory_when_the_held_map_solution_disagrees(
        logs: Logs, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A held-map solution placed 2 m off the localizer's map matches (as a look-alike place would) is not
    given: a warning says so, and the trajectory is the localizer's, smoothed."""
    real = session_frontends.held_map_scans

    def shifted(*args: object) -> HeldMapScans:
        found = real(*args)  # type: ignore[arg-type]
        return dataclasses.replace(found, poses=found.poses + np.array([2.0, 0.0, 0.0]))

    monkeypatch.setattr(session_frontends, "held_map_scans", shifted)
    start = logs.in_map_frame(logs.second_truth[0])
    with pytest.warns(LogWarning, match="solved in the saved map"):
        pipeline.replay(logs.second, out_dir=tmp_path, map=logs.session, initial_pose=tuple(start))
    _, poses = tum_poses(tmp_path / "second.tum")
    summary = json.loads((tmp_path / "second.json").read_text())
    counts = summary["counts"]
    assert counts["held_map_used"] == 0 and counts["scans_held_map"] == 0
    assert counts["held_map_apart_from_matches_mm"] > 1000 * HELD_MAP_AGREEMENT
    assert counts["scans_smoothed"] == len(poses) and counts["smoothing_converged"] == 1
    assert any("solved in the saved map" in warning["message"] for warning in summary["warnings"])
    assert position_errors(poses, logs.in_map_frame(logs.second_truth)).max() < MAP_TOLERANCE


def test_map_solves_the_run_s_own_graph_with_the_default_optimizer_whatever_the_config_says(
        logs: Logs, tmp_path: Path) -> None:
    """--map refuses --method: a config file's [optimizer] must not steer it either (sgd alone, a fixed
    number of iterations, never converges, and the held map's trajectory was silently dropped)."""
    from pipeline.config import config_from_mapping

    start = tuple(logs.in_map_frame(logs.second_truth[0]))
    pipeline.replay(logs.second, out_dir=tmp_path / "default", map=logs.session, initial_pose=start)
    sgd = config_from_mapping({"optimizer": {"method": "sgd", "iterations": 3}})
    pipeline.replay(logs.second, sgd, out_dir=tmp_path / "sgd", map=logs.session, initial_pose=start)
    counts = json.loads((tmp_path / "sgd" / "second.json").read_text())["counts"]
    assert counts["held_map_converged"] == 1 and counts["held_map_used"] == 1
    written = [(tmp_path / run / "second.tum").read_bytes() for run in ("default", "sgd")]
    assert written[0] == written[1]


def test_map_warns_when_the_held_map_solve_did_not_converge(logs: Logs, tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    real = session_frontends.held_map_scans

    def unconverged(*args: object) -> HeldMapScans:
        return dataclasses.replace(real(*args), converged=False)  # type: ignore[arg-type]

    monkeypatch.setattr(session_frontends, "held_map_scans", unconverged)
    start = logs.in_map_frame(logs.second_truth[0])
    with pytest.warns(LogWarning, match="solved in the saved map, did not converge"):
        pipeline.replay(logs.second, out_dir=tmp_path, map=logs.session, initial_pose=tuple(start))
    counts = json.loads((tmp_path / "second.json").read_text())["counts"]
    assert counts["held_map_used"] == 0 and counts["scans_smoothed"] > 0


@pytest.mark.parametrize("mode", ["map", "continue"])
def test_a_log_never_placed_in_the_map_is_one_line_naming_it_and_publishes_nothing(logs: Logs, tmp_path: Path,
                                                                                   mode: str) -> None:
    short = tmp_path / "short.mcap"
    # Three scans of a featureless corridor elsewhere: two walls, fitting the map's corridors anywhere along.
    write_drive(short, part=slice(40, 43), later_ns=3 * HOUR_NS, world=long_corridor())
    out = tmp_path / "out"
    result = run_replay(short, "--out", out, f"--{mode}", logs.session)
    assert result.exit_code == 2
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("replay: error: ") and "saved map" in lines[0]
    assert str(short) in lines[0]
    assert file_names(out) == set()
    with pytest.raises(MapPlacementError):
        pipeline.replay(short, out_dir=out, **({"map": logs.session} if mode == "map"
                                               else {"continue_from": logs.session}))


# -------------------------------------------------------------------------------------- --continue


def test_continue_maps_both_logs_into_one_trajectory_and_a_larger_session(logs: Logs, tmp_path: Path) -> None:
    result = run_replay(logs.second, "--out", tmp_path, "--continue", logs.session, "--allow-unconverged")
    assert result.exit_code == 0, result.stderr
    assert "continued" in result.stderr

    stamps, poses = tum_poses(tmp_path / "second.tum")
    old, new = len(logs.first_truth), len(logs.second_truth)
    assert len(stamps) == old + new, "every scan of the session, old and new"
    first_stamps, _ = tum_poses(logs.session.with_suffix(".tum"))
    np.testing.assert_array_equal(stamps[:old], first_stamps)  # the old log's scans first
    assert np.all(np.diff(stamps) > 0)
    truth = logs.in_map_frame(np.concatenate([logs.first_truth, logs.second_truth]))
    errors = position_errors(poses, truth)
    assert errors.max() < MAP_TOLERANCE, f"max error {errors.max():.3f} m at scan {errors.argmax()}"
    assert heading_errors(poses, truth).max() < math.radians(1.0)

    summary = json.loads((tmp_path / "second.json").read_text())
    assert summary["mode"] == "continue"
    assert summary["session"]["continued_from"] == str(logs.session)
    counts = summary["counts"]
    before = pipeline.load_session(logs.session)
    assert counts["session_keyframes"] == len(before.keyframe_points)
    assert counts["session_scans"] == old and counts["scans"] == new and counts["scans_unplaced"] == 0
    assert counts["loop_closures_old_new"] >= 2, "the return to the south corridor closes loops on the map"
    assert counts["keyframes_on_saved_path"] > 0 and "loops with the saved keyframes" not in result.stderr
    assert summary["chi2_per_iteration"][0]["stage"] == "initial"
    assert len(summary["chi2_per_iteration"]) > 2

    after = pipeline.load_session(tmp_path / "second.session")
    assert len(after.keyframe_points) > len(before.keyframe_points)
    assert len(after.arrays["scan_stamps_ns"]) == old + new
    assert after.header["continued_from"]["path"] == str(logs.session.resolve())
    assert after.header["continued_from"]["source"] == before.header["source"]
    entities = read_recording(tmp_path / "second.rrd")
    assert len(entities["/world/trajectory"].steps) >= 2  # recorded iteration by iteration


def test_info_describes_a_session_and_the_one_it_continued(logs: Logs, tmp_path: Path) -> None:
    result = run_replay("info", logs.session, "--json")
    assert result.exit_code == 0, result.output
    described = json.loads(result.stdout)
    saved = read_session(logs.session)
    assert described["container"] == "session" and described["sensor_kind"] == "scan"
    assert described["keyframes"] == len(saved.keyframe_points)
    assert described["measurements"] == len(logs.first_truth), "every scan of the log, placed"
    assert described["loop_closures"] == int(saved.arrays["is_loop"].sum())
    (source,) = described["source"]["files"]
    assert source["path"] == str(logs.first.resolve())
    assert source["sha256"] == hashlib.sha256(logs.first.read_bytes()).hexdigest()
    text = run_replay("info", logs.session)
    assert text.exit_code == 0
    assert text.stdout.startswith(f"{logs.session}: session") and "2D laser scans on /scan" in text.stdout
    assert f"{len(saved.keyframe_points)} keyframes and {len(logs.first_truth)} scans placed" in text.stdout

    continued = tmp_path / "twice.session"
    with continued.open("wb") as stream:  # what a --continue writes: the header names the session continued
        write_session(stream, {**saved.header, "continued_from": {
            "path": str(logs.session), "source": saved.header["source"], "continued_from": None}},
            saved.arrays, saved.keyframe_points)
    text = run_replay("info", continued)
    assert text.exit_code == 0
    assert f"continuing {logs.session} (from {logs.first.resolve()})" in text.stdout

    edited = tmp_path / "edited.session"  # a header edited by hand: said as it is, not a traceback
    with edited.open("wb") as stream:
        write_session(stream, {**saved.header, "source": {"files": ["a.mcap"]}, "continued_from": "old"},
                      saved.arrays, saved.keyframe_points)
    text = run_replay("info", edited)
    assert text.exit_code == 0 and text.exception is None
    assert "from " not in text.stdout and "continuing" not in text.stdout


def test_continue_with_a_log_not_after_the_session_warns_that_the_stamps_go_back(logs: Logs,
                                                                                   tmp_path: Path) -> None:
    # The first log continued on its own session: its scans are the session's again, at the same stamps.
    result = run_replay(logs.first, "--out", tmp_path, "--continue", logs.session, "--allow-unconverged")
    assert result.exit_code == 0, result.stderr
    warning = [line for line in result.stderr.splitlines() if "do not come after" in line]
    assert len(warning) == 1 and warning[0].startswith(f"replay: warning: {logs.first}: its scans (from ")
    assert "first.tum holds the session's first, then this log's" in warning[0]
    stamps, _ = tum_poses(tmp_path / "first.tum")
    first_stamps, _ = tum_poses(logs.session.with_suffix(".tum"))
    old = len(first_stamps)
    np.testing.assert_array_equal(stamps[:old], first_stamps)
    assert stamps[old] < stamps[old - 1]  # where the two join
    assert np.all(np.diff(stamps[old:]) > 0)


def test_continue_refuses_to_write_its_session_over_the_one_it_continues(logs: Logs, tmp_path: Path) -> None:
    session = tmp_path / "second.session"  # where continuing `second` would write its new session
    session.write_bytes(logs.session.read_bytes())
    result = run_replay(logs.second, "--out", tmp_path, "--continue", session)
    assert one_error_line(result) == (
        f"replay: error: {session}: is an input of this replay, and its output of the same name would "
        "replace it; write the outputs into another folder (--out)")
    assert session.read_bytes() == logs.session.read_bytes()
    assert file_names(tmp_path) == {"second.session"}


@pytest.mark.parametrize("mode", ["--map", "--continue"])
def test_a_swept_lidar_only_log_is_deskewed_in_a_saved_map(logs: Logs, tmp_path: Path, mode: str) -> None:
    # The second log again, its laser now sweeping its beams over 0.1 s at 1 m/s (1 rad/s in the corners),
    # time_increment set and no odometry: the localizer's and the resumed SLAM's own deskewing.
    swept = tmp_path / "swept.mcap"
    truth = logs.in_map_frame(write_drive(swept, part=slice(100, 191), later_ns=HOUR_NS, seed=8, sweep=0.1,
                                          with_odometry=False))
    settings = tmp_path / "no_deskew.toml"
    settings.write_text("[slam2d.matching]\ndeskew = false\n")
    median = {}
    for name, options in (("deskewed", []), ("as_if_instant", ["--config", settings])):
        result = run_replay(swept, "--out", tmp_path / name, mode, logs.session, "--allow-unconverged",
                            *options)
        assert result.exit_code == 0, result.stderr
        stamps, poses = tum_poses(tmp_path / name / "swept.tum")
        swept_stamps = START_NS + HOUR_NS + np.arange(len(truth)) * SCAN_PERIOD_NS
        mine = np.isin(stamps, swept_stamps)  # --continue writes the first log's scans too
        assert mine.sum() >= len(truth) - 5
        expected = truth[np.searchsorted(swept_stamps, stamps[mine])]
        median[name] = float(np.median(position_errors(poses[mine], expected)))
    # When this was written: --map 0.024 against 0.039 m (the saved map holds the poses: the sweep costs
    # less), --continue 0.013 against 0.053.
    assert median["deskewed"] < (0.85 if mode == "--map" else 0.5) * median["as_if_instant"], median




def test_both_options_or_an_initial_pose_without_map_are_refused(logs: Logs, tmp_path: Path) -> None:
    line = one_error_line(run_replay(logs.inside, "--out", tmp_path, "--map", logs.session,
                                     "--continue", logs.session))
    assert "--map" in line and "--continue" in line
    line = one_error_line(run_replay(logs.inside, "--out", tmp_path, "--continue", logs.session,
                                     "--initial-pose", "1,2,0"))
    assert "--initial-pose" in line
    assert file_names(tmp_path) == set()


@pytest.mark.parametrize("option", [("--method", "sgd"), ("--iterations", "5"), ("--robust", "cauchy"),
                                    ("--repair-information",)])
def test_options_map_has_no_use_for_are_refused(logs: Logs, tmp_path: Path, option: tuple[str, ...]) -> None:
    line = one_error_line(run_replay(logs.inside, "--out", tmp_path, "--map", logs.session, *option))
    assert option[0] in line
    assert file_names(tmp_path) == set()


@pytest.mark.parametrize("text", ["1,2", "1,2,3,4", "a,b,c", "nan,0,0", "inf,0,0", "1_0,0,0", "1;2;3", ""])
def test_a_malformed_initial_pose_is_refused(logs: Logs, tmp_path: Path, text: str) -> None:
    line = one_error_line(run_replay(logs.inside, "--out", tmp_path, "--map", logs.session,
                                     "--initial-pose", text))
    assert "--initial-pose" in line
    assert file_names(tmp_path) == set()


def test_graph_inputs_and_batches_are_refused(logs: Logs, tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    out = tmp_path / "out"
    line = one_error_line(run_replay(graph, "--out", out, "--map", logs.session))
    assert "pose graph" in line and str(graph) in line
    line = one_error_line(run_replay(logs.inside, logs.second, "--out", out, "--continue", logs.session))
    assert "exactly one log" in line
    one_error_line(run_replay("--out", out, "--map", logs.session))  # the bundled sample
    assert file_names(out) == set()
    with pytest.raises(PipelineError, match="pose graph"):
        pipeline.replay(graph, out_dir=out, continue_from=logs.session)


@pytest.mark.parametrize("damage", ["cut", "newer", "information not positive definite",
                                    "constraint from a keyframe to itself"])
def test_a_damaged_or_newer_session_is_one_line_naming_it(logs: Logs, tmp_path: Path, damage: str) -> None:
    session = tmp_path / "bad.session"
    if damage == "cut":
        data = logs.session.read_bytes()
        session.write_bytes(data[: len(data) // 2])
    elif damage == "newer":
        with session.open("wb") as stream:
            write_session(stream, {"version": SESSION_VERSION + 1, "sensor_kind": "scan"}, {}, [])
    else:  # a well-formed file whose graph a graph file would not be allowed to hold
        saved = read_session(logs.session)
        arrays = dict(saved.arrays)
        if damage.startswith("information"):
            arrays["information"] = -arrays["information"]
        else:
            arrays["edge_to"] = arrays["edge_from"].copy()
        with session.open("wb") as stream:
            write_session(stream, saved.header, arrays, saved.keyframe_points)
    out = tmp_path / "out"
    for option in ("--map", "--continue"):
        line = one_error_line(run_replay(logs.inside, "--out", out, option, session))
        assert line.startswith(f"replay: error: {session}: ")
        assert "damaged session file (constraint 0" in line or damage in ("cut", "newer")
    assert file_names(out) == set()
    if damage in ("cut", "newer"):  # unreadable: `replay info` says so in one line too
        assert one_error_line(run_replay("info", session)).startswith(f"replay: error: {session}: ")
    with pytest.raises(SessionError, match=r"bad\.session"):
        pipeline.replay(logs.inside, out_dir=out, map=session)


def rewritten_session(session: Path, folder: Path, keyframe_points: list[np.ndarray]) -> Path:
    """`session` with other keyframe scans, written into `folder`."""
    saved = read_session(session)
    rewritten = folder / "rewritten.session"
    with rewritten.open("wb") as stream:
        write_session(stream, dict(saved.header), dict(saved.arrays), keyframe_points)
    return rewritten


@pytest.mark.parametrize("mode", ["--map", "--continue"])
def test_a_session_keyframe_without_points_is_no_obstacle(logs: Logs, tmp_path: Path, mode: str) -> None:
    """A keyframe whose scan holds no point (a laser that saw nothing) is stored as such; the saved map
    around it still serves."""
    points = list(read_session(logs.session).keyframe_points)
    session = rewritten_session(logs.session, tmp_path, [np.zeros((0, 2)), *points[1:]])
    result = run_replay(logs.inside, "--out", tmp_path / "out", "--quiet", mode, session)
    assert result.exit_code == 0, result.output  # type: ignore[attr-defined]
    _, poses = tum_poses(tmp_path / "out" / "inside.tum")
    truth = logs.in_map_frame(logs.inside_truth)
    if mode == "--continue":  # the session's scans first
        poses = poses[-len(truth):]
    assert np.median(position_errors(poses, truth)) < MAP_TOLERANCE


def test_a_session_without_a_usable_scan_is_one_line_naming_it(logs: Logs, tmp_path: Path) -> None:
    points = read_session(logs.session).keyframe_points
    session = rewritten_session(logs.session, tmp_path, [p[:3] for p in points])  # too few to match
    for mode in ("--map", "--continue"):
        line = one_error_line(run_replay(logs.inside, "--out", tmp_path / "out", mode, session))
        assert line.startswith(f"replay: error: {session}: ") and "nothing to localize in" in line
    assert file_names(tmp_path / "out") == set()


def test_a_session_of_the_other_sensor_kind_is_refused(logs: Logs, tmp_path: Path) -> None:
    session = tmp_path / "clouds.session"
    with session.open("wb") as stream:
        write_session(stream, {"sensor_kind": "cloud"}, {"keyframe_poses": np.zeros((1, 3))},
                      [np.zeros((4, 3))])
    out = tmp_path / "out"
    line = one_error_line(run_replay(logs.inside, "--out", out, "--continue", session))
    assert "3D point clouds" in line and "2D laser scans" in line and str(session) in line
    assert file_names(out) == set()
    with pytest.raises(PipelineError, match="3D point clouds"):
        pipeline.replay(logs.inside, out_dir=out, map=session)


def test_a_saved_map_too_large_for_one_grid_is_one_line_naming_the_session(logs: Logs,
                                                                          tmp_path: Path) -> None:
    # The localizer matches against one grid of the whole map, at up to 4 × coarser cells where the map is
    # large: beyond that the error names the session, not only the grid.
    content = read_session(logs.session)
    arrays = dict(content.arrays)
    poses = np.array(arrays["keyframe_poses"], dtype=np.float64)
    poses[-1, :2] += (200_000.0, 0.0)  # one keyframe 200 km away: 4 M × 300+ cells, 8 × 0.05 m to fit
    arrays["keyframe_poses"] = poses
    session = tmp_path / "huge.session"
    with session.open("wb") as stream:
        write_session(stream, dict(content.header), arrays, list(content.keyframe_points))
    for mode in ("--map", "--continue"):
        out = tmp_path / mode.strip("-")
        line = one_error_line(run_replay(logs.inside, "--out", out, mode, session))
        assert str(session) in line and "too large to" in line
        assert file_names(out) == set()


def test_the_api_refuses_what_the_command_refuses(logs: Logs, tmp_path: Path) -> None:
    with pytest.raises(PipelineError, match="not both"):
        pipeline.replay(logs.inside, out_dir=tmp_path, map=logs.session, continue_from=logs.session)
    with pytest.raises(PipelineError, match="initial pose"):
        pipeline.replay(logs.inside, out_dir=tmp_path, continue_from=logs.session, initial_pose=(0, 0, 0))
    for pose in ((0.0, math.nan, 0.0), "1,2,3", "123", (1.0, 2.0), ("x", 0, 0), 5.0):
        with pytest.raises(PipelineError, match="three finite numbers"):
            pipeline.replay(logs.inside, out_dir=tmp_path, map=logs.session, initial_pose=pose)  # type: ignore[arg-type]
    assert file_names(tmp_path) == set()
    assert issubclass(MapPlacementError, FrontendError)


def test_a_log_driving_through_the_walls_of_another_buildings_map_is_warned_of(tmp_path: Path) -> None:
    # Real logs: CSAIL placed in the mumble loop's map (an RPLidar robot's hallway and room) by a look-alike
    # stretch. All of its 39 scans on the mapping robot's path matched the map, so the on-path share said
    # nothing; tracked on its own scans from there, the run crosses the map's walls 14 times.
    mapped = pipeline.replay(shared_file("logs/mumble/hallway_room_loop"), out_dir=tmp_path / "map")
    other = run_replay(shared_file("logs/csail/csail.mcap"), "--map", mapped.outputs["session"],
                       "--out", tmp_path / "other")
    assert other.exit_code == 2 or "cross its walls" in other.stderr, other.output
    if other.exit_code == 0:
        counts = json.loads((tmp_path / "other" / "csail.json").read_text())["counts"]
        assert counts["saved_map_wall_crossings"] >= 10
    # The log of the map's own place does not cross them.
    own = run_replay(shared_file("logs/mumble/hallway_room_loop"), "--map", mapped.outputs["session"],
                     "--out", tmp_path / "own")
    assert own.exit_code == 0 and "cross its walls" not in own.stderr, own.output
    own_counts = json.loads((tmp_path / "own" / "hallway_room_loop.json").read_text())["counts"]
    assert own_counts["saved_map_wall_crossings"] == 0


def test_a_log_placed_in_the_map_of_another_building_is_warned_of(tmp_path: Path) -> None:
    # Real logs: the CSAIL map, the CSAIL log of another container (the same run), and ACES (Austin): its
    # first 1500 scans (5 minutes; the whole log, 30 s longer, was refused or warned of alike).
    mapped = pipeline.replay(shared_file("logs/csail/csail.mcap"), out_dir=tmp_path / "map")
    session = mapped.outputs["session"]
    own = run_replay(shared_file("logs/csail/csail.bag"), "--map", session, "--out", tmp_path / "own")
    assert own.exit_code == 0, own.output
    assert "did not match the saved map" not in own.stderr
    counts = json.loads((tmp_path / "own" / "csail.json").read_text())["counts"]
    assert counts["scans_on_saved_path"] > 1000 and counts["scans_on_saved_path_unmatched"] == 0
    aces = write_log_start(shared_file("logs/aces/aces.mcap"), tmp_path / "aces.mcap", 1500)
    other = run_replay(aces, "--map", session, "--out", tmp_path / "other")
    # Refused (no unambiguous match anywhere), or placed by a look-alike corridor and then said to be off.
    assert other.exit_code == 2 or "did not match the saved map" in other.stderr, other.output
    # Mapping ACES on from CSAIL's session: refused, or said to close no loop where it overlays the map.
    merged = run_replay(aces, "--continue", session, "--out", tmp_path / "merged", "--allow-unconverged")
    assert merged.exit_code == 2 or "closed 0 loops with the saved keyframes" in merged.stderr, merged.output
