"""Benchmark of 3D sessions (issue 13): localization in a saved point-cloud map, and mapping continued.

    NUMBA_NUM_THREADS=1 python benchmarks/sessions3d_bench.py [--shared ../shared] [--out /tmp/sessions3d]

The KITTI log (../shared/data/logs/kitti/kitti_city.mcap, 154 clouds, 71.5 m; CC BY-NC-SA: read from the
shared folder, never copied into the repo) is cut in two at its middle cloud with `benchmarks/cut_log.py`
(the second part's KISS-ICP odometry starts at its own first cloud: its origin says nothing). Everything
runs through `pipeline.replay`, as `replay` does:
- the whole log (the reference: "the full run's own optimized trajectory");
- the first half, mapped (its session);
- `--map`: the second half localized in the first half's map with no initial pose. The first half's map
  frame is the full run's (both start at the same cloud), so errors need no alignment. Reported: the
  share of clouds with a pose, matched, the global fixes, the median / 95 % / max position error against
  the full run, and clouds per second of the whole replay (wall and process CPU);
- `--continue`: the second half continued from the first half's session. Reported: the final position's
  distance to the full run's, the ATE (RMS position difference over every cloud, no alignment) against
  the full run, loop closures between the runs;
- `--continue` the other way round: the second half mapped, the first half continued from its session.
  The first half drives towards the second's map and is placed in it only near its end: nearly all its
  clouds come before the placement (the early stretch joined to the graph after it, issue 13). Its map
  frame is the second half's: the TUM is aligned to the full run by a rigid fit over the second half's
  clouds (Kabsch, positions), then the first half's clouds before and after the placement are compared
  with the full run's (RMS and max position difference);
- the session file's size and the time to load and check it (`read_session` + `saved_map_3d`).
KITTI city drives forward: the second half leaves the first half's map after a few metres, so the
localization relies on the map's far points and then on odometry (what "matched" counts).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import pipeline  # noqa: E402
from pipeline.session_file import read_session, saved_map_3d  # noqa: E402
from pipeline.trajectory_io import read_tum  # noqa: E402

LOG = "data/logs/kitti/kitti_city.mcap"


def timed_replay(path: Path, out: Path, **session: object) -> tuple[object, float, float]:
    """The replay, its wall and process CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = pipeline.replay(path, out_dir=out, **session)
    return result, time.perf_counter() - wall, time.process_time() - cpu


def positions_at(reference: Path, stamps: np.ndarray) -> np.ndarray:
    """The reference TUM's positions at `stamps` (the same clouds: their stamps match exactly)."""
    trajectory = read_tum(reference)
    index = {int(s): k for k, s in enumerate(trajectory.stamps_ns)}
    return trajectory.positions[[index[int(s)] for s in stamps]]


def rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimizing Σ‖R·source + t − target‖² over (N, 3) point pairs (Kabsch,
    scipy's `Rotation.align_vectors` on the centred points)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    fit, _ = Rotation.align_vectors(target - target_mean, source - source_mean)
    rotation = fit.as_matrix()
    return rotation, target_mean - rotation @ source_mean


def continue_the_other_way(first: Path, second: Path, full_tum: Path, out: Path) -> None:
    """The second half mapped, the first half continued from its session (see the module docstring)."""
    timed_replay(second, out / "second")
    session = out / "second" / f"{second.stem}.session"
    _, wall, cpu = timed_replay(first, out / "reverse", continue_from=session)
    summary = json.loads((out / "reverse" / f"{first.stem}.json").read_text())
    trajectory = read_tum(out / "reverse" / f"{first.stem}.tum")
    is_old = np.isin(trajectory.stamps_ns, read_tum(out / "second" / f"{second.stem}.tum").stamps_ns)
    reference = positions_at(full_tum, trajectory.stamps_ns)
    rotation, translation = rigid_fit(trajectory.positions[is_old], reference[is_old])
    aligned = trajectory.positions @ rotation.T + translation
    difference = np.linalg.norm(aligned - reference, axis=1)
    new = difference[~is_old][np.argsort(trajectory.stamps_ns[~is_old])]
    placed_at = summary["session"]["placement"].get("scan")
    waited = (placed_at or 0) - summary["counts"]["scans_unplaced"]  # the TUM has no unplaced cloud
    early, later = new[:waited], new[waited:]
    print(f"--continue, second half then first: placed at cloud {placed_at} of "
          f"{summary['counts']['clouds']}; vs the full run (aligned on the second half, RMS "
          f"{np.sqrt(np.mean(difference[is_old] ** 2)):.3f} m there): clouds before the placement RMS "
          f"{np.sqrt(np.mean(early ** 2)) if len(early) else float('nan'):.3f} m, max "
          f"{early.max(initial=0.0):.3f} m, first cloud {early[0] if len(early) else float('nan'):.3f} m; "
          f"after it RMS {np.sqrt(np.mean(later ** 2)) if len(later) else float('nan'):.3f} m; "
          f"loop closures old-new {summary['counts']['loop_closures_old_new']}, "
          f"keyframes {summary['counts']['keyframes']}; {wall:.1f} s wall, {cpu:.1f} s CPU")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--out", type=Path, default=Path("/tmp/sessions3d"))
    args = parser.parse_args()
    log = args.shared / LOG
    out = args.out
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "cut_log.py"), str(log), str(out / "cut")],
                   check=True, stdout=subprocess.DEVNULL)
    first, second = out / "cut" / f"{log.stem}_first.mcap", out / "cut" / f"{log.stem}_second.mcap"
    full, full_wall, _ = timed_replay(log, out / "full")
    full_tum = out / "full" / f"{log.stem}.tum"
    mapped, first_wall, _ = timed_replay(first, out / "first")
    session = out / "first" / f"{first.stem}.session"

    started = time.perf_counter()
    saved = saved_map_3d(session, read_session(session))
    load_seconds = time.perf_counter() - started
    print(f"session: {session.stat().st_size / 1e6:.2f} MB, {len(saved.graph.keyframe_poses)} keyframes, "
          f"{len(saved.graph.cloud_stamps_ns)} clouds; read and checked in {load_seconds:.3f} s")
    print(f"full run {full_wall:.1f} s wall; first half {first_wall:.1f} s wall")

    localized, wall, cpu = timed_replay(second, out / "map", map=session)
    summary = json.loads((out / "map" / f"{second.stem}.json").read_text())
    found = summary["localization"]
    trajectory = read_tum(out / "map" / f"{second.stem}.tum")
    errors = np.linalg.norm(trajectory.positions[:, :2]
                            - positions_at(full_tum, trajectory.stamps_ns)[:, :2], axis=1)
    clouds = found["scans"]
    print(f"--map: {clouds} clouds, {100 * found['with_pose'] / clouds:.1f} % with a pose, "
          f"{100 * found['matched'] / clouds:.1f} % matched, {len(found['global_fixes'])} global fixes "
          f"(first after {found['first_fix_after_s']} s); error vs the full run median "
          f"{np.median(errors):.3f} m, 95 % {np.percentile(errors, 95):.3f} m, max {errors.max():.3f} m; "
          f"{clouds / wall:.1f} clouds/s wall, {clouds / cpu:.1f} clouds/s CPU (whole replay)")
    matched = np.array([state == "m" for state in summary["per_scan"]["state"]])
    has_pose = np.array([state != "-" for state in summary["per_scan"]["state"]])
    if matched[has_pose].any():
        print(f"  matched clouds: median error {np.median(errors[matched[has_pose]]):.3f} m")

    continued, wall, cpu = timed_replay(second, out / "continue", continue_from=session)
    summary = json.loads((out / "continue" / f"{second.stem}.json").read_text())
    trajectory = read_tum(out / "continue" / f"{second.stem}.tum")
    reference = positions_at(full_tum, trajectory.stamps_ns)
    difference = np.linalg.norm(trajectory.positions - reference, axis=1)
    ate = float(np.sqrt(np.mean(difference**2)))
    placed_at = summary["session"]["placement"].get("scan")
    print(f"--continue: {len(trajectory.stamps_ns)} clouds of both runs; final position "
          f"{difference[-1]:.3f} m from the full run's; ATE vs the full run {ate:.3f} m "
          f"(max {difference.max():.3f} m); loop closures old-new "
          f"{summary['counts']['loop_closures_old_new']}; placed at cloud {placed_at}; "
          f"{wall:.1f} s wall, {cpu:.1f} s CPU")
    joint = out / "continue" / f"{second.stem}.session"
    print(f"joint session: {joint.stat().st_size / 1e6:.2f} MB")
    continue_the_other_way(first, second, full_tum, out)
    del full, mapped, localized, continued


if __name__ == "__main__":
    main()
