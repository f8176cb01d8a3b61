"""Where a point-cloud replay spends its time: process CPU and wall seconds per stage (issue 12, item 3).

    python benchmarks/slam3d_stages.py [LOG.mcap ...] [--shared ../shared] [--town [--laps N]]

Runs `replay_log` (what `replay LOG` runs) with the stages' functions wrapped by timers, then KISS-ICP
alone (its default configuration, `kiss_icp.config.load_config(None)` as in `slam3d_bench.py`) on the
same decoded frames, deskewed from the azimuths as our default does (or with their per-point times).
Default log: `kitti_city.mcap`; `--town` adds the synthetic town loop of `kiss_slam_compare.py`
(`tests.lidar_world.loop_drive`, written as an MCAP in a temporary folder): loop closures happen there;
`--laps N` drives it N times around (`kiss_slam_compare.town_drive`).

Times are *exclusive*: entering a stage pauses the one it was entered from (a loop verification inside
the loop search counts only once). CPU time is the process's (`time.process_time`: every thread, so
KISS-ICP's and small_gicp's worker threads are counted, and so is rerun's writer thread, charged to the
stage running beside it). On a loaded machine the wall times mostly measure the load; compare CPU.
The wrapping is done here, by patching the functions for the run: the library has no timing hooks.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rerun as rr  # noqa: E402
from kiss_icp import kiss_icp, mapping, preprocess, registration  # noqa: E402
from kiss_icp.config import load_config  # noqa: E402

import pipeline.replay_log as replay_module  # noqa: E402
from benchmarks.kiss_slam_compare import town_drive  # noqa: E402
from frontends.logs import open_log  # noqa: E402
from frontends.slam3d import frontend, odometry, pose_graph3d, slam  # noqa: E402
from frontends.slam3d.odometry import azimuth_point_times, normalized_point_times  # noqa: E402
from pipeline import recording  # noqa: E402
from pipeline.recording import clouds as cloud_recording  # noqa: E402
from tests.lidar_world import write_cloud_log  # noqa: E402

KITTI = "data/logs/kitti/kitti_city.mcap"


class StageClock:
    """Exclusive CPU and wall seconds per named stage; time outside every stage goes to "other"."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = defaultdict(float)
        self.wall: dict[str, float] = defaultdict(float)
        self._stack = ["other"]
        self._cpu_mark = time.process_time()
        self._wall_mark = time.perf_counter()

    def _charge(self) -> None:
        cpu, wall = time.process_time(), time.perf_counter()
        self.cpu[self._stack[-1]] += cpu - self._cpu_mark
        self.wall[self._stack[-1]] += wall - self._wall_mark
        self._cpu_mark, self._wall_mark = cpu, wall

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self._charge()
        self._stack.append(name)
        try:
            yield
        finally:
            self._charge()
            self._stack.pop()

    def timed(self, function: Callable[..., Any], name: str) -> Callable[..., Any]:
        def run(*args: Any, **kwargs: Any) -> Any:
            with self.stage(name):
                return function(*args, **kwargs)

        return run

    def timed_iterator(self, iterator: Iterator[Any], name: str) -> Iterator[Any]:
        while True:
            with self.stage(name):
                item = next(iterator, StopIteration)
            if item is StopIteration:
                return
            yield item


READ = "read + decode PointCloud2"
SETUP = "tf, odometry, outputs staged"
TIMES = "deskew: times from azimuths"
DESKEW = "deskew: points moved (ours)"
KISS_DESKEW = "KISS-ICP: range filter (+ deskew given times)"
KISS_VOXEL = "KISS-ICP: voxelize"
KISS_ICP = "KISS-ICP: registration (ICP)"
KISS_MAP = "KISS-ICP: local map update"
KISS_OTHER = "KISS-ICP: rest of register_frame"
KEYFRAME = "keyframes (downsample, descriptor)"
LOOP_SEARCH = "loop search (descriptors, paths)"
VERIFY = "loop verification (GICP, ambiguity)"
ONLINE = "online optimization (Gauss–Newton)"
BACKEND = "final SGD backend"
POLISH = "SE(3) polish"
RECORD = "recording (rerun)"
MAP = "map (placed, voxel)"
PLY, PCD, SESSION, FILES = "write .ply", "write .pcd", "write .session", "write .tum/.g2o/.kitti/.json"
ORDER = (READ, SETUP, TIMES, DESKEW, KISS_DESKEW, KISS_VOXEL, KISS_ICP, KISS_MAP, KISS_OTHER, KEYFRAME,
         LOOP_SEARCH, VERIFY, ONLINE, BACKEND, POLISH, RECORD, MAP, PLY, PCD, SESSION, FILES, "other")


def _patches(clock: StageClock) -> list[Any]:
    """(owner, attribute, stage) of every function timed; see `ORDER` for the stages."""
    targets = [
        (frontend.LidarFrontend, "__init__", SETUP),
        (odometry.KissOdometry, "_sweep_times", TIMES),
        (odometry, "_deskew", DESKEW),
        (kiss_icp.KissICP, "register_frame", KISS_OTHER),
        (preprocess.Preprocessor, "preprocess", KISS_DESKEW),
        (kiss_icp.KissICP, "voxelize", KISS_VOXEL),
        (registration.Registration, "align_points_to_map", KISS_ICP),
        (mapping.VoxelHashMap, "update", KISS_MAP),
        (slam, "downsample", KEYFRAME),
        (slam.LidarSlam3D, "_add_keyframe", KEYFRAME),
        (slam.LidarSlam3D, "_close_loops", LOOP_SEARCH),
        (slam.LidarSlam3D, "_verify_loop", VERIFY),
        (slam.LidarSlam3D, "optimize_online", ONLINE),
        (replay_module, "optimize_keyframes", BACKEND),
        (pose_graph3d, "polish", POLISH),
        (slam.Slam3DGraph, "map_points", MAP),
        (replay_module, "write_ply", PLY),
        (replay_module, "write_map_pcd", PCD),
        (replay_module, "write_session_file", SESSION),
        (replay_module, "write_tum", FILES),
        (replay_module, "write_g2o", FILES),
        (replay_module, "write_kitti_poses", FILES),
        (replay_module, "write_text", FILES),
        (recording, "create_recording", RECORD),
        (recording, "close_recording", RECORD),
        (rr.RecordingStream, "log", RECORD),
        (rr.RecordingStream, "send_columns", RECORD),
        (rr.RecordingStream, "send_blueprint", RECORD),
        (cloud_recording.CloudReplayRecording, "frontend_done", RECORD),
        (cloud_recording.CloudReplayRecording, "final", RECORD),
        (cloud_recording.KeyframePoseRecorder, "add", RECORD),
        (cloud_recording.KeyframePoseRecorder, "flush", RECORD),
    ]
    patches = [mock.patch.object(owner, name, clock.timed(getattr(owner, name), stage))
               for owner, name, stage in targets]
    measurements = frontend.LidarFrontend.measurements
    patches.append(mock.patch.object(
        frontend.LidarFrontend, "measurements",
        lambda self: clock.timed_iterator(iter(measurements(self)), READ)))
    return patches


def _replay_with(clock: StageClock, path: Path, out_dir: Path) -> Any:
    with ExitStack() as stack:
        for patch in _patches(clock):
            stack.enter_context(patch)
        return replay_module.replay_log(path, out_dir=out_dir)


def kiss_icp_alone(path: Path) -> tuple[float, float, int]:
    """CPU and wall seconds of KISS-ICP alone (defaults, azimuth deskewing) on the log's frames, and the
    number of frames; reading excluded."""
    with open_log(path) as log:
        frames = [(c.points.astype(np.float64), c.point_times) for c in log.clouds()]
    odometry_only = kiss_icp.KissICP(load_config(None))
    cpu, wall = time.process_time(), time.perf_counter()
    for points, point_times in frames:
        times = azimuth_point_times(points) - 1.0 if point_times is None else point_times
        odometry_only.register_frame(points, normalized_point_times(times)[0])
    return time.process_time() - cpu, time.perf_counter() - wall, len(frames)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="*", type=Path)
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--town", action="store_true", help="also the synthetic town loop")
    parser.add_argument("--laps", type=int, default=1, help="with --town: drive the loop this many times")
    args = parser.parse_args()
    logs = list(args.logs) or [args.shared / KITTI]
    if args.town:
        town = Path(tempfile.mkdtemp()) / "town_loop.mcap"
        write_cloud_log(town, town_drive(args.laps))
        logs.append(town)
    for path in logs:
        clock = StageClock()
        cpu, wall = time.process_time(), time.perf_counter()
        result = _replay_with(clock, path, Path(tempfile.mkdtemp()))
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        frames = result.measurements
        kiss_cpu, kiss_wall, kiss_frames = kiss_icp_alone(path)
        counts = result.counts
        print(f"### {path.name}: {frames} clouds, {counts.get('points_per_cloud')} points each, "
              f"{counts.get('keyframes')} keyframes, {result.loop_closures['accepted']} loop closures\n")
        print("| stage | CPU s | CPU ms/frame | share | wall s |")
        print("|---|---|---|---|---|")
        for name in ORDER:
            if name in clock.cpu:
                print(f"| {name} | {clock.cpu[name]:.2f} | {1e3 * clock.cpu[name] / frames:.1f} | "
                      f"{100 * clock.cpu[name] / cpu:.0f} % | {clock.wall[name]:.2f} |")
        frontend_stages = (READ, TIMES, DESKEW, KISS_DESKEW, KISS_VOXEL, KISS_ICP, KISS_MAP, KISS_OTHER,
                           KEYFRAME, LOOP_SEARCH, VERIFY, ONLINE)
        frontend_cpu = sum(clock.cpu[name] for name in frontend_stages)
        print(f"| **total** | {cpu:.2f} | {1e3 * cpu / frames:.1f} | 100 % | {wall:.2f} |\n")
        print("| run | frames per CPU second | frames/s (wall) |")
        print("|---|---|---|")
        print(f"| replay end to end | {frames / cpu:.1f} | {frames / wall:.1f} |")
        print(f"| frontend (reading, odometry, keyframes, loops) | {frames / frontend_cpu:.1f} | "
              f"{frames / result.wall_time['frontend']:.1f} |")
        print(f"| KISS-ICP alone (frames in memory) | {kiss_frames / kiss_cpu:.1f} | "
              f"{kiss_frames / kiss_wall:.1f} |\n")


if __name__ == "__main__":
    main()
