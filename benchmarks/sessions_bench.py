"""Benchmark of sessions (issue 13): localization in a saved map, and mapping continued from one.

    python benchmarks/sessions_bench.py [--shared ../shared] [--logs ACES CSAIL "mumble loop"]
        [--extra LOG ...] [--skip-continue] [--repeats N] [--beam-times-sweep SECONDS]

(a) Localization. Each log is cut in two at its middle scan. The first half is mapped (LaserSlam2D, then
    the default optimizer from the odometry and the online estimates, as `replay` does); the second half is
    localized as `replay --map` does (`localize_as_replay`), with no initial pose and its odometry origin
    dropped (re-expressed from its own first pose): `MapLocalizer` scan by scan, and the run's own SLAM
    resumed on the first half's graph, placed by the localizer, its joint graph solved with the saved
    keyframes held (`frontends.slam2d.held_map`). The reference is the whole log mapped in one run,
    optimized the same way (the issue's "full run's own optimized trajectory"). Two rows per log:

    - "half map": the map is the first half as mapped alone (what a user has). Its frame is not the full
      run's, and its shape is not either: without the second half's loop closures the first half bends
      differently. The full run is moved onto it by the least-squares SE(2) fit (positions, Umeyama without
      scale) over the keyframes the two runs share — the first half's keyframes are the same scans in both
      runs (the frontend is deterministic up to the cut; checked) — and the fit's residual (median / max
      over those keyframes) is printed: it is how far the two maps disagree where both saw the same thing,
      a floor under any localization error measured this way, whatever the localizer does.
    - "full-run poses": the same first-half keyframe scans, placed at the full run's optimized poses of
      those keyframes. The map holds only the first half's scans, exactly as above, but its frame and its
      shape are the reference's: no alignment, no residual. This row measures the localizer alone.

    The reference has defects of its own: where the full run's SLAM slipped along a corridor, its scan poses
    jump against the wheel odometry. "reference slips" counts the stretches where the reference moves more
    than 0.2 m + 10 % of the distance differently from the odometry over 10 scans (about 2 s on ACES):
    errors there may be the reference's (or the odometry slipped: CSAIL's is poor).

    Reported: scans of the second half; seconds to the first global fix; share of scans localized when
    processed (a map-frame pose given at once); the error of the trajectory `replay --map` writes (the held
    map's where it agrees with the localizer's map matches, else the smoothed one: the issue's figure), and
    whether the held map's was given (with its median distance from the map matches); split by how:
    map-matched (the saved map placed the scan), tracked on the rolling local map (recent scans at their
    tracked poses with the nearest saved keyframes: outside the saved map), predicted by odometry (no match),
    all among the scans more than 10 s after the start; median / 95 % translational error of the localized
    scans after 10 s, overall and per state (same scans), as given online and as smoothed offline
    (`localization_smoothing`: what the replay writes when the held map's disagrees), with the CPU time of the
    smoothing and of the held-map solve; the median over those in places the first half saw well (the scan at
    its reference pose scores ≥ 0.5 on the map: the split is the reference's, not the localizer's), with their
    share; global fixes and local re-acquisitions; scans per second of the whole localization (localizer, held
    SLAM, smoothing and held-map solve; global search included) over process CPU time and over wall time (the
    two differ on a loaded machine: CPU time is the localization's own cost; with `--repeats N` the fastest
    of N runs). Last, for the scans within 3 m
    of a first-half keyframe: the reference carried into the map through that keyframe (its pose relative to
    the keyframe in the full run, applied to the keyframe's pose in the map: where the map's own walls put the
    scan), how far that lies from the rigidly aligned reference (the map's disagreement with the full run
    there: a floor under the error against the full run, whatever the localizer does), and the error as given
    against it (the localizer's error in the map it was given). For the "full-run poses" row the two
    references are one. Last, the scans placed within 1 m of a map keyframe (the saved run's path) and how
    many of them did not match the map (`frontends.protocol.unmatched_on_saved_path`; the replay warns when
    more than a fifth did not).
(b) Continue. The second half goes to `LaserSlam2D.resume` on the first half's saved graph (odometry
    origin dropped); the joint graph is optimized once. ACES: every scan of both halves is scored against
    aces.relations; the single run's figure is the reference (target: within 10 %). CSAIL (no ground
    truth): every scan's distance to the single run's estimate of it after a rigid alignment, with the scan
    where it is largest and how many scans lie over 0.3 m.
(c) The same log again (a user replaying the log a session was made from): the whole log, its first
    scans before any odometry message included, localized in the full run's own map (`--map`, as
    `localize_as_replay` does) and
    continued from the full run's own graph (`--continue`); every scan's distance from the full run's pose
    (median / 95 % / max, scans farther than 0.5 m), and for the continued one the constraints between the
    old and the new keyframes.

`--beam-times-sweep S` is a diagnostic of motion distortion: every scan is given beam times as if swept
over S seconds (`with_assumed_sweep`), which the frontend and the localizer deskew.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from frontends.logs import open_log  # noqa: E402
from frontends.protocol import unmatched_on_saved_path  # noqa: E402
from frontends.slam2d import read_odometry, scans_in_base_frame  # noqa: E402
from frontends.slam2d.grid import LikelihoodGrid  # noqa: E402
from frontends.slam2d.held_map import (  # noqa: E402
    HeldMapTrajectory,
    HeldOdometry,
    held_map_scans,
    held_map_trajectory,
)
from frontends.slam2d.local_map import place  # noqa: E402
from frontends.slam2d.localization import LocalizedScan, MapLocalizer  # noqa: E402
from frontends.slam2d.localization_smoothing import SmoothedTrajectory, smooth_scans  # noqa: E402
from frontends.slam2d.resume import SavedConstraints, SavedScans  # noqa: E402
from frontends.slam2d.slam import LaserSlam2D, Slam2DGraph  # noqa: E402
from frontends.threads import InOrderWorker  # noqa: E402
from optimizer import se2  # noqa: E402
from optimizer.graph import PoseGraph  # noqa: E402
from optimizer.solve import DEFAULT_METHOD, optimize  # noqa: E402
from pipeline.evaluation import read_relations, relations_error  # noqa: E402

FloatArray = NDArray[np.float64]

LOGS = {"ACES": "data/logs/aces/aces.mcap", "CSAIL": "data/logs/csail/csail.mcap",
        "mumble loop": "data/logs/mumble/hallway_room_loop"}
"""The shared 2D logs: two with wheel odometry, and a real RPLidar's loop without any (a ROS 2 bag)."""
ACES_RELATIONS = "data/logs/aces/aces.relations"
SETTLE_SECONDS = 10.0
NEAR_MAP = 3.0
"""A second-half scan this close (m) to a first-half keyframe is near the map (see `carried_into_map`)."""
COVERED_FIT = 0.5
"""A second-half scan whose reference pose scores this on the map (mean likelihood of its points, as the
correlative matcher scores) is in a place the first half saw well; a scan scoring less is where the first
half only glimpsed the walls from afar, or never went."""


@dataclass(frozen=True)
class LogScan:
    stamp_ns: int
    points: FloatArray
    odometry: FloatArray | None
    interval: float
    times: FloatArray | None = None
    """Beam times (s after the stamp); None: all taken at the stamp (`read_scans` gives None: it does not
    read the LaserScan timing)."""


def read_scans(path: Path) -> list[LogScan]:
    """The scans in the base frame with their interpolated wheel odometry, as the replay feeds them."""
    out = []
    with open_log(path) as log:
        topic, _ = log.sensor_topic(None)
        odometry = read_odometry(log)
        tree = log.transform_tree()
        base = odometry.child_frame if odometry is not None else "base_link"
        for scan, _ in scans_in_base_frame(log, topic, tree, base):
            prediction, interval = None, 0.0
            if odometry is not None:
                at, intervals = odometry.interpolate(np.array([scan.stamp_ns]))
                prediction = None if np.isnan(at[0, 0]) else at[0]
                interval = float(intervals[0]) * 1e-9
            out.append(LogScan(scan.stamp_ns, scan.points, prediction, interval))
    return out


def without_origin(scans: list[LogScan]) -> list[LogScan]:
    """The odometry seen from its first pose: a second recording knows nothing of the first's frame."""
    origin = next((s.odometry for s in scans if s.odometry is not None), None)
    if origin is None:
        return scans
    return [LogScan(s.stamp_ns, s.points, None if s.odometry is None else se2.relative(origin, s.odometry),
                    s.interval, s.times) for s in scans]


def sweep_fractions(points: FloatArray) -> FloatArray:
    """How far through a sweep in order of bearing each point was taken: 0 at the smallest bearing, 1 at the
    largest (counter-clockwise, seen from the base frame's origin: the laser's own bearings where it sits
    there, as in ACES and CSAIL)."""
    bearings = np.arctan2(points[:, 1], points[:, 0])
    if not len(bearings):
        return bearings
    return (bearings - bearings.min()) / max(float(np.ptp(bearings)), 1e-9)


def with_assumed_sweep(scans: list[LogScan], sweep: float) -> list[LogScan]:
    """A diagnostic of motion distortion: each scan without beam times given them as if its beams were
    taken over `sweep` seconds in order of bearing (`sweep_fractions`), the first at the stamp; the
    frontend then deskews them itself, under its own motion estimates (`frontends.slam2d.deskew`)."""
    out = []
    for scan in scans:
        times = scan.times
        if times is None and sweep and len(scan.points):
            times = sweep * sweep_fractions(scan.points)
        out.append(LogScan(scan.stamp_ns, scan.points, scan.odometry, scan.interval, times))
    return out


def optimized(frontend: Slam2DGraph) -> FloatArray:
    """The keyframe poses after the default optimization from both starts (what `replay` writes)."""
    chain = frontend.odometry_chain
    run = optimize(frontend.graph.with_poses(chain), method=DEFAULT_METHOD,
                   starts={"odometry": chain, "online": frontend.graph.poses})
    poses = chain
    for iteration in run:
        poses = iteration.poses
    return np.array(poses)


def map_scans(slam: LaserSlam2D, scans: list[LogScan]) -> tuple[Slam2DGraph, FloatArray]:
    for s in scans:
        slam.add_scan(s.stamp_ns, s.points, s.odometry, s.interval, s.times)
    frontend = slam.finish()
    return frontend, optimized(frontend)


@dataclass(frozen=True, eq=False)
class Mapped:
    """One log mapped whole and its first half mapped alone (shared by (a) and (b))."""

    scans: list[LogScan]
    full: Slam2DGraph
    full_keyframes: FloatArray
    first: Slam2DGraph
    first_keyframes: FloatArray

    @classmethod
    def of(cls, scans: list[LogScan]) -> Mapped:
        full, full_keyframes = map_scans(LaserSlam2D(), scans)
        first, first_keyframes = map_scans(LaserSlam2D(), scans[: len(scans) // 2])
        return cls(scans, full, full_keyframes, first, first_keyframes)


def reference_slips(reference: FloatArray, scans: list[LogScan], span: int = 10, tolerance: float = 0.2,
                     tolerance_per_metre: float = 0.1) -> int:
    """Stretches where the reference moves over `span` scans more than `tolerance` (m) plus
    `tolerance_per_metre` of the distance driven differently from the wheel odometry: the full run's SLAM
    slipped there, or the odometry did (no odometry: 0, nothing to check against)."""
    if any(s.odometry is None for s in scans) or len(scans) <= span:
        return 0
    odometry = np.array([s.odometry for s in scans])
    moved = se2.relative(reference[:-span], reference[span:])
    driven = se2.relative(odometry[:-span], odometry[span:])
    allowed = tolerance + tolerance_per_metre * np.hypot(driven[:, 0], driven[:, 1])
    slipped = np.hypot(*(moved[:, :2] - driven[:, :2]).T) > allowed
    return int(np.count_nonzero(slipped[1:] & ~slipped[:-1]) + slipped[0])


def map_fit(grid: LikelihoodGrid, scans: list[LogScan], poses: FloatArray, max_range: float) -> FloatArray:
    """Each scan's mean likelihood on the map at `poses` (the correlative score, without search)."""
    fits = np.zeros(len(scans))
    for k, (scan, pose) in enumerate(zip(scans, poses, strict=True)):
        points = scan.points[np.einsum("ij,ij->i", scan.points, scan.points) <= max_range**2]
        if len(points) == 0:
            continue
        cells = np.floor((place(points, pose) - grid.origin) / grid.resolution).astype(np.int64)
        height, width = grid.values.shape
        inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < width) & (cells[:, 1] < height)
        fits[k] = grid.values[cells[inside, 1], cells[inside, 0]].sum() / len(points)
    return fits


@dataclass(frozen=True, eq=False)
class LocalizedRun:
    localizer: MapLocalizer
    results: list[LocalizedScan]
    smoothed: SmoothedTrajectory
    held: HeldMapTrajectory
    given: FloatArray
    """(S, 3) what `replay --map` writes: the held-map poses where they agree with the map matches, else
    the smoothed ones."""
    seconds: float
    cpu_seconds: float
    smoothing_cpu: float
    held_cpu: float


def localize_as_replay(saved: Slam2DGraph, map_poses: FloatArray, scans: list[LogScan]) -> LocalizedRun:
    """`scans` localized in the map of `saved`'s keyframe scans at `map_poses` as `replay --map` does
    (`LocalizingLaserFrontend`): the localizer, the run's own SLAM resumed on the saved graph and placed by
    it, the localizer's trajectory smoothed, the SLAM's graph solved with the saved map held."""
    started, started_cpu = time.perf_counter(), time.process_time()
    localizer = MapLocalizer(saved.keyframe_scans, map_poses)
    resumed = LaserSlam2D.resume(saved.keyframe_scans, map_poses, SavedConstraints.of(saved.graph),
                                 placed_by_caller=True)
    results = []
    beside = InOrderWorker("held-map")  # each scan's SLAM beside the next one's localizer, as in replay
    odometry_of = HeldOdometry()
    for s in scans:
        results.append(localizer.localize(s.stamp_ns, s.points, s.odometry, s.interval, s.times))
        odometry, interval, restart = odometry_of.of(s.odometry, s.interval, results[-1])
        if restart:
            beside.submit(resumed.odometry_restarts)
        beside.submit(partial(resumed.add_scan, s.stamp_ns, s.points, odometry, interval, s.times,
                              located=results[-1]))
    beside.drain()
    smoothing_started = time.process_time()
    smoothed = smooth_scans(results)
    smoothing_cpu = time.process_time() - smoothing_started
    held_started = time.process_time()
    held = held_map_trajectory(held_map_scans(resumed, map_poses), np.array([s.stamp_ns for s in scans]),
                               np.array([r.pose for r in results]), np.array([r.matched for r in results]))
    held_cpu = time.process_time() - held_started
    given = np.where(np.isfinite(held.poses[:, :1]) & held.agrees, held.poses, smoothed.poses)
    return LocalizedRun(localizer, results, smoothed, held, given, time.perf_counter() - started,
                        time.process_time() - started_cpu, smoothing_cpu, held_cpu)


def localization_row(name: str, mapped: Mapped, *, full_run_poses: bool, repeats: int = 1) -> tuple[str, ...]:
    scans, full, full_keyframes = mapped.scans, mapped.full, mapped.full_keyframes
    first, first_keyframes = mapped.first, mapped.first_keyframes
    half = len(scans) // 2
    shared = len(first_keyframes)
    if not np.array_equal(full.scan_keyframes[:half], first.scan_keyframes):
        raise SystemExit(f"{name}: the full run's first half made other keyframes than the half run")
    reference = full.scan_poses(full_keyframes)[half:]
    in_full_frame = reference
    carried, near_map = carried_into_map(reference, full_keyframes[:shared], first_keyframes)
    if full_run_poses:
        map_poses = full_keyframes[:shared]
        residual = np.zeros(1)
        carried = reference
    else:
        map_poses = first_keyframes
        to_map = se2.rigid_fit(full_keyframes[:shared], first_keyframes)
        reference = se2.compose(to_map, reference)
        residual = np.hypot(*(se2.compose(to_map, full_keyframes[:shared])[:, :2] - first_keyframes[:, :2]).T)
    second = without_origin(scans[half:])
    # The same localization each time (deterministic): the fastest is its cost on a machine at rest.
    localized_run = min((localize_as_replay(first, map_poses, second) for _ in range(repeats)),
                        key=lambda run: run.cpu_seconds)
    results, smoothed, held, given = (localized_run.results, localized_run.smoothed, localized_run.held,
                                      localized_run.given)
    seconds, cpu_seconds = localized_run.seconds, localized_run.cpu_seconds
    smoothing_cpu, held_cpu = localized_run.smoothing_cpu, localized_run.held_cpu
    localized = np.array([r.localized for r in results])
    states = {"matched": np.array([r.matched for r in results]),
              "tracked": np.array([r.tracked for r in results]),
              "predicted": np.array([r.predicted for r in results])}
    poses = np.array([r.pose for r in results])
    stamps = np.array([s.stamp_ns for s in second])
    settled = stamps >= stamps[0] + int(SETTLE_SECONDS * 1e9)
    errors = np.full(len(second), np.nan)
    errors[localized] = np.hypot(*(poses[localized, :2] - reference[localized, :2]).T)
    smoothed_errors = np.full(len(second), np.nan)
    smoothed_errors[localized] = np.hypot(*(smoothed.poses[localized, :2] - reference[localized, :2]).T)
    given_errors = np.full(len(second), np.nan)
    given_errors[localized] = np.hypot(*(given[localized, :2] - reference[localized, :2]).T)
    # As `evo_ape -a` measures it: the trajectory moved onto the reference by its own best fit.
    scored = localized & settled
    onto_full = se2.rigid_fit(given[scored], in_full_frame[scored])
    self_aligned = np.hypot(*(se2.compose(onto_full, given[scored])[:, :2] - in_full_frame[scored, :2]).T)
    first_fix = next((r.index for r in results if r.global_fix), -1)
    fix_seconds = (stamps[first_fix] - stamps[0]) * 1e-9 if first_fix >= 0 else float("nan")
    # Where the first half saw the place well: the reference pose puts the scan on the map's walls.
    localizer = localized_run.localizer
    covered = map_fit(localizer.map.grid, second, reference, localizer.config.matching.max_range)[scored]
    covered = covered >= COVERED_FIT
    covered_median = np.median(errors[scored][covered]) if covered.any() else np.nan
    # Near the map, the reference carried in through the nearest keyframe: what the map's own walls say.
    near = scored & near_map
    disagreement = np.hypot(*(carried[near, :2] - reference[near, :2]).T)
    against_carried = np.hypot(*(given[near, :2] - carried[near, :2]).T)
    shares = [f"{100 * (state & settled).sum() / settled.sum():.1f}" for state in states.values()]
    return (name, "full-run poses" if full_run_poses else "half map", f"{len(second)}", f"{fix_seconds:.1f}",
            f"{100 * localized[settled].mean():.1f}", error_figures(given_errors[scored]),
            error_figures(self_aligned),
            f"{'yes' if held.agrees else 'no'} ({held.apart:.3f})", *shares, error_figures(errors[scored]),
            *(error_figures(errors[state & settled]) for state in states.values()),
            error_figures(smoothed_errors[scored]),
            *(error_figures(smoothed_errors[states[state] & settled]) for state in ("matched", "tracked")),
            f"{smoothing_cpu:.2f}{'' if smoothed.converged else ' (not converged)'} / {held_cpu:.2f}",
            f"{covered_median:.3f} ({100 * covered.mean():.0f} %)", f"{sum(r.global_fix for r in results)}",
            f"{sum(r.relocalized for r in results)}", f"{len(second) / cpu_seconds:.0f}",
            f"{len(second) / seconds:.0f}", f"{np.median(residual):.3f} / {residual.max():.3f}",
            f"{reference_slips(reference, second)}", f"{100 * near.sum() / scored.sum():.0f}",
            error_figures(disagreement), error_figures(against_carried),
            "{1} / {0}".format(*unmatched_on_saved_path(poses[localized, :2], states["matched"][localized],
                                                        map_poses[:, :2])))


def carried_into_map(reference: FloatArray, full_map: FloatArray,
                     half_map: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Each reference pose carried into the half map through the map keyframe nearest to it: its pose
    relative to that keyframe (full run) applied to the same keyframe's pose in the half map. Near the map
    this is where the map's own walls put the scan, whatever the map's bend elsewhere; and whether the
    keyframe is within `NEAR_MAP` (m) (farther, a heading difference at the keyframe swings it)."""
    offsets = reference[:, None, :2] - full_map[None, :, :2]
    distances = np.hypot(offsets[..., 0], offsets[..., 1])
    nearest = np.argmin(distances, axis=1)
    carried = se2.compose(half_map[nearest], se2.relative(full_map[nearest], reference))
    return carried, distances[np.arange(len(reference)), nearest] <= NEAR_MAP


def error_figures(errors: FloatArray) -> str:
    """"median / 95 %" of translational errors (m), or "-" when there are none."""
    if len(errors) == 0:
        return "-"
    return f"{np.median(errors):.3f} / {np.percentile(errors, 95):.3f}"


LOCALIZATION_HEADER = (
    "| log | map | scans | first fix after (s) | localized after 10 s (%) "
    "| error, as replay gives it (held map, else smoothed): median / 95 % (m) "
    "| the same, aligned on itself (evo_ape -a) (m) "
    "| held map given (median distance from the map matches, m) | map-matched (%) "
    "| tracked on the rolling map (%) | predicted by odometry (%) | error, localized: median / 95 % (m) "
    "| map-matched (m) | tracked (m) | predicted (m) "
    "| smoothed: error, localized (m) | smoothed: map-matched (m) | smoothed: tracked (m) "
    "| CPU (s): smoothing / held-map solve "
    "| median error where the map covers the place (m) (share of scans) | global fixes "
    "| local re-acquisitions | scans/s (CPU) | scans/s (wall) "
    "| alignment residual, median / max (m) | reference slips "
    "| scans within 3 m of a map keyframe (%) | there: map against the full run (m) "
    "| there: error as given against the full run carried into the map (m) "
    "| on the saved path (1 m): scans unmatched / placed |"
)


def continue_rows(mapped: Mapped, relations_path: Path) -> list[tuple[str, ...]]:
    relations = read_relations(relations_path)
    full, full_keyframes = mapped.full, mapped.full_keyframes
    first = mapped.first
    single = relations_error(full.scan_stamps_ns, full.scan_poses(full_keyframes), relations)
    joint, joint_keyframes, seconds = continued(mapped)
    both = relations_error(joint.scan_stamps_ns, joint.scan_poses(joint_keyframes), relations)
    old = first.graph.num_poses
    graph = joint.graph
    crossing = old_new_constraints(graph, old)
    return [
        ("single run", f"{len(full.scan_stamps_ns)}", f"{single.count}", f"{single.translation_mean:.4f}",
         f"{single.rotation_mean_deg:.3f}", f"{full.loop_closures_accepted}", "", ""),
        ("two halves, resumed", f"{len(joint.scan_stamps_ns)}", f"{both.count}",
         f"{both.translation_mean:.4f}", f"{both.rotation_mean_deg:.3f}", f"{joint.loop_closures_accepted}",
         f"{crossing}", f"{seconds:.1f}"),
        ("ratio", "", "", f"{both.translation_mean / single.translation_mean:.3f}",
         f"{both.rotation_mean_deg / single.rotation_mean_deg:.3f}", "", "", ""),
    ]


def old_new_constraints(graph: PoseGraph, old: int) -> int:
    """The loop closures of a joint graph between its first `old` keyframes (the saved run's) and the rest."""
    return int((((graph.edge_from < old) != (graph.edge_to < old)) & ~graph.is_odometry).sum())


def continued(mapped: Mapped) -> tuple[Slam2DGraph, FloatArray, float]:
    """The second half resumed on the first half's saved graph (odometry origin dropped), the joint graph
    optimized once; and the seconds it took."""
    first, first_keyframes = mapped.first, mapped.first_keyframes
    started = time.perf_counter()
    slam = LaserSlam2D.resume(first.keyframe_scans, first_keyframes, SavedConstraints.of(first.graph),
                              scans=SavedScans.of(first))
    joint, joint_keyframes = map_scans(slam, without_origin(mapped.scans[len(mapped.scans) // 2:]))
    return joint, joint_keyframes, time.perf_counter() - started


def continue_agreement_row(name: str, mapped: Mapped) -> tuple[str, ...]:
    """A log without ground truth (CSAIL): how far every scan of the continued session lies from the single
    run's estimate of it, after the least-squares rigid transform between the two."""
    joint, joint_keyframes, seconds = continued(mapped)
    full = mapped.full
    reference = full.scan_poses(mapped.full_keyframes)
    _, in_full, in_joint = np.intersect1d(full.scan_stamps_ns, joint.scan_stamps_ns, return_indices=True)
    poses = joint.scan_poses(joint_keyframes)[in_joint]
    moved = se2.compose(se2.rigid_fit(poses, reference[in_full]), poses)
    errors = np.hypot(*(moved[:, :2] - reference[in_full, :2]).T)
    old = mapped.first.graph.num_poses
    graph = joint.graph
    crossing = old_new_constraints(graph, old)
    worst = int(np.argmax(errors))
    worst_seconds = (full.scan_stamps_ns[in_full[worst]] - full.scan_stamps_ns[0]) * 1e-9
    return (name, f"{len(joint.scan_stamps_ns)}", f"{len(errors)}", f"{np.median(errors):.3f}",
            f"{np.percentile(errors, 95):.3f}",
            f"{errors.max():.3f} (scan {in_full[worst]}, {worst_seconds:.0f} s)",
            f"{np.count_nonzero(errors > 0.3)}", f"{full.loop_closures_accepted}",
            f"{joint.loop_closures_accepted}", f"{crossing}", f"{seconds:.1f}")


def same_log_rows(mapped: Mapped) -> list[tuple[str, ...]]:
    """(c): the whole log again, localized in its own map and continued from its own graph."""
    scans, full, full_keyframes = mapped.scans, mapped.full, mapped.full_keyframes
    reference = full.scan_poses(full_keyframes)
    localized_run = localize_as_replay(full, full_keyframes, scans)
    localized = np.array([r.localized for r in localized_run.results])
    poses = localized_run.given
    rows = [("--map", f"{int(localized.sum())} / {len(scans)}",
             distance_figures(poses[localized], reference[localized]), "")]
    slam = LaserSlam2D.resume(full.keyframe_scans, full_keyframes, SavedConstraints.of(full.graph),
                              scans=SavedScans.of(full))
    joint, joint_keyframes = map_scans(slam, scans)
    old = full.graph.num_poses
    graph = joint.graph
    crossing = old_new_constraints(graph, old)
    new_poses = joint.scan_poses(joint_keyframes)[len(scans):]
    placed = len(new_poses)
    rows.append(("--continue", f"{placed} / {len(scans)}",
                 distance_figures(new_poses, reference[len(scans) - placed:]), f"{crossing}"))
    return rows


def distance_figures(poses: FloatArray, reference: FloatArray) -> str:
    """"median / 95 % / max (scans over 0.5 m)" of the positions' distances (m)."""
    distances = np.hypot(*(poses[:, :2] - reference[:, :2]).T)
    return f"{error_figures(distances)} / {distances.max():.3f} ({np.count_nonzero(distances > 0.5)})"


def print_same_log(name: str, mapped: Mapped) -> None:
    print(f"## {name} (c) The same log again, in its own session: against the single run\n")
    print("| log | replay | scans placed | median / 95 % / max (m) (scans > 0.5 m) | old-new constraints |")
    print("|---|---|---|---|---|")
    for row in same_log_rows(mapped):
        print(f"| {name} | " + " | ".join(row) + " |", flush=True)
    print()


def print_continue_agreement(name: str, mapped: Mapped) -> None:
    print(f"## {name} (b) Continue: two halves, the second resumed on the first's graph, against the single "
          "run (no ground truth)\n")
    print("| log | scans | scans in both | median (m) | 95 % (m) | max (m) (at) | scans > 0.3 m "
          "| loop closures, single | loop closures, resumed | old-new loop closures | resumed half (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("| " + " | ".join(continue_agreement_row(name, mapped)) + " |\n", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--logs", nargs="*", default=list(LOGS), help="shared logs (none: --extra only)")
    parser.add_argument("--extra", nargs="+", type=Path, default=[],
                        help="other 2D logs, benchmarked as CSAIL is (named by their file stem)")
    parser.add_argument("--skip-continue", action="store_true")
    parser.add_argument("--repeats", type=int, default=1,
                        help="localize each second half this many times; the fastest (CPU) is reported")
    parser.add_argument("--beam-times-sweep", type=float, default=0.0,
                        help="diagnostic: give every scan beam times as if swept over this many seconds "
                             "(`with_assumed_sweep`)")
    args = parser.parse_args()
    paths = {name: args.shared / LOGS[name] for name in args.logs} | {path.stem: path for path in args.extra}
    with threadpool_limits(limits=1, user_api="blas"):
        for name, path in paths.items():  # ACES first: both of its tables print before CSAIL is mapped
            mapped = Mapped.of(with_assumed_sweep(read_scans(path), args.beam_times_sweep))
            print(f"## {name} (a) Localization: second half in the first half's map, no initial pose, "
                  "odometry origin dropped\n")
            print(LOCALIZATION_HEADER)
            print("|---" * LOCALIZATION_HEADER.count(" | ") + "|---|")
            for full_run_poses in (False, True):
                row = localization_row(name, mapped, full_run_poses=full_run_poses, repeats=args.repeats)
                print("| " + " | ".join(row) + " |", flush=True)
            print()
            if name == "ACES" and not args.skip_continue:
                print("## ACES (b) Continue: two halves, the second resumed on the first's graph\n")
                print("| run | scans | relations | translation (m) | rotation (deg) | loop closures "
                      "| old-new loop closures | resumed half (s) |")
                print("|---|---|---|---|---|---|---|---|")
                for row in continue_rows(mapped, args.shared / ACES_RELATIONS):
                    print("| " + " | ".join(row) + " |", flush=True)
                print()
            elif not args.skip_continue:
                print_continue_agreement(name, mapped)
            if not args.skip_continue:
                print_same_log(name, mapped)


if __name__ == "__main__":
    main()
