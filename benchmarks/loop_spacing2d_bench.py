"""Benchmark of the spacing of the 2D loop closures (`LoopClosureConfig.travel_between_closures`).

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/loop_spacing2d_bench.py [--shared ../shared] [--spacings 0 1 2 3] [--seeds 6]
        [--laps 3] [--skip-aces] [--skip-band]

Three measures, each printed as a markdown table:

1. Synthetic drives with ground truth (`tests/laser_world.py`: the square loop of corridors driven `--laps`
   times, 360-beam scans every 0.2 m, drifting wheel odometry, one run per seed): each spacing maps every
   run (`LaserSlam2D`, then the default optimization from both starts as `replay` does); reported per
   spacing, as the mean over the seeds: loop closures, the absolute trajectory error (RMSE over every
   scan, the first pose aligned) and the relative error over 50 scans (10 m): translation (m) and rotation
   (deg). Seeds where the spacing beats no spacing are counted.
2. ACES against its Freiburg relations (Kümmerle et al. 2009), per spacing, with the replay's time.
3. The band: how much the ACES relations error moves when the default settings are nudged by amounts that
   change no design (keyframe distance ± 1 cm, keyframe angle ± 0.5°, loop-closure separation ± 1
   keyframe, local map ± 1 keyframe, acceptance score ± 0.01), all with the spacing of 0 m that the
   defaults were chosen with: the noise floor of a single log's figure, against which a change to the
   spacing can be judged.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import laser_world  # noqa: E402

from benchmarks.sessions_bench import LogScan, map_scans  # noqa: E402
from frontends.slam2d.config import Slam2DConfig  # noqa: E402
from frontends.slam2d.slam import LaserSlam2D  # noqa: E402
from optimizer import se2  # noqa: E402
from pipeline.evaluation import evaluate_files  # noqa: E402
from pipeline.replay_log import replay_log  # noqa: E402

ACES = "data/logs/aces/aces.mcap"
ACES_RELATIONS = "data/logs/aces/aces.relations"
RELATIVE_SPAN = 50
"""Scans over which the relative error is taken (10 m at 0.2 m a scan)."""


def spaced(config: Slam2DConfig, spacing: float) -> Slam2DConfig:
    return replace(config, loop_closure=replace(config.loop_closure, travel_between_closures=spacing))


def laps_world(laps: int) -> laser_world.World:
    """The square loop's building with its route driven `laps` times round, then on past the start."""
    world = laser_world.square_loop()
    lap = world.route[:-1]
    route = np.concatenate([np.tile(lap, (laps, 1)), world.route[-1:]])
    return laser_world.World(world.segments, route, world.turn_radius)


def synthetic_errors(run: laser_world.Run, config: Slam2DConfig) -> dict[str, float]:
    scans = [LogScan(int(stamp), points, odometry, 0.0)
             for stamp, points, odometry in zip(run.stamps_ns, run.scans, run.odometry, strict=True)]
    frontend, keyframe_poses = map_scans(LaserSlam2D(config), scans)
    poses = frontend.scan_poses(keyframe_poses)
    aligned = laser_world.align_to_first(poses, run.truth)
    ate = float(np.sqrt(np.mean(np.sum((aligned[:, :2] - run.truth[:, :2]) ** 2, axis=1))))
    estimated = se2.relative(poses[:-RELATIVE_SPAN], poses[RELATIVE_SPAN:])
    true = laser_world.between(run.truth[:-RELATIVE_SPAN], run.truth[RELATIVE_SPAN:])
    return {
        "loops": frontend.loop_closures_accepted,
        "ate": ate,
        "relative_m": float(np.mean(np.hypot(*(estimated[:, :2] - true[:, :2]).T))),
        "relative_deg": float(np.degrees(np.mean(np.abs(laser_world.wrap(estimated[:, 2] - true[:, 2]))))),
    }


def synthetic_table(spacings: list[float], seeds: int, laps: int) -> None:
    world = laps_world(laps)
    rows: dict[float, list[dict[str, float]]] = {s: [] for s in spacings}
    for seed in range(seeds):
        run = laser_world.simulate_run(world, seed=seed)
        for spacing in spacings:
            rows[spacing].append(synthetic_errors(run, spaced(Slam2DConfig(), spacing)))
    print(f"\n## Synthetic square loop, {laps} laps, {seeds} seeds (mean over seeds)\n")
    print("| spacing (m) | loop closures | ATE RMSE (m) | relative, 10 m (m) | relative, 10 m (deg) "
          "| seeds with lower ATE than 0 m |")
    print("|---|---|---|---|---|---|")
    for spacing, found in rows.items():
        mean = {key: np.mean([r[key] for r in found]) for key in found[0]}
        better = "-" if spacing == 0 or 0.0 not in rows else str(
            sum(r["ate"] < b["ate"] for r, b in zip(found, rows[0.0], strict=True)))
        print(f"| {spacing:g} | {mean['loops']:.0f} | {mean['ate']:.4f} | {mean['relative_m']:.4f} "
              f"| {mean['relative_deg']:.3f} | {better} |")


def aces_row(shared: Path, out: Path, config: Slam2DConfig, label: str) -> str:
    started = time.perf_counter()
    result = replay_log(shared / ACES, out_dir=out, slam2d=config)
    seconds = time.perf_counter() - started
    score = evaluate_files(result.outputs.tum, shared / ACES_RELATIONS)
    return (f"| {label} | {result.frontend.result.loop_closures_accepted} | {score.translation_mean:.4f} "
            f"| {score.rotation_mean_deg:.3f} | {seconds:.1f} |")


def aces_tables(shared: Path, out: Path, spacings: list[float], band: bool) -> None:
    header = ("| {} | loop closures | translation (m) | rotation (deg) | replay wall (s) |\n"
              "|---|---|---|---|---|")
    print("\n## ACES relations error per spacing\n")
    print(header.format("spacing (m)"))
    for spacing in spacings:
        print(aces_row(shared, out, spaced(Slam2DConfig(), spacing), f"{spacing:g}"), flush=True)
    if not band:
        return
    base = spaced(Slam2DConfig(), 0.0)
    keyframes, loops = base.keyframes, base.loop_closure
    nudges = {
        "keyframe distance 0.29 m": replace(base, keyframes=replace(keyframes, distance=0.29)),
        "keyframe distance 0.31 m": replace(base, keyframes=replace(keyframes, distance=0.31)),
        "keyframe angle 11.5°": replace(base, keyframes=replace(keyframes, angle=math.radians(11.5))),
        "keyframe angle 12.5°": replace(base, keyframes=replace(keyframes, angle=math.radians(12.5))),
        "separation 39 keyframes": replace(base, loop_closure=replace(loops, min_separation_keyframes=39)),
        "separation 41 keyframes": replace(base, loop_closure=replace(loops, min_separation_keyframes=41)),
        "local map 24 keyframes": replace(base, keyframes=replace(keyframes, local_map_keyframes=24)),
        "local map 26 keyframes": replace(base, keyframes=replace(keyframes, local_map_keyframes=26)),
        "acceptance score 0.54": replace(base, loop_closure=replace(loops, min_score=0.54)),
        "acceptance score 0.56": replace(base, loop_closure=replace(loops, min_score=0.56)),
    }
    print("\n## ACES relations error with the defaults nudged (spacing 0 m): the noise floor\n")
    print(header.format("nudge"))
    for label, config in nudges.items():
        print(aces_row(shared, out, config, label), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "loop_spacing2d")
    parser.add_argument("--spacings", type=float, nargs="+", default=[0.0, 1.0, 2.0, 3.0])
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--laps", type=int, default=3)
    parser.add_argument("--skip-aces", action="store_true")
    parser.add_argument("--skip-band", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with threadpool_limits(limits=1):
        synthetic_table(args.spacings, args.seeds, args.laps)
        if not args.skip_aces:
            aces_tables(args.shared, args.out, args.spacings, band=not args.skip_band)


if __name__ == "__main__":
    main()
