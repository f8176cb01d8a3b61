"""Localization in a saved map and continued mapping (issue 13) on the synthetic laser world.

The saved map of the localization tests is made of simulated scans at TRUE poses (tests/laser_world.py),
so the map frame is the world frame and every localized pose is compared with the simulation's truth.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
import pytest

from frontends.errors import LogWarning, MapExtentError
from frontends.protocol import checked_on_saved_path, unmatched_on_saved_path
from frontends.slam2d.config import (
    OPTIMIZE_EVERY_LOOP_CLOSURES,
    SMALL_CORRECTION_ANGULAR,
    SMALL_CORRECTION_LINEAR,
    Slam2DConfig,
)
from frontends.slam2d.global_match import VerifiedMatch
from frontends.slam2d.grid import MAX_LIKELIHOOD_CELLS
from frontends.slam2d.icp import scan_normals
from frontends.slam2d.local_map import Keyframe, place
from frontends.slam2d.localization import (
    EmptyMapError,
    LocalizationConfig,
    LocalizedScan,
    MapLocalizer,
    whole_map_resolution,
)
from frontends.slam2d.localization_smoothing import smooth_localized, smooth_scans, tracking_drift
from frontends.slam2d.resume import MapPlacementError, SavedConstraints, SavedScans
from frontends.slam2d.scan_odometry import ScanOdometry
from frontends.slam2d.slam import LaserSlam2D, _LoopHypothesis
from optimizer import se2
from optimizer.solve import optimize
from tests.laser_world import (
    Run,
    align_to_first,
    between,
    corridor_of_doors,
    route_length,
    route_poses,
    simulate_run,
    simulate_scan,
    square_loop,
)
from tests.laser_world import compose as compose_poses

MAP_EVERY = 3
"""A map keyframe every 3rd pose of the mapping drive (0.6 m apart)."""


@pytest.fixture(scope="module")
def mapping_run() -> Run:
    return simulate_run(square_loop(), seed=1)


@pytest.fixture(scope="module")
def localizer_map(mapping_run: Run) -> tuple[list[np.ndarray], np.ndarray]:
    keyframes = np.arange(0, len(mapping_run.truth), MAP_EVERY)
    return [mapping_run.scans[k] for k in keyframes], mapping_run.truth[keyframes]


@pytest.fixture(scope="module")
def new_run() -> Run:
    """Another drive of the same building: a different scan spacing (its poses are not the map's) and
    different noise."""
    return simulate_run(square_loop(), step=0.15, seed=5)


def position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1])


def heading_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.abs((poses[:, 2] - truth[:, 2] + np.pi) % (2.0 * np.pi) - np.pi)


def test_without_an_initial_pose_the_robot_is_found_and_tracked(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    localizer = MapLocalizer(*localizer_map)
    start = 120  # the east corridor: nothing tells the localizer where the drive starts
    odometry = between(new_run.odometry[start], new_run.odometry[start:])  # its origin dropped
    results = [localizer.localize(int(stamp), scan, odo)
               for stamp, scan, odo in zip(new_run.stamps_ns[start:], new_run.scans[start:], odometry,
                                           strict=True)]
    truth = new_run.truth[start:]
    fixes = [r for r in results if r.global_fix]
    assert len(fixes) == 1, "one global localization, then tracking without losing the robot"
    fix = fixes[0]
    assert fix.index < 20, f"found only after {fix.index} scans"
    assert all(not r.localized for r in results[: fix.index])
    assert all(r.localized and r.matched for r in results[fix.index:])
    poses = np.array([r.pose for r in results[fix.index:]])
    assert position_errors(poses, truth[fix.index:]).max() < 0.05
    assert heading_errors(poses, truth[fix.index:]).max() < math.radians(1.0)
    # The scans before the fix (none when the first scan fits one place only) get their map poses from it.
    np.testing.assert_array_equal(fix.recovered_indices, np.arange(fix.index))
    assert np.all(position_errors(fix.recovered_poses, truth[: fix.index]) < 0.05)
    assert np.all(np.linalg.eigvalsh(fix.information) > 0)


def test_the_scans_before_a_fix_keep_their_poses_when_the_wheel_odometry_starts_late(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """A log's first scan often comes before its first odometry message (the Freiburg 079 log's does).
    The localizer tracks such a scan with its own scan odometry, then the wheels' takes over, in a frame
    of its own: the lost stretch's tracker must not take that change of frame as a motion. It did, and
    `--continue` with the log its session was made from placed the run's first scan 10 m off, turned
    round, and the whole new run with it."""
    start = 120
    wheels_origin = np.array([-3.0, 8.3, -3.1])  # where the wheels' frame has the robot: anywhere
    wheels = compose_poses(wheels_origin, between(new_run.odometry[start], new_run.odometry[start + 1:]))
    odometry = [None, *wheels]
    localizer = MapLocalizer(*localizer_map, first_scan_alone=False)  # as `--continue` places a run
    results = [localizer.localize(int(stamp), scan, odo)
               for stamp, scan, odo in zip(new_run.stamps_ns[start:], new_run.scans[start:], odometry,
                                           strict=True)]
    fix = next(r for r in results if r.global_fix)
    assert fix.index > 1, "the first scans wait for a few keyframes"
    np.testing.assert_array_equal(fix.recovered_indices, np.arange(fix.index))
    truth = new_run.truth[start:start + fix.index]
    assert np.all(position_errors(fix.recovered_poses, truth) < 0.05)
    assert np.all(heading_errors(fix.recovered_poses, truth) < math.radians(1.0))


def test_a_robot_standing_still_is_found_from_its_first_scan(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """A recording often starts before the robot moves: no keyframe comes to wait for. Without odometry or
    an initial pose, a scan that fits one place of the map only is placed at once (in the south and the
    east corridor); one that passes the tests nowhere alone (at the north-east corner) is not placed at all
    while the robot stands, rather than placed wrong."""
    rng = np.random.default_rng(3)
    for start, distinct in ((30, True), (120, True), (200, False)):
        localizer = MapLocalizer(*localizer_map)
        scan = new_run.scans[start]
        results = [localizer.localize(1_000_000_000 + i * 100_000_000,
                                      scan + rng.normal(0.0, 0.005, scan.shape), None)
                   for i in range(30)]  # 3 s standing
        fixes = [r.index for r in results if r.global_fix]
        if not distinct:
            assert fixes == [] and not any(r.localized for r in results)
            continue
        assert fixes == [0]
        assert all(r.localized for r in results)
        poses = np.array([r.pose for r in results])
        assert position_errors(poses, np.tile(new_run.truth[start], (30, 1))).max() < 0.02


def test_with_an_initial_pose_tracking_starts_at_once(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    start = 30
    guess = new_run.truth[start] + np.array([0.2, -0.15, math.radians(4.0)])  # a rough start pose
    localizer = MapLocalizer(*localizer_map, initial_pose=guess)
    results = [localizer.localize(int(new_run.stamps_ns[k]), new_run.scans[k], new_run.odometry[k])
               for k in range(start, start + 60)]
    assert all(r.localized and r.matched and not r.global_fix for r in results)
    poses = np.array([r.pose for r in results])
    assert position_errors(poses, new_run.truth[start:start + 60]).max() < 0.05


def test_tracking_a_whole_drive_stays_on_the_truth(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """Once round the building and on past the start, from a rough start pose: every scan is localized
    and matched, within a few centimetres of the truth although the odometry drifts metres."""
    guess = new_run.truth[0] + np.array([-0.15, 0.1, math.radians(-3.0)])
    localizer = MapLocalizer(*localizer_map, initial_pose=guess)
    results = [localizer.localize(int(stamp), scan, odo)
               for stamp, scan, odo in zip(new_run.stamps_ns, new_run.scans, new_run.odometry, strict=True)]
    assert all(r.localized and r.matched and not r.predicted for r in results)
    assert not any(r.global_fix or r.relocalized for r in results)
    poses = np.array([r.pose for r in results])
    errors = position_errors(poses, new_run.truth)
    drift = position_errors(align_to_first(new_run.odometry, new_run.truth), new_run.truth)
    assert drift.max() > 1.0, "the odometry alone would be metres off: the map does the work"
    assert errors[5:].max() < 0.05 and np.median(errors) < 0.02
    assert heading_errors(poses[5:], new_run.truth[5:]).max() < math.radians(1.0)


def matched_poses(localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run, order: list[int],
                  odometry: Sequence[np.ndarray]) -> np.ndarray:
    """The new run's scans `order` localized with `odometry` from the first one's true pose, 0.3 s apart;
    every one must match the map."""
    localizer = MapLocalizer(*localizer_map, initial_pose=new_run.truth[order[0]])
    results = [localizer.localize(int(new_run.stamps_ns[0]) + k * 300_000_000, new_run.scans[scan], odo)
               for k, (scan, odo) in enumerate(zip(order, odometry, strict=True))]
    assert all(r.matched for r in results)
    return np.array([r.pose for r in results])


def test_wheels_that_report_driving_forwards_while_the_robot_backs_up_do_not_drag_it_off_the_map(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """The Freiburg 079 log's odometry drives forwards while the robot backs up, 0.1 m a scan. Where the
    map places each scan distinctly, the wheels' prediction off its score plateau must not pull the match
    towards it: fused as it weighs, it took the pose 5 m off that log's own map, here 11 m."""
    forward = list(range(120, 160))
    order = forward + forward[::-1][1:]  # down the east corridor and back, facing the same way
    truth = new_run.truth[order]
    steps = between(truth[:-1], truth[1:])
    steps[len(forward) - 1:, 0] *= -1.0  # backing up: the wheels say forwards
    odometry = [truth[0]]
    for step in steps:
        odometry.append(compose_poses(odometry[-1], step))
    poses = matched_poses(localizer_map, new_run, order, odometry)
    assert position_errors(poses, truth).max() < 0.05
    assert heading_errors(poses, truth).max() < math.radians(1.0)


def test_wheels_that_stop_counting_and_then_jump_are_paid_back_what_the_map_matched(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """CSAIL's odometry holds its position for a few scans while the robot drives on, its heading still
    turning, then jumps by the whole motion. The map overrules the held wheels meanwhile; the jump must not
    add that motion again: sought from the matched pose 0.75 m ahead, the scan was placed 0.5–1.3 m off."""
    order = list(range(120, 150))
    truth = new_run.truth[order]
    odometry = truth.copy()
    odometry[10:15, :2] = odometry[9, :2]  # five scans (0.75 m) without counting the wheels' turns
    odometry[10:15, 2] += 1e-3 * np.arange(1, 6)  # while the heading still updates
    poses = matched_poses(localizer_map, new_run, order, odometry)
    assert position_errors(poses, truth).max() < 0.05


def test_scans_that_do_not_match_keep_the_prediction(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """People block the laser for 3 m of a corridor (a handful of returns a scan): those scans keep the
    odometry's prediction, localized but counted as predicted; the track then matches the map again."""
    span = range(40, 140)
    blocked = range(60, 80)
    localizer = MapLocalizer(*localizer_map, initial_pose=new_run.truth[span.start])
    results = []
    for k in span:
        scan = new_run.scans[k][:8] if k in blocked else new_run.scans[k]
        results.append(localizer.localize(int(new_run.stamps_ns[k]), scan, new_run.odometry[k]))
    inside = [k - span.start for k in blocked]
    assert all(r.localized for r in results)
    assert all(results[i].predicted and not results[i].matched for i in inside)
    assert not any(r.predicted for i, r in enumerate(results) if i not in inside)
    poses = np.array([r.pose for r in results])
    truth = new_run.truth[span.start:span.stop]
    odometry_error = position_errors(align_to_first(new_run.odometry[blocked.start - 1:blocked.stop],
                                                    new_run.truth[blocked.start - 1:blocked.stop]),
                                     new_run.truth[blocked.start - 1:blocked.stop]).max()
    assert position_errors(poses[inside], truth[inside]).max() < odometry_error + 0.05
    assert position_errors(poses[inside[-1] + 3:], truth[inside[-1] + 3:]).max() < 0.05


def kidnapped_drive(run: Run, before: range, after: range) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The scans of `before` then of `after` (the robot carried elsewhere between the two), with odometry
    that goes on smoothly across the jump (it never saw the robot lifted), and the true poses."""
    scans = [run.scans[k] for k in before] + [run.scans[k] for k in after]
    first = run.odometry[list(before)]
    carried_on = compose_poses(first[-1], between(run.odometry[after.start - 1], run.odometry[list(after)]))
    return scans, np.concatenate([first, carried_on]), np.concatenate([run.truth[list(before)],
                                                                       run.truth[list(after)]])


def test_a_kidnapped_robot_is_found_again(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """Tracked along the south corridor heading east, then carried to the east corridor heading north, its
    odometry none the wiser. Seen from inside, one corridor looks like another: at the prediction the scans
    still fit the map, worse than a true track's, then ever worse as the doors and the clutter disagree;
    once nothing has matched well for `max_dead_reckoning` metres (shortened here from 30 m, so the test
    stays short) the robot is lost, and the global search finds it again. Its estimate drives on east out of
    the map, where by default the rolling local map would track it on its own scans (see
    `LocalizationConfig.map_reach`): `count_rolling_tracks_near_map` with `map_reach` = inf keeps every
    rolling track counted as dead reckoning."""
    before, after = range(10, 60), range(130, 300)
    scans, odometry, truth = kidnapped_drive(new_run, before, after)
    settings = LocalizationConfig(max_dead_reckoning=4.0, map_reach=math.inf,
                                  count_rolling_tracks_near_map=True)
    localizer = MapLocalizer(*localizer_map, initial_pose=truth[0], settings=settings)
    results = [localizer.localize(int(new_run.stamps_ns[0]) + k * 300_000_000, scan, odo)
               for k, (scan, odo) in enumerate(zip(scans, odometry, strict=True))]
    poses = np.array([r.pose for r in results])
    jump = len(before)
    assert position_errors(poses[:jump], truth[:jump]).max() < 0.05
    assert min(r.score for r in results[:jump]) > 0.9
    fixes = [r.index for r in results if r.global_fix]
    assert len(fixes) == 1 and jump < fixes[0] < jump + 80, f"found again at {fixes}"
    wrong = results[jump:fixes[0]]
    assert all(not (r.matched and r.score > 0.8) for r in wrong), "the wrong place fits like the right one"
    # Declared lost, the robot is looked for at once, from its scan alone: no scan is left without a pose.
    assert all(r.localized for r in wrong)
    after_fix = slice(fixes[0], None)
    assert all(r.localized and r.matched for r in results[after_fix])
    assert position_errors(poses[after_fix], truth[after_fix]).max() < 0.05


def test_outside_the_saved_map_the_rolling_local_map_tracks_the_robot(mapping_run: Run, new_run: Run) -> None:
    """The saved map holds only the south corridor (its keyframes' points south of y = 2.5 m); the robot
    drives the whole loop. Out of the south corridor nothing of the map is in sight: the recent scans
    (the rolling local map) carry the pose, tracked rather than predicted, and the odometry's metres of
    drift never show; back in the south corridor the saved map matches again, once a re-acquisition as
    wide as the 50 m off the map allow for, of the scan the map fits, lands where the track is. The map is
    not changed."""
    keyframes = [k for k in range(0, len(mapping_run.truth), MAP_EVERY) if mapping_run.truth[k, 1] < 2.0]
    scans = [mapping_run.scans[k][place(mapping_run.scans[k], mapping_run.truth[k])[:, 1] < 2.5]
             for k in keyframes]
    localizer = MapLocalizer(scans, mapping_run.truth[keyframes], initial_pose=new_run.truth[0])
    saved_points = localizer.map.points.copy()
    results = [localizer.localize(int(stamp), scan, odo)
               for stamp, scan, odo in zip(new_run.stamps_ns, new_run.scans, new_run.odometry, strict=True)]
    assert all(r.localized for r in results)
    assert not any(r.global_fix for r in results)
    outside = new_run.truth[:, 1] > 5.0  # the east, north and west corridors: no map point within 2.5 m
    tracked = np.array([r.tracked for r in results])
    matched = np.array([r.matched for r in results])
    assert not (tracked & matched).any()
    assert tracked[outside].mean() > 0.95, "outside the map, the rolling local map carries the pose"
    assert not any(r.predicted for r in results)
    poses = np.array([r.pose for r in results])
    errors = position_errors(poses, new_run.truth)
    drift = position_errors(align_to_first(new_run.odometry, new_run.truth), new_run.truth)
    assert drift[outside].max() > 2.0, "the odometry alone would be metres off outside the map"
    assert errors[outside].max() < 0.1
    back = np.flatnonzero(new_run.truth[:, 1] < 2.0)
    back = back[back > np.flatnonzero(outside).max()]  # the south corridor again, at the end of the drive
    assert len(back) > 30 and (matched | tracked)[back].all()
    assert matched[back[10:]].all(), "1.5 m back in the saved map, its matches place the scans"
    assert errors[back].max() < 0.05
    np.testing.assert_array_equal(localizer.map.points, saved_points)


@pytest.mark.parametrize("offset", [-3.0, 3.0])
def test_a_pose_that_drifted_metres_outside_the_map_is_found_as_far_off_as_it_may_be(mapping_run: Run,
                                                                                    offset: float) -> None:
    """The saved map holds only the south corridor; the robot starts in the north corridor heading west,
    its given pose `offset` metres off along x, drives round through the west corridor (tracked on the
    rolling local map, carrying the offset like a drift) and enters the south corridor with the pose 3 m
    off along it. Searching only a window capped short of that (`max_relocalize_window`, shortened here to
    1 m so the drive stays short), the corridor's walls fitted a look-alike stretch inside it, and the
    scans were map-matched there, 2.4–2.8 m off, to the end: the re-acquisition searches as far as the
    distance driven off the map allows (its coarse grid, the ambiguity test), and only it may bring the
    pose back onto the map."""
    keyframes = [k for k in range(0, len(mapping_run.truth), MAP_EVERY) if mapping_run.truth[k, 1] < 2.0]
    scans = [mapping_run.scans[k][place(mapping_run.scans[k], mapping_run.truth[k])[:, 1] < 2.5]
             for k in keyframes]
    run = simulate_run(square_loop(), step=0.15, seed=5, max_range=4.0)
    start = int(np.flatnonzero((run.truth[:, 1] > 18.0) & (run.truth[:, 0] < 14.0))[0])
    truth = run.truth[start:]
    settings = LocalizationConfig(max_relocalize_window=1.0)
    localizer = MapLocalizer(scans, mapping_run.truth[keyframes], initial_pose=truth[0] + [offset, 0.0, 0.0],
                             settings=settings)
    results = [localizer.localize(int(stamp), scan, odo) for stamp, scan, odo
               in zip(run.stamps_ns[start:], run.scans[start:], run.odometry[start:], strict=True)]
    errors = position_errors(np.array([r.pose for r in results]), truth)
    matched = np.array([r.matched for r in results])
    in_south = truth[:, 1] < 2.0
    assert in_south[-40:].all() and errors[~in_south].min() > 2.5, "driven into the map with the pose off"
    assert matched[-40:].all() and errors[-40:].max() < 0.05
    assert errors[matched].max() < 0.1, "never matched to the map in the wrong place"
    assert sum(r.relocalized for r in results) == 1


def test_a_wide_match_moving_the_track_is_taken_only_when_another_metres_on_agrees(
        localizer_map: tuple[list[np.ndarray], np.ndarray]) -> None:
    """One wide match may be a look-alike of a place the map never saw (CSAIL: 9.4 m off, unambiguous in
    the map): a match landing where the track is is taken at once; one moving the track waits until
    another, at least `relocalize_every_outside` metres on (mostly other scans), moves it the same way."""
    localizer = MapLocalizer(*localizer_map, initial_pose=[5.0, 1.0, 0.0])
    assert localizer._pose is not None
    every = localizer.settings.relocalize_every_outside

    def match(pose: list[float]) -> VerifiedMatch:
        return VerifiedMatch(np.array(pose), 0.8, None)  # type: ignore[arg-type]  # not read

    localizer._travelled = 10.0
    assert localizer._confirmed(match([5.1, 1.05, 0.01])) is not None, "where the track is: taken"
    assert localizer._confirmed(match([8.0, 1.0, 0.0])) is None, "3 m off: waits"
    localizer._travelled += 0.5 * every
    assert localizer._confirmed(match([8.0, 1.0, 0.0])) is None, "the same scans, mostly"
    localizer._travelled += every
    assert localizer._confirmed(match([11.0, 1.0, 0.0])) is None, "another correction: waits again"
    localizer._travelled += every
    assert localizer._confirmed(match([11.1, 1.0, 0.02])) is not None, "two agreeing, metres apart"
    assert localizer._pending_correction is None


def test_a_region_hours_of_driving_wide_is_searched_as_the_whole_map(
        localizer_map: tuple[list[np.ndarray], np.ndarray], mapping_run: Run) -> None:
    """The region a wide re-acquisition may search grows with the distance driven off the map: 100 km of
    it (a 200 km square) searches the map's own extent, in the memory and time of a whole-map search."""
    import time
    import tracemalloc

    localizer = MapLocalizer(*localizer_map, initial_pose=mapping_run.truth[40])
    scans, poses = list(mapping_run.scans[36:41]), list(mapping_run.truth[36:41])
    tracemalloc.start()
    started = time.process_time()
    found = localizer._wide_match(scans, poses, 1e5)
    seconds = time.process_time() - started
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert found is not None and position_errors(found.pose[None], mapping_run.truth[40][None])[0] < 0.05
    assert peak < 50e6 and seconds < 5.0, f"{peak / 1e6:.0f} MB, {seconds:.1f} s"


def localized_in_the_south_corridor_map(mapping_run: Run, run: Run) -> list[LocalizedScan]:
    """`run` localized from its true start in a map of the south corridor only (the mapping run's
    keyframes there, with their points south of y = 2.5 m)."""
    keyframes = [k for k in range(0, len(mapping_run.truth), MAP_EVERY) if mapping_run.truth[k, 1] < 2.0]
    scans = [mapping_run.scans[k][place(mapping_run.scans[k], mapping_run.truth[k])[:, 1] < 2.5]
             for k in keyframes]
    localizer = MapLocalizer(scans, mapping_run.truth[keyframes], initial_pose=run.truth[0])
    return [localizer.localize(int(stamp), scan, odo)
            for stamp, scan, odo in zip(run.stamps_ns, run.scans, run.odometry, strict=True)]


def test_a_stretch_tracked_outside_the_map_is_smoothed_between_the_map_fixes(mapping_run: Run) -> None:
    """The saved map holds only the south corridor; the new run's laser reaches 4 m and its odometry is
    3 % long. Around the east, north and west corridors the rolling local map sees mostly two parallel
    walls: the tracked pose drifts along them with the odometry, and back in the south corridor the map's
    match corrects it at once. Smoothed offline (the locally measured motions between the map fixes at
    both ends), the tracked stretch lies far nearer the truth; the map-matched scans stay where they were."""
    run = simulate_run(square_loop(), step=0.15, seed=5, max_range=4.0, scale_error=0.03)
    results = localized_in_the_south_corridor_map(mapping_run, run)
    assert all(r.localized for r in results)
    tracked = np.array([r.tracked for r in results])
    matched = np.array([r.matched for r in results])
    assert tracked.sum() > 200 and matched[:50].all() and matched[-50:].all(), "out of the map and back"
    online = position_errors(np.array([r.pose for r in results]), run.truth)
    assert np.median(online[tracked]) > 0.1, "the tracked stretch drifts (else nothing to smooth)"
    smoothed = smooth_scans(results)
    assert smoothed.converged and smoothed.smoothed.all()
    errors = position_errors(smoothed.poses, run.truth)
    assert np.median(errors[tracked]) < 0.6 * np.median(online[tracked])
    assert errors[tracked].max() < online[tracked].max()
    # The map-matched scans stay where they were, but for the first ones beside the stretch, which the
    # chain may pull towards itself: none ends farther from the truth than the farthest was online (give
    # or take a millimetre: that farthest is the re-acquired scan ending the stretch, 0.0158 → 0.0165 m).
    assert np.median(np.abs(errors[matched] - online[matched])) < 0.001
    assert errors[matched].max() <= online[matched].max() + 0.001


RANGE_NOISE = 0.01
"""The simulated laser's range noise σ (m) (`simulate_run`'s default)."""


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_a_stretch_tracked_with_little_drift_is_not_made_worse_by_smoothing(mapping_run: Run,
                                                                            seed: int) -> None:
    """The saved map holds only the south corridor; the new run's laser reaches 20 m, so the rolling local
    map tracks the rest of the loop to within a centimetre or so. The smoothing may not bend such a track
    away from the truth: its tracked scans end no farther from it than online, give or take the laser's
    own noise, and nowhere by more than the map matches it is tied to are off (seed 7 was 0.005 m online,
    0.027 m smoothed while the tracked steps were weighed by the rolling map's match as independent
    steps)."""
    run = simulate_run(square_loop(), step=0.15, seed=seed, range_noise=RANGE_NOISE)
    results = localized_in_the_south_corridor_map(mapping_run, run)
    tracked = np.array([r.tracked for r in results])
    assert tracked.sum() > 200
    online = position_errors(np.array([r.pose for r in results]), run.truth)
    assert np.median(online[tracked]) < 2.0 * RANGE_NOISE, "the track barely drifts"
    smoothed = smooth_scans(results)
    assert smoothed.converged and smoothed.smoothed[tracked].all()
    errors = position_errors(smoothed.poses, run.truth)
    assert np.median(errors[tracked]) <= np.median(online[tracked]) + RANGE_NOISE
    # The smoothing ties the track to the map matches beside it: it may inherit their error, no more.
    matched = np.array([r.matched for r in results])
    assert errors[tracked].max() <= online[tracked].max() + online[matched].max()


def test_the_tracking_drift_is_measured_by_the_jumps_at_map_reentry() -> None:
    """Scans 1 m apart along x, the motions measured exactly but at the two re-entries: after 3 tracked
    scans (4 steps to the map match) the map places the scan (0.3, 0.4, 0.02) off the track, after 5 (6
    steps) (0, 0.1, 0). A random walk of variance q per step drifts by 4 q and 6 q: the pooled estimate is
    q = Σ J² / 10 steps, x and y pooled alike. A tracked stretch not started from a map match (the last
    one) is no re-entry and measures nothing."""
    count = 18
    poses = np.column_stack([np.arange(count, dtype=float), np.zeros(count), np.zeros(count)])
    motions = np.tile([1.0, 0.0, 0.0], (count, 1))
    tracked = np.zeros(count, dtype=bool)
    tracked[[1, 2, 3, 6, 7, 8, 9, 10, 15, 16]] = True
    anchored = ~tracked
    anchored[14] = False  # unlocalized before the last stretch
    motions[4] = se2.relative(poses[3], poses[4] - [0.3, 0.4, 0.02])
    motions[11] = se2.relative(poses[10], poses[11] - [0.0, 0.1, 0.0])
    motions[17] = [0.5, 0.5, 0.5]
    linked = np.ones(count, dtype=bool)
    linked[[0, 14, 15]] = False
    drift = tracking_drift(poses, linked, tracked, anchored, motions)
    assert drift is not None
    np.testing.assert_allclose(drift, [0.5 * (0.09 + 0.16 + 0.01) / 10, 0.5 * (0.09 + 0.16 + 0.01) / 10,
                                       0.02**2 / 10], rtol=1e-9)
    assert tracking_drift(poses, linked, np.zeros(count, dtype=bool), anchored, motions) is None


def test_smoothing_spreads_a_chain_drift_between_its_anchors_and_leaves_unanchored_chains() -> None:
    """Ten scans 1 m apart along x: the locally measured motions are 1.1 m (10 % long), the first and the
    last scan are anchored at their true poses. Smoothed, the drift is spread evenly: every scan at x = k
    (the chain's steps all shortened alike, by symmetry). A chain after an unlocalized scan has no anchor:
    its poses stay as given; the unlocalized scan keeps no pose."""
    count = 14
    truth = np.column_stack([np.arange(count, dtype=float), np.zeros(count), np.zeros(count)])
    motions = np.tile([1.1, 0.0, 0.0], (count, 1))
    motions[0] = np.nan
    online = np.column_stack([1.1 * np.arange(count), np.zeros(count), np.zeros(count)])
    localized = np.ones(count, dtype=bool)
    localized[10] = False
    online[10] = np.nan
    motion_information = np.tile(np.diag([100.0, 100.0, 1000.0]), (count, 1, 1))
    map_information = np.zeros((count, 3, 3))
    map_information[[0, 9]] = np.diag([1e8, 1e8, 1e8])
    online[9] = truth[9]
    smoothed = smooth_localized(online, localized, motions, motion_information, map_information,
                                np.zeros(count, dtype=bool))
    assert smoothed.converged
    np.testing.assert_allclose(smoothed.poses[:10], truth[:10], atol=1e-5)
    np.testing.assert_array_equal(smoothed.poses[11:], online[11:])
    assert np.isnan(smoothed.poses[10]).all()
    np.testing.assert_array_equal(smoothed.smoothed, np.arange(count) < 10)


def test_a_map_without_points_is_refused() -> None:
    with pytest.raises(EmptyMapError):
        MapLocalizer([np.zeros((3, 2))], np.zeros((1, 3)))


# ------------------------------------------------------------------------------------ continue mapping


FIRST_SCANS = 260
"""The first session maps the south and east corridors and part of the north one."""
SECOND_START = 150
"""The second session is another drive starting in the east corridor (inside the saved map) and going
round the rest of the loop back to the start: it ends where the first session began."""


def test_resume_joins_a_second_session_to_the_saved_graph(mapping_run: Run) -> None:
    first = LaserSlam2D()
    for k in range(FIRST_SCANS):
        first.add_scan(int(mapping_run.stamps_ns[k]), mapping_run.scans[k], mapping_run.odometry[k])
    saved = first.finish()
    *_, optimized = optimize(saved.graph)
    old_keyframes = saved.graph.num_poses

    second_run = simulate_run(square_loop(), seed=7)
    stamps = second_run.stamps_ns[SECOND_START:] + 10**12  # recorded later
    odometry = between(second_run.odometry[SECOND_START], second_run.odometry[SECOND_START:])
    slam = LaserSlam2D.resume(saved.keyframe_scans, optimized.poses, SavedConstraints.of(saved.graph),
                              scans=SavedScans.of(saved))
    estimates = [slam.add_scan(int(s), scan, odo)
                 for s, scan, odo in zip(stamps, second_run.scans[SECOND_START:], odometry, strict=True)]
    assert slam.placement is not None and slam.scans_unplaced == 0
    placed_at = next(i for i, e in enumerate(estimates) if e.keyframe >= 0)
    assert placed_at < 60  # corridors look alike: a few metres of driving before it is unambiguous
    assert all(np.isnan(e.pose).all() for e in estimates[:placed_at])
    assert all(e.keyframe >= old_keyframes for e in estimates[placed_at:])
    joint = slam.finish()

    # Every scan of both sessions, old ones first, each hanging off a keyframe of its own session.
    new_count = len(second_run.truth) - SECOND_START
    assert len(joint.scan_stamps_ns) == FIRST_SCANS + new_count
    np.testing.assert_array_equal(joint.scan_stamps_ns[FIRST_SCANS:], stamps)
    assert np.all(joint.scan_keyframes[:FIRST_SCANS] < old_keyframes)
    assert np.all(joint.scan_keyframes[FIRST_SCANS:] >= old_keyframes)
    graph = joint.graph
    crossing = ((graph.edge_from < old_keyframes) != (graph.edge_to < old_keyframes)) & ~graph.is_odometry
    assert crossing.sum() >= 2, "the second session's return to the start closes no loop on the first"

    *_, final = optimize(graph.with_poses(joint.odometry_chain),
                         starts={"odometry": joint.odometry_chain, "online": graph.poses})
    poses = joint.scan_poses(final.poses)
    truth = np.concatenate([mapping_run.truth[:FIRST_SCANS], second_run.truth[SECOND_START:]])
    aligned = align_to_first(poses, truth)
    errors = position_errors(aligned, truth)
    assert errors.max() < 0.15, f"max position error {errors.max():.3f} m at scan {errors.argmax()}"
    assert heading_errors(aligned, truth).max() < math.radians(1.0)


def test_a_second_session_that_never_matches_the_map_is_refused(mapping_run: Run) -> None:
    first = LaserSlam2D()
    for k in range(60):
        first.add_scan(int(mapping_run.stamps_ns[k]), mapping_run.scans[k], mapping_run.odometry[k])
    saved = first.finish()
    slam = LaserSlam2D.resume(saved.keyframe_scans, saved.graph.poses, SavedConstraints.of(saved.graph))
    for k in range(5):  # too few keyframes to search with
        estimate = slam.add_scan(int(mapping_run.stamps_ns[k]) + 10**12, mapping_run.scans[k])
        assert estimate.keyframe == -1 and not estimate.matched
    with pytest.raises(MapPlacementError):
        slam.finish()


def test_resumed_slam_optimizes_at_once_after_a_loop_closure_that_moves_the_map_far() -> None:
    """A plain SLAM waits for `OPTIMIZE_EVERY_LOOP_CLOSURES` loop closures before re-optimizing; a resumed
    one does not when a loop closure moves its keyframe by more than a small correction (the new run came
    back to the old map far off: left uncorrected, the estimate falls outside the search radius the new
    loop closure just shrank, and the loop closures that would follow are never searched for). What counts
    is the keyframe's own move, not the map's rotation about a far origin."""
    rng = np.random.default_rng(3)
    far = np.array([[50.0, 0.0, 0.0], [50.3, 0.0, 0.0]])  # 50 m from the map's origin
    scans = [rng.uniform(-5.0, 5.0, size=(200, 2)) for _ in far]
    saved = SavedConstraints(np.array([0]), np.array([1]), np.array([[0.3, 0.0, 0.0]]), np.eye(3)[None])
    resumed = LaserSlam2D.resume(scans, far, saved)
    plain = LaserSlam2D()

    def loop(correction: tuple[float, float, float]) -> _LoopHypothesis:
        return _LoopHypothesis(0, 1, np.zeros(3), np.eye(3), np.array(correction))

    small = [loop((0.5 * SMALL_CORRECTION_LINEAR, 0.0, 0.0))]
    metres_off = [loop((3.0, -3.5, 0.0))]
    turned = [loop((0.0, 0.0, 2.0 * SMALL_CORRECTION_ANGULAR))]
    # Keyframe 1 turned in place by half the small angle: as a move of the map about its origin that is
    # also a 0.46 m shift (50 m × 0.026 rad), yet the keyframe stays where it is.
    in_place = far[1] + np.array([0.0, 0.0, 0.5 * SMALL_CORRECTION_ANGULAR])
    about_origin = [loop(tuple(se2.compose(in_place, se2.inverse(far[1]))))]
    for slam in (plain, resumed):
        slam._pending_loops = OPTIMIZE_EVERY_LOOP_CLOSURES - 1
        assert not slam._optimization_due(small)
        slam._pending_loops = OPTIMIZE_EVERY_LOOP_CLOSURES
        assert slam._optimization_due(small)
        slam._pending_loops = 1
    assert not any(plain._optimization_due(h) for h in (metres_off, turned, about_origin))
    assert resumed._optimization_due(metres_off) and resumed._optimization_due(turned)
    assert not resumed._optimization_due(about_origin)


def map_seen_from_afar(mapping_run: Run) -> tuple[list[np.ndarray], np.ndarray]:
    """The mapping run's keyframes without their points between y = 5 m and y = 15 m (the middle of the
    east and west corridors, seen only from their ends)."""
    keyframes = list(range(0, len(mapping_run.truth), MAP_EVERY))
    scans = []
    for k in keyframes:
        world_y = place(mapping_run.scans[k], mapping_run.truth[k])[:, 1]
        scans.append(mapping_run.scans[k][(world_y <= 5.0) | (world_y >= 15.0)])
    return scans, mapping_run.truth[keyframes]


def test_a_stretch_the_map_saw_only_from_afar_is_tracked_not_lost(mapping_run: Run, new_run: Run) -> None:
    """The saved map lost every point between y = 5 m and y = 15 m (the middle of the east and west
    corridors: the first run saw them only from their ends), but keeps its keyframes there. Driving through,
    the map's matches are weak or fail, and the rolling local map (the recent scans with those keyframes)
    explains the scans: that is tracking, not dead reckoning, so the robot is never lost, even with
    `max_dead_reckoning` (shortened here to 4 m) below the 8 m of the gap; and it stays on the truth."""
    settings = LocalizationConfig(max_dead_reckoning=4.0)
    localizer = MapLocalizer(*map_seen_from_afar(mapping_run), initial_pose=new_run.truth[0],
                             settings=settings)
    results = [localizer.localize(int(stamp), scan, odo)
               for stamp, scan, odo in zip(new_run.stamps_ns, new_run.scans, new_run.odometry, strict=True)]
    gap = (new_run.truth[:, 1] > 6.0) & (new_run.truth[:, 1] < 14.0)
    assert gap.sum() > 80, "both corridors' middles are driven"
    in_gap = [r for r, g in zip(results, gap, strict=True) if g]
    assert not any(r.matched and r.score >= settings.min_tracking_score for r in in_gap)
    assert np.mean([r.tracked for r in in_gap]) > 0.5, "the rolling local map tracks there"
    assert all(r.localized for r in results)
    assert not any(r.global_fix for r in results)
    poses = np.array([r.pose for r in results])
    assert position_errors(poses, new_run.truth).max() < 0.05


@pytest.mark.parametrize("seed", [5, 6])
def test_where_the_map_matches_weakly_poor_wheel_odometry_does_not_steer_the_pose(mapping_run: Run,
                                                                               seed: int) -> None:
    """The map saw the middles of the east and west corridors only from afar, and the new run's wheels
    turn 3.4° (σ) a scan more or less than the robot (CSAIL's turn 5° off). Where the map's matches are
    weak, the motion is measured on the rolling local map (the recent scans), not taken from the wheels:
    weighed against the wheels' prediction, the weak matches left the heading there 6–7° off and the pose
    0.25–3 m off; measured on the recent scans, the heading stays within 0.3° there and the pose within
    2 cm everywhere."""
    new_run = simulate_run(square_loop(), step=0.15, seed=seed, angular_noise=0.06)
    localizer = MapLocalizer(*map_seen_from_afar(mapping_run), initial_pose=new_run.truth[0])
    results = [localizer.localize(int(stamp), scan, odo)
               for stamp, scan, odo in zip(new_run.stamps_ns, new_run.scans, new_run.odometry, strict=True)]
    assert all(r.localized for r in results)
    gap = (new_run.truth[:, 1] > 6.0) & (new_run.truth[:, 1] < 14.0)
    assert any(r.matched and r.score < LocalizationConfig().min_tracking_score
               for r, g in zip(results, gap, strict=True) if g), "weak matches in the gap"
    drift = heading_errors(align_to_first(new_run.odometry, new_run.truth), new_run.truth)
    assert drift.max() > math.radians(20.0), "the wheels alone would turn the pose far off"
    poses = np.array([r.pose for r in results])
    assert heading_errors(poses[gap], new_run.truth[gap]).max() < math.radians(1.0)
    assert position_errors(poses, new_run.truth).max() < 0.05


def test_scans_placed_on_the_saved_path_that_match_nothing_are_counted() -> None:
    keyframes = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    poses = np.array([[0.5, 0.2, 0.0],  # 0.54 m from a keyframe: on the path, matched
                      [2.9, 0.0, 1.0],  # 0.9 m: on the path, not matched
                      [4.0, 0.99, 0.0],  # 0.99 m: on the path, not matched
                      [1.0, 1.5, 0.0],  # 1.8 m: off the path
                      [10.0, 0.0, 0.0],  # far off
                      [np.nan, np.nan, np.nan]])  # no pose
    matched = np.array([True, False, False, True, False, False])
    assert unmatched_on_saved_path(poses[:, :2], matched, keyframes[:, :2]) == (3, 2)


def test_more_than_a_fifth_of_the_measurements_on_the_saved_path_matching_nothing_are_warned_of() -> None:
    keyframes = np.column_stack([np.arange(30.0), np.zeros(30)])
    positions = keyframes + 0.5
    a_fifth_unmatched = np.arange(30) < 24
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert checked_on_saved_path("a.mcap", "scans", positions, a_fifth_unmatched, keyframes) == (30, 6)
    with pytest.warns(LogWarning, match=r"a\.mcap: 7 of the 30 scans placed on the saved run's path"):
        checked_on_saved_path("a.mcap", "scans", positions, np.arange(30) < 23, keyframes)
    with warnings.catch_warnings():  # too few on the path to say
        warnings.simplefilter("error")
        checked_on_saved_path("a.mcap", "scans", positions[:19], np.arange(19) < 1, keyframes)
    # None matched at all: said whatever their number (an initial pose off the map, tracked from there).
    with pytest.warns(LogWarning, match=r"a\.mcap: none of the 19 scans placed in the saved map matched it"):
        checked_on_saved_path("a.mcap", "scans", positions[:19] + 100.0, np.zeros(19, dtype=bool), keyframes)


def test_without_odometry_a_gap_through_a_corner_is_tracked_across(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    # 2.4 s without scans while the robot drives round a corner (about half its 90°): the last scan's motion
    # carried over the gap, searched ±35° around, left the next scan unmatched and the robot lost; the
    # motion carried at its velocity, searched as far as the robot could have gone, keeps it tracked.
    turn = np.abs(np.diff(np.unwrap(new_run.truth[:, 2])))
    corner = int(np.argmax(turn > math.radians(2.0)))
    kept = [k for k in range(corner + 40) if not corner - 2 <= k < corner + 6]
    localizer = MapLocalizer(*localizer_map, initial_pose=new_run.truth[0])
    results = [localizer.localize(int(new_run.stamps_ns[k]), new_run.scans[k], None) for k in kept]
    assert all(r.matched and not r.relocalized and not r.global_fix for r in results)
    poses, truth = np.array([r.pose for r in results]), new_run.truth[kept]
    assert position_errors(poses, truth).max() < 0.05
    assert heading_errors(poses, truth).max() < math.radians(1.0)


def test_the_scans_own_odometry_goes_on_in_one_frame_across_its_restarts(new_run: Run) -> None:
    """Without wheel odometry the localizer predicts by the scans' own odometry, which restarts its tracking
    every few keyframes to bound memory: the restart's scan is placed by both trackings, so the motion
    between any two scans is measured as by one that never restarted."""
    span = range(0, 120)
    truth = new_run.truth[list(span)]
    whole = ScanOdometry(Slam2DConfig(), max_keyframes=10**6)
    unbroken = np.array([whole.pose(int(new_run.stamps_ns[k]), new_run.scans[k], None) for k in span])
    assert position_errors(align_to_first(unbroken, truth), truth).max() < 0.1
    # Restarting every 4 keyframes, or every 7 scans (a robot standing still makes no keyframes).
    for restarting in (ScanOdometry(Slam2DConfig(), max_keyframes=4),
                       ScanOdometry(Slam2DConfig(), max_keyframes=10**6, max_scans=7)):
        restarted = np.array([restarting.pose(int(new_run.stamps_ns[k]), new_run.scans[k], None)
                              for k in span])
        steps, true_steps = se2.relative(restarted[:-1], restarted[1:]), se2.relative(truth[:-1], truth[1:])
        assert np.abs(steps[:, :2] - true_steps[:, :2]).max() < 0.02
        assert np.abs(se2.wrap_angle(steps[:, 2] - true_steps[:, 2])).max() < math.radians(1.0)
        # Over the whole drive (round corners, 24 m), no more drift than the tracking that never restarted.
        assert position_errors(align_to_first(restarted, truth), truth).max() < 0.1


def test_without_odometry_a_whole_drive_is_tracked_on_the_truth(
        localizer_map: tuple[list[np.ndarray], np.ndarray], new_run: Run) -> None:
    """No wheel odometry: every scan is matched on the map around the scans' own odometry's prediction."""
    localizer = MapLocalizer(*localizer_map, initial_pose=new_run.truth[0])
    results = [localizer.localize(int(stamp), scan, None)
               for stamp, scan in zip(new_run.stamps_ns, new_run.scans, strict=True)]
    assert all(r.localized and r.matched for r in results)
    assert not any(r.global_fix or r.relocalized for r in results)
    poses = np.array([r.pose for r in results])
    errors = position_errors(poses, new_run.truth)
    assert errors.max() < 0.05 and np.median(errors) < 0.02
    assert heading_errors(poses, new_run.truth).max() < math.radians(1.0)
    assert localizer.stage_times.wall["scan odometry"] > 0.0


def test_without_odometry_the_scans_own_odometry_carries_the_pose_where_the_map_cannot() -> None:
    """The map was made with the corridor's doors shut: its plain walls cannot tell where along the
    corridor a scan was taken. The new run, with the doors open and no wheel odometry, drives it in spurts
    (0.6 m/s for 3 s, standing for 2 s). Constant velocity carried every spurt on into each stop, and
    nothing brought it back: 19 m off at most. The scans' own odometry sees the open doors go by."""
    mapped_world, new_world = corridor_of_doors(False), corridor_of_doors(True)
    rng = np.random.default_rng(4)
    map_poses = route_poses(mapped_world, np.arange(0.0, route_length(mapped_world), 0.5))
    map_scans = [simulate_scan(mapped_world.segments, pose, range_noise=0.01, rng=rng, max_range=8.0)
                 for pose in map_poses]
    seconds = np.arange(0.0, 90.0, 0.2)
    speed = np.where(seconds % 5.0 < 3.0, 0.6, 0.0)
    truth = route_poses(new_world, np.clip(np.cumsum(speed * 0.2), 0.0, route_length(new_world) - 0.01))
    scans = [simulate_scan(new_world.segments, pose, range_noise=0.01, rng=rng, max_range=8.0)
             for pose in truth]
    stamps = 1_700_000_000_000_000_000 + np.round(seconds * 1e9).astype(np.int64)
    localizer = MapLocalizer(map_scans, map_poses, initial_pose=truth[0])
    results = [localizer.localize(int(stamp), scan, None) for stamp, scan in zip(stamps, scans, strict=True)]
    errors = position_errors(np.array([r.pose for r in results]), truth)
    assert errors.max() < 0.4 and np.median(errors) < 0.02


def test_a_saved_map_too_large_for_one_grid_is_localized_in_on_coarser_cells_up_to_a_bound() -> None:
    scan = np.column_stack([np.linspace(-10.0, 10.0, 50), np.full(50, 10.0)])  # 14.1 m reach
    keyframes = [Keyframe(scan, scan_normals(scan))] * 2
    margin = 1.0
    # 100 m between the keyframes: 5 560 × 700 cells at 5 cm, well within the bound.
    near = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
    assert whole_map_resolution(keyframes, near, 0.05, margin) == 0.05
    # A building of 410 × 250 m (the Freiburg clinic's is 439 × 246) needs 8 201 × 5 001 cells at 5 cm,
    # 41 M: 10 cm cells fit.
    reach = float(np.hypot(10.0, 10.0))
    building = np.array([[0.0, 0.0, 0.0], [410.0 - 2 * (reach + margin), 250.0 - 2 * (reach + margin), 0.0]])
    assert MAX_LIKELIHOOD_CELLS < 8_201 * 5_001
    assert whole_map_resolution(keyframes, building, 0.05, margin) == pytest.approx(0.10)
    far = np.array([[0.0, 0.0, 0.0], [2_000.0, 2_000.0, 0.0]])
    with pytest.raises(MapExtentError, match="would need cells of"):
        whole_map_resolution(keyframes, far, 0.05, margin)
