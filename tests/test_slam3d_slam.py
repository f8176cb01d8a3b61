"""The 3D SLAM frontend end to end on a synthetic town loop: keyframes, loop closures, the planar graph."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from frontends.errors import FrontendError
from frontends.logs import Cloud3D
from frontends.slam3d import planar, se3
from frontends.slam3d.config import OdometryConfig, Slam3DConfig
from frontends.slam3d.odometry import OdometryStep
from frontends.slam3d.slam import LidarSlam3D, Slam3DGraph
from optimizer import se2
from optimizer.cost import chi2
from tests.lidar_world import (
    DistortedOdometry,
    Drive,
    Lidar,
    drive,
    homogeneous,
    loop_drive,
    rotation_z,
    town_loop,
)

PERIOD_NS = 100_000_000
YAW_DRIFT_PER_METRE = math.radians(0.08)


def yaw_drift(travel: float) -> np.ndarray:
    """KISS-ICP's heading drifting by a fixed rate per metre driven: the odometry a loop closure fixes.
    Locally (over a few keyframes) it is as good as KISS-ICP; over the loop it bends by 10°."""
    return homogeneous(rotation_z(YAW_DRIFT_PER_METRE * travel), np.zeros(3))


def clouds(drive_: Drive) -> list[Cloud3D]:
    return [
        Cloud3D(k * PERIOD_NS, k * PERIOD_NS, "lidar", points, times.astype(np.float64))
        for k, (points, times) in enumerate(zip(drive_.clouds, drive_.times, strict=True))
    ]


def planar_errors(graph: Slam3DGraph, keyframe_poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Position error of every cloud, both trajectories taken relative to their first pose."""
    poses = planar.planar(graph.cloud_poses(keyframe_poses))
    estimated = se2.relative(poses[0], poses)
    expected = se2.relative(truth[0], truth)
    return np.hypot(*(estimated[:, :2] - expected[:, :2]).T)


@pytest.fixture(scope="module")
def drifting_run() -> tuple[Slam3DGraph, list, Drive]:
    loop = loop_drive()
    slam = LidarSlam3D(sensor_to_base=loop.mount, odometry=DistortedOdometry(yaw_drift))
    estimates = [slam.add_cloud(cloud) for cloud in clouds(loop)]
    return slam.finish(), estimates, loop


def test_loop_closures_undo_the_odometry_drift(drifting_run: tuple[Slam3DGraph, list, Drive]) -> None:
    graph, estimates, loop = drifting_run
    odometry_errors = planar_errors(graph, graph.lift(graph.odometry_chain), loop.base_poses)
    slam_errors = planar_errors(graph, graph.keyframe_poses, loop.base_poses)
    assert odometry_errors[-1] > 1.0  # 10° of heading drift over the loop
    assert slam_errors[-1] < 0.3
    assert graph.loop_closures_accepted >= 2
    assert graph.loop_closures_rejected == 0
    # The loop closures pair the start with the end of the drive (the keyframes that see the same place).
    loops = [
        (a, b) for a, b, is_loop in zip(graph.edge_from, graph.edge_to, graph.is_loop, strict=True) if is_loop
    ]
    assert all(a < 10 and b > graph.num_keyframes - 12 for a, b in loops)
    assert sum(len(e.new_loop_closures) for e in estimates) == graph.loop_closures_accepted


def closing_keyframes(graph: Slam3DGraph, estimates: list) -> tuple[np.ndarray, np.ndarray]:
    """The keyframes whose loop search accepted loop closures, and every keyframe's path length (m)."""
    keyframes = np.array(sorted({e.keyframe for e in estimates if e.new_loop_closures}), dtype=np.int64)
    steps = np.linalg.norm(np.diff(graph.keyframe_odometry[:, :3, 3], axis=0), axis=1)
    return keyframes, np.concatenate([[0.0], np.cumsum(steps)])


def test_a_revisited_stretch_closes_once_per_travel_between_closures(
    drifting_run: tuple[Slam3DGraph, list, Drive],
) -> None:
    graph, estimates, loop = drifting_run
    spacing = Slam3DConfig().loop_closure.travel_between_closures
    assert spacing > 0
    closing, travel = closing_keyframes(graph, estimates)
    assert len(closing) >= 1 and np.all(np.diff(travel[closing]) >= spacing)
    # Without the spacing the same drive closes at one searching keyframe after another, each a verification.
    config = Slam3DConfig()
    every = replace(config, loop_closure=replace(config.loop_closure, travel_between_closures=0.0))
    slam = LidarSlam3D(every, sensor_to_base=loop.mount, odometry=DistortedOdometry(yaw_drift))
    every_estimates = [slam.add_cloud(cloud) for cloud in clouds(loop)]
    every_graph = slam.finish()
    every_closing, every_travel = closing_keyframes(every_graph, every_estimates)
    assert len(every_closing) > len(closing)
    assert np.any(np.diff(every_travel[every_closing]) < spacing)
    assert every_graph.loop_closures_accepted > graph.loop_closures_accepted
    # …and the spaced closures end no farther from the truth (within 5 cm)
    spaced_error = planar_errors(graph, graph.keyframe_poses, loop.base_poses)[-1]
    every_error = planar_errors(every_graph, every_graph.keyframe_poses, loop.base_poses)[-1]
    assert spaced_error < every_error + 0.05


def test_the_se3_polish_keeps_a_level_loop_level(drifting_run: tuple[Slam3DGraph, list, Drive]) -> None:
    graph, _, loop = drifting_run
    lifted = graph.lift(planar.planar(graph.keyframe_poses))
    polished = graph.polish_se3(lifted)
    assert polished.chi2_after <= polished.chi2_before
    assert planar_errors(graph, polished.poses, loop.base_poses)[-1] < 0.3
    # the street is level (heights relative to the first keyframe): KISS-ICP's height wanders on this
    # sparse sensor; the loop closures pull the end back onto the start and the wander does not grow
    before = se3.relative(lifted[0], lifted)[:, 2, 3]
    heights = se3.relative(polished.poses[0], polished.poses)[:, 2, 3]
    assert np.abs(heights).max() <= np.abs(before).max() + 0.01
    assert abs(heights[-1]) < 0.15


def test_the_graph_holds_the_whole_drive(drifting_run: tuple[Slam3DGraph, list, Drive]) -> None:
    graph, estimates, loop = drifting_run
    count = len(loop.clouds)
    assert len(graph.cloud_stamps_ns) == count and graph.clouds_untracked == 0
    np.testing.assert_array_equal(graph.cloud_stamps_ns, np.arange(count) * PERIOD_NS)
    assert np.all(np.diff(graph.cloud_keyframes) >= 0)
    assert np.all(graph.edge_from < graph.edge_to)
    odometry = ~graph.is_loop
    np.testing.assert_array_equal(graph.edge_to[odometry] - graph.edge_from[odometry], 1)
    assert len(graph.keyframe_clouds) == graph.num_keyframes
    # a keyframe once 1 m from the last: every second cloud at 0.8 m per cloud (after the start-up)
    assert 75 <= graph.num_keyframes <= 90
    # the online estimate of each cloud is its keyframe's pose times its offset
    final = graph.cloud_poses(graph.keyframe_poses)
    np.testing.assert_allclose(final[-1], estimates[-1].pose, atol=1e-9)
    # heights, roll and pitch are those of the odometry: the planar optimization never changes them
    np.testing.assert_allclose(graph.keyframe_poses[:, 2, :], graph.keyframe_odometry[:, 2, :], atol=1e-9)
    # the graph the backend gets is consistent with the online estimate (a low χ² per constraint)
    planar_graph = graph.planar_graph()
    assert chi2(planar_graph) / planar_graph.num_edges < 1.0


def test_keyframe_clouds_line_up_in_the_map(drifting_run: tuple[Slam3DGraph, list, Drive]) -> None:
    graph = drifting_run[0]
    # keyframe clouds are in the base frame: the ground lies at z ≈ 0 below the base
    first = graph.keyframe_clouds[0]
    ground = first[np.hypot(first[:, 0], first[:, 1]) < 8.0]
    assert abs(np.median(ground[:, 2])) < 0.05
    world = graph.map_points(graph.keyframe_poses, 0.5)
    assert world.dtype == np.float32 and world.shape[1] == 3
    assert len(world) < sum(len(c) for c in graph.keyframe_clouds)


def test_clouds_without_enough_points_are_skipped_or_keep_the_previous_pose() -> None:
    short = drive(town_loop(), sweeps=6, step=0.5, lidar=Lidar(columns=360))
    slam = LidarSlam3D(Slam3DConfig(odometry=OdometryConfig(min_points=200)))
    empty = Cloud3D(0, 0, "lidar", np.zeros((0, 3), np.float32), None)
    first = slam.add_cloud(empty)
    assert first.keyframe == -1 and not first.tracked
    estimates = [slam.add_cloud(cloud) for cloud in clouds(short)]
    sparse = Cloud3D(10 * PERIOD_NS, 0, "lidar", short.clouds[-1][:150], None)
    last = slam.add_cloud(sparse)
    assert not last.tracked
    np.testing.assert_array_equal(last.pose, estimates[-1].pose)
    graph = slam.finish()
    assert graph.clouds_dropped == 1 and graph.clouds_untracked == 2
    assert len(graph.cloud_stamps_ns) == len(short.clouds) + 1


def test_a_log_without_usable_clouds_is_an_error() -> None:
    slam = LidarSlam3D()
    slam.add_cloud(Cloud3D(0, 0, "lidar", np.zeros((3, 3), np.float32), None))
    with pytest.raises(FrontendError, match="none of the 1 clouds"):
        slam.finish()


def test_the_sensor_mount_is_taken_out_of_the_poses() -> None:
    mount = homogeneous(rotation_z(math.pi / 2), np.array([1.0, 0.0, 2.0]))  # sensor turned 90°, 1 m ahead
    poses = np.stack([homogeneous(rotation_z(0.1 * k), np.array([k, 0.0, 0.0])) for k in range(3)])

    class Scripted:
        def __init__(self) -> None:
            self.index = 0

        def register(
            self,
            points: np.ndarray,
            point_times: np.ndarray | None = None,
            motion_guess: np.ndarray | None = None,
        ) -> OdometryStep:
            # the sensor's poses when the base moves along `poses`
            sensor = se3.inverse(mount) @ poses[self.index] @ mount
            self.index += 1
            return OdometryStep(sensor, np.asarray(points, dtype=np.float64), sensor, False)

    slam = LidarSlam3D(sensor_to_base=mount, odometry=Scripted())
    points = np.random.default_rng(0).uniform(-5, 5, (300, 3)).astype(np.float32)
    estimates = [slam.add_cloud(Cloud3D(k, k, "lidar", points, None)) for k in range(3)]
    np.testing.assert_allclose(np.array([e.pose for e in estimates]), poses, atol=1e-12)
    # the keyframe cloud is in the base frame: (x, y, z) of the sensor is (1 − y, x, z + 2) of the base
    kept = slam.finish().keyframe_clouds[0]
    assert len(kept) > 0
    assert kept[:, 0].min() >= -4.0 - 1e-5 and kept[:, 0].max() > 5.5
    assert kept[:, 2].min() >= -3.0 - 1e-5 and kept[:, 2].max() > 6.5


def test_the_3d_frontend_never_imports_the_2d_one() -> None:
    # Start-up: a replay of clouds pays for what the 3D frontend imports; the 2D frontend (its matcher,
    # grids, localization) cost 0.3 CPU-s more. A fresh process, as other tests may have imported it.
    modules = sorted(
        f"frontends.slam3d.{path.stem}"
        for path in (Path(__file__).resolve().parents[1] / "frontends" / "slam3d").glob("*.py")
        if path.stem != "__init__"
    )
    program = (
        "import importlib, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        "print(sorted(name for name in sys.modules if name.startswith('frontends.slam2d')))\n"
    )
    run = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=300,
                         stdin=subprocess.DEVNULL, cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stdout + run.stderr
    assert len(modules) > 10  # every module of the 3D frontend was imported
    assert run.stdout.strip().splitlines()[-1] == "[]"
