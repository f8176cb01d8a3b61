"""Benchmark of the 3D LiDAR SLAM (issue 6): agreement with KISS-ICP on KITTI, frames per second.

    python benchmarks/slam3d_bench.py [--shared ../shared] [--out benchmarks/results] [--frames 163]

1. `../shared/data/logs/kitti/kitti_city.mcap` (154 real KITTI frames, read in place — never copied):
   `replay_log` (what `replay LOG` runs, here on point clouds) against KISS-ICP's own odometry run frame by
   frame with its default configuration (`kiss_icp.config.load_config(None)`) on the same decoded
   frames. Figures: the final position difference as a percentage of the path length (target ≤ 1 %),
   and frames per second of each.
2. Synthetic 100k-point frames (a 100-ring × 1024-column sensor driving once around the synthetic town of
   the tests, with per-point times, written as a ROS 2 MCAP in a temporary folder): frames per second end
   to end (reading, odometry, loop closures, optimization, recording, map and files; target ≥ 10 on this
   2-core machine), of the frontend alone and of KISS-ICP alone.

Prints markdown tables and writes the numbers to `<out>/slam3d_bench.json`. Outputs of the replays go to
temporary folders and are deleted (the KITTI licence is non-commercial: no derived map in the repo).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from kiss_icp.config import load_config  # noqa: E402
from kiss_icp.kiss_icp import KissICP  # noqa: E402

from frontends.logs import open_log  # noqa: E402
from frontends.slam3d import se3  # noqa: E402
from pipeline.replay_log import LogReplayResult, replay_log  # noqa: E402
from tests.lidar_world import Lidar, drive, planar_to_matrix, town_loop, write_cloud_log  # noqa: E402

KITTI = "data/logs/kitti/kitti_city.mcap"
TARGET_PERCENT = 1.0
TARGET_FPS = 10.0
SYNTHETIC_LIDAR = Lidar(rings=100, columns=1024)


def read_frames(path: Path) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    with open_log(path) as log:
        clouds = list(log.clouds())
    return [c.points.astype(np.float64) for c in clouds], [c.point_times for c in clouds]


def kiss_icp_alone(frames: list[np.ndarray], times: list[np.ndarray | None]) -> tuple[np.ndarray, float]:
    """KISS-ICP's own odometry with its default configuration, frame by frame: poses and seconds."""
    odometry = KissICP(load_config(None))
    poses = []
    started = time.perf_counter()
    for points, point_times in zip(frames, times, strict=True):
        stamps = np.empty(0) if point_times is None else _normalised(point_times)
        odometry.register_frame(points, stamps)
        poses.append(odometry.last_pose.copy())
    return np.array(poses), time.perf_counter() - started


def _normalised(times: np.ndarray) -> np.ndarray:
    span = float(np.ptp(times))
    return (times - times.min()) / span if span > 0 else np.empty(0)


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def kitti_section(shared: Path) -> dict[str, float]:
    path = shared / KITTI
    frames, times = read_frames(path)
    reference, kiss_seconds = kiss_icp_alone(frames, times)
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        result = replay_log(path, out_dir=Path(folder))
        replay_seconds = time.perf_counter() - started
    ours = result.poses
    length = path_length(reference)
    differences = np.linalg.norm(ours[:, :3, 3] - reference[:, :3, 3], axis=1)
    heading = se3.rotation_angle(se3.relative(reference[-1], ours[-1]))
    return {
        "frames": len(frames),
        "points_per_frame": float(np.mean([len(f) for f in frames])),
        "path_length_m": length,
        "final_difference_m": float(differences[-1]),
        "final_difference_percent": 100.0 * float(differences[-1]) / length,
        "max_difference_m": float(differences.max()),
        "final_rotation_difference_deg": float(np.degrees(heading)),
        "loop_closures": result.loop_closures["accepted"],
        "keyframes": len(result.keyframe_poses),
        "kiss_icp_fps": len(frames) / kiss_seconds,
        "replay_fps": len(frames) / replay_seconds,
        "frontend_fps": len(frames) / result.wall_time["frontend"],
    }


def synthetic_section(frames: int) -> dict[str, float]:
    loop = drive(town_loop(), sweeps=frames, step=0.8, lidar=SYNTHETIC_LIDAR)
    with tempfile.TemporaryDirectory() as folder:
        log = Path(folder) / "town100k.mcap"
        write_cloud_log(log, loop)
        clouds, times = read_frames(log)
        _, kiss_seconds = kiss_icp_alone(clouds, times)
        started = time.perf_counter()
        result = replay_log(log, out_dir=Path(folder) / "out")
        replay_seconds = time.perf_counter() - started
    errors = _errors_against_truth(result, loop.base_poses)
    return {
        "frames": frames,
        "points_per_frame": float(np.mean([len(c) for c in loop.clouds])),
        "path_length_m": float(loop.distances[-1] - loop.distances[0]),
        "loop_closures": result.loop_closures["accepted"],
        "keyframes": len(result.keyframe_poses),
        "final_error_m": float(errors[-1]),
        "max_error_m": float(errors.max()),
        "kiss_icp_fps": frames / kiss_seconds,
        "replay_fps": frames / replay_seconds,
        "frontend_fps": frames / result.wall_time["frontend"],
        "wall_time_s": result.wall_time,
    }


def _errors_against_truth(result: LogReplayResult, truth: np.ndarray) -> np.ndarray:
    estimated = se3.relative(result.poses[0], result.poses)[:, :2, 3]
    expected = se3.relative(planar_to_matrix(truth[0]), planar_to_matrix(truth))[:, :2, 3]
    return np.linalg.norm(estimated - expected, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument(
        "--frames", type=int, default=163, help="synthetic frames (163: once around the loop)"
    )
    args = parser.parse_args()
    results: dict[str, object] = {}
    print("## 3D LiDAR SLAM benchmark\n")
    if (args.shared / KITTI).is_file():
        kitti = kitti_section(args.shared)
        results["kitti_city"] = kitti
        ok = "✅" if kitti["final_difference_percent"] <= TARGET_PERCENT else "❌"
        fps_ok = "✅" if kitti["replay_fps"] >= TARGET_FPS else "❌"
        print(
            f"### kitti_city.mcap ({kitti['frames']} frames, {kitti['points_per_frame']:.0f} points each)\n"
        )
        print("| measure | value | target |")
        print("|---|---|---|")
        print(f"| path length (KISS-ICP alone) | {kitti['path_length_m']:.2f} m | |")
        print(
            f"| final position, ours − KISS-ICP | {kitti['final_difference_m']:.4f} m "
            f"({kitti['final_difference_percent']:.4f} % of the path) | ≤ {TARGET_PERCENT} % {ok} |"
        )
        print(f"| largest position difference on the way | {kitti['max_difference_m']:.4f} m | |")
        print(f"| final rotation difference | {kitti['final_rotation_difference_deg']:.4f}° | |")
        print(f"| keyframes / loop closures | {kitti['keyframes']} / {kitti['loop_closures']} | (no loop) |")
        print(f"| KISS-ICP alone | {kitti['kiss_icp_fps']:.1f} frames/s | |")
        print(f"| our frontend (odometry, keyframes, loop search) | {kitti['frontend_fps']:.1f} frames/s | |")
        print(f"| our replay end to end | {kitti['replay_fps']:.1f} frames/s | ≥ {TARGET_FPS} {fps_ok} |\n")
    else:
        print(f"(skipped kitti_city: {args.shared / KITTI} not found)\n")
    synthetic = synthetic_section(args.frames)
    results["synthetic_100k"] = synthetic
    fps_ok = "✅" if synthetic["replay_fps"] >= TARGET_FPS else "❌"
    print(
        f"### synthetic town loop ({synthetic['frames']} frames, {synthetic['points_per_frame']:.0f} points "
        "each, per-point times)\n"
    )
    print("| measure | value | target |")
    print("|---|---|---|")
    print(f"| path length | {synthetic['path_length_m']:.1f} m | |")
    print(f"| keyframes / loop closures | {synthetic['keyframes']} / {synthetic['loop_closures']} | |")
    print(
        f"| position error vs truth: final / largest | {synthetic['final_error_m']:.3f} m / "
        f"{synthetic['max_error_m']:.3f} m | |"
    )
    print(f"| KISS-ICP alone | {synthetic['kiss_icp_fps']:.1f} frames/s | |")
    print(f"| our frontend | {synthetic['frontend_fps']:.1f} frames/s | |")
    print(f"| our replay end to end | {synthetic['replay_fps']:.1f} frames/s | ≥ {TARGET_FPS} {fps_ok} |")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "slam3d_bench.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
