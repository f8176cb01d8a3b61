"""Correlative scan matching on a likelihood grid (Olson 2009), exhaustive or branch-and-bound.

A candidate pose (x, y, θ) scores the mean grid likelihood of the scan's points placed by it.
Translations are searched in whole cells of the grid, rotations in `angular_step` steps; the result is a
starting point for a sub-cell refinement (ICP), not the final estimate.

- `match_exhaustive`: every candidate of a small window (scan-to-local-map odometry).
- `match_branch_and_bound`: wide windows (loop closures): candidates on coarse levels of the max pyramid
  bound the scores of all finer translations they contain, so whole blocks are pruned at once
  (Hess et al. 2016, "Real-time loop closure in 2D LIDAR SLAM"); the result is the exhaustive optimum.

The score of a translation (tx, ty) in whole cells on pyramid level h, whose cells hold the max over blocks
of 2^h × 2^h cells (the block score): each point's cell shifted by (tx, ty) is read, the edge cell where its
block only partly overlaps the grid (which covers the overlapping part: the level stays an upper bound of
the finer ones), nothing where it misses it; the values are summed over the points in their order and
divided by the point count. Level 0 is the grid itself and the score the mean likelihood. Every kernel
below sums in that order, so their scores agree up to round-off.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import TypeVar

import numpy as np
from numba import config as numba_config
from numba import njit
from numpy.typing import NDArray

from frontends.slam2d.grid import LikelihoodGrid

FloatArray = NDArray[np.float64]
T = TypeVar("T")

PYRAMID_SLOTS = 8
"""Levels `_branch_and_bound` takes: a shorter pyramid is padded to this many with its top level (never
read: the kernel is told the top), so every `levels` up to 7 shares one compiled kernel. numba compiles a
tuple argument once per length: the 3, 4 and 5 levels of the odometry, loop and localization searches
were three compilations of it, seconds each on a cold cache."""


@dataclass(frozen=True)
class SearchWindow:
    """± `linear` metres in x and y, ± `angular` radians, rotations every `angular_step` radians."""

    linear: float
    angular: float
    angular_step: float

    def holds(self, pose: FloatArray, center: FloatArray, resolution: float) -> bool:
        """Whether `pose` lies in the window around `center`, with one cell of `resolution` and one angular
        step of slack (ICP refining a match that ends beyond it slid along a corridor the search never
        scored)."""
        return (max(abs(pose[0] - center[0]), abs(pose[1] - center[1])) <= self.linear + resolution
                and _turn(pose, center) <= self.angular + self.angular_step)

    @property
    def steps(self) -> int:
        """Rotations searched on either side of the centre's heading."""
        return max(math.floor(self.angular / self.angular_step), 0)

    def turned_past(self, pose: FloatArray, center: FloatArray) -> SearchWindow | None:
        """This window turning twice as far (at most a half-turn) when `pose`, a search's optimum, lies on
        its angular edge (the outermost rotation searched around `center`): the optimum may be the edge of a
        better one beyond. None when it lies inside, or the window turns half a turn already.

        Rotations only: along a corridor the score is flat, and a translation's optimum on the edge is as
        likely a plateau's as a cut-off peak's; a wider window there finds look-alikes, not the truth."""
        if _turn(pose, center) < (self.steps - 0.5) * self.angular_step or self.angular >= math.pi:
            return None
        return SearchWindow(self.linear, min(2.0 * self.angular, math.pi), self.angular_step)


@dataclass(frozen=True)
class Match:
    pose: FloatArray
    """(x, y, θ) of the scan in the grid's frame."""
    score: float
    """Mean likelihood of the scan's points, in [0, 1]."""


def _turn(pose: FloatArray, center: FloatArray) -> float:
    """How far `pose` is turned from `center` (rad, in [0, π])."""
    return abs(math.remainder(float(pose[2] - center[2]), math.tau))


def _reach(window: SearchWindow, grid: LikelihoodGrid) -> int:
    """The window's half-width in cells (0.05000000000000001 m at 5 cm is one cell, not two)."""
    return math.ceil(window.linear / grid.resolution - 1e-9)


def _angles(center: float, window: SearchWindow) -> FloatArray:
    return center + window.angular_step * np.arange(-window.steps, window.steps + 1, dtype=np.float64)


@njit(cache=True, nogil=True)
def _base_cells(
    points: FloatArray, x: float, y: float, angles: FloatArray, origin: FloatArray, resolution: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Cell of every point, for every rotation, with the translation (x, y): (A, N) arrays."""
    count = points.shape[0]
    cells_x = np.empty((angles.shape[0], count), dtype=np.int64)
    cells_y = np.empty((angles.shape[0], count), dtype=np.int64)
    for a in range(angles.shape[0]):
        c = math.cos(angles[a])
        s = math.sin(angles[a])
        for i in range(count):
            wx = x + c * points[i, 0] - s * points[i, 1]
            wy = y + s * points[i, 0] + c * points[i, 1]
            cells_x[a, i] = int(math.floor((wx - origin[0]) / resolution))
            cells_y[a, i] = int(math.floor((wy - origin[1]) / resolution))
    return cells_x, cells_y


@njit(cache=True, nogil=True)
def _exhaustive(
    values: NDArray[np.float32], cells_x: NDArray[np.int64], cells_y: NDArray[np.int64], reach: int
) -> tuple[int, int, int, float]:
    """The best (angle, tx, ty, score) of every translation within ±`reach` cells: the block score on level 0.

    Point by point, each adding its (2·reach + 1)² patch of the grid to the totals of all translations:
    rows read contiguously instead of one random cell per point and candidate. Consecutive points in one
    cell (a dense laser has several per 5 cm cell) add their patch once, times their count. The first best
    is taken in (angle, ty, tx) order.
    """
    height, width = values.shape
    side = 2 * reach + 1
    count = cells_x.shape[1]
    totals = np.empty((side, side))
    best = (0, 0, 0, -1.0)
    for a in range(cells_x.shape[0]):
        totals[:] = 0.0
        i = 0
        while i < count:
            # A run of consecutive points in one cell adds that cell's patch once, times the run's length.
            run = 1
            while (i + run < count and cells_x[a, i + run] == cells_x[a, i]
                   and cells_y[a, i + run] == cells_y[a, i]):
                run += 1
            left = cells_x[a, i] - reach
            bottom = cells_y[a, i] - reach
            i += run
            if left >= 0 and bottom >= 0 and left + side <= width and bottom + side <= height:
                for j in range(side):
                    for k in range(side):
                        totals[j, k] += run * values[bottom + j, left + k]
            else:
                for j in range(side):
                    cy = bottom + j
                    if cy < 0 or cy >= height:
                        continue
                    for k in range(side):
                        cx = left + k
                        if 0 <= cx < width:
                            totals[j, k] += run * values[cy, cx]
        for j in range(side):
            for k in range(side):
                score = totals[j, k] / max(count, 1)
                if score > best[3]:
                    best = (a, k - reach, j - reach, score)
    return best


def match_exhaustive(
    points: FloatArray, grid: LikelihoodGrid, center: FloatArray, window: SearchWindow
) -> Match:
    """The best pose of `points` (robot frame) within `window` around `center` on `grid`."""
    angles = _angles(float(center[2]), window)
    cells_x, cells_y = _base_cells(  # contiguous: strided points compiled the kernel a second time
        np.ascontiguousarray(points), float(center[0]), float(center[1]), angles, grid.origin, grid.resolution
    )
    reach = _reach(window, grid)
    a, tx, ty, score = _exhaustive(grid.values, cells_x, cells_y, reach)
    pose = np.array([center[0] + tx * grid.resolution, center[1] + ty * grid.resolution, angles[a]])
    return Match(pose, float(score))


@njit(cache=True, inline="always")
def _excluded(tx: int, ty: int, span: int, exclude_x: int, exclude_y: int, radius: int) -> bool:
    """Whether the whole block of translations [tx, tx + span) × [ty, ty + span) lies in the disc."""
    if radius < 0:
        return False
    dx = max(abs(tx - exclude_x), abs(tx + span - 1 - exclude_x))
    dy = max(abs(ty - exclude_y), abs(ty + span - 1 - exclude_y))
    return dx * dx + dy * dy <= radius * radius


@njit(cache=True, inline="always")
def _block_cell(cell: int, span: int, size: int) -> int:
    """The cell the block score reads for a point whose block [cell, cell + span) is shifted there: the edge
    cell where the block only partly overlaps the grid, −1 where it misses it."""
    if cell < 0:
        return 0 if cell + span > 0 else -1
    return cell if cell < size else -1


@njit(cache=True, nogil=True)
def _top_level(
    values: NDArray[np.float32],
    top: int,
    cells_x: NDArray[np.int64],
    cells_y: NDArray[np.int64],
    reach: int,
    rotations: NDArray[np.int64],
    scores: FloatArray,
    keys: NDArray[np.int64],
) -> None:
    """Scores of every candidate (angle, tx, ty) of the coarsest level, level `top` (its `values`), and
    those keys, for the `rotations` (indices into `cells_x`): their rows of `scores` and `keys`, side²
    rows a rotation, in the order of `rotations`.

    Each point adds its cells of all translations at once (`_block_cell`), so its row is read for all of
    them together."""
    span = 1 << top
    height, width = values.shape
    starts = np.arange(-reach, reach + 1, span)
    side = starts.shape[0]
    count = cells_x.shape[1]
    totals = np.empty((side, side))
    columns = np.empty(side, dtype=np.int64)
    k = 0
    for a in rotations:
        totals[:] = 0.0
        for i in range(count):
            for t in range(side):
                columns[t] = _block_cell(cells_x[a, i] + starts[t], span, width)
            for j in range(side):
                row = _block_cell(cells_y[a, i] + starts[j], span, height)
                if row < 0:
                    continue
                for t in range(side):
                    if columns[t] >= 0:
                        totals[j, t] += values[row, columns[t]]
        for j in range(side):
            for t in range(side):
                scores[k] = totals[j, t] / max(count, 1)
                keys[k, 0] = a
                keys[k, 1] = starts[t]
                keys[k, 2] = starts[j]
                k += 1


@njit(cache=True, nogil=True)
def _child_scores(
    values: NDArray[np.float32],
    cells_x: NDArray[np.int64],
    cells_y: NDArray[np.int64],
    tx: int,
    ty: int,
    half: int,
    wanted: NDArray[np.bool_],
    out: FloatArray,
) -> None:
    """The block scores of the four children (tx + half·(c & 1), ty + half·(c >> 1)) with span `half`, in
    one pass over the points; −1 for a child not `wanted`."""
    height, width = values.shape
    total0 = total1 = total2 = total3 = 0.0
    for i in range(cells_x.shape[0]):
        left = _block_cell(cells_x[i] + tx, half, width)
        right = _block_cell(cells_x[i] + tx + half, half, width)
        bottom = _block_cell(cells_y[i] + ty, half, height)
        top = _block_cell(cells_y[i] + ty + half, half, height)
        if bottom >= 0:
            if left >= 0:
                total0 += values[bottom, left]
            if right >= 0:
                total1 += values[bottom, right]
        if top >= 0:
            if left >= 0:
                total2 += values[top, left]
            if right >= 0:
                total3 += values[top, right]
    count = max(cells_x.shape[0], 1)
    out[0] = total0 / count if wanted[0] else -1.0
    out[1] = total1 / count if wanted[1] else -1.0
    out[2] = total2 / count if wanted[2] else -1.0
    out[3] = total3 / count if wanted[3] else -1.0


@njit(cache=True, nogil=True)
def _branch_and_bound(
    levels: tuple[NDArray[np.float32], ...],
    top: int,
    cells_x: NDArray[np.int64],
    cells_y: NDArray[np.int64],
    reach: int,
    top_scores: FloatArray,
    keys: NDArray[np.int64],
    top_order: NDArray[np.int64],
    min_score: float,
    exclude_x: int,
    exclude_y: int,
    exclude_radius: int,
) -> tuple[int, int, int, float]:
    """The best leaf above `min_score`, skipping translations within `exclude_radius` cells of
    (exclude_x, exclude_y) (a negative radius excludes nothing); `levels[top]` is the coarsest level
    (`levels` may hold more, `PYRAMID_SLOTS`); `top_scores` and `keys` are `_top_level`'s, shared by every
    search of the same points on the same pyramid, and `top_order` the indices of `top_scores` in ascending
    order (sorted by the caller, in numpy: a sort in here compiled numba's quicksort, 2 of this kernel's 4 s
    of compilation on a fresh install)."""
    span = 1 << top
    count = top_scores.shape[0]
    scores = top_scores.copy()
    for k in range(count):
        if _excluded(keys[k, 1], keys[k, 2], span, exclude_x, exclude_y, exclude_radius):
            scores[k] = -1.0
    # Stack of candidates (angle, tx, ty, level, score) in arrays: depth first, a path holds at most 3
    # siblings a level above the top candidates. The best-scoring child is pushed last so it is explored
    # first, and a candidate no better than the best leaf found so far is pruned whole.
    capacity = count + 4 * (top + 1)
    stack_a = np.empty(capacity, dtype=np.int64)
    stack_x = np.empty(capacity, dtype=np.int64)
    stack_y = np.empty(capacity, dtype=np.int64)
    stack_level = np.empty(capacity, dtype=np.int64)
    stack_score = np.empty(capacity)
    size = 0
    for k in top_order:
        if scores[k] <= min_score:  # would be pruned when popped
            continue
        stack_a[size] = keys[k, 0]
        stack_x[size] = keys[k, 1]
        stack_y[size] = keys[k, 2]
        stack_level[size] = top
        stack_score[size] = scores[k]
        size += 1
    best = (0, 0, 0, min_score)
    found = False
    child_scores = np.empty(4)
    wanted = np.empty(4, dtype=np.bool_)
    order = np.empty(4, dtype=np.int64)
    while size > 0:
        size -= 1
        a = stack_a[size]
        tx = stack_x[size]
        ty = stack_y[size]
        level = stack_level[size]
        score = stack_score[size]
        if score <= best[3]:
            continue
        if level == 0:
            best = (a, tx, ty, score)
            found = True
            continue
        half = 1 << (level - 1)
        for c in range(4):
            cx = tx + half * (c & 1)
            cy = ty + half * (c >> 1)
            wanted[c] = not (cx > reach or cy > reach
                             or _excluded(cx, cy, half, exclude_x, exclude_y, exclude_radius))
        _child_scores(levels[level - 1], cells_x[a], cells_y[a], tx, ty, half, wanted, child_scores)
        # Ascending, ties in index order (what argsort gives on four values), by insertion.
        for c in range(4):
            j = c
            while j > 0 and child_scores[order[j - 1]] > child_scores[c]:
                order[j] = order[j - 1]
                j -= 1
            order[j] = c
        for i in range(4):
            c = order[i]
            if child_scores[c] > best[3]:
                stack_a[size] = a
                stack_x[size] = tx + half * (c & 1)
                stack_y[size] = ty + half * (c >> 1)
                stack_level[size] = level - 1
                stack_score[size] = child_scores[c]
                size += 1
    if not found:
        return (0, 0, 0, -1.0)
    return best


@dataclass(frozen=True, eq=False)
class BranchAndBoundSearch:
    """Points placed for a wide-window search (`prepare_branch_and_bound`): their cells at every rotation,
    the pyramid they read and the scores of the coarsest candidates, computed once for every search of
    these points in this window (the optimum, then a rival away from it)."""

    center: FloatArray
    resolution: float
    angles: FloatArray
    reach: int
    pyramid: tuple[NDArray[np.float32], ...]
    cells_x: NDArray[np.int64]
    cells_y: NDArray[np.int64]
    top_scores: FloatArray
    top_keys: NDArray[np.int64]
    parts: tuple[slice, ...]
    """Rows of `top_scores` and `top_keys` searched side by side (`_side_by_side`), a share of the
    rotations each."""
    top_orders: tuple[NDArray[np.int64], ...]
    """Each part's rows of `top_scores` in ascending order of score (where scores tie, in row order)."""

    def best(self, min_score: float, exclude: tuple[FloatArray, float] | None = None) -> Match | None:
        """`match_branch_and_bound` of these points with this `min_score` and `exclude`."""
        center, resolution = self.center, self.resolution
        exclude_x = exclude_y = 0
        exclude_radius = -1
        if exclude is not None:
            (x, y), radius = exclude
            exclude_x = round((x - center[0]) / resolution)
            exclude_y = round((y - center[1]) / resolution)
            exclude_radius = round(radius / resolution)
        top = len(self.pyramid) - 1
        padded = self.pyramid + (self.pyramid[-1],) * max(PYRAMID_SLOTS - len(self.pyramid), 0)
        found = _side_by_side([
            partial(_branch_and_bound, padded, top, self.cells_x, self.cells_y, self.reach,
                    self.top_scores[part], self.top_keys[part], order, float(min_score), exclude_x,
                    exclude_y, exclude_radius)
            for part, order in zip(self.parts, self.top_orders, strict=True)
        ])
        # The best of the parts; of equal scores the first rotation's, whatever thread finished first.
        a, tx, ty, score = max(found, key=lambda f: (f[3], -f[0]))
        if score < 0.0:
            return None
        return Match(np.array([center[0] + tx * resolution, center[1] + ty * resolution, self.angles[a]]),
                     float(score))


TOP_LEVEL_SIDE = 8
"""`branch_and_bound_levels` gives a window at most this many coarsest candidates a side."""


def branch_and_bound_levels(radius: float, resolution: float, *, minimum: int) -> int:
    """Pyramid levels for a branch and bound over ± `radius` on a grid of `resolution`: `minimum`, more
    where the coarsest level would hold more than `TOP_LEVEL_SIDE` candidates a side. The optimum does not
    depend on the levels; the work does: the coarsest level's scores cost points × angles × candidates,
    26² of them for ± 10 m at 5 cm and 4 levels (three quarters of a loop search on the UAL outdoor log),
    7² at 6."""
    cells = 2 * math.ceil(radius / resolution - 1e-9) + 1
    return max(minimum, math.ceil(math.log2(cells / TOP_LEVEL_SIDE)))


def prepare_branch_and_bound(
    points: FloatArray,
    grid: LikelihoodGrid,
    center: FloatArray,
    window: SearchWindow,
    levels: int = 4,
    crop_pyramid: bool = False,
) -> BranchAndBoundSearch:
    """What every `match_branch_and_bound` of `points` in `window` around `center` on `grid` computes
    before it searches; see there for `levels` and `crop_pyramid`."""
    angles = _angles(float(center[2]), window)
    cells_x, cells_y = _base_cells(  # contiguous: strided points compiled the kernel a second time
        np.ascontiguousarray(points), float(center[0]), float(center[1]), angles, grid.origin, grid.resolution
    )
    reach = _reach(window, grid)
    height, width = grid.values.shape
    top, bottom, left, right = 0, height, 0, width
    if crop_pyramid and grid.stamped_window is not None:
        # Beyond the stamped cells the grid reads zeros, as past its edges: the pyramid of those cells bounds
        # every block the search reads (one that starts before them by their first cells' block, a bound
        # as valid), and scores every translation as the whole grid's would. Built once per grid, not per
        # query: a submap searched again from the next keyframes reuses it.
        top, bottom, left, right = grid.stamped_window
    if left >= right or top >= bottom:  # the search reads nothing: any window will do
        top, bottom, left, right = 0, height, 0, width
    pyramid = tuple(grid.pyramid(levels, (top, bottom, left, right)))
    cells_x = cells_x - left
    cells_y = cells_y - top
    top = len(pyramid) - 1
    side = len(range(-reach, reach + 1, 1 << top))
    rotations = _rotation_shares(len(angles), len(angles) * len(points) * side * side)
    top_scores = np.empty(len(angles) * side * side)
    top_keys = np.empty((len(angles) * side * side, 3), dtype=np.int64)
    bounds = np.cumsum([0] + [len(share) * side * side for share in rotations])
    parts = tuple(slice(int(first), int(stop)) for first, stop in itertools.pairwise(bounds))
    _side_by_side([
        partial(_top_level, pyramid[-1], top, cells_x, cells_y, reach, share, top_scores[part],
                top_keys[part])
        for share, part in zip(rotations, parts, strict=True)
    ])
    top_orders = tuple(np.argsort(top_scores[part], kind="stable") for part in parts)
    return BranchAndBoundSearch(np.asarray(center, dtype=np.float64), grid.resolution, angles, reach, pyramid,
                                cells_x, cells_y, top_scores, top_keys, parts, top_orders)


SIDE_BY_SIDE_READS = 250_000
"""A search reads at least this many cells on its coarsest level (rotations × points × candidates) before
its rotations are shared among threads: a hand-over costs ~50 µs (two or three per search). Measured with
two threads on a scan of the synthetic hall: 117 000 reads 0.12 → 0.17 ms, 289 000 0.29 → 0.27 ms,
868 000 0.70 → 0.52 ms; a loop-closure search reads millions (UAL: 2.7 million)."""

_pool: tuple[int, int, ThreadPoolExecutor] | None = None
"""The worker threads: the process that started them (a forked child has none of them), how many."""
_pool_lock = threading.Lock()


def _rotation_shares(rotations: int, reads: int) -> list[NDArray[np.int64]]:
    """The rotations' indices, one share per thread of numba's (`NUMBA_NUM_THREADS`): every n-th rotation,
    so that the ones near the optimum, which the search descends deepest, are spread over all; all in one
    where the search is small."""
    threads = numba_config.NUMBA_NUM_THREADS if reads >= SIDE_BY_SIDE_READS else 1  # type: ignore[attr-defined]
    threads = max(1, min(threads, rotations))
    return [np.arange(first, rotations, threads, dtype=np.int64) for first in range(threads)]


def _side_by_side(calls: list[Callable[[], T]]) -> list[T]:
    """Every call's result: the first made in this thread, each other one in a worker thread at the same
    time (the kernels let go of the GIL)."""
    global _pool
    if len(calls) == 1:
        return [calls[0]()]
    with _pool_lock:  # two trackers may search at once (`replay --map`: `frontends.threads`)
        if _pool is None or _pool[0] != os.getpid() or _pool[1] < len(calls) - 1:
            if _pool is not None and _pool[0] == os.getpid():
                _pool[2].shutdown(wait=False)
            _pool = (os.getpid(), len(calls) - 1,
                     ThreadPoolExecutor(max_workers=len(calls) - 1, thread_name_prefix="correlative"))
        others = [_pool[2].submit(call) for call in calls[1:]]
    return [calls[0](), *(other.result() for other in others)]


def match_branch_and_bound(
    points: FloatArray,
    grid: LikelihoodGrid,
    center: FloatArray,
    window: SearchWindow,
    min_score: float,
    levels: int = 4,
    exclude: tuple[FloatArray, float] | None = None,
    crop_pyramid: bool = False,
) -> Match | None:
    """The best pose within a wide `window`, or None when no candidate scores above `min_score`.

    Equal to `match_exhaustive` on the same window (same optimum), in a fraction of the evaluations.
    `exclude` = (x, y, radius): translations within the radius of (x, y) are not candidates, which is how
    a second, distinct solution is found (an ambiguity test). `crop_pyramid`: build the grid's pyramid
    only over its stamped cells (a loop-closure submap, whose margin of the whole search radius is zeros),
    not over the whole grid (a local map, searched by many scans). Several searches of the same points and
    window: `prepare_branch_and_bound` once, then `best` for each.
    """
    search = prepare_branch_and_bound(points, grid, center, window, levels, crop_pyramid)
    return search.best(min_score, exclude)
