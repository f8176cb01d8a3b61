"""3D outputs: the map as a binary PCD beside the PLY, poses in KITTI's format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pypcd4 import PointCloud
from scipy.spatial.transform import Rotation

from pipeline.errors import OutputError
from pipeline.ply import write_map_pcd, write_ply
from pipeline.trajectory_io import TrajectoryFileError, read_kitti_poses, write_kitti_poses
from tests.pipeline_fixtures import read_ply


def test_the_pcd_map_is_binary_xyz_and_holds_the_points(tmp_path: Path) -> None:
    points = np.random.default_rng(3).uniform(-50, 50, (1000, 3)).astype(np.float32)
    write_map_pcd(tmp_path / "map.pcd", points)
    data = (tmp_path / "map.pcd").read_bytes()
    header = data[: data.index(b"DATA binary\n")].decode("ascii")
    assert "FIELDS x y z" in header and "SIZE 4 4 4" in header and "TYPE F F F" in header
    assert "POINTS 1000" in header and "WIDTH 1000" in header and "HEIGHT 1" in header
    # binary PCD: the header, then the float32 x y z of every point, nothing else
    body = data[data.index(b"DATA binary\n") + len(b"DATA binary\n") :]
    np.testing.assert_array_equal(np.frombuffer(body, dtype="<f4").reshape(-1, 3), points)
    # and PCL's format as pypcd4 reads it back
    np.testing.assert_array_equal(PointCloud.from_path(tmp_path / "map.pcd").numpy(("x", "y", "z")), points)


def test_pcd_and_ply_hold_the_same_map(tmp_path: Path) -> None:
    points = np.random.default_rng(4).normal(0, 10, (500, 3))
    write_map_pcd(tmp_path / "map.pcd", points)
    write_ply(tmp_path / "map.ply", points)
    ply = read_ply(tmp_path / "map.ply")
    pcd = PointCloud.from_path(tmp_path / "map.pcd").numpy(("x", "y", "z"))
    np.testing.assert_array_equal(np.stack([ply["x"], ply["y"], ply["z"]], axis=1), pcd)


def test_pcd_writing_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="N, 3"):
        write_map_pcd(tmp_path / "map.pcd", np.zeros((4, 2)))
    with pytest.raises(OutputError, match="cannot write"):
        write_map_pcd(tmp_path / "missing" / "map.pcd", np.zeros((4, 3)))


def test_kitti_poses_round_trip_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    poses = np.zeros((20, 4, 4))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, (20, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 100, (20, 3))
    poses[:, 3, 3] = 1.0
    write_kitti_poses(tmp_path / "poses.txt", poses)
    lines = (tmp_path / "poses.txt").read_text().splitlines()
    assert len(lines) == 20 and all(len(line.split()) == 12 for line in lines)
    # KITTI's layout: the 3×4 [R | t] row-major; the 4th field is tx
    assert float(lines[3].split()[3]) == poses[3, 0, 3]
    np.testing.assert_array_equal(read_kitti_poses(tmp_path / "poses.txt"), poses)


def test_kitti_poses_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="S, 4, 4"):
        write_kitti_poses(tmp_path / "p.txt", np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="finite"):
        write_kitti_poses(tmp_path / "p.txt", np.full((1, 4, 4), np.nan))
    (tmp_path / "bad.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n")
    with pytest.raises(TrajectoryFileError, match=r"bad\.txt:2"):
        read_kitti_poses(tmp_path / "bad.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(TrajectoryFileError, match="no poses"):
        read_kitti_poses(tmp_path / "empty.txt")


def test_evo_reads_our_kitti_file(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface", reason="evo is in the test extras")
    rng = np.random.default_rng(6)
    poses = np.zeros((10, 4, 4))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, (10, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 10, (10, 3))
    poses[:, 3, 3] = 1.0
    write_kitti_poses(tmp_path / "poses.txt", poses)
    trajectory = file_interface.read_kitti_poses_file(str(tmp_path / "poses.txt"))
    np.testing.assert_allclose(np.array(trajectory.poses_se3), poses, atol=1e-12)
