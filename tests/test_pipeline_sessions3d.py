"""`replay CLOUDLOG --map SESSION` and `replay CLOUDLOG --continue SESSION` end to end (issue 13, 3D).

The simulated town loop (tests/lidar_world.py) is driven three times, each a log of its own recorded
apart (its own stamps; its KISS-ICP odometry starts at its own first cloud, so the odometry origin says
nothing about where it is in the map):
- `first`: the first ~60 m of the loop (of ~116 m), mapped by a plain replay;
- `inside`: 20 clouds from 20 m on, all inside the first map: localized with `--map`;
- `second`: from 75 m on (a stretch the first map never drove through) round into the mapped start of the
  loop: localized with `--map` (no initial pose: global localization must find it);
- `around`: `second` driven on round the loop, through the mapped stretch and back over its own start
  (128 m): continued with `--continue`. Its first ~45 m are placed in the map only once it reaches it.
The map's frame is the first log's: its first cloud's base pose is the origin, so the simulator's truth
seen from it is what every pose written must match.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

import pipeline
from frontends.slam3d import planar, se3
from frontends.slam3d.config import Slam3DConfig
from pipeline.cli import app
from pipeline.errors import PipelineError
from pipeline.session_file import SESSION_VERSION, SessionError, read_session, write_session
from pipeline.trajectory_io import read_kitti_poses, read_tum
from tests.lidar_world import Drive, Lidar, drive, planar_to_matrix, town_loop, write_cloud_log
from tests.pipeline_fixtures import one_error_line, read_recording, write_drive

HOUR_NS = 3600 * 10**9
STEP = 0.8
"""Metres per sweep (8 m/s)."""
SLACK = 0.1
"""What a localization may add (m) to the error of the map it localizes in: the map's own clouds are
placed with that error, and a registration onto them cannot do better than they are."""
UNMAPPED_TOLERANCE = 1.0
"""Position error (m) allowed of clouds placed by odometry alone from where global localization placed the
run, over an unmapped stretch of up to ~45 m (KISS-ICP drifts ~1 % here)."""
LOOP_TOLERANCE = 0.5
"""Position error (m) allowed of a drive round the whole loop mapped with its loop closures (as for a
plain replay of the loop in tests/test_pipeline_cloud.py)."""


@dataclass(frozen=True)
class Logs:
    first: Path
    first_drive: Drive
    inside: Path
    inside_drive: Drive
    second: Path
    second_drive: Drive
    around: Path
    around_drive: Drive
    session: Path
    map_error: float
    """The largest position error (m) of the first replay's own trajectory against the truth."""

    def truth_in_map_frame(self, *drives: Drive) -> np.ndarray:
        """(S, 3) planar truth of the drives' clouds, seen from the first log's first base pose."""
        poses = np.concatenate([d.base_poses for d in drives])
        origin = planar_to_matrix(self.first_drive.base_poses[0])
        return planar.planar(se3.relative(origin, planar_to_matrix(poses)))


def position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1])


def heading_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.abs((poses[:, 2] - truth[:, 2] + np.pi) % (2.0 * np.pi) - np.pi)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Logs:
    folder = tmp_path_factory.mktemp("sessions3d")
    world, lidar = town_loop(), Lidar(columns=720)
    first_drive = drive(world, sweeps=80, step=STEP, lidar=lidar, seed=1)
    inside_drive = drive(world, sweeps=20, step=STEP, start=20.0, lidar=lidar, seed=3)
    second_drive = drive(world, sweeps=75, step=STEP, start=75.0, lidar=lidar, seed=2)
    around_drive = drive(world, sweeps=160, step=STEP, start=75.0, lidar=lidar, seed=2)
    first, inside, second = folder / "first.mcap", folder / "inside.mcap", folder / "second.mcap"
    around = folder / "around.mcap"
    write_cloud_log(first, first_drive)
    write_cloud_log(inside, inside_drive, later_ns=2 * HOUR_NS)
    write_cloud_log(second, second_drive, later_ns=HOUR_NS)
    write_cloud_log(around, around_drive, later_ns=HOUR_NS)
    mapped = pipeline.replay(first, out_dir=folder / "first_out")
    logs = Logs(first, first_drive, inside, inside_drive, second, second_drive, around, around_drive,
                mapped.outputs["session"], 0.0)
    errors = position_errors(read_tum(folder / "first_out" / "first.tum").planar(),
                             logs.truth_in_map_frame(first_drive))
    return Logs(**{**logs.__dict__, "map_error": float(errors.max())})


def run_replay(*args: object) -> object:
    return CliRunner().invoke(app, [str(arg) for arg in args])


def file_names(folder: Path) -> set[str]:
    return {path.name for path in folder.iterdir()} if folder.exists() else set()


# ------------------------------------------------------------------------------------------- --map


def test_the_first_map_is_good_enough_to_test_against(logs: Logs) -> None:
    assert logs.map_error < 0.5  # 60 m of KISS-ICP without a loop closure


def test_map_localizes_a_log_inside_the_saved_map_without_an_initial_pose(logs: Logs, tmp_path: Path) -> None:
    session_bytes = logs.session.read_bytes()
    result = pipeline.replay(logs.inside, out_dir=tmp_path, map=logs.session)

    assert file_names(tmp_path) == {"inside.tum", "inside.kitti", "inside.json", "inside.rrd"}
    assert logs.session.read_bytes() == session_bytes
    trajectory = read_tum(tmp_path / "inside.tum")
    clouds = len(logs.inside_drive.clouds)
    assert len(trajectory.stamps_ns) == clouds, "every cloud placed: one pose per cloud"
    kitti = read_kitti_poses(tmp_path / "inside.kitti")
    np.testing.assert_allclose(kitti[:, :3, 3], trajectory.positions, atol=1e-6)
    truth = logs.truth_in_map_frame(logs.inside_drive)
    poses = trajectory.planar()
    assert position_errors(poses, truth).max() < logs.map_error + SLACK
    assert heading_errors(poses, truth).max() < math.radians(1.5)
    np.testing.assert_allclose(result.poses[:, :2], poses[:, :2], atol=1e-9)

    summary = json.loads((tmp_path / "inside.json").read_text())
    assert summary["mode"] == "map" and summary["sensor"] == "cloud"
    found = summary["localization"]
    assert found["scans"] == found["with_pose"] == clouds and found["never_localized"] == 0
    assert len(found["global_fixes"]) == 1, "found once, then tracked"
    per_scan = summary["per_scan"]
    assert len(per_scan["state"]) == len(per_scan["score"]) == clouds
    assert per_scan["state"].count("m") >= clouds - 2
    assert found["inlier_fraction"]["median"] > 0.8 and found["rms_m"]["median"] < 0.1
    assert summary["counts"]["map_keyframes"] == result.stats.poses
    # Placed where the mapping run drove, the clouds match the map there: no warning of another place.
    counts = summary["counts"]
    assert counts["scans_on_saved_path"] > 0 and counts["scans_on_saved_path_unmatched"] == 0
    assert summary["warnings"] == []

    entities = read_recording(tmp_path / "inside.rrd", timeline="scan")
    assert entities["/world3d/saved_map"].static_rows == 1
    assert entities["/world3d/final_trajectory"].static_rows == 1
    matched = [k for k, state in enumerate(per_scan["state"]) if state == "m"]
    assert entities["/localization/inlier_fraction"].steps == matched
    assert "/localization/score" not in entities, "a cloud's score is its inlier fraction: one curve"
    assert "/optimizer/log10_chi2" not in entities


def test_map_finds_a_log_that_starts_outside_the_saved_map(logs: Logs, tmp_path: Path) -> None:
    result = run_replay(logs.second, "--out", tmp_path, "--map", logs.session)
    assert result.exit_code == 0, result.stderr
    assert "localized in" in result.stderr
    summary = json.loads((tmp_path / "second.json").read_text())
    found = summary["localization"]
    assert found["global_fixes"], "global localization placed the run"
    trajectory = read_tum(tmp_path / "second.tum")
    stamps = logs.second_drive.clouds
    has_pose = np.array([state != "-" for state in summary["per_scan"]["state"]])
    assert len(trajectory.stamps_ns) == has_pose.sum() == found["with_pose"] <= len(stamps)
    assert has_pose[len(stamps) // 2:].all(), "the second half, back in the map, is localized"
    truth = logs.truth_in_map_frame(logs.second_drive)[has_pose]
    errors = position_errors(trajectory.planar(), truth)
    # Clouds placed after the fact through the odometry carry its drift over the unmapped stretch.
    in_map = np.array([state == "m" for state in summary["per_scan"]["state"]])[has_pose]
    assert errors[in_map].max() < logs.map_error + SLACK
    assert errors.max() < UNMAPPED_TOLERANCE


def test_map_with_an_initial_pose_tracks_from_the_first_cloud(logs: Logs, tmp_path: Path) -> None:
    start = logs.truth_in_map_frame(logs.inside_drive)[0] + np.array([0.3, -0.2, math.radians(3.0)])
    result = run_replay(logs.inside, "--out", tmp_path, "--map", logs.session,
                        "--initial-pose", ",".join(f"{value:.6f}" for value in start))
    assert result.exit_code == 0, result.stderr
    summary = json.loads((tmp_path / "inside.json").read_text())
    assert summary["localization"]["global_fixes"] == []
    assert summary["initial_pose"] == pytest.approx(start.tolist(), abs=1e-6)
    assert summary["per_scan"]["state"] == "m" * len(logs.inside_drive.clouds)
    poses = read_tum(tmp_path / "inside.tum").planar()
    assert position_errors(poses, logs.truth_in_map_frame(logs.inside_drive)).max() < logs.map_error + SLACK


# -------------------------------------------------------------------------------------- --continue


@dataclass(frozen=True)
class Continued:
    out: Path
    stderr: str
    summary: dict[str, Any]
    errors: np.ndarray
    """(S,) position error of every cloud of the session, old and new, in the TUM's order."""
    early: np.ndarray
    """(S,) the new clouds before the one placed in the map."""


@pytest.fixture(scope="module")
def continued(logs: Logs, tmp_path_factory: pytest.TempPathFactory) -> Continued:
    out = tmp_path_factory.mktemp("continued")
    result = run_replay(logs.around, "--out", out, "--continue", logs.session, "--allow-unconverged")
    assert result.exit_code == 0, result.stderr
    summary = json.loads((out / "around.json").read_text())
    truth = logs.truth_in_map_frame(logs.first_drive, logs.around_drive)
    errors = position_errors(read_tum(out / "around.tum").planar(), truth)
    old = len(logs.first_drive.clouds)
    index = np.arange(len(errors))
    early = (index >= old) & (index < old + summary["session"]["placement"]["scan"])
    return Continued(out, result.stderr, summary, errors, early)


def test_continue_maps_both_logs_into_one_trajectory_and_a_larger_session(logs: Logs,
                                                                          continued: Continued) -> None:
    assert "continued" in continued.stderr
    trajectory = read_tum(continued.out / "around.tum")
    old, new = len(logs.first_drive.clouds), len(logs.around_drive.clouds)
    summary = continued.summary
    counts = summary["counts"]
    unplaced = counts["scans_unplaced"]
    assert len(trajectory.stamps_ns) == old + new - unplaced, "every cloud of the session, old and new"
    first_stamps = read_tum(logs.session.with_suffix(".tum")).stamps_ns
    np.testing.assert_array_equal(trajectory.stamps_ns[:old], first_stamps)  # the old log's clouds first
    assert np.all(np.diff(trajectory.stamps_ns) > 0)
    assert unplaced == 0
    truth = logs.truth_in_map_frame(logs.first_drive, logs.around_drive)
    assert continued.errors.max() < LOOP_TOLERANCE, f"max error {continued.errors.max():.3f} m"
    assert heading_errors(trajectory.planar(), truth).max() < math.radians(1.5)
    assert len(read_kitti_poses(continued.out / "around.kitti")) == old + new

    assert summary["mode"] == "continue"
    assert summary["session"]["continued_from"] == str(logs.session)
    assert summary["session"]["placement"]["saved_keyframe"] >= 0
    before = pipeline.load_session(logs.session)
    assert counts["session_keyframes"] == len(before.keyframe_points)
    assert counts["session_scans"] == old and counts["clouds"] == new
    assert counts["loop_closures_old_new"] >= 2, "back at the start of the loop the runs close loops"
    assert summary["chi2_per_iteration"][0]["stage"] == "initial"

    after = pipeline.load_session(continued.out / "around.session")
    assert len(after.keyframe_points) > len(before.keyframe_points)
    assert len(after.arrays["cloud_stamps_ns"]) == old + new
    assert after.header["continued_from"]["path"] == str(logs.session.resolve())
    np.testing.assert_allclose(after.arrays["sensor_to_base"], logs.first_drive.mount, atol=1e-6)
    entities = read_recording(continued.out / "around.rrd")
    assert len(entities["/world3d/trajectory"].steps) >= 2  # recorded iteration by iteration


def test_continue_corrects_the_clouds_before_the_placement_by_loop_closures(logs: Logs,
                                                                            continued: Continued) -> None:
    """The new run's first ~45 m (outside the saved map) are placed only once it reaches the map; back over
    them a lap later the run closes loops with them, so they join the graph as keyframes of their own
    and end as well placed as the rest of the joint map (hung off the placed cloud by odometry alone they
    carried its drift back from the placement, ~0.5 m)."""
    session = pipeline.load_session(continued.out / "around.session").arrays
    keyframes = session["cloud_keyframes"]
    early = keyframes[continued.early]
    placed = keyframes[np.flatnonzero(continued.early)[-1] + 1]
    assert early.min() >= continued.summary["counts"]["session_keyframes"] and early.max() < placed
    driven = continued.early.sum() * STEP
    # a keyframe at every `distance` driven: with clouds STEP apart, at least one per 2 × distance
    assert len(np.unique(early)) >= driven / (2.0 * Slam3DConfig().keyframes.distance)
    loops = session["is_loop"] & np.isin(session["edge_from"], early) & (session["edge_to"] > placed)
    assert loops.any(), "the run, back over its first stretch, closes loops with it"
    errors = continued.errors
    # closed at both ends (placement and loop closures), its clouds are placed as the map they are in
    assert errors[continued.early].max() < errors[~continued.early].max() + SLACK


# ----------------------------------------------------------------------------------------- refusals


@pytest.mark.parametrize("damage", ["information zero", "no cloud"])
def test_a_session_with_nothing_to_use_is_one_line_naming_it(logs: Logs, tmp_path: Path, damage: str) -> None:
    saved = read_session(logs.session)
    arrays, clouds = dict(saved.arrays), list(saved.keyframe_points)
    if damage == "information zero":  # singular: a 3D constraint could not be projected onto the plane
        arrays["information"] = np.zeros_like(arrays["information"])
    else:
        clouds = [cloud[:0] for cloud in clouds]
    session = tmp_path / "bad.session"
    with session.open("wb") as stream:
        write_session(stream, dict(saved.header), arrays, clouds)
    for mode in ("--map", "--continue"):
        line = one_error_line(run_replay(logs.inside, "--out", tmp_path / "out", mode, session))
        assert line.startswith(f"replay: error: {session}: ")
        assert ("not symmetric positive definite" if damage == "information zero"
                else "no keyframe cloud") in line
    assert file_names(tmp_path / "out") == set()


@pytest.mark.parametrize("mode", ["--map", "--continue"])
def test_a_log_tf_does_not_tie_to_the_session_s_base_frame_is_refused(logs: Logs, tmp_path: Path,
                                                                       mode: str) -> None:
    """The saved poses are of base_link; a log without tf gives its LiDAR's poses, which were joined to
    them without a word (the continued .tum mixed the two frames, 1.9 m apart in height)."""
    bare = tmp_path / "bare.mcap"
    write_cloud_log(bare, logs.inside_drive, with_mount=False, later_ns=HOUR_NS)
    line = one_error_line(run_replay(bare, "--out", tmp_path / "out", mode, logs.session))
    assert line == (f"replay: error: {bare}: tf does not link base frame 'base_link' (the frame "
                    "first.session's poses are of; --base-frame names another) to the LiDAR frame 'lidar' "
                    "(frames in tf: none)")
    assert file_names(tmp_path / "out") == set()


def test_sessions_of_the_other_sensor_kind_are_refused(logs: Logs, tmp_path: Path) -> None:
    laser_log = tmp_path / "laser.mcap"
    write_drive(laser_log, part=slice(0, 5))
    laser_session = tmp_path / "laser.session"
    with laser_session.open("wb") as stream:
        write_session(stream, {"sensor_kind": "scan"}, {"keyframe_poses": np.zeros((1, 3))},
                      [np.zeros((4, 2))])
    out = tmp_path / "out"
    line = one_error_line(run_replay(laser_log, "--out", out, "--map", logs.session))
    assert "3D point clouds" in line and "2D laser scans" in line and str(logs.session) in line
    line = one_error_line(run_replay(logs.inside, "--out", out, "--continue", laser_session))
    assert "3D point clouds" in line and "2D laser scans" in line and str(laser_session) in line
    assert file_names(out) == set()


@pytest.mark.parametrize("mode", ["map", "continue"])
def test_a_log_never_placed_in_the_map_is_one_line_naming_it(logs: Logs, tmp_path: Path, mode: str) -> None:
    """Two clouds where the first map never drove: too little to place; the error names the log."""
    far = tmp_path / "far.mcap"
    two_clouds = drive(town_loop(), sweeps=2, step=STEP, start=75.0, lidar=Lidar(columns=720), seed=5)
    write_cloud_log(far, two_clouds, later_ns=HOUR_NS)
    out = tmp_path / "out"
    line = one_error_line(run_replay(far, "--out", out, f"--{mode}", logs.session))
    assert "saved map" in line and str(far) in line
    assert file_names(out) == set()


@pytest.mark.parametrize("damage", ["cut", "newer", "no poses", "information not positive definite"])
def test_a_damaged_or_newer_cloud_session_is_one_line_naming_it(logs: Logs, tmp_path: Path,
                                                                damage: str) -> None:
    session = tmp_path / "bad.session"
    if damage == "cut":
        data = logs.session.read_bytes()
        session.write_bytes(data[: len(data) // 2])
    elif damage.startswith("information"):  # well-formed arrays, a graph no graph file may hold
        saved = read_session(logs.session)
        arrays = {**saved.arrays, "information": -saved.arrays["information"]}
        with session.open("wb") as stream:
            write_session(stream, saved.header, arrays, saved.keyframe_points)
    else:
        header = {"sensor_kind": "cloud", **({"version": SESSION_VERSION + 1} if damage == "newer" else {})}
        with session.open("wb") as stream:
            write_session(stream, header, {"edge_from": np.zeros(0, dtype=np.int64)}, [np.zeros((4, 3))])
    out = tmp_path / "out"
    for option in ("--map", "--continue"):
        line = one_error_line(run_replay(logs.inside, "--out", out, option, session))
        assert line.startswith(f"replay: error: {session}: ")
    assert file_names(out) == set()
    with pytest.raises(SessionError, match=r"bad\.session"):
        pipeline.replay(logs.inside, out_dir=out, continue_from=session)


def test_the_api_refuses_an_initial_pose_when_continuing(logs: Logs, tmp_path: Path) -> None:
    with pytest.raises(PipelineError, match="initial pose"):
        pipeline.replay(logs.inside, out_dir=tmp_path, continue_from=logs.session, initial_pose=(0, 0, 0))
    assert file_names(tmp_path) == set()
