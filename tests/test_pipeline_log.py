"""`replay LOG`: a simulated drive written as a real ROS 2 MCAP, replayed end to end through the CLI."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer as McapWriter
from PIL import Image
from typer.testing import CliRunner

from optimizer import se2
from pipeline.cli import app
from pipeline.trajectory_io import read_tum
from tests._frontends_fixtures import RosMessages, quaternion_from_yaw, ros2_mcap
from tests.laser_world import drive, simulate_scan, square_loop, wheel_odometry
from tests.test_pipeline_replay import read_recording

LASER_MOUNT = np.array([0.25, 0.0, 0.0])
"""The laser sits 25 cm ahead of the base: the replay must take that from /tf_static."""
BEAMS = 360
SCAN_PERIOD_NS = 400_000_000
START_NS = 1_700_000_000_000_000_000


def _ranges(points: np.ndarray) -> np.ndarray:
    """Sensor-frame points back to a 360-beam LaserScan's ranges (inf where a beam had no return)."""
    ranges = np.full(BEAMS, np.inf, dtype=np.float32)
    bearings = np.arctan2(points[:, 1], points[:, 0]) % (2 * math.pi)
    index = np.round(bearings / (2 * math.pi / BEAMS)).astype(int) % BEAMS
    ranges[index] = np.hypot(points[:, 0], points[:, 1])
    return ranges


def write_drive(path: Path, *, with_odometry: bool = True, scans: int | None = None) -> np.ndarray:
    """Drive the simulated building's loop, writing /scan, /odom, /tf and /tf_static; returns the truth
    (base poses) per scan."""
    rng = np.random.default_rng(7)
    truth = drive(square_loop(), 0.4)[:scans]
    odometry = wheel_odometry(truth, rng)
    with ros2_mcap(path) as (messages, add):
        types = messages.types

        def transform(stamp: int, parent: str, child: str, pose: np.ndarray) -> object:
            q = quaternion_from_yaw(float(pose[2]))
            return types["geometry_msgs/msg/TransformStamped"](
                header=messages.header(stamp, parent),
                child_frame_id=child,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=float(pose[0]), y=float(pose[1]), z=0.0),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )

        add(
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            START_NS,
            types["tf2_msgs/msg/TFMessage"](
                transforms=[transform(START_NS, "base_link", "laser", LASER_MOUNT)]
            ),
        )
        for k, pose in enumerate(truth):
            stamp = START_NS + k * SCAN_PERIOD_NS
            if with_odometry:
                q = quaternion_from_yaw(float(odometry[k, 2]))
                covariance = np.zeros(36)
                odom = types["nav_msgs/msg/Odometry"](
                    header=messages.header(stamp, "odom"),
                    child_frame_id="base_link",
                    pose=types["geometry_msgs/msg/PoseWithCovariance"](
                        pose=types["geometry_msgs/msg/Pose"](
                            position=types["geometry_msgs/msg/Point"](
                                x=odometry[k, 0], y=odometry[k, 1], z=0.0
                            ),
                            orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                        ),
                        covariance=covariance,
                    ),
                    twist=types["geometry_msgs/msg/TwistWithCovariance"](
                        twist=types["geometry_msgs/msg/Twist"](
                            linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        ),
                        covariance=covariance,
                    ),
                )
                add("/odom", "nav_msgs/msg/Odometry", stamp, odom)
                add(
                    "/tf",
                    "tf2_msgs/msg/TFMessage",
                    stamp,
                    types["tf2_msgs/msg/TFMessage"](
                        transforms=[transform(stamp, "odom", "base_link", odometry[k])]
                    ),
                )
            laser_pose = se2.compose(pose, LASER_MOUNT)
            points = simulate_scan(
                square_loop().segments, laser_pose, beams=BEAMS, max_range=20.0, range_noise=0.01, rng=rng
            )
            scan = types["sensor_msgs/msg/LaserScan"](
                header=messages.header(stamp, "laser"),
                angle_min=0.0,
                angle_max=float(2 * math.pi * (BEAMS - 1) / BEAMS),
                angle_increment=float(2 * math.pi / BEAMS),
                time_increment=0.0,
                scan_time=0.1,
                range_min=0.05,
                range_max=20.0,
                ranges=_ranges(points),
                intensities=np.zeros(0, dtype=np.float32),
            )
            add("/scan", "sensor_msgs/msg/LaserScan", stamp, scan)
    return truth


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
        "drive.tum",
        "drive_map.png",
    ]

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
    assert trajectory_entity.steps == list(range(len(summary["chi2_per_iteration"])))
    assert entities["/world/map"].static_rows == 1
    for static in ("/world/final_trajectory", "/world/odometry_trajectory", "/occupancy/grid"):
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


def test_replay_without_odometry_still_tracks(tmp_path: Path) -> None:
    path = tmp_path / "no_odometry.mcap"
    truth = write_drive(path, with_odometry=False, scans=60)
    result = CliRunner().invoke(app, [str(path), "--out", str(tmp_path / "out"), "--quiet"])
    assert result.exit_code == 0, result.output
    trajectory = read_tum(tmp_path / "out" / "no_odometry.tum")
    assert _max_position_error(trajectory.planar(), truth) < 0.15
    assert json.loads((tmp_path / "out" / "no_odometry.json").read_text())["odometry_topic"] is None


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
