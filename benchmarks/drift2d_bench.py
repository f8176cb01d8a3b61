"""Benchmark of the 2D frontend's open-loop drift (issue 13): loop closing off, against the log's own
closed-loop run.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/drift2d_bench.py [--shared ../shared] [--logs ACES CSAIL ...]

Each 2D log of the shared data is mapped twice by `LaserSlam2D`, fed as the replay feeds it (scans in the
base frame, interpolated wheel odometry): once as `replay` maps it (loop closing on, then the default
optimizer: the reference), once with loop closing off (scan-to-local-map matching and the odometry alone:
what a log without loops, or the first half of one, gets). Every scan's pose is compared:

- segment drift (the KITTI odometry metric): for start scans every metre of the reference's path, the
  open-loop run's motion over the next `L` metres against the reference's, its rotational error (deg) and
  translational error (m), both divided by `L` and given per 100 m, the mean over the segments; `L` is
  100 m, or half the log's path where shorter (short logs say little about drift per 100 m: the column
  gives `L`);
- end: the open-loop run's heading and position at the last scan against the reference's (both runs start
  at the same pose), and the largest heading difference along the log;
- heading drift: the open-loop heading error's growth per 100 m of the reference's path, signed
  (counter-clockwise positive), fitted to its increments over 10 m windows (± the fit's standard error); a
  matcher biased per metre driven drifts one way whatever the turns;
- turn bias: the slope of the open-loop heading error against the reference's heading turned since the
  start (%, least squares, with its R²): a matcher that over- or under-rotates by a fixed share of every
  turn drifts with the net turn, whatever the path length (ACES circles the same way ~3.5 times).

`--assumed-sweep SECONDS` is a diagnostic of where such a bias comes from: each scan is first deskewed in
rotation as if its beams were taken over that many seconds from the first bearing to the last, at the
reference's angular rate there (motion distortion: a scan taken while turning is stretched or squeezed).
It uses the reference, so it is not a frontend; the logs' own LaserScan timing is not read by the frontend.
`--beam-times-sweep SECONDS` gives the open-loop scans beam times as if swept over that many seconds in
order of bearing (`sessions_bench.with_assumed_sweep`) and lets the frontend deskew them itself, in
translation and rotation, under its own motion estimates: no reference involved.

The reference has errors of its own (a loop closure, the optimizer), so on ACES both runs are also scored
against the Freiburg relations (Kümmerle et al. 2009): the closed-loop figure is the one the SLAM is judged
by, the open-loop one says how far the frontend alone gets. The frontend's CPU seconds per run are printed
beside (the 2D speed figure itself is `speed2d_bench.py`'s).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.sessions_bench import (  # noqa: E402
    LogScan,
    map_scans,
    read_scans,
    sweep_fractions,
    with_assumed_sweep,
)
from frontends.slam2d.config import Slam2DConfig  # noqa: E402
from frontends.slam2d.slam import LaserSlam2D  # noqa: E402
from optimizer import se2  # noqa: E402
from pipeline.evaluation import read_relations, relations_error  # noqa: E402

FloatArray = NDArray[np.float64]

LOGS = {
    "ACES": "data/logs/aces/aces.mcap",
    "CSAIL": "data/logs/csail/csail.mcap",
    "mumble loop": "data/logs/mumble/hallway_room_loop",
    "mumble straight": "data/logs/mumble/straight",
}
RELATIONS = {"ACES": "data/logs/aces/aces.relations"}
SEGMENT_LENGTH = 100.0
SEGMENT_STARTS_EVERY = 1.0


def path_lengths(poses: FloatArray) -> FloatArray:
    """Distance travelled (m) from the first pose to each pose."""
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    return np.concatenate([[0.0], np.cumsum(steps)])


def segment_drift(reference: FloatArray, estimate: FloatArray, length: float) -> tuple[float, float, int]:
    """Mean rotational (deg / 100 m) and translational (% = m / 100 m) error of `estimate`'s motion over
    segments of `length` metres of the reference's path, and the number of segments."""
    travelled = path_lengths(reference)
    starts = np.searchsorted(travelled, np.arange(0.0, travelled[-1] - length, SEGMENT_STARTS_EVERY))
    ends = np.searchsorted(travelled, travelled[starts] + length)
    keep = ends < len(reference)
    starts, ends = starts[keep], ends[keep]
    if len(starts) == 0:
        return float("nan"), float("nan"), 0
    error = se2.relative(se2.relative(reference[starts], reference[ends]),
                         se2.relative(estimate[starts], estimate[ends]))
    spans = travelled[ends] - travelled[starts]
    rotation = np.degrees(np.abs(se2.wrap_angle(error[:, 2]))) / spans * 100.0
    translation = np.hypot(error[:, 0], error[:, 1]) / spans * 100.0
    return float(rotation.mean()), float(translation.mean()), len(starts)


HEADING_WINDOW = 10.0
"""Metres of the reference's path per increment of the heading-drift fit."""


def heading_drift(reference: FloatArray, estimate: FloatArray) -> tuple[float, float]:
    """The estimate's heading error growth (deg / 100 m, signed) fitted through the origin to its increments
    over `HEADING_WINDOW` metres of the reference's path, and the fit's standard error."""
    travelled = path_lengths(reference)
    error = np.unwrap(estimate[:, 2] - reference[:, 2])
    edges = np.searchsorted(travelled, np.arange(0.0, travelled[-1], HEADING_WINDOW))
    grown, spans = np.diff(error[edges]), np.diff(travelled[edges])
    if len(spans) < 2:
        return float("nan"), float("nan")
    slope = float(grown @ spans / (spans @ spans))
    residual = grown - slope * spans
    spread = float(np.sqrt(residual @ residual / (len(spans) - 1) / (spans @ spans)))
    return float(np.degrees(slope) * 100.0), float(np.degrees(spread) * 100.0)


def turn_bias(reference: FloatArray, estimate: FloatArray) -> tuple[float, float]:
    """Slope (%) of the estimate's heading error against the reference's heading turned since the start,
    and the fit's R²."""
    turned = np.degrees(np.unwrap(reference[:, 2]) - reference[0, 2])
    error = np.degrees(se2.wrap_angle(estimate[:, 2] - reference[:, 2]))
    slope, intercept = np.polyfit(turned, error, 1)
    residual = error - (slope * turned + intercept)
    spread = np.sum((error - error.mean()) ** 2)
    return float(100.0 * slope), float(1.0 - np.sum(residual**2) / spread) if spread > 1e-12 else float("nan")


def deskewed(scans: list[LogScan], reference: FloatArray, sweep: float) -> list[LogScan]:
    """The scans with each point rotated by the reference's turn between the scan's middle and the point's
    time, its beams taken over `sweep` seconds in order of bearing (a diagnostic, see the module's text)."""
    seconds = np.array([s.stamp_ns for s in scans], dtype=np.float64) * 1e-9
    rates = np.gradient(np.unwrap(reference[:, 2]), seconds)
    out = []
    for scan, rate in zip(scans, rates, strict=True):
        angle = rate * sweep * (sweep_fractions(scan.points) - 0.5)
        c, s = np.cos(angle), np.sin(angle)
        points = np.stack([c * scan.points[:, 0] - s * scan.points[:, 1],
                           s * scan.points[:, 0] + c * scan.points[:, 1]], axis=1)
        out.append(LogScan(scan.stamp_ns, points, scan.odometry, scan.interval))
    return out


def scan_poses(scans: list[LogScan], config: Slam2DConfig,
               optimize: bool) -> tuple[FloatArray, NDArray[np.int64], float, int]:
    """Every scan's pose (optimized when `optimize`), stamps, frontend CPU seconds, loop closures."""
    started = time.process_time()
    if optimize:
        frontend, keyframes = map_scans(LaserSlam2D(config), scans)
    else:
        slam = LaserSlam2D(config)
        for s in scans:
            slam.add_scan(s.stamp_ns, s.points, s.odometry, s.interval, s.times)
        frontend = slam.finish()
        keyframes = frontend.graph.poses
    seconds = time.process_time() - started
    return (frontend.scan_poses(np.asarray(keyframes)), frontend.scan_stamps_ns, seconds,
            frontend.loop_closures_accepted)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--logs", nargs="+", default=list(LOGS), choices=list(LOGS))
    parser.add_argument("--save-reference", type=Path,
                        help="write each log's closed-loop scan poses to DIR/<log>.npy")
    parser.add_argument("--reference", type=Path,
                        help="also score the open-loop run against DIR/<log>.npy, a closed-loop run saved "
                             "by --save-reference (e.g. of main): a fixed reference for comparing versions")
    parser.add_argument("--extra", nargs="+", type=Path, default=[],
                        help="other 2D logs (named by their file stem)")
    parser.add_argument("--beam-times-sweep", type=float, default=0.0,
                        help="diagnostic: give the open-loop scans beam times as if swept over this many "
                             "seconds; the frontend deskews them")
    parser.add_argument("--assumed-sweep", type=float, default=0.0,
                        help="diagnostic: deskew the open-loop scans as if swept over this many seconds")
    args = parser.parse_args()
    closed = Slam2DConfig()
    open_loop = replace(closed, loop_closure=replace(closed.loop_closure, enabled=False))
    rows, relation_rows, fixed_rows = [], [], []
    with threadpool_limits(limits=1, user_api="blas"):
        paths = {name: args.shared / LOGS[name] for name in args.logs} | {p.stem: p for p in args.extra}
        for name, path in paths.items():
            if not path.exists():
                print(f"{name}: {path} absent, skipped", file=sys.stderr)
                continue
            scans = read_scans(path)
            reference, stamps, closed_seconds, loops = scan_poses(scans, closed, optimize=True)
            open_scans = deskewed(scans, reference, args.assumed_sweep) if args.assumed_sweep else scans
            open_scans = with_assumed_sweep(open_scans, args.beam_times_sweep)
            estimate, open_stamps, open_seconds, _ = scan_poses(open_scans, open_loop, optimize=False)
            if not np.array_equal(stamps, open_stamps):
                raise RuntimeError(f"{name}: the two runs have different scans")
            if args.save_reference is not None:
                args.save_reference.mkdir(parents=True, exist_ok=True)
                np.save(args.save_reference / f"{name}.npy", reference)
            saved = args.reference / f"{name}.npy" if args.reference is not None else None
            if saved is not None and saved.exists():
                fixed = np.load(saved)
                fixed_rotation, fixed_translation, _ = segment_drift(fixed, estimate,
                                                                     min(SEGMENT_LENGTH,
                                                                         0.5 * path_lengths(fixed)[-1]))
                fixed_rows.append((name, fixed_rotation, fixed_translation))
            travelled = path_lengths(reference)[-1]
            length = min(SEGMENT_LENGTH, 0.5 * travelled)
            rotation, translation, segments = segment_drift(reference, estimate, length)
            end = se2.relative(reference[-1], estimate[-1])
            heading = np.degrees(np.abs(se2.wrap_angle(estimate[:, 2] - reference[:, 2])))
            rows.append((name, len(scans), travelled, loops, length, segments, rotation, translation,
                         float(np.degrees(abs(se2.wrap_angle(end[2])))),
                         float(np.hypot(*(estimate[-1, :2] - reference[-1, :2]))), float(heading.max()),
                         heading_drift(reference, estimate), turn_bias(reference, estimate), open_seconds,
                         closed_seconds))
            if name in RELATIONS:
                relations = read_relations(args.shared / RELATIONS[name])
                for run, poses in (("closed loop (as replay)", reference), ("open loop", estimate)):
                    score = relations_error(stamps, poses, relations)
                    relation_rows.append((name, run, score.count, score.translation_mean,
                                          score.translation_std, score.rotation_mean_deg,
                                          score.rotation_std_deg))
            print(f"{name} done", file=sys.stderr, flush=True)
    print("## Open-loop drift of the 2D frontend against the log's own closed-loop run\n")
    print("| log | scans | path (m) | loop closures (reference) | L (m) | segments | rotation (deg/100 m) "
          "| translation (m/100 m) | end heading (deg) | end position (m) | max heading (deg) "
          "| heading drift (deg/100 m) | turn bias (%, R²) | open-loop CPU s | closed-loop CPU s |")
    print("|---" * 15 + "|")
    for (name, scans_count, travelled, loops, length, segments, rotation, translation, end_heading,
         end_position, max_heading, (drift, drift_error), (bias, fit), open_seconds, closed_seconds) in rows:
        print(f"| {name} | {scans_count} | {travelled:.1f} | {loops} | {length:.1f} | {segments} "
              f"| {rotation:.3f} | {translation:.3f} | {end_heading:.2f} | {end_position:.2f} "
              f"| {max_heading:.2f} | {drift:+.2f} ± {drift_error:.2f} | {bias:+.3f} ({fit:.2f}) "
              f"| {open_seconds:.1f} | {closed_seconds:.1f} |")
    if fixed_rows:
        print(f"\n## The open-loop run against the closed-loop run saved in {args.reference}\n")
        print("| log | rotation (deg/100 m) | translation (m/100 m) |")
        print("|---|---|---|")
        for name, rotation, translation in fixed_rows:
            print(f"| {name} | {rotation:.3f} | {translation:.3f} |")
    if relation_rows:
        print("\n## Relations error (Kümmerle et al. 2009)\n")
        print("| log | run | relations | translation (m) | rotation (deg) |")
        print("|---|---|---|---|---|")
        for name, run, count, t_mean, t_std, r_mean, r_std in relation_rows:
            print(f"| {name} | {run} | {count} | {t_mean:.4f} ± {t_std:.4f} | {r_mean:.3f} ± {r_std:.3f} |")


if __name__ == "__main__":
    main()
