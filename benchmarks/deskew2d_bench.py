"""Benchmark of the 2D deskewing (`frontends.slam2d.deskew`): how much a laser's sweep costs the map, and
how much of it the deskewing wins back.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/deskew2d_bench.py [--seeds 2] [--speeds 0.5 1.0 1.5] [--lasers rplidar hokuyo slow]

Synthetic drives with ground truth (`tests/laser_world.py`, `simulate_swept_run`): the square loop of
corridors (corners rounded at 1 m, so the robot turns at `speed` rad/s there), a laser that takes its
beams one after the other while the robot moves, drifting wheel odometry. Each drive is mapped three
times by `LaserSlam2D`, then optimized as `replay` does:
- "instant": a laser taking all its beams at once (the floor: no sweep at all),
- "swept": the swept scans, their beam times not given (a driver leaving `time_increment` at 0),
- "deskewed": the swept scans with their beam times (the default when a driver sets `time_increment`):
  under the wheel odometry read over each sweep (`LaserFrontend`'s way), or without odometry under the
  recent matched motions (`ScanDeskewer`).

Reported per laser, speed and odometry (with / without), as the mean over the seeds: the absolute
trajectory error (RMSE over every scan, the first pose aligned) and the relative error over 10 m of
driving: translation (m) and rotation (deg).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import laser_world  # noqa: E402

from benchmarks.sessions_bench import optimized  # noqa: E402
from frontends.slam2d.frontend import deskewed_by_odometry  # noqa: E402
from frontends.slam2d.log_input import OdometryTrack  # noqa: E402
from frontends.slam2d.slam import LaserSlam2D  # noqa: E402

RELATIVE_DISTANCE = 10.0
"""The relative error is taken between scans this far apart along the drive (m)."""


@dataclass(frozen=True)
class Laser:
    description: str
    beams: int
    fov: float
    scan_rate: float
    """Scans per second."""
    sweep: float
    """Seconds from the first beam to the last."""


LASERS = {
    "rplidar": Laser("360°, 360 beams, 10 Hz, beams over the whole 0.1 s", 360, 2.0 * math.pi, 10.0, 0.1),
    "hokuyo": Laser("270°, 541 beams, 40 Hz, beams over 0.019 s", 541, math.radians(270.0), 40.0,
                    0.75 / 40.0),
    "slow": Laser("360°, 360 beams, 5 Hz, beams over the whole 0.2 s", 360, 2.0 * math.pi, 5.0, 0.2),
}


def errors(run: laser_world.Run, times: tuple[np.ndarray, ...] | None,
           with_odometry: bool) -> dict[str, float]:
    slam = LaserSlam2D()
    track = OdometryTrack(run.stamps_ns, run.odometry, "odom", "base_link")
    for index, (stamp, points) in enumerate(zip(run.stamps_ns, run.scans, strict=True)):
        odometry = run.odometry[index] if with_odometry else None
        point_times = None if times is None else times[index]
        if odometry is not None and point_times is not None:  # as `LaserFrontend.add` does
            points, point_times = deskewed_by_odometry(points, point_times, int(stamp), track, odometry, 0)
        slam.add_scan(int(stamp), points, odometry, 0.0, point_times)
    graph = slam.finish()
    return laser_world.drive_errors(graph.scan_poses(optimized(graph)), run.truth, RELATIVE_DISTANCE)


def _cell(table: dict[str, list[dict[str, float]]], key: str, digits: int) -> str:
    return " / ".join(f"{np.mean([e[key] for e in table[variant]]):.{digits}f}"
                      for variant in ("instant", "swept", "deskewed"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.5, 1.0, 1.5])
    parser.add_argument("--lasers", nargs="+", choices=sorted(LASERS), default=list(LASERS))
    args = parser.parse_args()
    world = laser_world.square_loop()
    print("| laser | speed (m/s) | odometry | ATE m: instant / swept / deskewed "
          "| 10 m relative m: instant / swept / deskewed | 10 m relative deg: instant / swept / deskewed |")
    print("|---|---:|---|---|---|---|")
    with threadpool_limits(1):
        for name in args.lasers:
            laser = LASERS[name]
            for speed in args.speeds:
                runs = []
                for seed in range(args.seeds):
                    settings = dict(speed=speed, scan_rate=laser.scan_rate, seed=seed, beams=laser.beams,
                                    fov=laser.fov)
                    instant = laser_world.simulate_swept_run(world, sweep=0.0, **settings)
                    swept = laser_world.simulate_swept_run(world, sweep=laser.sweep, **settings)
                    runs.append((instant, swept))
                for with_odometry in (True, False):
                    table: dict[str, list[dict[str, float]]] = {"instant": [], "swept": [], "deskewed": []}
                    for instant, swept in runs:
                        table["instant"].append(errors(instant, None, with_odometry))
                        table["swept"].append(errors(swept, None, with_odometry))
                        table["deskewed"].append(errors(swept, swept.point_times, with_odometry))
                    print(f"| {name} | {speed:g} | {'yes' if with_odometry else 'no'} "
                          f"| {_cell(table, 'ate', 3)} | {_cell(table, 'relative_m', 3)} "
                          f"| {_cell(table, 'relative_deg', 2)} |", flush=True)
    print()
    for name in args.lasers:
        print(f"- {name}: {LASERS[name].description}")


if __name__ == "__main__":
    main()
