"""What the 2D path's speed work must keep: the exhaustive search returns the brute-force optimum, the
matcher without odometry the optimum of the window the motion needs, a grid's cached pyramid is
`max_pyramid`, a keyframe placed from its cache is `place`, and the stage timers charge nested stages once
(checked on a fake clock, not timed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from frontends.errors import MapExtentError
from frontends.logs.types import Scan2D, Transform
from frontends.loop_closing import Constraints, path_lengths
from frontends.slam2d import correlative, stage_times
from frontends.slam2d import slam as slam_module
from frontends.slam2d.correlative import (
    SearchWindow,
    match_branch_and_bound,
    match_exhaustive,
    prepare_branch_and_bound,
)
from frontends.slam2d.grid import LikelihoodGrid, build_likelihood_grid, max_pyramid, stamp_more
from frontends.slam2d.icp import scan_normals
from frontends.slam2d.local_map import Keyframe, Submap, one_per_cell, place
from frontends.slam2d.log_input import OdometryTrack, scans_in_base_frame
from frontends.slam2d.match_covariance import score_plateau
from frontends.slam2d.slam import (
    COARSE_THINNING,
    NARROW_WINDOW_ANGULAR,
    NARROW_WINDOW_LINEAR,
    LaserSlam2D,
    match_without_odometry,
)
from frontends.slam2d.stage_times import StageTimes
from optimizer.solve import optimize
from tests._frontends_fixtures import ScanListLog
from tests.laser_world import align_to_first, between, simulate_run, simulate_scan, square_loop

RESOLUTION = 0.05
SIGMA = 0.06


def brute_force_best(points: np.ndarray, values: np.ndarray, origin: np.ndarray, centre: np.ndarray,
                     window: SearchWindow, excluded: tuple[int, int, int] | None = None
                     ) -> tuple[float, np.ndarray]:
    """Every candidate scored from scratch (cells outside the grid read 0); the first best in (angle, ty,
    tx) order, as the matcher documents. `excluded` = (tx, ty, radius) in cells: translations within the
    radius of (tx, ty) are not candidates."""
    reach = math.ceil(window.linear / RESOLUTION - 1e-9)
    count = int(math.floor(window.angular / window.angular_step))
    height, width = values.shape
    best_score, best_pose = -1.0, np.zeros(3)
    for a in range(-count, count + 1):
        theta = centre[2] + window.angular_step * a
        c, s = math.cos(theta), math.sin(theta)
        world_x = centre[0] + c * points[:, 0] - s * points[:, 1]
        world_y = centre[1] + s * points[:, 0] + c * points[:, 1]
        base_x = np.floor((world_x - origin[0]) / RESOLUTION).astype(np.int64)
        base_y = np.floor((world_y - origin[1]) / RESOLUTION).astype(np.int64)
        for ty in range(-reach, reach + 1):
            for tx in range(-reach, reach + 1):
                if excluded is not None and (
                        (tx - excluded[0]) ** 2 + (ty - excluded[1]) ** 2 <= excluded[2] ** 2):
                    continue
                cx, cy = base_x + tx, base_y + ty
                inside = (cx >= 0) & (cy >= 0) & (cx < width) & (cy < height)
                score = values[cy[inside], cx[inside]].astype(np.float64).sum() / len(points)
                if score > best_score + 1e-12:
                    best_score = score
                    best_pose = np.array([centre[0] + tx * RESOLUTION, centre[1] + ty * RESOLUTION, theta])
    return best_score, best_pose


@settings(max_examples=6, deadline=None)
@given(
    shift=st.tuples(st.floats(-0.15, 0.15), st.floats(-0.15, 0.15), st.floats(-0.05, 0.05)),
    linear=st.sampled_from([0.1, 0.2, 0.6]),
    margin=st.sampled_from([0.0, 1.0]),
    dense=st.booleans(),
)
def test_exhaustive_search_finds_the_brute_force_optimum_even_across_the_grid_edge(
        shift: tuple[float, float, float], linear: float, margin: float, dense: bool) -> None:
    reference = simulate_scan(square_loop().segments, np.array([6.5, 9.0, 0.3]))[:, :2]
    # Without a margin, translations push points off the grid: the edge handling is exercised.
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=margin)
    # Dense: a 1081-beam laser's scan, runs of neighbouring points in one cell (added once, times the run).
    scan = (simulate_scan(square_loop().segments, np.array([6.5, 9.0, 0.3]), beams=1081)[:, :2] if dense
            else reference[::3])
    centre = np.array(shift)
    window = SearchWindow(linear, math.radians(2.0), math.radians(0.5))
    match = match_exhaustive(scan, grid, centre, window)
    score, pose = brute_force_best(scan, grid.values, grid.origin, centre, window)
    assert match.score == pytest.approx(score, abs=1e-9)
    np.testing.assert_allclose(match.pose, pose, atol=1e-12)


@settings(max_examples=12, deadline=None)
@given(
    centre=st.tuples(st.floats(-12.0, 12.0), st.floats(-12.0, 12.0), st.floats(-0.3, 0.3)),
    linear=st.sampled_from([0.5, 2.0, 4.0]),
    min_score=st.sampled_from([0.0, 0.2]),
    margin=st.sampled_from([1.0, 5.0]),
)
def test_branch_and_bound_on_the_cropped_pyramid_finds_what_it_finds_on_the_whole_one(
        centre: tuple[float, float, float], linear: float, min_score: float, margin: float) -> None:
    # The cropped pyramid spans the stamped cells only; a loop-closure submap's margin (5 m here) is zeros
    # the search reads past them.
    world = square_loop().segments
    reference = simulate_scan(world, np.array([6.5, 9.0, 0.3]))[:, :2]
    scan = simulate_scan(world, np.array([6.9, 8.7, 0.35]))[::2, :2]
    window = SearchWindow(linear, math.radians(6.0), math.radians(1.0))
    results = []
    for crop in (False, True):
        # A fresh grid each time: the whole grid's pyramid must not serve the cropped search.
        grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=margin)
        results.append(match_branch_and_bound(scan, grid, np.array(centre), window, min_score, levels=4,
                                              crop_pyramid=crop))
        rival = results[-1]
        if rival is not None:  # the ambiguity search (an excluded disc) as well
            results.append(match_branch_and_bound(scan, grid, np.array(centre), window, 0.5 * rival.score,
                                                  levels=4, exclude=(rival.pose[:2], 0.5), crop_pyramid=crop))
    half = len(results) // 2
    for whole, cropped in zip(results[:half], results[half:], strict=True):
        assert (whole is None) == (cropped is None)
        if whole is not None:
            np.testing.assert_array_equal(whole.pose, cropped.pose)
            assert whole.score == cropped.score


@settings(max_examples=5, deadline=None)
@given(
    centre=st.tuples(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4), st.floats(-0.1, 0.1)),
    crop=st.booleans(),
)
def test_one_prepared_search_finds_the_optimum_then_the_best_rival_outside_its_disc(
        centre: tuple[float, float, float], crop: bool) -> None:
    world = square_loop().segments
    reference = simulate_scan(world, np.array([6.5, 9.0, 0.3]))[:, :2]
    scan = simulate_scan(world, np.array([6.6, 8.9, 0.32]))[::6, :2] - np.array([6.5, 9.0])
    grid = build_likelihood_grid(reference - np.array([6.5, 9.0]), RESOLUTION, SIGMA, margin=1.0)
    window = SearchWindow(0.5, math.radians(3.0), math.radians(1.0))
    search = prepare_branch_and_bound(scan, grid, np.array(centre), window, levels=3, crop_pyramid=crop)
    best = search.best(0.0)
    score, pose = brute_force_best(scan, grid.values, grid.origin, np.array(centre), window)
    assert best is not None
    assert best.score == pytest.approx(score, abs=1e-9)
    np.testing.assert_allclose(best.pose, pose, atol=1e-12)
    # The rival of the ambiguity test: the same prepared search with the optimum's disc (0.2 m, 4 cells)
    # excluded is the brute-force best outside it, and equals a search prepared from scratch.
    offset = np.rint((best.pose[:2] - np.array(centre[:2])) / RESOLUTION).astype(int)
    rival = search.best(0.0, exclude=(best.pose[:2], 0.2))
    rival_score, rival_pose = brute_force_best(scan, grid.values, grid.origin, np.array(centre), window,
                                               excluded=(int(offset[0]), int(offset[1]), 4))
    assert rival is not None
    assert rival.score == pytest.approx(rival_score, abs=1e-9)
    np.testing.assert_allclose(rival.pose, rival_pose, atol=1e-12)
    fresh = match_branch_and_bound(scan, grid, np.array(centre), window, 0.0, levels=3,
                                   exclude=(best.pose[:2], 0.2), crop_pyramid=crop)
    assert fresh is not None
    np.testing.assert_array_equal(fresh.pose, rival.pose)
    assert fresh.score == rival.score


def test_a_grid_builds_its_pyramid_once_and_serves_fewer_levels_from_it() -> None:
    reference = simulate_scan(square_loop().segments, np.array([6.5, 9.0, 0.3]))[:, :2]
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=0.5)
    pyramid = grid.pyramid(4)
    expected = max_pyramid(grid.values, 4)
    assert len(pyramid) == 5
    for level, (built, reference_level) in enumerate(zip(pyramid, expected, strict=True)):
        np.testing.assert_array_equal(built, reference_level, err_msg=f"level {level}")
    assert all(a is b for a, b in zip(grid.pyramid(4), pyramid, strict=True))  # built once
    fewer = grid.pyramid(2)
    assert len(fewer) == 3 and all(a is b for a, b in zip(fewer, pyramid, strict=False))


@pytest.mark.parametrize("pairing", [0.0, 0.3])
def test_a_grids_stamped_window_holds_its_nonzero_cells_and_not_its_margin(pairing: float) -> None:
    world = square_loop().segments
    reference = simulate_scan(world, np.array([6.5, 9.0, 0.3]))[:, :2]
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=3.0, pairing_distance=pairing)

    def holds_every_stamp(grid: LikelihoodGrid) -> None:
        assert grid.stamped_window is not None
        top, bottom, left, right = grid.stamped_window
        rows, columns = np.nonzero(grid.values)
        assert top <= rows.min() and rows.max() < bottom and left <= columns.min() and columns.max() < right
        # and little more: a cell beyond the stamps (the 3 m margins are left out)
        assert rows.min() - top <= 1 and bottom - rows.max() <= 2
        assert columns.min() - left <= 1 and right - columns.max() <= 2

    holds_every_stamp(grid)
    # A grid grown in place (a local map, never cropped) does not know its stamped window any more.
    more = simulate_scan(world, np.array([7.5, 9.5, 1.3]))[:, :2]
    grown = stamp_more(grid, np.concatenate([reference, more]), len(reference), SIGMA, pairing)
    assert grown.stamped_window is None


def test_a_loop_submap_is_built_again_only_when_its_keyframes_moved_or_its_margin_changed() -> None:
    world = square_loop().segments
    slam = LaserSlam2D()
    for k in range(8):
        pose = np.array([5.0 + 0.4 * k, 9.0, 0.05 * k])
        slam.add_scan(k * 200_000_000, simulate_scan(world, pose)[:, :2], odometry=pose)
    around = tuple(range(1, 6))

    def built_now(margin: float) -> Submap:
        return Submap.of([slam._keyframes[k] for k in around], [slam._keyframe_poses[k] for k in around],
                         resolution=RESOLUTION, likelihood_sigma=SIGMA, margin=margin, pairing_distance=0.3)

    first = slam._loop_submap(around, 3.0)
    np.testing.assert_array_equal(first.grid.values, built_now(3.0).grid.values)
    assert slam._loop_submap(around, 3.0) is first
    wider = slam._loop_submap(around, 4.0)
    assert wider is not first
    np.testing.assert_array_equal(wider.grid.values, built_now(4.0).grid.values)
    slam._keyframe_poses[3] = slam._keyframe_poses[3] + np.array([0.2, 0.0, 0.0])  # an optimization moved it
    moved = slam._loop_submap(around, 4.0)
    assert moved is not wider
    np.testing.assert_array_equal(moved.grid.values, built_now(4.0).grid.values)
    assert slam._loop_submap(tuple(range(2, 6)), 4.0) is not moved  # other keyframes: another submap


def test_a_loop_submap_leaves_out_neighbours_by_index_that_are_far_in_space() -> None:
    """The seam of a resumed session: the saved map's last keyframes and the new run's first are neighbours
    by index, not in space (a run placed 10⁶ m away, by a wrong --initial-pose, built a grid from one to
    the other and failed). Within one run, every neighbour stays."""
    world = square_loop().segments
    slam = LaserSlam2D()
    for k in range(8):
        pose = np.array([5.0 + 0.4 * k, 9.0, 0.05 * k])
        slam.add_scan(k * 200_000_000, simulate_scan(world, pose)[:, :2], odometry=pose)
    current = 7 + slam.config.loop_closure.min_separation_keyframes  # as if that many keyframes followed
    assert slam._loop_submap_members(4, current, 3.0) == tuple(range(8))
    for k in range(4):  # the saved map's keyframes, far from the run that resumed on them
        slam._keyframe_poses[k] = slam._keyframe_poses[k] + np.array([1e6, 0.0, 0.0])
    assert slam._loop_submap_members(4, current, 3.0) == (4, 5, 6, 7)
    assert slam._loop_submap_members(2, current, 3.0) == (0, 1, 2, 3)
    slam._loop_submap(slam._loop_submap_members(5, current, 3.0), 3.0)  # a grid of a few metres


def test_a_keyframe_placed_from_its_cache_is_placed_as_by_place() -> None:
    points = simulate_scan(square_loop().segments, np.array([6.5, 9.0, 0.3]))[:, :2].copy()
    keyframe = Keyframe(points, scan_normals(points))
    for pose in (np.array([1.0, -2.0, 0.4]), np.array([1.0, -2.0, 0.4]), np.array([0.5, 0.0, -2.0])):
        placed, normals = keyframe.placed(pose)
        np.testing.assert_array_equal(placed, place(points, pose))
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rotated = np.stack([keyframe.normals[:, 0] * c - keyframe.normals[:, 1] * s,
                            keyframe.normals[:, 0] * s + keyframe.normals[:, 1] * c], axis=1)
        np.testing.assert_allclose(normals, rotated, atol=1e-12)
    submap = Submap.of([keyframe], [np.array([0.5, 0.0, -2.0])], resolution=RESOLUTION,
                       likelihood_sigma=SIGMA, margin=0.5, pairing_distance=0.3)
    assert len(submap.points) > 0.5 * len(points)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), old=st.integers(2, 400), new=st.integers(0, 400),
       pairing=st.sampled_from([0.0, 0.3]))
def test_points_stamped_into_a_grid_give_the_grid_built_from_all_of_them(
        seed: int, old: int, new: int, pairing: float) -> None:
    rng = np.random.default_rng(seed)
    # The old points hold the box's corners, the new ones lie inside it: both grids span the same cells.
    corners = np.array([[-4.0, -3.0], [5.0, 4.0]])
    earlier = np.concatenate([corners, rng.uniform(-4.0, 5.0, (old, 2)) * [1.0, 7.0 / 9.0]])
    later = rng.uniform([-4.0, -3.0], [5.0, 4.0], (new, 2))
    later[: new // 2] = earlier[rng.integers(0, len(earlier), new // 2)]  # ties with old points
    points = np.concatenate([earlier, later])
    whole = build_likelihood_grid(points, RESOLUTION, SIGMA, 0.5, pairing)
    first = build_likelihood_grid(earlier, RESOLUTION, SIGMA, 0.5, pairing)
    stamped = stamp_more(first, points, len(earlier), SIGMA, pairing)
    np.testing.assert_array_equal(stamped.origin, whole.origin)
    np.testing.assert_array_equal(stamped.nearest, whole.nearest)
    np.testing.assert_array_equal(stamped.values, whole.values)


def test_a_keyframe_reaching_past_the_margin_leaves_the_local_map_untouched() -> None:
    world = square_loop().segments
    scan = simulate_scan(world, np.array([6.5, 9.0, 0.3]))[:, :2].copy()
    keyframe = Keyframe(scan, scan_normals(scan))
    submap = Submap.of([keyframe], [np.zeros(3)], resolution=RESOLUTION, likelihood_sigma=SIGMA, margin=1.0,
                       pairing_distance=0.3)
    values, nearest, points = submap.grid.values.copy(), submap.grid.nearest.copy(), submap.points.copy()
    settings = {"likelihood_sigma": SIGMA, "margin": 1.0, "pairing_distance": 0.3}
    assert submap.extended(keyframe, np.array([1.2, 0.0, 0.0]), **settings) is None  # 0.2 m into the margin
    np.testing.assert_array_equal(submap.grid.values, values)
    np.testing.assert_array_equal(submap.grid.nearest, nearest)
    np.testing.assert_array_equal(submap.points, points)
    inside = Keyframe(0.9 * scan, scan_normals(0.9 * scan))  # the room seen 10 % smaller: within the grid
    extended = submap.extended(inside, np.zeros(3), **settings)
    assert extended is not None
    np.testing.assert_array_equal(extended.points[: len(points)], points)
    assert len(extended.points) > len(points)
    assert extended.grid is not submap.grid  # a fresh grid object: no pyramid of the old values


def test_the_local_map_grows_in_place_between_builds_and_tracks_as_well(
        monkeypatch: pytest.MonkeyPatch) -> None:
    run = simulate_run(square_loop(), seed=1)
    builds: dict[str, int] = {}
    errors: dict[str, float] = {}
    original = LaserSlam2D._rebuild_local_map
    for mode, growth in (("in place", slam_module.LOCAL_MAP_GROWTH), ("every keyframe", -1)):
        monkeypatch.setattr(slam_module, "LOCAL_MAP_GROWTH", growth)
        count = [0]

        def counted(slam: LaserSlam2D, counter: list[int] = count) -> None:
            counter[0] += 1
            original(slam)

        monkeypatch.setattr(LaserSlam2D, "_rebuild_local_map", counted)
        slam = LaserSlam2D()
        for stamp, scan, odometry in zip(run.stamps_ns, run.scans, run.odometry, strict=True):
            slam.add_scan(int(stamp), scan, odometry)
        result = slam.finish()
        *_, final = optimize(result.graph)
        aligned = align_to_first(result.scan_poses(final.poses), run.truth)
        errors[mode] = float(np.hypot(*(aligned[:, :2] - run.truth[:, :2]).T).max())
        builds[mode] = count[0]
        keyframes = len(result.graph.poses)
    # Until the map holds `local_map_keyframes`, every keyframe is added in place in both modes.
    assert builds["every keyframe"] >= keyframes - LaserSlam2D().config.keyframes.local_map_keyframes
    assert builds["in place"] < 0.5 * builds["every keyframe"]
    assert errors["in place"] < 0.1  # the loop drifts metres on odometry (`test_slam2d_slam`)
    assert errors["in place"] < 1.5 * errors["every keyframe"] + 0.01


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_nested_stages_are_charged_to_the_innermost_one_only(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    monkeypatch.setattr(stage_times.time, "perf_counter", clock)
    monkeypatch.setattr(stage_times.time, "process_time", clock)
    times = StageTimes()
    clock.now = 10.0
    with times.stage("loop_search"):
        clock.now += 1.0
        with times.stage("verification"):
            clock.now += 3.0
        clock.now += 0.5
        with times.stage("verification"):
            clock.now += 2.0
    clock.now += 100.0  # outside every stage: charged to none
    with times.stage("matching"):
        clock.now += 0.25
    assert times.wall == pytest.approx({"loop_search": 1.5, "verification": 5.0, "matching": 0.25})
    assert times.cpu == times.wall


def test_the_frontend_reports_its_stages() -> None:
    slam = LaserSlam2D()
    world = square_loop()
    for k in range(6):
        pose = np.array([6.5 + 0.2 * k, 9.0, 0.3])
        slam.add_scan(k * 100_000_000, simulate_scan(world.segments, pose)[:, :2], odometry=pose)
    result = slam.finish()
    assert set(result.stage_times.wall) >= {"matching", "keyframes"}
    assert all(seconds >= 0.0 for seconds in result.stage_times.cpu.values())


def test_one_stamp_is_interpolated_exactly_as_in_a_batch() -> None:
    rng = np.random.default_rng(3)
    stamps = np.cumsum(rng.integers(1, 400_000_000, 300)).astype(np.int64)
    stamps[150:] += 6_000_000_000  # a gap longer than the odometry may bridge
    poses = np.cumsum(rng.normal(0.0, 0.3, (300, 3)), axis=0)
    poses[:, 2] = (poses[:, 2] + np.pi) % (2.0 * np.pi) - np.pi  # headings crossing ±π
    track = OdometryTrack(stamps, poses, "odom", "base_link")
    queries = np.concatenate([stamps[::7], stamps[::5] + 12_345, [stamps[0] - 1, stamps[-1] + 1],
                              stamps[149:152] + 1_000])
    batch_poses, batch_intervals = track.interpolate(queries)
    assert np.isnan(batch_poses).any() and np.isfinite(batch_poses).any()
    for query, pose, interval in zip(queries, batch_poses, batch_intervals, strict=True):
        one_pose, one_interval = track.interpolate(np.array([query]))
        np.testing.assert_array_equal(one_pose[0], pose)
        assert one_interval[0] == interval


class MountTree:
    def __init__(self, mount: Transform) -> None:
        self.mount = mount

    def sensor_mount(self, base_frame: str, frame: str, stamp_ns: int) -> Transform:
        return self.mount


def test_scans_are_moved_into_the_base_frame_as_by_their_own_transform() -> None:
    rng = np.random.default_rng(4)
    half = 0.5 * math.radians(20.0)
    mount = Transform("base_link", "laser", 0, 0, np.array([0.3, -0.1, 0.2]),
                      np.array([0.0, 0.0, math.sin(half), math.cos(half)]), True)
    scans = []
    for k in range(5):
        ranges = rng.uniform(0.5, 10.0, 40)
        bearings = np.linspace(-1.5, 1.5, 40)
        points = np.stack([ranges * np.cos(bearings), ranges * np.sin(bearings)], axis=1)
        scans.append(Scan2D(k * 1000, k * 1000, "laser", points, ranges, bearings, 40))
    log, tree = ScanListLog(scans), MountTree(mount)
    moved = list(scans_in_base_frame(log, "/scan", tree, "base_link"))  # type: ignore[arg-type]
    assert len(moved) == len(scans)
    for scan, (result, has_mount) in zip(scans, moved, strict=True):
        expected = scan.transformed(mount)
        assert has_mount and result.frame_id == "base_link"
        np.testing.assert_array_equal(result.points, expected.points)
        np.testing.assert_array_equal(result.ranges, scan.ranges)


@settings(max_examples=30, deadline=None)
@given(
    count=st.integers(0, 400),
    spread=st.sampled_from([0.05, 1.0, 50.0]),
    seed=st.integers(0, 2**31),
    keep_last=st.booleans(),
)
def test_one_point_per_cell_keeps_the_first_or_last_of_each_cell_in_order(
        count: int, spread: float, seed: int, keep_last: bool) -> None:
    points = np.random.default_rng(seed).normal(scale=spread, size=(count, 2))
    kept = one_per_cell(points, 0.1, keep_last=keep_last)
    cells = [tuple(c) for c in np.floor(points / 0.1).astype(np.int64)]
    chosen: dict[tuple[int, int], int] = {}
    for index, key in enumerate(cells):
        if keep_last or key not in chosen:
            chosen[key] = index
    assert kept.tolist() == sorted(chosen.values())


def every_pose_scored(points: np.ndarray, values: np.ndarray, origin: np.ndarray, centre: np.ndarray,
                      window: SearchWindow) -> tuple[float, np.ndarray]:
    """`brute_force_best` with all translations of a rotation scored at once (wide windows)."""
    reach = math.ceil(window.linear / RESOLUTION - 1e-9)
    count = int(math.floor(window.angular / window.angular_step))
    height, width = values.shape
    shifts = np.arange(-reach, reach + 1)
    best_score, best_pose = -1.0, np.zeros(3)
    for a in range(-count, count + 1):
        theta = centre[2] + window.angular_step * a
        c, s = math.cos(theta), math.sin(theta)
        base_x = np.floor((centre[0] + c * points[:, 0] - s * points[:, 1] - origin[0]) / RESOLUTION)
        base_y = np.floor((centre[1] + s * points[:, 0] + c * points[:, 1] - origin[1]) / RESOLUTION)
        cx = base_x.astype(np.int64)[None, None, :] + shifts[None, :, None]  # (1, tx, point)
        cy = base_y.astype(np.int64)[None, None, :] + shifts[:, None, None]  # (ty, 1, point)
        inside = (cx >= 0) & (cy >= 0) & (cx < width) & (cy < height)
        read = np.where(inside, values[np.clip(cy, 0, height - 1), np.clip(cx, 0, width - 1)], 0.0)
        scores = read.astype(np.float64).sum(axis=2) / len(points)  # (ty, tx)
        ty, tx = np.unravel_index(int(np.argmax(scores)), scores.shape)  # the first best in (ty, tx) order
        if scores[ty, tx] > best_score + 1e-12:
            best_score = float(scores[ty, tx])
            best_pose = np.array([centre[0] + shifts[tx] * RESOLUTION, centre[1] + shifts[ty] * RESOLUTION,
                                  theta])
    return best_score, best_pose


@pytest.mark.parametrize(
    ("error", "narrow"),
    [
        (np.array([0.05, -0.05, math.radians(2.0)]), True),  # the prediction was close
        (np.array([0.35, 0.1, math.radians(3.0)]), False),  # moved farther than the narrow window
        (np.array([0.0, 0.05, math.radians(22.0)]), False),  # turned farther than the narrow window
    ],
)
def test_matching_without_odometry_finds_the_optimum_of_the_window_the_motion_needs(
        error: np.ndarray, narrow: bool) -> None:
    world = square_loop().segments
    keyframe_pose, scan_pose = np.array([6.5, 9.0, 0.3]), np.array([6.8, 8.9, 0.45])
    grid = build_likelihood_grid(simulate_scan(world, keyframe_pose)[:, :2], RESOLUTION, SIGMA, margin=1.0)
    scan = simulate_scan(world, scan_pose, beams=1440)[:, :2]  # denser than the cells near the walls
    truth = between(keyframe_pose, scan_pose)
    prior = truth - error
    wide = SearchWindow(0.5, math.radians(35.0), math.radians(0.5))
    match, searched = match_without_odometry(scan, grid, prior, wide)
    assert match is not None
    assert searched == wide  # the optimum is inside the window: not widened
    # The search reads the scan thinned to one point per cell; its optimum is the brute-force optimum of
    # those points over the narrow window when the prediction was close (that optimum in the window's
    # inner half), else over the wide window.
    thinned = scan[one_per_cell(scan, COARSE_THINNING)]
    assert len(thinned) < len(scan)
    window = SearchWindow(NARROW_WINDOW_LINEAR, NARROW_WINDOW_ANGULAR, wide.angular_step) if narrow else wide
    score, pose = every_pose_scored(thinned, grid.values, grid.origin, prior, window)
    assert match.score == pytest.approx(score, abs=1e-9)
    np.testing.assert_allclose(match.pose, pose, atol=1e-12)
    # Either way, within a cell and a step of the truth.
    assert np.all(np.abs(match.pose[:2] - truth[:2]) <= RESOLUTION + 1e-9)
    assert abs(match.pose[2] - truth[2]) <= wide.angular_step + 1e-9



def test_matching_without_odometry_searches_past_an_optimum_on_the_window_edge() -> None:
    # The robot turned 45° more than predicted (a scan dropped during a turn): beyond the ±35° window, whose
    # optimum then lies on its edge. Twice as wide there, the search finds the truth.
    world = square_loop().segments
    keyframe_pose, scan_pose = np.array([6.5, 9.0, 0.3]), np.array([6.8, 8.9, 0.45])
    grid = build_likelihood_grid(simulate_scan(world, keyframe_pose)[:, :2], RESOLUTION, SIGMA, margin=1.0)
    scan = simulate_scan(world, scan_pose, beams=1440)[:, :2]
    truth = between(keyframe_pose, scan_pose)
    prior = truth - np.array([0.0, 0.0, math.radians(45.0)])
    wide = SearchWindow(0.5, math.radians(35.0), math.radians(0.5))
    match, searched = match_without_odometry(scan, grid, prior, wide)
    assert searched == SearchWindow(0.5, math.radians(70.0), wide.angular_step)
    assert match is not None
    assert np.all(np.abs(match.pose[:2] - truth[:2]) <= RESOLUTION + 1e-9)
    assert abs(match.pose[2] - truth[2]) <= wide.angular_step + 1e-9


def test_a_window_turns_farther_only_where_its_optimum_lies_on_its_angular_edge() -> None:
    step = math.radians(0.5)
    window = SearchWindow(0.5, math.radians(35.0), step)
    centre = np.array([1.0, 2.0, 0.1])

    def turned(offset: tuple[float, float, float], searched: SearchWindow = window) -> SearchWindow | None:
        return searched.turned_past(centre + np.array(offset), centre)

    assert turned((0.45, -0.2, math.radians(34.5))) is None  # a step inside
    assert turned((0.5, 0.5, 0.0)) is None  # a translation's edge: not widened (a corridor's plateau)
    assert turned((0.1, 0.0, math.radians(35.0))) == SearchWindow(0.5, math.radians(70.0), step)
    assert turned((0.0, -0.5, math.radians(-35.0))) == SearchWindow(0.5, math.radians(70.0), step)
    assert turned((0.0, 0.0, math.radians(100.0)), SearchWindow(0.5, math.radians(100.0), step)) == \
        SearchWindow(0.5, math.pi, step)
    assert turned((0.0, 0.0, math.pi), SearchWindow(0.5, math.pi, step)) is None  # a half-turn already


def test_top_level_scores_are_each_candidates_sum_of_its_points_clamped_blocks() -> None:
    """Every coarsest candidate's score is the mean, over the points, of the coarsest level at the point's
    shifted cell: a block starting left of (or below) the grid but reaching into it reads the edge cell,
    one wholly outside reads nothing (written from the definition, point by point); for the rotations
    asked, in their order, each keyed by its own index."""
    rng = np.random.default_rng(7)
    values = rng.random((37, 29)).astype(np.float32)
    levels = tuple(max_pyramid(values, 3))
    span = 8
    cells_x = rng.integers(-12, 40, size=(3, 25)).astype(np.int64)
    cells_y = rng.integers(-12, 48, size=(3, 25)).astype(np.int64)
    reach = 13
    rotations = np.array([2, 0], dtype=np.int64)
    candidates = len(rotations) * len(range(-reach, reach + 1, span)) ** 2
    scores, keys = np.full(candidates, np.nan), np.full((candidates, 3), -1, dtype=np.int64)
    correlative._top_level(levels[-1], len(levels) - 1, cells_x, cells_y, reach, rotations, scores, keys)
    top = levels[-1]
    height, width = top.shape

    def clamped(cell: int, size: int) -> int:
        if cell < 0:
            return 0 if cell + span > 0 else -1
        return cell if cell < size else -1

    assert list(keys[:: candidates // 2, 0]) == [2, 0]
    for score, (a, tx, ty) in zip(scores, keys, strict=True):
        total = 0.0
        for x, y in zip(cells_x[a], cells_y[a], strict=True):
            column, row = clamped(int(x + tx), width), clamped(int(y + ty), height)
            if column >= 0 and row >= 0:
                total += float(top[row, column])
        assert score == pytest.approx(total / cells_x.shape[1], rel=1e-12, abs=1e-15)


def test_a_grid_spans_its_points_plus_the_margin_and_refuses_non_finite_points() -> None:
    points = np.array([[3.0, -2.0], [-1.5, 4.0], [0.25, 7.5]])
    grid = build_likelihood_grid(points, RESOLUTION, SIGMA, margin=1.0)
    np.testing.assert_array_equal(grid.origin, [-2.5, -3.0])
    assert grid.values.shape == (math.ceil(11.5 / RESOLUTION) + 1, math.ceil(6.5 / RESOLUTION) + 1)
    with pytest.raises(MapExtentError):
        build_likelihood_grid(np.vstack([points, [np.nan, 0.0]]), RESOLUTION, SIGMA, margin=1.0)


def test_constraint_lengths_follow_their_constraints_through_removals() -> None:
    constraints = Constraints(measurement_shape=(3,), information_size=3)
    for k, (x, y) in enumerate([(3.0, 4.0), (0.3, 0.0), (-6.0, 8.0), (0.0, -0.5)]):
        constraints.add(k, k + 1, np.array([x, y, 0.1]), np.eye(3), is_loop=k == 2)
    constraints.remove(1)
    assert constraints.planar_length == [5.0, 10.0, 0.5]
    assert constraints.first == [0, 2, 3]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 40))
def test_path_lengths_are_the_shortest_over_constraints_either_way(seed: int, count: int) -> None:
    rng = np.random.default_rng(seed)
    # Repeated pairs too: two constraints between the same keyframes (odometry and a loop closure).
    pairs = [(int(a), int(b)) for a, b in rng.integers(0, count, size=(int(rng.integers(0, 3 * count)), 2))]
    first = np.array([a for a, _ in pairs], dtype=np.int64)
    second = np.array([b for _, b in pairs], dtype=np.int64)
    lengths = rng.choice([0.0, 0.25, 1.0, 3.0], size=len(pairs)) * rng.random(len(pairs))
    source = int(rng.integers(0, count))
    # Bellman–Ford from scratch: a constraint is walked either way; one of zero length counts a micrometre.
    expected = np.full(count, np.inf)
    expected[source] = 0.0
    for _ in range(count):
        for a, b, length in zip(first, second, np.maximum(lengths, 1e-6), strict=True):
            expected[b] = min(expected[b], expected[a] + length)
            expected[a] = min(expected[a], expected[b] + length)
    np.testing.assert_allclose(path_lengths(count, first, second, lengths, source), expected, rtol=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 300))
def test_path_lengths_along_a_chain_are_the_sparse_searchs_to_the_bit(seed: int, count: int) -> None:
    # Until a loop closes, the constraints are one chain, summed outwards without the sparse search.
    rng = np.random.default_rng(seed)
    first = np.arange(count - 1, dtype=np.int64)
    lengths = rng.choice([0.0, 1e-9, 0.3, 30.0], size=count - 1) * rng.random(count - 1)
    source = int(rng.integers(0, count))
    chain = path_lengths(count, first, first + 1, lengths, source)
    # The same chain with a repeated last constraint is no chain: the sparse search answers.
    repeated = np.append(first, count - 2) if count > 1 else first
    searched = path_lengths(count, repeated, repeated + 1, np.append(lengths, lengths[-1:]), source)
    np.testing.assert_array_equal(chain, searched)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), step_cells=st.integers(1, 3))
def test_plateau_scores_are_each_shifts_mean_over_the_points_also_across_the_grid_edge(
        seed: int, step_cells: int) -> None:
    rng = np.random.default_rng(seed)
    # A 2 m × 1.5 m grid at 5 cm: points near its edges shift out of it (they then score 0).
    grid = build_likelihood_grid(rng.uniform([0.0, 0.0], [2.0, 1.5], size=(15, 2)), 0.05, 0.06, margin=0.0)
    grid.values[:] = rng.random(grid.values.shape, dtype=np.float32)
    points = rng.uniform(-1.2, 1.2, size=(int(rng.integers(1, 40)), 2))
    # Runs of points in one cell, as a dense laser gives (each run's patch is added once, times its length).
    points = np.repeat(points, rng.integers(1, 4, size=len(points)), axis=0)
    points[1::2] += rng.uniform(-0.004, 0.004, size=points[1::2].shape)
    pose = np.array([rng.uniform(0.0, 2.0), rng.uniform(0.0, 1.5), rng.uniform(-math.pi, math.pi)])
    plateau = score_plateau(points, grid, pose, reach=0.3, step_cells=step_cells)
    reach = (plateau.scores.shape[0] - 1) // 2
    cells = grid.cell_of(place(points, pose))
    height, width = grid.values.shape
    for j in range(2 * reach + 1):
        for i in range(2 * reach + 1):
            x = cells[:, 0] + (i - reach) * step_cells
            y = cells[:, 1] + (j - reach) * step_cells
            inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
            expected = grid.values[y[inside], x[inside]].astype(np.float64).sum() / len(points)
            assert plateau.scores[j, i] == pytest.approx(expected, rel=1e-9, abs=1e-12)
