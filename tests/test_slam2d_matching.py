"""slam2d matching: likelihood grids, max pyramids, correlative search (exhaustive and branch-and-bound),
point-to-line ICP and scan normals, on scans of the synthetic laser world (tests/laser_world.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from frontends.slam2d import correlative
from frontends.slam2d.correlative import (
    SearchWindow,
    match_branch_and_bound,
    match_exhaustive,
    prepare_branch_and_bound,
)
from frontends.slam2d.grid import LikelihoodGrid, build_likelihood_grid, max_pyramid
from frontends.slam2d.icp import _solve_3x3, refine_point_to_line, scan_normals
from tests.laser_world import between, box, long_corridor, simulate_scan, square_loop, transform_points, wall

RESOLUTION = 0.05
SIGMA = 0.06
PAIRING = 0.3
Scans = tuple[np.ndarray, np.ndarray, np.ndarray]
HALL_POSE = np.array([6.5, 9.0, 0.3])
"""Inside the west hall of the square-loop floor: walls, a door, furniture boxes."""


def gaussian(distance: np.ndarray, sigma: float) -> np.ndarray:
    return np.exp(-(distance**2) / (2.0 * sigma**2))


def cell_centres(grid: LikelihoodGrid) -> np.ndarray:
    height, width = grid.values.shape
    ix, iy = np.meshgrid(np.arange(width), np.arange(height))
    return np.stack([grid.origin[0] + (ix + 0.5) * grid.resolution,
                     grid.origin[1] + (iy + 0.5) * grid.resolution], axis=-1)


def grid_score(points: np.ndarray, grid: LikelihoodGrid, pose: np.ndarray) -> float:
    """Mean grid value at the cells of `points` placed by `pose` (0 outside the grid), from scratch."""
    cells = np.floor((transform_points(points, pose) - grid.origin) / grid.resolution).astype(np.int64)
    height, width = grid.values.shape
    inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < width) & (cells[:, 1] < height)
    return float(grid.values[cells[inside, 1], cells[inside, 0]].sum() / len(points))


# ------------------------------------------------------------------------------------------ the world


def test_ray_caster_sees_the_walls_of_a_box_room_where_they_are() -> None:
    segments = box(-2.0, -1.0, 3.0, 4.0)
    pose = np.array([0.5, 0.5, 0.4])
    points = simulate_scan(segments, pose, beams=720)
    assert len(points) == 720  # a closed room: every beam returns
    world = transform_points(points, pose)
    distance_to_wall = np.min(np.abs(np.column_stack([world[:, 0] + 2.0, world[:, 0] - 3.0,
                                                      world[:, 1] + 1.0, world[:, 1] - 4.0])), axis=1)
    np.testing.assert_allclose(distance_to_wall, 0.0, atol=1e-9)
    bearings = np.unwrap(np.arctan2(points[:, 1], points[:, 0]))
    assert np.all(np.diff(bearings) > 0)  # bearing-ordered
    # Beyond the range, through a door gap, or behind a narrower field of view: no return.
    assert len(simulate_scan(segments, pose, max_range=2.0)) < 360
    doorway = wall((-2.0, -1.0), (3.0, -1.0), doors=[(2.5, 1.0)])
    assert len(doorway) == 2 and np.isclose(doorway[0, 2], 0.0) and np.isclose(doorway[1, 0], 1.0)
    half = simulate_scan(segments, pose, beams=181, fov=math.pi)
    assert len(half) == 181 and np.all(half[:, 0] >= -1e-9)


# -------------------------------------------------------------------------------------------- grids


def test_a_point_own_cell_is_one_and_the_likelihood_falls_as_the_gaussian() -> None:
    # With this margin the point sits at the centre of cell (10, 10).
    point = np.array([[1.234, -0.5]])
    grid = build_likelihood_grid(point, RESOLUTION, SIGMA, margin=10.5 * RESOLUTION)
    assert grid.values[10, 10] == pytest.approx(1.0, abs=1e-6)
    assert grid.nearest[10, 10] == 0
    along_row = grid.values[10, 10:]
    expected = gaussian(np.arange(len(along_row)) * RESOLUTION, SIGMA)
    within = np.arange(len(along_row)) * RESOLUTION <= 3.0 * SIGMA
    np.testing.assert_allclose(along_row[within], expected[within], rtol=1e-5)
    assert np.all(np.diff(along_row) <= 0.0)
    assert along_row[-1] == 0.0


@pytest.mark.parametrize("pairing", [0.0, 0.3, 0.7])
@pytest.mark.parametrize("margin_cells", [2, 9, 40])
def test_a_stamp_covers_exactly_the_square_of_its_radius_around_the_point_cell(
        pairing: float, margin_cells: int) -> None:
    # Narrow stamps are written in rows of a fixed width where they fit (`grid.STAMP_WIDTH`): the cells of
    # such a row past the stamp stay unstamped, near the grid's edges too.
    radius = max(1, math.ceil(max(3.0 * SIGMA, pairing) / RESOLUTION))
    point = np.array([0.5 * RESOLUTION, 0.5 * RESOLUTION])
    grid = build_likelihood_grid(point[None, :], RESOLUTION, SIGMA, margin=margin_cells * RESOLUTION,
                                 pairing_distance=pairing)
    column, row = grid.cell_of(point)
    height, width = grid.values.shape
    rows, columns = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    inside = (np.abs(rows - row) <= radius) & (np.abs(columns - column) <= radius)
    np.testing.assert_array_equal(grid.nearest >= 0, inside)
    assert not np.any(grid.values[~inside])


@settings(max_examples=60, deadline=None)
@given(
    points=hnp.arrays(np.float64, st.tuples(st.integers(1, 25), st.just(2)),
                      elements=st.floats(-1.0, 1.0, allow_nan=False)),
    resolution=st.sampled_from([0.03, 0.05, 0.1]),
    sigma=st.floats(0.02, 0.15),
    pairing=st.sampled_from([0.0, 0.3]),
)
def test_likelihood_grid_is_the_gaussian_of_the_distance_to_the_nearest_point(
        points: np.ndarray, resolution: float, sigma: float, pairing: float) -> None:
    margin = 0.4
    grid = build_likelihood_grid(points, resolution, sigma, margin, pairing_distance=pairing)
    assert np.all(grid.origin <= points.min(axis=0) - margin + 1e-12)
    top = grid.origin + resolution * np.array(grid.values.shape[::-1])
    assert np.all(top >= points.max(axis=0) + margin - 1e-12)
    centres = cell_centres(grid)
    distances = np.linalg.norm(centres[:, :, None, :] - points[None, None, :, :], axis=-1)
    nearest_distance = distances.min(axis=-1)
    expected = gaussian(nearest_distance, sigma)
    # Never more than the nearest point allows; exactly that within the stamping radius.
    assert np.all(grid.values <= expected + 1e-6)
    stamped = nearest_distance <= max(3.0 * sigma, pairing)
    np.testing.assert_allclose(grid.values[stamped], expected[stamped], rtol=1e-5, atol=1e-7)
    index = grid.nearest[stamped]
    assert np.all(index >= 0)
    chosen = np.take_along_axis(distances[stamped], index[:, None].astype(np.int64), axis=1)[:, 0]
    np.testing.assert_allclose(chosen, nearest_distance[stamped], atol=1e-9)
    assert np.all(grid.values[grid.nearest < 0] == 0.0)


@settings(max_examples=80, deadline=None)
@given(
    values=hnp.arrays(np.float32, st.tuples(st.integers(1, 23), st.integers(1, 23)),
                      elements=st.floats(0.0, 1.0, width=32)),
    levels=st.integers(1, 4),
)
def test_max_pyramid_levels_bound_the_finer_levels(values: np.ndarray, levels: int) -> None:
    pyramid = max_pyramid(values, levels)
    assert len(pyramid) == levels + 1
    np.testing.assert_array_equal(pyramid[0], values)
    height, width = values.shape
    for level in range(1, levels + 1):
        span, half = 1 << level, 1 << (level - 1)
        coarse, fine = pyramid[level], pyramid[level - 1]
        assert coarse.shape == values.shape
        for y in range(height):
            for x in range(width):
                assert coarse[y, x] == values[y:y + span, x:x + span].max()
                block = fine[y:y + span:half, x:x + span:half]  # the finer level's 2 × 2 sub-blocks
                assert coarse[y, x] >= block.max()


# ---------------------------------------------------------------------------------- correlative search


@pytest.fixture(scope="module")
def hall_scans() -> Scans:
    """A reference scan in the hall, a second scan 14 cm / 3° away, and their true relative pose."""
    rng = np.random.default_rng(5)
    world = square_loop()
    second = np.array([HALL_POSE[0] + 0.1, HALL_POSE[1] - 0.1, HALL_POSE[2] + math.radians(3.0)])
    reference = simulate_scan(world.segments, HALL_POSE, range_noise=0.01, rng=rng)
    scan = simulate_scan(world.segments, second, range_noise=0.01, rng=rng)
    return reference, scan, between(HALL_POSE, second)


def test_exhaustive_search_finds_the_true_pose_within_a_cell_and_a_step(hall_scans: Scans) -> None:
    reference, scan, truth = hall_scans
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=1.0)
    window = SearchWindow(0.3, math.radians(6.0), math.radians(0.5))
    match = match_exhaustive(scan, grid, np.zeros(3), window)
    assert np.all(np.abs(match.pose[:2] - truth[:2]) <= RESOLUTION)
    assert abs(match.pose[2] - truth[2]) <= math.radians(0.5)
    assert match.score == pytest.approx(grid_score(scan, grid, match.pose), abs=3.0 / len(scan))
    assert match.score > grid_score(scan, grid, np.zeros(3))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**31 - 1),
    offset=st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(-0.15, 0.15)),
    linear=st.floats(0.05, 0.6),
    angular=st.floats(0.0, math.radians(5.0)),
    levels=st.integers(1, 5),
    reference_range=st.sampled_from([4.0, 20.0]),
)
def test_branch_and_bound_scores_the_same_as_exhaustive_search(
        seed: int, offset: tuple[float, float, float], linear: float, angular: float, levels: int,
        reference_range: float) -> None:
    rng = np.random.default_rng(seed)
    world = square_loop()
    reference_pose = np.array([rng.uniform(3.0, 9.0), rng.uniform(3.0, 17.0), rng.uniform(-np.pi, np.pi)])
    scan_pose = reference_pose + np.array([*rng.uniform(-0.4, 0.4, 2), rng.uniform(-0.1, 0.1)])
    # A short-range reference puts many of the scan's points off the grid: the edges must stay bounds.
    reference = simulate_scan(world.segments, reference_pose, beams=120, max_range=reference_range,
                              range_noise=0.01, rng=rng)
    scan = simulate_scan(world.segments, scan_pose, beams=90, range_noise=0.01, rng=rng)
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=0.3)
    centre = between(reference_pose, scan_pose) + np.array(offset)
    window = SearchWindow(linear, angular, math.radians(1.0))
    exhaustive = match_exhaustive(scan, grid, centre, window)
    bounded = match_branch_and_bound(scan, grid, centre, window, min_score=0.0, levels=levels)
    if exhaustive.score <= 0.0:
        assert bounded is None
        return
    assert bounded is not None
    assert bounded.score == pytest.approx(exhaustive.score, rel=1e-9, abs=1e-12)
    # The pose it returns is inside the window and really scores that.
    assert np.all(np.abs(bounded.pose[:2] - centre[:2]) <= linear + RESOLUTION)
    assert abs(bounded.pose[2] - centre[2]) <= angular + 1e-9
    assert grid_score(scan, grid, bounded.pose) == pytest.approx(bounded.score, abs=3.0 / len(scan))
    # Asking for more than the optimum finds nothing; for a little less, finds it.
    assert match_branch_and_bound(scan, grid, centre, window, min_score=exhaustive.score + 1e-6,
                                  levels=levels) is None
    again = match_branch_and_bound(scan, grid, centre, window, min_score=exhaustive.score - 1e-3,
                                   levels=levels)
    assert again is not None and again.score == pytest.approx(exhaustive.score, rel=1e-9)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), threads=st.integers(2, 5), levels=st.integers(2, 5))
def test_branch_and_bound_shared_among_threads_finds_what_one_thread_finds(
        seed: int, threads: int, levels: int) -> None:
    """A wide search's rotations dealt out to threads, each searching its own: the optimum and the rival
    away from it are those of one thread's search of them all."""
    rng = np.random.default_rng(seed)
    world = square_loop()
    reference_pose = np.array([rng.uniform(3.0, 9.0), rng.uniform(3.0, 17.0), rng.uniform(-np.pi, np.pi)])
    scan_pose = reference_pose + np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.2, 0.2)])
    reference = simulate_scan(world.segments, reference_pose, beams=180, range_noise=0.01, rng=rng)
    scan = simulate_scan(world.segments, scan_pose, beams=120, range_noise=0.01, rng=rng)
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=1.5)
    window = SearchWindow(1.2, math.radians(15.0), math.radians(1.0))
    centre = np.zeros(3)

    def searched(thread_count: int) -> tuple[correlative.Match | None, correlative.Match | None, int]:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(correlative, "SIDE_BY_SIDE_READS", 0)
            patch.setattr(correlative.numba_config, "NUMBA_NUM_THREADS", thread_count)
            search = prepare_branch_and_bound(scan, grid, centre, window, levels=levels)
            best = search.best(0.1)
            rival = None if best is None else search.best(0.1, exclude=(best.pose[:2], 0.4))
            return best, rival, len(search.parts)

    alone, alone_rival, parts = searched(1)
    shared, shared_rival, shared_parts = searched(threads)
    assert (parts, shared_parts) == (1, threads)
    for one, many in ((alone, shared), (alone_rival, shared_rival)):
        assert (one is None) == (many is None)
        if one is not None and many is not None:
            assert many.score == one.score  # each rotation's scores summed in the same order
            assert grid_score(scan, grid, many.pose) == pytest.approx(many.score, abs=3.0 / len(scan))


# ---------------------------------------------------------------------------------------------- ICP


def test_icp_recovers_a_small_transform_between_two_scans_of_a_room(hall_scans: Scans) -> None:
    reference, scan, truth = hall_scans
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=1.0, pairing_distance=PAIRING)
    result = refine_point_to_line(scan, grid, reference, scan_normals(reference), np.zeros(3),
                                  max_distance=PAIRING, sigma=0.03, iterations=30)
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.01
    assert abs(result.pose[2] - truth[2]) < math.radians(0.2)
    assert result.inlier_fraction > 0.9
    assert result.rms < 0.05  # 1 cm noise, plus the few pairs across doors and occlusions
    assert np.all(np.linalg.eigvalsh(result.information) > 0.0)


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float64, (3, 3), elements=st.floats(-1e3, 1e3)),
       hnp.arrays(np.float64, 3, elements=st.floats(-1e3, 1e3)))
def test_icp_3x3_solve_agrees_with_numpy_where_the_matrix_is_regular(matrix: np.ndarray,
                                                                     rhs: np.ndarray) -> None:
    """ICP's step solve, written out (numba's `np.linalg.solve` binding took half the kernel's compile
    time), must give what LAPACK gives wherever the system is well posed."""
    if np.linalg.cond(matrix) > 1e8:
        return
    solution = rhs.copy()
    assert _solve_3x3(matrix.copy(), solution)
    np.testing.assert_allclose(matrix @ solution, rhs, atol=1e-6 * (1.0 + np.abs(rhs).max()))
    np.testing.assert_allclose(solution, np.linalg.solve(matrix, rhs), rtol=1e-6,
                               atol=1e-9 * (1.0 + np.abs(solution).max()))


def test_icp_3x3_solve_pivots_past_a_zero_and_refuses_a_singular_matrix() -> None:
    needs_pivot = np.array([[0.0, 2.0, 1.0], [3.0, 0.0, 1.0], [1.0, 1.0, 0.0]])  # a zero first pivot
    rhs = np.array([1.0, 2.0, 3.0])
    solution = rhs.copy()
    assert _solve_3x3(needs_pivot.copy(), solution)
    np.testing.assert_allclose(solution, np.linalg.solve(needs_pivot, rhs), rtol=1e-12)
    singular = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]])
    assert not _solve_3x3(singular.copy(), rhs.copy())


@pytest.mark.parametrize("heading", [0.0, 0.7, -2.0])
@pytest.mark.parametrize("noise", [0.0, 0.005])
def test_scan_normals_of_a_wall_are_perpendicular_to_it(heading: float, noise: float) -> None:
    wall_angle = 0.4
    direction = np.array([math.cos(wall_angle), math.sin(wall_angle)])
    across = np.array([-direction[1], direction[0]])
    segments = np.array([[*(2.0 * across - 12.0 * direction), *(2.0 * across + 12.0 * direction)]])
    pose = np.array([0.0, 0.0, heading])
    points = simulate_scan(segments, pose, beams=360, max_range=6.0, range_noise=noise,
                           rng=np.random.default_rng(1))
    normals = scan_normals(points)
    assert normals.shape == points.shape
    seen = np.isfinite(normals[:, 0])
    # Every point of the well-sampled middle of the wall (closer than 4 m) has a normal.
    assert seen[np.hypot(points[:, 0], points[:, 1]) < 4.0].all()
    np.testing.assert_allclose(np.hypot(normals[seen, 0], normals[seen, 1]), 1.0, atol=1e-9)
    # In the sensor frame the wall runs along `direction` rotated by −heading.
    c, s = math.cos(-heading), math.sin(-heading)
    wall_in_sensor = np.array([c * direction[0] - s * direction[1], s * direction[0] + c * direction[1]])
    deviation = np.degrees(np.arcsin(np.clip(np.abs(normals[seen] @ wall_in_sensor), 0.0, 1.0)))
    if noise == 0.0:
        assert deviation.max() < 1e-6
    else:
        assert np.median(deviation) < 2.0 and deviation.max() < 10.0


def test_scan_normals_are_nan_where_no_line_is_seen() -> None:
    scattered = np.random.default_rng(2).uniform(-20.0, 20.0, size=(50, 2))
    scattered = scattered[np.argsort(np.arctan2(scattered[:, 1], scattered[:, 0]))]
    # Points this sparse have no neighbours within the normal radius: no line, and marked (0, 0), too
    # sparse to pair with.
    assert np.all(scan_normals(scattered) == 0.0)


def test_icp_in_a_featureless_corridor_keeps_the_prior_along_it() -> None:
    """Two walls and nothing else within range: the scans fix the across-corridor offset and the heading,
    never the position along the corridor, which must stay where the prior puts it, with about the
    prior's information."""
    world = long_corridor()
    rng = np.random.default_rng(3)
    reference_pose = np.array([0.0, 0.1, 0.0])
    scan_pose = np.array([0.4, -0.05, math.radians(2.0)])
    reference = simulate_scan(world.segments, reference_pose, range_noise=0.01, rng=rng)
    scan = simulate_scan(world.segments, scan_pose, range_noise=0.01, rng=rng)
    truth = between(reference_pose, scan_pose)
    prior = truth + np.array([-0.25, 0.08, math.radians(-1.5)])
    prior_information = np.diag([0.1**-2, 0.1**-2, math.radians(3.0) ** -2])
    grid = build_likelihood_grid(reference, RESOLUTION, SIGMA, margin=1.0, pairing_distance=PAIRING)
    result = refine_point_to_line(scan, grid, reference, scan_normals(reference), prior,
                                  max_distance=PAIRING, sigma=0.03, prior=prior,
                                  prior_information=prior_information)
    # Across the corridor and in heading the scans win over the prior …
    assert abs(result.pose[1] - truth[1]) < 0.01
    assert abs(result.pose[2] - truth[2]) < math.radians(0.2)
    # … along it nothing is measured: the information stays about the prior's (noisy normals leak a
    # little of the across-wall information), and the estimate stays at the prior within the σ it reports.
    along, across = result.information[0, 0], result.information[1, 1]
    assert along < 3.0 * prior_information[0, 0], (
        f"information along the corridor {along:.0f} vs the prior's {prior_information[0, 0]:.0f}")
    assert abs(result.pose[0] - prior[0]) < 1.0 / math.sqrt(along), (
        f"along the corridor: prior {prior[0]:.3f}, ICP moved it to {result.pose[0]:.3f} "
        f"(truth {truth[0]:.3f}, reported σ {1.0 / math.sqrt(along):.3f})")
    assert along < 0.01 * across
