"""Loop closures beyond the fine search's window (`global_match.match_beyond`): where the drift since the
candidate allows more than the window a search on the submap's own grid covers, the wider window is searched
on a coarser grid; a match counts only beyond the fine window and where the submap's own grid scores it.
On the synthetic square-loop floor (tests/laser_world.py)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from frontends.slam2d.config import LOOP_QUERY_KEYFRAMES, LoopClosureConfig, MatchingConfig, Slam2DConfig
from frontends.slam2d.correlative import SearchWindow, branch_and_bound_levels, match_exhaustive
from frontends.slam2d.global_match import match_beyond
from frontends.slam2d.icp import scan_normals
from frontends.slam2d.local_map import Keyframe, Submap
from frontends.slam2d.slam import BRANCH_AND_BOUND_LEVELS, LaserSlam2D
from optimizer import se2
from tests.laser_world import Run, between, compose, drive, ring_corridors, simulate_scan, square_loop
from tests.slam2d_runs import position_errors, run_slam, wrong_loop_closures

MATCHING = MatchingConfig()
ACCEPTANCE = LoopClosureConfig()
FINE_CELLS = 200
FINE_RADIUS = FINE_CELLS * MATCHING.resolution
"""10 m: the window a search on the submap's own grid covers."""
WIDE_SEARCH = {"cells": FINE_CELLS, "min_levels": BRANCH_AND_BOUND_LEVELS}
"""`match_beyond`'s grid and levels, as the SLAM's loop closures ask for them."""


def test_wider_windows_get_more_levels_up_to_a_bounded_coarsest_level() -> None:
    # 2.3 m at 5 cm (93 cells across): 6 coarsest candidates a side at the minimum of 4 levels.
    assert branch_and_bound_levels(2.3, 0.05, minimum=4) == 4
    # 5 m (201 cells): 4 levels would leave 13 a side, 5 leave 7.
    assert branch_and_bound_levels(5.0, 0.05, minimum=4) == 5
    # 10 m (401 cells): 26 a side at 4 levels, 7 at 6.
    assert branch_and_bound_levels(10.0, 0.05, minimum=4) == 6
    assert branch_and_bound_levels(30.0, 0.15, minimum=4) == 6
    assert branch_and_bound_levels(0.2, 0.05, minimum=3) == 3
    for radius, resolution in ((2.3, 0.05), (5.0, 0.05), (10.0, 0.05), (50.0, 0.05)):
        levels = branch_and_bound_levels(radius, resolution, minimum=1)
        side = (2 * math.ceil(radius / resolution) + 1) / 2**levels
        assert side <= 8 < side * 2


@pytest.fixture(scope="module")
def south_corridor_submap() -> Submap:
    """The keyframes a robot scanned driving the square loop's south corridor, x from 3 to 17 m."""
    world = square_loop()
    rng = np.random.default_rng(3)
    poses = [np.array([x, 1.0, 0.0]) for x in np.arange(3.0, 17.01, 1.0)]
    scans = [simulate_scan(world.segments, pose, beams=360, range_noise=0.01, rng=rng) for pose in poses]
    return Submap.of([Keyframe(s, scan_normals(s)) for s in scans], poses, resolution=MATCHING.resolution,
                     likelihood_sigma=MATCHING.likelihood_sigma, margin=FINE_RADIUS + 1.0,
                     pairing_distance=MATCHING.icp_max_distance)


def query_at(pose: np.ndarray, range_noise: float = 0.01) -> np.ndarray:
    """A scan taken at `pose` in the square loop, in the robot's frame."""
    return simulate_scan(square_loop().segments, pose, beams=360, range_noise=range_noise,
                         rng=np.random.default_rng(4))


def fine_window() -> SearchWindow:
    return SearchWindow(FINE_RADIUS, ACCEPTANCE.angular_window, ACCEPTANCE.angular_step)


def test_a_match_beyond_the_fine_window_is_found_on_the_coarser_grid(south_corridor_submap: Submap) -> None:
    truth = np.array([9.5, 1.2, 0.1])
    # The drift put the current keyframe 12 m off, beyond a 10 m window; 16 m of drift are allowed.
    estimate = truth + np.array([12.0, 2.0, math.radians(4.0)])
    found = match_beyond(query_at(truth), south_corridor_submap, estimate, fine_window(), 16.0,
                         matching=MATCHING, acceptance=ACCEPTANCE, **WIDE_SEARCH)
    assert found is not None
    error = se2.relative(truth, found.icp.pose)
    assert math.hypot(error[0], error[1]) < 0.05
    assert abs(error[2]) < math.radians(0.5)


def test_no_match_is_taken_inside_the_fine_window(south_corridor_submap: Submap) -> None:
    # Inside the fine window the search on the submap's own grid decides (it found nothing there, or a
    # rival): the coarser search must not overrule it.
    truth = np.array([9.5, 1.2, 0.1])
    estimate = truth + np.array([6.0, 2.0, math.radians(4.0)])
    assert match_beyond(query_at(truth), south_corridor_submap, estimate, fine_window(), 16.0,
                        matching=MATCHING, acceptance=ACCEPTANCE, **WIDE_SEARCH) is None
    # The same scan and drift with a fine window of 5 m: the match lies beyond it, and is found.
    narrow = SearchWindow(5.0, ACCEPTANCE.angular_window, ACCEPTANCE.angular_step)
    assert match_beyond(query_at(truth), south_corridor_submap, estimate, narrow, 16.0,
                        matching=MATCHING, acceptance=ACCEPTANCE, **WIDE_SEARCH) is not None


def test_a_match_the_submap_grid_does_not_score_is_refused(south_corridor_submap: Submap) -> None:
    truth = np.array([9.5, 1.2, 0.1])
    estimate = truth + np.array([12.0, 2.0, math.radians(4.0)])
    # Noisier ranges (5 cm) and a 30 m window, searched on 15 cm cells: the coarse grid's likelihood (σ of a
    # cell) scores the match higher than the submap's own grid (σ 6 cm) does, best within a cell and an
    # angular step of the match.
    query = query_at(truth, range_noise=0.05)
    lenient = LoopClosureConfig(min_score=0.3)
    found = match_beyond(query, south_corridor_submap, estimate, fine_window(), 30.0,
                         matching=MATCHING, acceptance=lenient, **WIDE_SEARCH)
    assert found is not None
    around = SearchWindow(MATCHING.resolution, ACCEPTANCE.angular_step, ACCEPTANCE.angular_step)
    fine_score = match_exhaustive(query, south_corridor_submap.grid, found.icp.pose, around).score
    assert fine_score < found.score - 0.02
    between_the_two = LoopClosureConfig(min_score=0.5 * (fine_score + found.score))
    assert match_beyond(query, south_corridor_submap, estimate, fine_window(), 30.0,
                        matching=MATCHING, acceptance=between_the_two, **WIDE_SEARCH) is None
    just_below = LoopClosureConfig(min_score=fine_score - 1e-3)
    assert match_beyond(query, south_corridor_submap, estimate, fine_window(), 30.0,
                        matching=MATCHING, acceptance=just_below, **WIDE_SEARCH) is not None


def slipping_lap(slip: float) -> Run:
    """A lap of `ring_corridors`, its wheels slipping on the way out: along the first corridor the odometry
    counts `slip` times the distance driven (12 %: 14 m too far over its 116 m), elsewhere it is exact."""
    world = ring_corridors()
    truth = drive(world, 0.2)
    steps = between(truth[:-1], truth[1:])
    outward = (np.arange(len(steps)) < len(steps) // 2) & (truth[:-1, 1] < 3.0) & (truth[:-1, 0] > 14.0)
    steps[outward & (truth[:-1, 0] < 130.0), :2] *= slip
    odometry = np.empty_like(truth)
    odometry[0] = truth[0]
    for k, step in enumerate(steps):
        odometry[k + 1] = compose(odometry[k], step)
    rng = np.random.default_rng(0)
    scans = tuple(simulate_scan(world.segments, pose, range_noise=0.01, rng=rng) for pose in truth)
    stamps = 1_700_000_000_000_000_000 + np.arange(len(truth), dtype=np.int64) * 400_000_000
    return Run(stamps, truth, odometry, scans)


def test_a_lap_that_comes_back_13_m_off_closes_its_loop_beyond_the_fine_window() -> None:
    run = slipping_lap(1.12)
    config = Slam2DConfig()
    # The drift allowed at the start after a lap (2 m + 5 % of 280 m) holds 13 m; a 10 m window does not.
    widened = run_slam(run, with_odometry=True, config=config)
    assert widened.result.loop_closures_accepted >= 1
    assert wrong_loop_closures(widened) == []
    assert position_errors(widened.final_scan_poses, run.truth)[-1] < 0.2
    capped_config = replace(config, loop_closure=replace(config.loop_closure, max_search_radius=10.0))
    capped = run_slam(run, with_odometry=True, config=capped_config)
    assert capped.result.loop_closures_accepted == 0
    assert position_errors(capped.final_scan_poses, run.truth)[-1] > 10.0


def test_a_submap_searched_wide_in_vain_is_searched_wide_again_only_by_a_query_of_new_keyframes(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Coming back 13 m off, the keyframes search the same candidates beyond the fine window long before one
    # matches (the UAL vehicle: 116 wide searches in vain, 0.65 s of its 4 s replay). Their fine windows
    # are still searched: there a search that failed matches a few keyframes later.
    events: list[tuple[int, int, bool, bool] | None] = []
    verify, set_poses = LaserSlam2D._verify_loop, LaserSlam2D._set_keyframe_poses

    def recorded_verify(self: LaserSlam2D, candidate: int, current: int, fine_radius: float, radius: float,
                        fine_first: bool) -> Any:
        hypothesis = verify(self, candidate, current, fine_radius, radius, fine_first)
        events.append((candidate, current, radius > fine_radius, hypothesis is not None))
        return hypothesis

    def recorded_set_poses(self: LaserSlam2D, poses: Any) -> None:
        set_poses(self, poses)
        events.append(None)  # the poses moved: every submap is new

    monkeypatch.setattr(LaserSlam2D, "_verify_loop", recorded_verify)
    monkeypatch.setattr(LaserSlam2D, "_set_keyframe_poses", recorded_set_poses)
    run = slipping_lap(1.12)
    outcome = run_slam(run, with_odometry=True)
    spacing = LoopClosureConfig().submap_keyframes
    failed_wide: list[tuple[int, int]] = []
    wide_again, fine_again = [], []
    for event in events:
        if event is None:
            failed_wide = []
            continue
        candidate, current, wide, found = event
        recent = [(c, k) for c, k in failed_wide
                  if abs(candidate - c) <= spacing and current - k <= LOOP_QUERY_KEYFRAMES]
        (wide_again if wide else fine_again).extend(recent)
        if wide and not found:
            failed_wide.append((candidate, current))
    assert wide_again == []
    assert fine_again != []  # the fine window of such a candidate is searched still
    assert sum(wide and not found for *_, wide, found in filter(None, events)) >= 5  # put to the test
    # The loop still closes, as well as when every keyframe searched everything.
    assert outcome.result.loop_closures_accepted >= 1
    assert wrong_loop_closures(outcome) == []
    assert position_errors(outcome.final_scan_poses, run.truth)[-1] < 0.2
