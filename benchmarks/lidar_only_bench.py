"""Benchmark of the 2D path without wheel odometry on real logs: each Radish log replayed with its odometry
and without, the latter also with scans dropped and with jittered stamps.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/lidar_only_bench.py --radish DIR [--logs aces mit-csail fr079] [--out DIR]
        [--relations ../shared/data/logs/aces/aces.relations]

DIR holds the logs of MOLAorg/mola_test_datasets `datasets/radish/` (`<name>.clf`, unpacked from
`.clf.bz2`). Each is converted by `carmen_log.py` and replayed in process (`replay_log`, what `replay`
runs): with its odometry (the reference: no ground truth but ACES's relations), and lidar-only as
recorded, with 15 % of its scans left out (seed 1) and with every stamp moved by up to ±30 ms (seed 0).
Printed per run: the median / 95 % / largest distance (m) of every scan from the reference's estimate of
it after a rigid fit of the two trajectories (`optimizer.se2.rigid_fit`), loop closures, and for
ACES the relations error (translation m, rotation deg).

With `--sessions`, each lidar-only log as recorded is also cut in two (`cut_log.py`), its first half
mapped, and its second half localized in that map (`replay(..., map=)`) and mapped on from it
(`replay(..., continue_from=)`), lidar-only throughout: the same distances from the run with odometry,
the scans placed (matched / tracked outside the map / recovered by a global fix / never placed) and, for
ACES continued, the relations error over both halves.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.carmen_log import read_carmen, stamp_offsets, write_mcap  # noqa: E402
from benchmarks.cut_log import cut  # noqa: E402
from optimizer import se2  # noqa: E402
from pipeline.api import KNOWN_ERRORS, replay  # noqa: E402
from pipeline.evaluation import evaluate_files  # noqa: E402
from pipeline.replay_log import replay_log  # noqa: E402
from pipeline.trajectory_io import read_tum  # noqa: E402

VARIANTS = {"with odometry": ("odom", 0.0, 0.0), "lidar-only": ("none", 0.0, 0.0),
            "lidar-only, 15 % dropped": ("none", 0.15, 0.0), "lidar-only, ±30 ms": ("none", 0.0, 0.03)}
"""Name → (odometry, share of scans dropped, stamp jitter s) of `carmen_log.write_mcap`."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--radish", type=Path, required=True)
    parser.add_argument("--logs", nargs="+", default=["aces", "mit-csail", "fr079"])
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "lidar_only_bench")
    parser.add_argument("--relations", type=Path,
                        default=REPO.parent / "shared" / "data" / "logs" / "aces" / "aces.relations")
    parser.add_argument("--sessions", action="store_true", help="also localize and continue in halves")
    args = parser.parse_args()
    session_rows: list[str] = []
    print("| log | run | scans | vs with odometry: median / 95 % / max (m) | loop closures "
          "| relations (m, deg) |")
    print("|---|---|---|---|---|---|")
    for name in args.logs:
        log = read_carmen(args.radish / f"{name}.clf")
        reference: dict[int, np.ndarray] = {}
        for variant, (odometry, drop, jitter) in VARIANTS.items():
            if odometry == "odom" and not log.odometry:
                odometry = "scans"
            path = args.out / f"{name}_{variant.replace(' ', '_').replace(',', '').replace('%', 'pc')}.mcap"
            path.parent.mkdir(parents=True, exist_ok=True)
            write_mcap(log, path, odometry, drop, jitter)
            result = replay_log(path, out_dir=args.out / "replays")
            trajectory = read_tum(result.outputs.tum)
            # Each scan by its stamp as recorded (the jittered run's stamps moved by the same draws).
            offsets = stamp_offsets(len(log.scans), jitter)
            recorded = {int(scan.stamp_ns + offset): scan.stamp_ns
                        for scan, offset in zip(log.scans, offsets, strict=True)}
            stamps = [recorded[int(stamp)] for stamp in trajectory.stamps_ns]
            poses = trajectory.planar()
            if not reference:
                reference = dict(zip(stamps, poses, strict=True))
            distances = distances_from(reference, stamps, poses)
            relations = "-"
            if name == "aces" and drop == 0.0 and jitter == 0.0 and args.relations.exists():
                relations = relations_text(result.outputs.tum, args.relations)
            print(f"| {name} | {variant} | {len(stamps)} | {figures(distances)} | "
                  f"{result.loop_closures.get('accepted')} | {relations} |", flush=True)
            if args.sessions and variant == "lidar-only":
                session_rows += halves(name, path, reference, args)
    if session_rows:
        print("\n| log | lidar-only halves | scans | vs with odometry: median / 95 % / max (m) "
              "| placed: matched / tracked outside / recovered / never | relations (m, deg) |")
        print("|---|---|---|---|---|---|")
        print("\n".join(session_rows))


def distances_from(reference: dict[int, np.ndarray], stamps: list[int], poses: np.ndarray) -> np.ndarray:
    """Each scan's distance from the reference's pose of it (by stamp) after a rigid fit of the two."""
    both = [k for k, stamp in enumerate(stamps) if stamp in reference]
    mine, theirs = poses[both], np.array([reference[stamps[k]] for k in both])
    moved = se2.compose(se2.rigid_fit(mine, theirs), mine)
    return np.hypot(*(moved[:, :2] - theirs[:, :2]).T)


def relations_text(trajectory: Path, relations: Path) -> str:
    """The trajectory's relations error: translation mean ± std (m), rotation mean ± std (deg)."""
    scored = evaluate_files(trajectory, relations)
    return (f"{scored.translation_mean:.4f} ± {scored.translation_std:.4f}, "
            f"{scored.rotation_mean_deg:.3f} ± {scored.rotation_std_deg:.3f}")


def figures(distances: np.ndarray) -> str:
    return f"{np.median(distances):.3f} / {np.percentile(distances, 95):.2f} / {distances.max():.2f}"


def halves(name: str, log: Path, reference: dict[int, np.ndarray], args: argparse.Namespace) -> list[str]:
    """The log cut in two, the second half localized in the first half's map and continued from it."""
    first, second, _ = cut(log, args.out / "halves")
    mapped = replay(first, out_dir=args.out / "halves" / "first")
    session = mapped.outputs["session"]
    rows = []
    for run, options in (("--map", {"map": session}), ("--continue", {"continue_from": session})):
        try:
            result = replay(second, out_dir=args.out / "halves" / run.strip("-"), **options)
        except KNOWN_ERRORS as error:  # what `replay` reports as a one-line error
            rows.append(f"| {name} | second {run} first | refused: {error} | | | |")
            continue
        assert result.stamps_ns is not None
        stamps = [int(stamp) for stamp in result.stamps_ns]
        placed, relations = "", "-"
        if run == "--map":
            counts = result.summary["localization"]
            placed = (f"{counts['matched']} / {counts['tracked_outside_map']} / "
                      f"{counts['recovered_by_a_global_fix']} / {counts['never_localized']}")
        elif name == "aces" and args.relations.exists():
            relations = relations_text(result.outputs["tum"], args.relations)
        distances = distances_from(reference, stamps, result.poses)
        rows.append(f"| {name} | second {run} first | {len(stamps)} | {figures(distances)} | {placed} "
                    f"| {relations} |")
    return rows


if __name__ == "__main__":
    main()
