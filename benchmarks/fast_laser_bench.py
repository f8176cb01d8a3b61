"""Benchmark of fast lasers (`frontends.slam2d.cadence`): how often the 2D SLAM must match a laser's scans.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/fast_laser_bench.py [--seeds 3] [--intervals 0 0.05 0.1 0.2] [--lasers hokuyo sick]

Synthetic drives with ground truth (`tests/laser_world.py`, `simulate_swept_run` with instant scans): the
square loop of corridors driven at 1 and 2 m/s, drifting wheel odometry. Each drive is mapped by
`LaserSlam2D` with `[slam2d.matching] min_match_interval` set to each of `--intervals` (0: every scan
matched), with and without the odometry, then optimized as `replay` does. Every scan is scored, the ones
posed between matched scans too.

Reported per laser, speed, odometry and interval, as the mean over the seeds: the scans matched per
second of log (the cadence), the absolute trajectory error (RMSE over every scan, the first pose aligned),
the relative error over 10 m of driving (translation m, rotation deg), the error of each scan's motion from
the previous scan (mm, deg: what a user sees as jitter), and the SLAM's speed in scans per CPU second and
times real time (the frontend alone, in process: no reading, recording or outputs).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import laser_world  # noqa: E402

from benchmarks.deskew2d_bench import Laser  # noqa: E402
from benchmarks.sessions_bench import optimized  # noqa: E402
from frontends.slam2d.config import Slam2DConfig  # noqa: E402
from frontends.slam2d.slam import LaserSlam2D  # noqa: E402
from optimizer import se2  # noqa: E402

RELATIVE_DISTANCE = 10.0
"""The relative error is taken between scans this far apart along the drive (m)."""


LASERS = {  # taking every beam at the scan's stamp (no sweep): this measures the cadence alone
    "hokuyo": Laser("270°, 1081 beams, 40 Hz (Hokuyo UTM-30LX)", 1081, math.radians(270.0), 40.0, 0.0),
    "sick": Laser("270°, 541 beams, 25 Hz (SICK TiM / LMS1xx at 25 Hz)", 541, math.radians(270.0), 25.0, 0.0),
}


def figures(run: laser_world.Run, interval: float, with_odometry: bool) -> dict[str, float]:
    base = Slam2DConfig()
    matching = dataclasses.replace(base.matching, min_match_interval=interval)
    config = dataclasses.replace(base, matching=matching)
    slam = LaserSlam2D(config)
    started = time.process_time()
    for index, (stamp, points) in enumerate(zip(run.stamps_ns, run.scans, strict=True)):
        slam.add_scan(int(stamp), points, run.odometry[index] if with_odometry else None, 0.0)
    graph = slam.finish()
    cpu = time.process_time() - started
    poses = graph.scan_poses(optimized(graph))
    step_estimated = se2.relative(poses[:-1], poses[1:])
    step_true = laser_world.between(run.truth[:-1], run.truth[1:])
    seconds = (run.stamps_ns[-1] - run.stamps_ns[0]) * 1e-9
    return {
        "matched_rate": (len(poses) - graph.scans_between) / seconds,
        **laser_world.drive_errors(poses, run.truth, RELATIVE_DISTANCE),
        "step_mm": 1000.0 * float(np.mean(np.hypot(*(step_estimated[:, :2] - step_true[:, :2]).T))),
        "step_deg": float(np.degrees(np.mean(np.abs(laser_world.wrap(step_estimated[:, 2]
                                                                      - step_true[:, 2]))))),
        "scans_per_s": len(poses) / cpu,
        "real_time": seconds / cpu,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--speeds", type=float, nargs="+", default=[1.0, 2.0])
    parser.add_argument("--intervals", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.2])
    parser.add_argument("--lasers", nargs="+", choices=sorted(LASERS), default=list(LASERS))
    args = parser.parse_args()
    world = laser_world.square_loop()
    print("| laser | speed (m/s) | odometry | min_match_interval (s) | matched /s | ATE m | 10 m relative m "
          "| 10 m relative deg | scan-to-scan mm | scan-to-scan deg | scans/s (CPU) | × real time |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    with threadpool_limits(1):
        for name in args.lasers:
            laser = LASERS[name]
            for speed in args.speeds:
                runs = [laser_world.simulate_swept_run(world, speed=speed, scan_rate=laser.scan_rate,
                                                       sweep=0.0, seed=seed, beams=laser.beams,
                                                       fov=laser.fov, max_range=30.0)
                        for seed in range(args.seeds)]
                for with_odometry in (True, False):
                    for interval in args.intervals:
                        rows = [figures(run, interval, with_odometry) for run in runs]
                        mean = {key: float(np.mean([row[key] for row in rows])) for key in rows[0]}
                        print(f"| {name} | {speed:g} | {'yes' if with_odometry else 'no'} | {interval:g} "
                              f"| {mean['matched_rate']:.1f} | {mean['ate']:.3f} | {mean['relative_m']:.3f} "
                              f"| {mean['relative_deg']:.2f} | {mean['step_mm']:.2f} "
                              f"| {mean['step_deg']:.3f} "
                              f"| {mean['scans_per_s']:.0f} | {mean['real_time']:.0f} |", flush=True)
    print()
    for name in args.lasers:
        print(f"- {name}: {LASERS[name].description}")


if __name__ == "__main__":
    main()
