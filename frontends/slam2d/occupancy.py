"""An occupancy grid from keyframe scans at their optimized poses: the 2D map a person reads.

Each beam marks the cells it crosses as free and its end cell as occupied, in log-odds (the classic
inverse sensor model, Thrun et al., Probabilistic Robotics ch. 9); rays are traced with Bresenham's line
in a compiled loop. Returns that are farther than `max_range` only clear space up to it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.errors import MapExtentError

FloatArray = NDArray[np.float64]

LOG_ODDS_HIT = 0.85
LOG_ODDS_MISS = -0.4
LOG_ODDS_LIMIT = 5.0
OCCUPIED_ABOVE = 0.5
"""Log-odds above this is drawn occupied, below −this free, between unknown."""
MAX_MAP_CELLS = 50_000_000
"""The occupancy grid's cells (4 bytes each, and a 1-byte image): 2.5 km² at 5 cm. Larger maps are drawn
at a coarser `resolution` (see `OccupancyGrid.resolution`)."""


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """log_odds[iy, ix] of cell (ix, iy); cell (0, 0) starts at `origin` (x right, y up)."""

    origin: FloatArray
    resolution: float
    log_odds: NDArray[np.float32]

    def occupied_cells(self) -> NDArray[np.bool_]:
        return self.log_odds > OCCUPIED_ABOVE

    def free_cells(self) -> NDArray[np.bool_]:
        return self.log_odds < -OCCUPIED_ABOVE

    def image(self) -> NDArray[np.uint8]:
        """Grey-scale picture, north up: occupied black, free white, unknown grey."""
        picture = np.full(self.log_odds.shape, 205, dtype=np.uint8)
        picture[self.free_cells()] = 255
        picture[self.occupied_cells()] = 0
        return picture[::-1]  # image rows run downwards, y runs upwards


def occupancy_grid(scans: Sequence[FloatArray], poses: FloatArray, *, resolution: float = 0.05,
                   max_range: float = 20.0) -> OccupancyGrid:
    """The grid of keyframe `scans` (robot-frame points) seen from `poses` (x, y, θ)."""
    poses = np.asarray(poses, dtype=np.float64)
    ends = []
    for scan, pose in zip(scans, poses, strict=True):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        ends.append(scan @ np.array([[c, s], [-s, c]]) + pose[:2])
    points = np.concatenate(ends) if ends else np.zeros((0, 2))
    low = np.minimum(points.min(axis=0, initial=np.inf), poses[:, :2].min(axis=0)) - 1.0
    high = np.maximum(points.max(axis=0, initial=-np.inf), poses[:, :2].max(axis=0)) + 1.0
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        raise MapExtentError("occupancy grid: a keyframe pose or point is not finite")
    resolution = coarsest_needed(high - low, resolution, MAX_MAP_CELLS)
    shape = np.ceil((high - low) / resolution).astype(np.int64) + 1
    log_odds = np.zeros((int(shape[1]), int(shape[0])), dtype=np.float32)
    counts = np.array([len(scan) for scan in scans], dtype=np.int64)
    _integrate(points, counts, poses, low, resolution, max_range, log_odds)
    return OccupancyGrid(low, resolution, log_odds)


def coarsest_needed(extent: FloatArray, resolution: float, max_cells: int) -> float:
    """`resolution`, or the coarser one (a power of two times it) at which a grid over `extent` has at
    most `max_cells` cells: a map of a long drive is drawn coarser instead of taking gigabytes."""
    while float(np.prod(np.ceil(extent / resolution) + 1)) > max_cells:
        resolution *= 2.0
    return resolution


@njit(cache=True, nogil=True)  # traced beside the replay's sending of the recorded iterations
def _integrate(points: FloatArray, counts: NDArray[np.int64], poses: FloatArray, origin: FloatArray,
               resolution: float, max_range: float, log_odds: NDArray[np.float32]) -> None:
    height, width = log_odds.shape
    first = 0
    for k in range(poses.shape[0]):
        sx = int(math.floor((poses[k, 0] - origin[0]) / resolution))
        sy = int(math.floor((poses[k, 1] - origin[1]) / resolution))
        for i in range(first, first + counts[k]):
            dx = points[i, 0] - poses[k, 0]
            dy = points[i, 1] - poses[k, 1]
            distance = math.hypot(dx, dy)
            hit = distance <= max_range
            if not hit:
                dx *= max_range / distance
                dy *= max_range / distance
            ex = int(math.floor((poses[k, 0] + dx - origin[0]) / resolution))
            ey = int(math.floor((poses[k, 1] + dy - origin[1]) / resolution))
            _trace(sx, sy, ex, ey, hit, log_odds, width, height)
        first += counts[k]


@njit(cache=True, inline="always")
def _trace(x0: int, y0: int, x1: int, y1: int, hit: bool, log_odds: NDArray[np.float32], width: int,
           height: int) -> None:
    """Bresenham from (x0, y0) to (x1, y1): free along the way, occupied at the end when it was a return."""
    step_x = 1 if x1 > x0 else -1
    step_y = 1 if y1 > y0 else -1
    delta_x = abs(x1 - x0)
    delta_y = -abs(y1 - y0)
    error = delta_x + delta_y
    x, y = x0, y0
    while x != x1 or y != y1:
        if 0 <= x < width and 0 <= y < height:
            log_odds[y, x] = max(log_odds[y, x] + LOG_ODDS_MISS, -LOG_ODDS_LIMIT)
        twice = 2 * error
        if twice >= delta_y:
            error += delta_y
            x += step_x
        if twice <= delta_x:
            error += delta_x
            y += step_y
    if 0 <= x1 < width and 0 <= y1 < height:
        change = LOG_ODDS_HIT if hit else LOG_ODDS_MISS
        log_odds[y1, x1] = min(max(log_odds[y1, x1] + change, -LOG_ODDS_LIMIT), LOG_ODDS_LIMIT)
