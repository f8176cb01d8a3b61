"""Run kiss-slam (PyPI `kiss-slam`, the 3D anchor) on frames saved by `kiss_slam_compare.py`.

    <kiss-slam python> benchmarks/kiss_slam_runner.py FRAMES.npz RESULT.npz [--splitting-distance M]

Runs in an interpreter that has `kiss-slam` installed; it imports nothing of this project (kiss-slam's
`map_closures` pins numpy < 2.3, which our environment may not have, so the comparison calls it in its
own environment). FRAMES.npz holds `points_<k>` (N, 3) float64 and `times_<k>` (N,) (empty: none) for
k = 0 … count − 1. The loop is that of kiss-slam's own `SlamPipeline._run_pipeline`: `process_scan` per
frame, then the last node and the fine-grained optimization. RESULT.npz gets `poses` (frames, 4, 4) of
the sensor in the first frame's sensor frame, `closures` (count), `seconds` and `cpu_seconds` (wall and
process CPU time of the processing loop only, reading excluded) and `frames`.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time

import numpy as np
from kiss_slam.config import load_config
from kiss_slam.slam import KissSLAM


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("frames")
    parser.add_argument("result")
    parser.add_argument("--splitting-distance", type=float, default=None)
    args = parser.parse_args()
    data = np.load(args.frames)
    count = int(data["count"])
    frames = [np.ascontiguousarray(data[f"points_{k}"], dtype=np.float64) for k in range(count)]
    times = [np.asarray(data[f"times_{k}"], dtype=np.float64) for k in range(count)]
    config = load_config(None)
    if args.splitting_distance is not None:
        config.local_mapper.splitting_distance = args.splitting_distance
    started, cpu_started = time.perf_counter(), time.process_time()
    with contextlib.redirect_stdout(io.StringIO()):  # it prints a line per closure
        slam = KissSLAM(config)
        for frame, stamps in zip(frames, times, strict=True):
            slam.process_scan(frame, stamps)
        slam.generate_new_node()
        slam.local_map_graph.erase_last_local_map()
        poses, _ = slam.fine_grained_optimization()
    seconds, cpu_seconds = time.perf_counter() - started, time.process_time() - cpu_started
    np.savez(
        args.result,
        poses=np.array(poses),
        closures=len(slam.get_closures()),
        seconds=seconds,
        cpu_seconds=cpu_seconds,
        frames=count,
    )


if __name__ == "__main__":
    main()
