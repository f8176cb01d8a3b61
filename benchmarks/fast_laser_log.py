"""A simulated log of a fast laser with ground truth, to replay end to end, and its score.

    python benchmarks/fast_laser_log.py write OUT.mcap [--rate 40] [--beams 1081] [--fov 270] [--speed 1]
        [--no-odometry] [--seed 1]
    replay OUT.mcap --out DIR
    python benchmarks/fast_laser_log.py score OUT.truth.tum DIR/OUT.tum

`write`: the square loop of corridors (`tests/laser_world.py`) driven once round and on past the start at
`--speed` m/s, a laser taking all its beams at each stamp (`time_increment` 0), the drifting wheel odometry
on tf (odom → base_link), as a ROS 2 MCAP with zstd chunks; the true base poses beside it as OUT.truth.tum.
`score`: a replay's trajectory against that truth, by stamp: the absolute trajectory error (RMSE, the first
pose aligned) and the mean relative error over 10 m of driving (`laser_world.drive_errors`).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.trajectory_io import read_tum, write_tum  # noqa: E402
from tests._frontends_fixtures import ros2_mcap  # noqa: E402
from tests.laser_world import beam_bearings, drive_errors, simulate_swept_run, square_loop  # noqa: E402


def write(out: Path, rate: float, beams: int, fov: float, speed: float, odometry: bool, seed: int) -> None:
    run = simulate_swept_run(square_loop(), speed=speed, scan_rate=rate, sweep=0.0, seed=seed, beams=beams,
                             fov=fov, max_range=30.0)
    bearings = beam_bearings(beams, fov)
    increment = float(bearings[1] - bearings[0])
    with ros2_mcap(out) as (messages, add):
        types = messages.types
        for k, (stamp, points) in enumerate(zip(run.stamps_ns, run.scans, strict=True)):
            stamp = int(stamp)
            if odometry:
                x, y, yaw = (float(value) for value in run.odometry[k])
                edge = messages.transform_stamped(stamp, "odom", "base_link", (x, y, 0.0), yaw)
                add("/tf", "tf2_msgs/msg/TFMessage", stamp, messages.tf_message([edge]))
            ranges = np.full(beams, np.inf, dtype=np.float32)
            index = np.round((np.arctan2(points[:, 1], points[:, 0]) - bearings[0]) / increment).astype(int)
            inside = (index >= 0) & (index < beams)
            ranges[index[inside]] = np.hypot(points[inside, 0], points[inside, 1])
            add("/scan", "sensor_msgs/msg/LaserScan", stamp, types["sensor_msgs/msg/LaserScan"](
                header=messages.header(stamp, "base_link"), angle_min=float(bearings[0]),
                angle_max=float(bearings[-1]), angle_increment=increment, time_increment=0.0,
                scan_time=1.0 / rate, range_min=0.05, range_max=30.0, ranges=ranges,
                intensities=np.zeros(0, dtype=np.float32)))
    truth = out.with_suffix(".truth.tum")
    write_tum(truth, run.stamps_ns, run.truth)
    seconds = (run.stamps_ns[-1] - run.stamps_ns[0]) * 1e-9
    print(f"{out}: {len(run.scans)} scans over {seconds:.1f} s; truth {truth}")


def score(truth_path: Path, result_path: Path) -> None:
    truth, result = read_tum(truth_path), read_tum(result_path)
    common, in_truth, in_result = np.intersect1d(truth.stamps_ns, result.stamps_ns, return_indices=True)
    errors = drive_errors(result.planar()[in_result], truth.planar()[in_truth])
    print(f"{result_path}: {len(common)} of {len(truth.stamps_ns)} true poses scored; "
          f"ATE {errors['ate']:.4f} m, 10 m relative {errors['relative_m']:.4f} m, "
          f"{errors['relative_deg']:.3f} deg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    writing = commands.add_parser("write")
    writing.add_argument("out", type=Path)
    writing.add_argument("--rate", type=float, default=40.0, help="scans per second")
    writing.add_argument("--beams", type=int, default=1081)
    writing.add_argument("--fov", type=float, default=270.0, help="degrees")
    writing.add_argument("--speed", type=float, default=1.0, help="m/s")
    writing.add_argument("--no-odometry", action="store_true")
    writing.add_argument("--seed", type=int, default=1)
    scoring = commands.add_parser("score")
    scoring.add_argument("truth", type=Path)
    scoring.add_argument("result", type=Path)
    args = parser.parse_args()
    if args.command == "write":
        write(args.out, args.rate, args.beams, math.radians(args.fov), args.speed, not args.no_odometry,
              args.seed)
    else:
        score(args.truth, args.result)


if __name__ == "__main__":
    main()
