"""`replay LOG`: a simulated drive written as a real ROS 2 MCAP, replayed end to end through the CLI."""

from __future__ import annotations

import errno
import hashlib
import itertools
import json
import os
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.writer import Writer as McapWriter
from PIL import Image
from typer.testing import CliRunner

from frontends.errors import MapExtentError
from frontends.logs import open_log
from frontends.slam2d import ScanEstimate
from frontends.slam2d import frontend as laser_frontend
from frontends.slam2d.log_input import scans_in_base_frame
from frontends.slam2d.occupancy import OccupancyGrid, occupancy_grid
from optimizer import se2
from optimizer.graph_files import read_graph
from pipeline.api import replay
from pipeline.cli import app
from pipeline.session_file import read_session
from pipeline.trajectory_io import read_tum
from tests._frontends_fixtures import RosMessages
from tests.laser_world import square_loop, transform_points, wall_distances, wheel_odometry
from tests.pipeline_fixtures import (
    SCAN_PERIOD_NS,
    START_NS,
    modules_a_fresh_replay_loads,
    one_error_line,
    read_recording,
    write_drive,
)


@pytest.fixture(scope="module")
def drive_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("log") / "drive.mcap"
    return path, write_drive(path)


def _max_position_error(poses: np.ndarray, truth: np.ndarray) -> float:
    # Both trajectories start at their own first pose: compare them in that frame.
    estimated = se2.relative(poses[0], poses)
    expected = se2.relative(truth[0], truth)
    return float(np.hypot(*(estimated[:, :2] - expected[:, :2]).T).max())


def test_replay_of_a_log_writes_a_trajectory_per_scan_that_follows_the_truth(
    drive_log: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    path, truth = drive_log
    out = tmp_path / "out"
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [
        "drive.g2o",
        "drive.json",
        "drive.rrd",
        "drive.session",
        "drive.tum",
        "drive_map.pgm",
        "drive_map.png",
        "drive_map.yaml",
    ]
    # The session holds the written keyframe graph, every scan's place on it, and names its source log.
    session = read_session(out / "drive.session")
    keyframes = read_graph(out / "drive.g2o").graph
    np.testing.assert_allclose(session.arrays["keyframe_poses"], keyframes.poses, atol=1e-9)
    np.testing.assert_array_equal(session.arrays["edge_from"], keyframes.edge_from)
    assert len(session.keyframe_points) == keyframes.num_poses
    np.testing.assert_array_equal(session.arrays["scan_stamps_ns"], read_tum(out / "drive.tum").stamps_ns)
    assert session.header["sensor_kind"] == "scan" and session.header["base_frame"] == "base_link"
    assert session.header["source"]["files"][0]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    map_yaml = yaml.safe_load((out / "drive_map.yaml").read_text())
    assert map_yaml["image"] == "drive_map.pgm" and map_yaml["mode"] == "trinary"
    assert (out / "drive_map.pgm").read_bytes().startswith(b"P5")

    trajectory = read_tum(out / "drive.tum")
    np.testing.assert_array_equal(trajectory.stamps_ns, START_NS + np.arange(len(truth)) * SCAN_PERIOD_NS)
    # The odometry drifts by metres over the loop; the SLAM trajectory (of the base, not the laser, which
    # sits 25 cm ahead) stays within a few centimetres of the truth.
    odometry = wheel_odometry(truth, np.random.default_rng(7))
    assert _max_position_error(odometry, truth) > 1.0
    assert _max_position_error(trajectory.planar(), truth) < 0.15

    summary = json.loads((out / "drive.json").read_text())
    assert summary["counts"]["scans"] == len(truth)
    assert summary["counts"]["scans_with_tf_mount"] == len(truth)
    assert summary["topic"] == "/scan" and summary["odometry_topic"] == "/odom"
    frames = (summary["sensor"], summary["sensor_frame"], summary["base_frame"])
    assert frames == ("scan", "laser", "base_link")
    assert summary["warnings"] == []
    assert summary["loop_closures"]["accepted"] >= 1

    entities = read_recording(out / "drive.rrd")
    trajectory_entity = entities["/world/trajectory"]
    assert "iteration" in trajectory_entity.timelines
    last_step = len(summary["chi2_per_iteration"]) - 1  # iterations that moved nothing are not redrawn
    assert trajectory_entity.steps[0] == 0 and trajectory_entity.steps[-1] == last_step
    assert set(trajectory_entity.steps) <= set(range(last_step + 1))
    assert entities["/world/keyframes/k000000"].steps[-1] == last_step
    for static in ("/world/final_trajectory", "/world/odometry_trajectory", "/world/occupancy/grid"):
        assert entities[static].static_rows == 1, static
    scans_entity = read_recording(out / "drive.rrd", timeline="scan")["/world/scan"]
    assert {"scan", "time"} <= scans_entity.timelines
    assert scans_entity.steps == list(range(len(truth)))

    # The map image: walls (black) around free space (white) seen by the laser, unknown (grey) elsewhere.
    picture = np.asarray(Image.open(out / "drive_map.png"))
    assert picture.dtype == np.uint8 and picture.ndim == 2
    assert set(np.unique(picture)) == {0, 205, 255}
    assert (picture == 255).mean() > 5 * (picture == 0).mean() > 0
    rerun_cli = shutil.which("rerun")
    if rerun_cli is not None:  # installed with rerun-sdk
        check = subprocess.run(
            [rerun_cli, "rrd", "verify", str(out / "drive.rrd")],
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
        assert check.returncode == 0, check.stdout + check.stderr


def _by_bearing(points: np.ndarray) -> np.ndarray:
    return points[np.argsort(np.arctan2(points[:, 1], points[:, 0]) % (2 * np.pi))]


def test_a_laser_mounted_upside_down_replays_as_one_mounted_upright(tmp_path: Path) -> None:
    """A laser mounted rolled by π (under a robot's deck, hung from a mast) sees the world mirrored, its
    beams turning clockwise seen from above. Its mount, from tf, turns its points back into the base frame:
    they are the upright laser's points (in the reverse order), and the replay follows the truth as well."""
    upright, rolled = tmp_path / "upright.mcap", tmp_path / "rolled.mcap"
    truth = write_drive(upright)  # the same seed: the same odometry and range noise
    np.testing.assert_array_equal(write_drive(rolled, upside_down=True), truth)
    with open_log(upright) as upright_log, open_log(rolled) as rolled_log:
        pairs = zip(scans_in_base_frame(upright_log, "/scan", upright_log.transform_tree(), None),
                    scans_in_base_frame(rolled_log, "/scan", rolled_log.transform_tree(), None), strict=True)
        for (upright_scan, _), (rolled_scan, mount) in itertools.islice(pairs, 30):
            assert mount is not None and rolled_scan.frame_id == "base_link"
            # Read without its roll, every point would be mirrored across the heading, metres off.
            np.testing.assert_allclose(_by_bearing(rolled_scan.points), _by_bearing(upright_scan.points),
                                       atol=1e-5)  # float32 bearings
    out = tmp_path / "out"
    result = CliRunner().invoke(app, [str(rolled), "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    assert _max_position_error(read_tum(out / "rolled.tum").planar(), truth) < 0.15


def test_frames_named_the_tf1_way_are_the_frames_tf2_names_without_the_slash(tmp_path: Path) -> None:
    """The laser's driver stamps "/laser" (tf1's names) while tf says "laser": tf2 drops the leading slash
    on every lookup, so in ROS the scans sit on the base; here too, and `--base-frame /base_link` names the
    same frame. Read as two frames, the poses would be the laser's (25 cm ahead of the base)."""
    path, out = tmp_path / "tf1.mcap", tmp_path / "out"
    truth = write_drive(path, scan_frame="/laser")
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet", "--base-frame", "/base_link"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "tf1.json").read_text())
    assert (summary["sensor_frame"], summary["base_frame"]) == ("laser", "base_link")
    assert summary["counts"]["scans_with_tf_mount"] == len(truth) and summary["warnings"] == []
    assert _max_position_error(read_tum(out / "tf1.tum").planar(), truth) < 0.15


def test_odometry_of_a_frame_tf_does_not_link_to_the_laser_is_a_warning(tmp_path: Path) -> None:
    """No tf says where the laser sits on the robot whose odometry the log holds: the poses are the laser's
    (`base_frame` null), its motion taken from the odometry of base_link; the summary says so."""
    path, out = tmp_path / "unmounted.mcap", tmp_path / "out"
    write_drive(path, scans=40, mount_on_tf=False)
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "unmounted.json").read_text())
    assert (summary["sensor_frame"], summary["base_frame"]) == ("laser", None)
    [warning] = summary["warnings"]
    assert warning["message"].startswith("tf gives no path from the laser's frame laser to the odometry's "
                                         "base_link: the odometry was taken as the laser's own motion")
    # Scans that name no frame at all: the same, and said so (before: no warning).
    write_drive(path, scans=40, mount_on_tf=False, scan_frame="")
    assert CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"]).exit_code == 0
    [warning] = json.loads((out / "unmounted.json").read_text())["warnings"]
    assert warning["message"].startswith("tf gives no path from the scans, which name no frame (frame_id "
                                         "empty), to the odometry's base_link")


def test_odometry_on_another_clock_than_the_scans_is_a_warning(tmp_path: Path) -> None:
    """Odometry stamped in seconds since boot beside a laser in epoch time covers none of the scans: the
    run is matched without it, and the summary says so (before: silently)."""
    path, out = tmp_path / "clocks.mcap", tmp_path / "out"
    truth = write_drive(path, scans=40, odometry_clock_ns=-START_NS + 5 * 10**9)
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "clocks.json").read_text())
    assert summary["counts"]["scans_with_odometry"] == 0
    [warning] = summary["warnings"]
    assert warning["message"].startswith("the odometry on /odom covers none of the 40 scans' stamps (it runs "
                                         "from 5.000 to ")
    assert "another clock?" in warning["message"]
    assert _max_position_error(read_tum(out / "clocks.tum").planar(), truth) < 0.15  # matched alone


def test_a_laser_replay_never_imports_the_3d_frontend(tmp_path: Path) -> None:
    # Start-up: every `replay` pays its imports; the 3D frontend (KISS-ICP, scipy's rotations) is for
    # logs of clouds. A fresh process, as other tests of this session may have imported it.
    path = tmp_path / "drive.mcap"
    write_drive(path, scans=20)
    loaded = modules_a_fresh_replay_loads(path, tmp_path / "out", (
        "frontends.slam3d.", "kiss_icp", "scipy.spatial", "pipeline.recording.clouds"))
    # The 3D settings' dataclass is read by the configuration of every replay; nothing else of 3D.
    assert loaded == ["frontends.slam3d.config"]


@pytest.mark.parametrize("sweep", [0.0, 0.1], ids=["instant", "swept"])
def test_the_closing_summary_of_a_log_replay(tmp_path: Path, sweep: float) -> None:
    path = tmp_path / "drive.mcap"
    write_drive(path, scans=20, sweep=sweep)
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    assert lines[0].startswith("drive.mcap: 20 scans on /scan, odometry /odom, base frame base_link; ")
    timed = [line for line in lines if "beam times" in line]
    assert timed == (["  20 scans with beam times (time_increment): deskewed"] if sweep else [])
    assert lines[-2].startswith("  time ") and lines[-1].startswith("  wrote ")


def test_odometry_read_from_tf_is_named_as_such(tmp_path: Path) -> None:
    path = tmp_path / "tf_odometry.mcap"
    truth = write_drive(path, scans=20, odometry_topic=False)
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert result.stderr.startswith("tf_odometry.mcap: 20 scans on /scan, odometry tf odom -> base_link, "
                                    "base frame base_link; ")
    summary = json.loads((tmp_path / "out" / "tf_odometry.json").read_text())
    assert summary["odometry_topic"] == "tf odom -> base_link"
    assert summary["counts"]["scans_with_odometry"] == 20
    trajectory = read_tum(tmp_path / "out" / "tf_odometry.tum")
    assert _max_position_error(trajectory.planar(), truth) < 0.15


def test_a_multi_echo_log_replays_as_the_log_of_its_first_echoes(tmp_path: Path) -> None:
    # The same drive, once as LaserScans and once as MultiEchoLaserScans whose first echoes are those ranges.
    single, multi = tmp_path / "single.mcap", tmp_path / "multi.mcap"
    write_drive(single, scans=30)
    write_drive(multi, scans=30, multi_echo=True)
    for path in (single, multi):
        result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out"), "--quiet"])
        assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "multi.tum").read_bytes() == (tmp_path / "out" / "single.tum").read_bytes()
    summary = json.loads((tmp_path / "out" / "multi.json").read_text())
    assert summary["topic"] == "/scan" and summary["counts"]["scans"] == 30


def test_replay_without_odometry_still_tracks(tmp_path: Path) -> None:
    path = tmp_path / "no_odometry.mcap"
    truth = write_drive(path, with_odometry=False, scans=60)
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out"), "--quiet"])
    assert result.exit_code == 0, result.output
    trajectory = read_tum(tmp_path / "out" / "no_odometry.tum")
    assert _max_position_error(trajectory.planar(), truth) < 0.15
    assert json.loads((tmp_path / "out" / "no_odometry.json").read_text())["odometry_topic"] is None


def _mean_relative_error(poses: np.ndarray, truth: np.ndarray, span: int) -> float:
    estimated, expected = se2.relative(poses[:-span], poses[span:]), se2.relative(truth[:-span], truth[span:])
    return float(np.mean(np.hypot(*(estimated[:, :2] - expected[:, :2]).T)))


@pytest.mark.parametrize("with_odometry", [True, False], ids=["odometry", "lidar-only"])
def test_replay_deskews_a_swept_laser_by_its_time_increment(tmp_path: Path, with_odometry: bool) -> None:
    # The laser takes its 360 beams over 0.1 s at 1 m/s (1 rad/s in the corners) and says so in
    # time_increment. Deskewing is on by default; `deskew = false` reads the same log as if it were not.
    # Through the container, the decoder, the frontend (the odometry over each sweep) and the SLAM.
    path = tmp_path / "swept.mcap"
    truth = write_drive(path, with_odometry=with_odometry, sweep=0.1)
    settings = tmp_path / "no_deskew.toml"
    settings.write_text("[slam2d.matching]\ndeskew = false\n")
    errors = {}
    for name, options, said in (("deskewed", [], "deskewed"),
                                ("as_if_instant", ["--config", str(settings)], "not deskewed")):
        out = tmp_path / name
        result = CliRunner().invoke(app, [str(path), "--out", str(out), *options])
        assert result.exit_code == 0, result.output
        assert f"  {len(truth)} scans with beam times (time_increment): {said}" in result.output
        assert json.loads((out / "swept.json").read_text())["counts"]["scans_with_beam_times"] == len(truth)
        errors[name] = _mean_relative_error(read_tum(out / "swept.tum").planar(), truth, span=10)
    # With odometry read over each sweep 0.008 against 0.023 m when this was written; without, from the
    # matched motions of scans 0.4 s apart (late at every corner), 0.017 against 0.024.
    assert errors["deskewed"] < (0.6 if with_odometry else 0.85) * errors["as_if_instant"], errors


@pytest.mark.parametrize("with_odometry", [True, False], ids=["odometry", "lidar-only"])
def test_the_scans_a_swept_replay_hands_on_are_deskewed(tmp_path: Path, with_odometry: bool) -> None:
    # The scans the recording plays back (each estimate's points, else the measured ones): placed at the
    # true base poses they lie on the walls, where the measured scans do not.
    path = tmp_path / "swept.mcap"
    truth = write_drive(path, with_odometry=with_odometry, scans=60, sweep=0.1)
    estimates: list[ScanEstimate] = []
    replay(path, out_dir=tmp_path / "out", on_scan=estimates.append)
    with open_log(path) as log:
        measured = [scan.points for scan, _ in
                    scans_in_base_frame(log, "/scan", log.transform_tree(), "base_link")]
    assert len(estimates) == len(measured) == len(truth)
    # Without odometry the first scan has no motion known: shown as measured.
    assert (estimates[0].points is None) != with_odometry
    walls = square_loop().segments
    shown_off, measured_off = [], []
    for estimate, raw, pose in zip(estimates[1:], measured[1:], truth[1:], strict=True):
        assert estimate.points is not None and estimate.points.shape == raw.shape
        shown_off.append(np.percentile(wall_distances(transform_points(estimate.points, pose), walls), 90))
        measured_off.append(np.percentile(wall_distances(transform_points(raw, pose), walls), 90))
    assert np.median(shown_off) < 0.5 * np.median(measured_off), (shown_off, measured_off)


def test_evaluate_scores_the_replayed_trajectory_against_true_relations(
    drive_log: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    path, truth = drive_log
    out = tmp_path / "out"
    assert CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"]).exit_code == 0
    stamps = START_NS + np.arange(len(truth)) * SCAN_PERIOD_NS
    pairs = [(i, i + 3) for i in range(0, len(truth) - 3, 5)] + [(0, len(truth) - 1)]
    lines = []
    for i, j in pairs:
        motion = se2.relative(truth[i], truth[j])
        lines.append(
            f"{stamps[i] / 1e9:.9f} {stamps[j] / 1e9:.9f} {motion[0]:.9f} {motion[1]:.9f} 0 0 0 "
            f"{motion[2]:.9f}"
        )
    relations = tmp_path / "drive.relations"
    relations.write_text("\n".join(lines) + "\n")
    result = CliRunner().invoke(app, ["evaluate", str(out / "drive.tum"), str(relations), "--json"])
    assert result.exit_code == 0, result.output
    scores = json.loads(result.stdout)
    assert scores["count"] == len(pairs) and scores["unmatched"] == 0
    assert scores["translation_mean"] < 0.05
    assert scores["rotation_mean_deg"] < 1.0


def test_a_log_without_scans_is_a_one_line_error_and_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "odometry_only.mcap"
    messages = RosMessages(ros1=False)
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start(profile="ros2", library="sgdslam tests")
        definition, _ = messages.store.generate_msgdef("tf2_msgs/msg/TFMessage", ros_version=2)
        schema = writer.register_schema("tf2_msgs/msg/TFMessage", "ros2msg", definition.encode())
        channel = writer.register_channel("/tf", "cdr", schema)
        writer.add_message(
            channel,
            START_NS,
            messages.serialize(
                messages.types["tf2_msgs/msg/TFMessage"](transforms=[]), "tf2_msgs/msg/TFMessage"
            ),
            START_NS,
        )
        writer.finish()
    out = tmp_path / "out"
    result = CliRunner().invoke(app, [str(path), "--out", str(out)])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("replay: error: ") and str(path) in lines[0]
    assert "Traceback" not in result.output
    assert not out.exists()


def test_a_base_frame_tf_does_not_link_is_a_one_line_error_naming_the_log(
    drive_log: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """`--base-frame` misspelt: the scans would stay in the laser's frame and the poses be the laser's,
    given as the base's; refused. Without the option the base comes from tf (the first test)."""
    path, _ = drive_log
    out = tmp_path / "out"
    arguments = [str(path), "--out", str(out), "--base-frame", "base_footprnt"]
    line = one_error_line(CliRunner().invoke(app, arguments))
    assert line == (f"replay: error: {path}: tf does not link base frame 'base_footprnt' to the laser frame "
                    "'laser' (frames in tf: base_link, laser, odom)")
    assert not out.exists() or not any(out.iterdir())


def test_info_lists_topics_from_the_summary(tmp_path: Path) -> None:
    path = tmp_path / "short.mcap"
    write_drive(path, scans=5)
    result = CliRunner().invoke(app, ["info", str(path), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info["path"] == str(path) and info["container"] == "mcap"
    assert info["start_ns"] == START_NS and info["end_ns"] == START_NS + 4 * SCAN_PERIOD_NS
    counts = {topic["name"]: (topic["type"], topic["count"]) for topic in info["topics"]}
    assert counts == {
        "/scan": ("sensor_msgs/msg/LaserScan", 5),
        "/odom": ("nav_msgs/msg/Odometry", 5),
        "/tf": ("tf2_msgs/msg/TFMessage", 5),
        "/tf_static": ("tf2_msgs/msg/TFMessage", 1),
    }
    table = CliRunner().invoke(app, ["info", str(path)])
    assert table.exit_code == 0
    assert (
        "/scan" in table.stdout and "sensor_msgs/msg/LaserScan" in table.stdout and "2.50 Hz" in table.stdout
    )


def test_info_on_a_file_that_is_not_a_log_is_a_one_line_error(tmp_path: Path) -> None:
    path = tmp_path / "notes.mcap"
    path.write_text("not a log")
    result = CliRunner().invoke(app, ["info", str(path)])
    assert result.exit_code == 2
    assert result.output.strip().count("\n") == 0 and str(path) in result.output


def test_info_on_a_truncated_log_warns_in_one_line_and_lists_what_is_left(tmp_path: Path) -> None:
    whole, cut = tmp_path / "whole.mcap", tmp_path / "cut.mcap"
    write_drive(whole, scans=40)
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    result = CliRunner().invoke(app, ["info", str(cut)])
    assert result.exit_code == 0, result.output
    warnings = result.stderr.splitlines()
    assert len(warnings) == 1 and warnings[0].startswith(f"replay: warning: {cut}: file is truncated")
    assert result.stdout.startswith(f"{cut}: mcap")


def test_a_log_cut_before_its_scans_fails_in_one_line_that_says_it_was_cut(tmp_path: Path) -> None:
    """The error alone ('no LaserScan or PointCloud topic; the log has: no topics') hid the cause, which
    only `replay info` printed."""
    whole, cut = tmp_path / "whole.mcap", tmp_path / "cut.mcap"
    write_drive(whole, scans=40)
    cut.write_bytes(whole.read_bytes()[:200])
    result = CliRunner().invoke(app, [str(cut), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    [line] = result.stderr.splitlines()
    assert line.startswith(f"replay: error: {cut}: ") and "; while reading: file is truncated" in line


def test_a_map_picture_failing_on_its_own_thread_is_one_line_and_keeps_the_old_outputs(
    drive_log: tuple[Path, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The map files are written on a thread beside the replay (`replay_log._WrittenBeside`): what fails
    # there must reach the command as on the main thread.
    path, _ = drive_log
    out = tmp_path / "out"
    assert CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"]).exit_code == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    save = Image.Image.save

    def full_disk_for_png_files(image: Image.Image, fp: object, format: str | None = None,
                                **params: object) -> None:
        if format == "PNG" and isinstance(fp, os.PathLike):  # not the recording's, encoded in memory
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        save(image, fp, format, **params)  # type: ignore[arg-type]

    monkeypatch.setattr(Image.Image, "save", full_disk_for_png_files)
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and str(out / "drive_map.png") in lines[0]
    assert "No space left on device" in lines[0]
    assert "Traceback" not in result.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_the_map_made_beside_the_sent_iterations_is_the_written_poses_map_and_fails_as_one_line(
    drive_log: tuple[Path, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The map is made on the thread beside the replay while the recorded iterations are sent
    # (`replay_log._WrittenBeside.make_map`): it must be the map of the poses written, and what fails
    # there must reach the command as on the main thread.
    path, _ = drive_log
    out = tmp_path / "out"
    made: list[tuple[bool, np.ndarray]] = []

    def traced(scans: list[np.ndarray], poses: np.ndarray, **settings: float) -> OccupancyGrid:
        made.append((threading.current_thread() is threading.main_thread(), np.array(poses)))
        return occupancy_grid(scans, poses, **settings)

    monkeypatch.setattr(laser_frontend, "occupancy_grid", traced)
    assert CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"]).exit_code == 0
    assert len(made) == 1
    on_main_thread, poses = made[0]
    assert not on_main_thread
    written = read_graph(out / "drive.g2o").graph.poses
    np.testing.assert_allclose(poses, written, atol=1e-6)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def too_large(scans: list[np.ndarray], poses: np.ndarray, **settings: float) -> OccupancyGrid:
        raise MapExtentError("occupancy grid: a keyframe pose or point is not finite")

    monkeypatch.setattr(laser_frontend, "occupancy_grid", too_large)
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--quiet"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "occupancy grid: a keyframe pose or point is not finite" in lines[0]
    assert "Traceback" not in result.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
