"""Our trajectory files as evo (the trajectory-evaluation tool our users run next) reads them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.trajectory_io import write_tum

file_interface = pytest.importorskip("evo.tools.file_interface", reason="evo is in the test extras")
main_ape = pytest.importorskip("evo.main_ape", reason="evo is in the test extras")
from evo.core.metrics import PoseRelation  # noqa: E402  (after the skip)

START_NS = 1_700_000_000_123_456_789


def planar_drive(count: int) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * math.pi, count)
    heading = np.arctan2(5.0 * np.cos(t), -10.0 * np.sin(t))  # along the ellipse
    return np.stack([10.0 * np.cos(t), 5.0 * np.sin(t), heading], axis=1)


def test_evo_reads_our_tum_file(tmp_path: Path) -> None:
    poses = planar_drive(50)
    stamps = START_NS + np.arange(50, dtype=np.int64) * 100_000_000
    path = tmp_path / "run.tum"
    write_tum(path, stamps, poses)
    trajectory = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(trajectory.timestamps, stamps * 1e-9, rtol=0, atol=1e-6)
    np.testing.assert_allclose(trajectory.positions_xyz[:, :2], poses[:, :2], atol=1e-12)
    np.testing.assert_allclose(trajectory.positions_xyz[:, 2], 0.0, atol=1e-12)
    w, x, y, z = trajectory.orientations_quat_wxyz.T  # evo keeps w first
    np.testing.assert_allclose(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)), poses[:, 2],
                               atol=1e-12)


def test_evo_ape_between_two_of_our_files_is_their_offset(tmp_path: Path) -> None:
    poses = planar_drive(40)
    stamps = START_NS + np.arange(40, dtype=np.int64) * 50_000_000
    shifted = poses + np.array([0.3, -0.4, 0.0])  # 0.5 m everywhere
    write_tum(tmp_path / "reference.tum", stamps, poses)
    write_tum(tmp_path / "estimate.tum", stamps, shifted)
    reference = file_interface.read_tum_trajectory_file(str(tmp_path / "reference.tum"))
    estimate = file_interface.read_tum_trajectory_file(str(tmp_path / "estimate.tum"))
    result = main_ape.ape(reference, estimate, PoseRelation.translation_part)
    assert result.stats["rmse"] == pytest.approx(0.5, abs=1e-9)
    aligned = main_ape.ape(reference, estimate, PoseRelation.translation_part, align=True)
    assert aligned.stats["rmse"] == pytest.approx(0.0, abs=1e-9)


def test_a_log_with_scans_stamped_alike_replays_into_a_tum_file_evo_accepts(tmp_path: Path) -> None:
    from pipeline import replay
    from tests.hostile_fixtures import scan_log, walls

    log = scan_log(tmp_path / "twice.mcap", walls, count=40,
                   stamp=lambda i: START_NS + (i // 2) * 100_000_000)  # two scans a stamp
    with pytest.warns(Warning, match="20 scans skipped"):
        result = replay(log, out_dir=tmp_path / "out")
    trajectory = file_interface.read_tum_trajectory_file(str(result.outputs["tum"]))
    valid, details = trajectory.check()
    assert valid, details
    assert len(trajectory.timestamps) == 20
    assert result.summary["counts"]["scans_repeated_stamp"] == 20


def test_a_log_of_unstamped_scans_replays_one_pose_per_scan_at_its_log_time(tmp_path: Path) -> None:
    from pipeline import replay
    from tests.hostile_fixtures import scan_log, walls

    log = scan_log(tmp_path / "unstamped.mcap", walls, count=40, stamp=lambda i: 0)
    with pytest.warns(Warning, match="40 scans in frame 'base_link' had no stamp"):
        result = replay(log, out_dir=tmp_path / "out")
    trajectory = file_interface.read_tum_trajectory_file(str(result.outputs["tum"]))
    valid, details = trajectory.check()
    assert valid, details
    np.testing.assert_allclose(trajectory.timestamps, 1e9 + np.arange(40) * 0.1, rtol=0, atol=1e-6)
    assert result.summary["counts"]["messages_stamped_by_log_time"] == 40
