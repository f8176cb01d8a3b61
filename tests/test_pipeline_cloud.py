"""Replaying a 3D LiDAR log: a simulated town loop written as a real ROS 2 MCAP, replayed end to end."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from frontends.errors import TopicSelectionError
from frontends.slam3d import se3
from pipeline.ply import write_ply
from pipeline.replay_log import LogReplayResult, replay_log
from pipeline.trajectory_io import read_kitti_poses, read_tum
from tests._frontends_fixtures import write_mcap_ros
from tests.conftest import shared_file
from tests.lidar_world import (
    Lidar,
    drive,
    loop_drive,
    planar_to_matrix,
    town_loop,
    write_cloud_log,
)
from tests.pipeline_fixtures import modules_a_fresh_replay_loads, one_error_line, read_ply, read_recording


@pytest.fixture(scope="module")
def loop_replay(tmp_path_factory: pytest.TempPathFactory) -> tuple[LogReplayResult, Path, np.ndarray]:
    folder = tmp_path_factory.mktemp("cloud")
    path = folder / "town.mcap"
    stamps = write_cloud_log(path, loop_drive())
    result = replay_log(path, out_dir=folder / "out")
    return result, folder / "out", stamps


def test_outputs_are_written_and_the_trajectory_follows_the_truth(
    loop_replay: tuple[LogReplayResult, Path, np.ndarray],
) -> None:
    result, out, stamps = loop_replay
    assert sorted(p.name for p in out.iterdir()) == [
        "town.g2o",
        "town.json",
        "town.kitti",
        "town.pcd",
        "town.ply",
        "town.rrd",
        "town.session",
        "town.tum",
    ]
    trajectory = read_tum(out / "town.tum")
    # The KITTI file holds the same poses as the TUM file (both of base_link, in the map frame).
    kitti = read_kitti_poses(out / "town.kitti")
    assert len(kitti) == len(trajectory.stamps_ns)
    np.testing.assert_allclose(kitti[:, :2, 3], trajectory.planar()[:, :2], atol=1e-6)
    # The PCD map holds the PLY map's points.
    from pypcd4 import PointCloud

    pcd_points = PointCloud.from_path(out / "town.pcd").numpy(("x", "y", "z"))
    assert len(pcd_points) == len(read_ply(out / "town.ply"))
    np.testing.assert_array_equal(trajectory.stamps_ns, stamps)
    # poses are those of base_link (tf's mount taken out), from the first one; the truth likewise
    truth = loop_drive().base_poses
    estimated = trajectory.planar()
    relative = np.array(
        [se3.relative(planar_to_matrix(estimated[0]), planar_to_matrix(p)) for p in estimated]
    )
    expected = se3.relative(planar_to_matrix(truth[0]), planar_to_matrix(truth))
    errors = np.linalg.norm(relative[:, :2, 3] - expected[:, :2, 3], axis=1)
    assert errors.max() < 0.5 and errors[-1] < 0.2
    summary = json.loads((out / "town.json").read_text())
    assert summary["schema"] == "sgdslam.replay-log/3" and summary["sensor"] == "cloud"
    assert summary["topic"] == "/points" and summary["base_frame"] == "base_link"
    assert summary["sensor_frame"] == "lidar"
    assert summary["counts"]["clouds"] == len(stamps) == summary["counts"]["clouds_in_trajectory"]
    assert summary["loop_closures"]["accepted"] >= 1
    assert summary["counts"]["keyframes"] == len(result.keyframe_poses)
    assert summary["config"]["odometry"]["max_range"] == 100.0
    assert summary["warnings"] == []


def test_the_map_is_a_ply_of_points_on_the_world_s_surfaces(
    loop_replay: tuple[LogReplayResult, Path, np.ndarray],
) -> None:
    result, out, _ = loop_replay
    vertices = read_ply(out / "town.ply")
    assert vertices.dtype.names == ("x", "y", "z")
    assert len(vertices) == result.counts["map_points"]
    assert json.loads((out / "town.json").read_text())["counts"]["map_points"] == len(vertices)
    points = np.column_stack([vertices["x"], vertices["y"], vertices["z"]]).astype(np.float64)[::7]
    # Into the world frame with the true first pose: the points lie on the boxes or the ground, up to the
    # trajectory's errors (a few tenths of a degree of pitch moves a point 50 m away by decimetres).
    points = se3.transform_points(planar_to_matrix(loop_drive().base_poses[0]), points)
    boxes = town_loop().boxes
    gap = np.maximum(
        np.maximum(boxes[None, :, :3] - points[:, None, :], points[:, None, :] - boxes[None, :, 3:]), 0
    )
    distance = np.minimum(np.linalg.norm(gap, axis=2).min(axis=1), np.abs(points[:, 2]))
    assert np.median(distance) < 0.1
    assert np.mean(distance < 1.0) > 0.98


def test_the_recording_holds_every_iteration_in_2d_and_3d(
    loop_replay: tuple[LogReplayResult, Path, np.ndarray],
) -> None:
    result, out, _ = loop_replay
    entities = read_recording(out / "town.rrd")
    steps = list(range(len(result.chi2_per_iteration)))
    assert entities["/world/trajectory"].steps == steps
    assert entities["/world3d/trajectory"].steps == steps
    first = entities["/world3d/keyframes/k000000"]
    assert first.steps == steps and first.static_rows == 1
    last = f"/world3d/keyframes/k{len(result.keyframe_poses) - 1:06d}"
    assert entities[last].steps == steps
    assert entities["/world3d/map"].static_rows == 1
    assert entities["/world/loop_closures"].steps == steps
    rerun_cli = shutil.which("rerun")
    if rerun_cli is not None:  # installed with rerun-sdk
        check = subprocess.run(
            [rerun_cli, "rrd", "verify", str(out / "town.rrd")],
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
        assert check.returncode == 0, check.stdout + check.stderr


def _quaternion_values(column: object) -> np.ndarray:
    return np.asarray(column.as_arrow_array().flatten().flatten(), dtype=np.float64)  # type: ignore[attr-defined]


def test_keyframe_transform_columns_are_what_rerun_s_transform3d_makes_of_each_keyframe() -> None:
    import rerun as rr
    from scipy.spatial.transform import Rotation

    from pipeline.recording.clouds import keyframe_transform_columns, transform_columns

    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4, dtype=np.float32), (7, 5, 1, 1))
    poses[..., :3, :3] = Rotation.random(35, random_state=4).as_matrix().reshape(7, 5, 3, 3)
    poses[..., :3, 3] = rng.normal(scale=20.0, size=(7, 5, 3))
    batches = keyframe_transform_columns(poses)
    assert len(batches) == 5
    for k, columns in enumerate(batches):
        quaternions = Rotation.from_matrix(poses[:, k, :3, :3]).as_quat()
        expected = list(rr.Transform3D.columns(translation=poses[:, k, :3, 3].astype(np.float32),
                                               quaternion=quaternions.astype(np.float32)))
        assert [c.component_descriptor() for c in columns] == [c.component_descriptor() for c in expected]
        translation, quaternion = columns
        assert translation.as_arrow_array().equals(expected[0].as_arrow_array())
        # The same layout, and the quaternions within one float32 ulp of scipy's orthogonalizing conversion.
        assert quaternion.as_arrow_array().type == expected[1].as_arrow_array().type
        np.testing.assert_allclose(_quaternion_values(quaternion), _quaternion_values(expected[1]), atol=2e-7)
    single = transform_columns(poses[:, 2].astype(np.float64))
    assert all(a.as_arrow_array().equals(b.as_arrow_array()) for a, b in zip(single, batches[2], strict=True))


def test_without_tf_or_point_times_the_poses_are_the_sensor_s(tmp_path: Path) -> None:
    short = drive(town_loop(), sweeps=12, step=0.5, lidar=Lidar(columns=360))
    path = tmp_path / "bare.mcap"
    write_cloud_log(path, short, with_times=False, with_mount=False)
    result = replay_log(path, out_dir=tmp_path / "out", iterations=5)
    assert result.base_frame is None and result.sensor_frame == "lidar"
    summary = json.loads((tmp_path / "out" / "bare.json").read_text())
    assert summary["base_frame"] is None and summary["loop_closures"]["accepted"] == 0
    assert len(read_tum(tmp_path / "out" / "bare.tum")) == 12


def test_a_cloud_replay_never_imports_the_laser_frontend(tmp_path: Path) -> None:
    # Start-up: a replay of clouds should not pay for the laser frontend's compiled kernels (0.3 s). A fresh
    # process, as other tests of this session have imported it.
    short = drive(town_loop(), sweeps=6, step=0.5, lidar=Lidar(columns=360))
    path = tmp_path / "short.mcap"
    write_cloud_log(path, short)
    loaded = modules_a_fresh_replay_loads(path, tmp_path / "out", (
        "frontends.slam2d.", "pipeline.recording.scans", "pipeline.recording.map2d"))
    # The 2D settings' dataclass is read by the configuration of every replay; nothing else of 2D.
    assert loaded == ["frontends.slam2d.config"]


def test_a_replay_of_an_mcap_of_ros_messages_imports_neither_protobuf_nor_bag_readers(tmp_path: Path) -> None:
    # Start-up: protobuf's descriptors (through mcap_protobuf, for Foxglove channels) cost 0.1 s, the ROS bag
    # readers are of no use on an MCAP, and multiprocessing's process pool only runs several inputs; each
    # is imported only when needed.
    short = drive(town_loop(), sweeps=6, step=0.5, lidar=Lidar(columns=360))
    path = tmp_path / "short.mcap"
    write_cloud_log(path, short)
    loaded = modules_a_fresh_replay_loads(path, tmp_path / "out", (
        "google.protobuf", "mcap_protobuf", "frontends.logs.containers.rosbag", "multiprocessing",
        "concurrent.futures.process"))
    assert loaded == []


def test_a_log_with_scans_and_clouds_asks_which_and_writes_nothing(tmp_path: Path) -> None:
    path = write_mcap_ros(tmp_path / "both.mcap")  # /scan (LaserScan) and /points (PointCloud2)
    with pytest.raises(TopicSelectionError, match=r"/points .*/scan .*; choose one with --scan-topic"):
        replay_log(path, out_dir=tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_ply_round_trip(tmp_path: Path) -> None:
    points = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    write_ply(tmp_path / "cloud.ply", points)
    raw = (tmp_path / "cloud.ply").read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\n") and b"element vertex 50\n" in raw
    vertices = read_ply(tmp_path / "cloud.ply")
    np.testing.assert_array_equal(np.column_stack([vertices[a] for a in "xyz"]), points)
    with pytest.raises(ValueError, match="N, 3"):
        write_ply(tmp_path / "flat.ply", points[:, :2])


def test_kitti_city_replays_in_place(tmp_path: Path) -> None:
    """The shared KITTI sequence (read from ../shared, never copied): 154 clouds, no loop."""
    path = shared_file("logs/kitti/kitti_city.mcap")
    result = replay_log(path, out_dir=tmp_path, iterations=10)
    assert len(result.stamps_ns) == 154
    assert result.loop_closures["accepted"] == 0
    path_length = np.linalg.norm(np.diff(result.poses[:, :3, 3], axis=0), axis=1).sum()
    assert 60.0 < path_length < 85.0


def test_the_replay_command_routes_a_point_cloud_log_to_the_3d_replay(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    short = drive(town_loop(), sweeps=12, step=0.5, lidar=Lidar(columns=360))
    path = tmp_path / "street.mcap"
    write_cloud_log(path, short)
    out = tmp_path / "out"
    result = CliRunner().invoke(app, [str(path), "--out", str(out), "--iterations", "5"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [
        "street.g2o", "street.json", "street.kitti", "street.pcd", "street.ply", "street.rrd",
        "street.session", "street.tum"]
    assert "point clouds on /points" in result.stderr
    assert len(read_tum(out / "street.tum")) == 12


def test_options_and_progress_reach_the_3d_replay(tmp_path: Path) -> None:
    from pipeline import ReplayConfig, replay

    short = drive(town_loop(), sweeps=8, step=0.5, lidar=Lidar(columns=360))
    path = tmp_path / "street.mcap"
    write_cloud_log(path, short)
    seen: list[tuple[int, int]] = []
    config = ReplayConfig(input={"base_frame": "lidar"}, optimizer={"iterations": 3})
    result = replay(path, config, out_dir=tmp_path / "out",
                    on_scan=lambda estimate: seen.append((estimate.index, estimate.keyframe)))
    assert [index for index, _ in seen] == list(range(8))  # the progress callback sees every cloud
    assert seen[-1][1] + 1 == result.stats.poses > 1
    # the sensor frame chosen as the base: poses of the sensor, no mount
    assert (result.summary["base_frame"], result.summary["sensor_frame"]) == ("lidar", "lidar")
    # a keyframe distance longer than the drive: one keyframe, so the [slam3d] settings reached the SLAM
    far = replay(path, ReplayConfig(optimizer={"iterations": 3}, slam3d={"keyframes": {"distance": 100.0}}),
                 out_dir=tmp_path / "far")
    assert far.stats.poses == 1 and far.summary["config"]["keyframes"]["distance"] == 100.0
    with pytest.raises(TopicSelectionError, match=r"/nowhere.*--odom-topic"):
        replay(path, ReplayConfig(input={"odom_topic": "/nowhere"}), out_dir=tmp_path / "other")
    assert not (tmp_path / "other").exists()


def test_a_base_frame_tf_does_not_link_is_a_one_line_error_naming_the_log(tmp_path: Path) -> None:
    """`--base-frame` misspelt: the poses would be the LiDAR's, given as the base's; refused, the same
    rule and message as a laser log (`test_pipeline_log`)."""
    from typer.testing import CliRunner

    from pipeline.cli import app

    path = tmp_path / "street.mcap"
    write_cloud_log(path, drive(town_loop(), sweeps=3, step=0.5, lidar=Lidar(columns=360)))
    out = tmp_path / "out"
    arguments = [str(path), "--out", str(out), "--base-frame", "base_footprnt"]
    line = one_error_line(CliRunner().invoke(app, arguments))
    assert line == (f"replay: error: {path}: tf does not link base frame 'base_footprnt' to the LiDAR frame "
                    "'lidar' (frames in tf: base_link, lidar)")
    assert not out.exists() or not any(out.iterdir())


def test_ranges_that_keep_no_point_are_refused_naming_the_setting(tmp_path: Path) -> None:
    """A LiDAR range window that keeps nothing: refused with the settings when it is empty, and by the
    replay when it keeps none of this log's points (not identity poses and an empty map, exit 0)."""
    from frontends.errors import UnusableLogError
    from pipeline import replay
    from pipeline.config import ConfigError, config_from_mapping

    with pytest.raises(ConfigError, match=r"min_range: must be less than max_range \(10\)"):
        config_from_mapping({"slam3d": {"odometry": {"min_range": 50.0, "max_range": 10.0}}})
    path = tmp_path / "street.mcap"
    write_cloud_log(path, drive(town_loop(), sweeps=3, step=0.5, lidar=Lidar(columns=360)))
    # the town's nearest surfaces stand metres from the LiDAR
    config = config_from_mapping({"slam3d": {"odometry": {"max_range": 0.5}}})
    with pytest.raises(UnusableLogError, match=r"street\.mcap: no cloud on .* kept a point between"):
        replay(path, config, out_dir=tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_log_whose_clouds_cannot_be_registered_is_one_line_naming_it_and_skipped_clouds_are_warned_of(
        tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    street = drive(town_loop(), sweeps=8, step=0.5, lidar=Lidar(columns=360))
    few = tmp_path / "few.mcap"
    write_cloud_log(few, dataclasses.replace(street, clouds=tuple(c[:50] for c in street.clouds),
                                             times=tuple(t[:50] for t in street.times)))
    result = CliRunner().invoke(app, [str(few), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [f"replay: error: {few}: none of the 8 clouds had the 100 points "
                                          "spread over more than a voxel needed to register it"]
    one_bad = tmp_path / "one_bad.mcap"
    clouds = list(street.clouds)
    clouds[4] = clouds[4][:1].repeat(len(clouds[4]), axis=0)  # every point at one spot
    write_cloud_log(one_bad, dataclasses.replace(street, clouds=tuple(clouds)))
    result = CliRunner().invoke(app, [str(one_bad), "--out", str(tmp_path / "out"), "--quiet"])
    assert result.exit_code == 0, result.output
    warnings = json.loads((tmp_path / "out" / "one_bad.json").read_text())["warnings"]
    assert [w["message"] for w in warnings] == [
        "1 of the 8 clouds on /points had fewer than 100 points spread over more than a voxel to register: "
        "each was given the pose of the last registered cloud"]
