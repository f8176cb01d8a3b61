"""Run our 3D SLAM on frames saved by `kiss_slam_compare.py`, as `kiss_slam_runner.py` runs kiss-slam.

    python benchmarks/ours_runner.py FRAMES.npz RESULT.npz

The counterpart of `kiss_slam_runner.py` for the in-memory comparison: a fresh interpreter, the imports
done and the frames loaded before the clock starts, then timed what kiss-slam's runner times for its side:
the SLAM constructed, every frame through `LidarSlam3D.add_cloud`, and the final optimization of the
keyframe graph (the default method from the odometry and online starts, as `replay` runs it, lifted to
3D and polished in SE(3)). No reading, recording or files, like kiss-slam's loop. Numba kernels load from
their cache inside the clock (kiss-slam's lazy initialisation is inside its clock too).

FRAMES.npz holds `count`, `points_<k>` (N, 3) float32 in the sensor frame, `times_<k>` (N,) seconds
relative to the cloud's stamp, `stamps_ns` (count,) and `sensor_to_base` (4, 4). RESULT.npz gets `poses`
(clouds in the trajectory, 4, 4) of the base, `closures`, `seconds`, `cpu_seconds` and `frames`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from frontends.logs import Cloud3D  # noqa: E402
from frontends.slam3d import LidarSlam3D, Slam3DConfig, planar  # noqa: E402
from optimizer.solve import DEFAULT_METHOD, optimize  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("frames")
    parser.add_argument("result")
    args = parser.parse_args()
    data = np.load(args.frames)
    count = int(data["count"])
    stamps = data["stamps_ns"]
    clouds = [Cloud3D(int(stamps[k]), int(stamps[k]), "lidar", np.ascontiguousarray(data[f"points_{k}"]),
                      np.asarray(data[f"times_{k}"], dtype=np.float64)) for k in range(count)]
    mount = np.asarray(data["sensor_to_base"], dtype=np.float64)
    config = Slam3DConfig()
    started, cpu_started = time.perf_counter(), time.process_time()
    slam = LidarSlam3D(config, sensor_to_base=mount)
    for cloud in clouds:
        slam.add_cloud(cloud)
    graph = slam.finish()
    chain = planar.planar(graph.keyframe_odometry)
    online = planar.planar(graph.keyframe_poses)
    planar_poses = chain
    for iteration in optimize(graph.planar_graph(chain), method=DEFAULT_METHOD,
                              starts={"odometry": chain, "online": online}):
        planar_poses = iteration.poses
    polished = graph.polish_se3(graph.lift(planar_poses), config.se3_polish.max_iterations)
    poses = graph.cloud_poses(polished.poses)
    seconds, cpu_seconds = time.perf_counter() - started, time.process_time() - cpu_started
    np.savez(args.result, poses=poses, closures=graph.loop_closures_accepted, seconds=seconds,
             cpu_seconds=cpu_seconds, frames=count)


if __name__ == "__main__":
    main()
