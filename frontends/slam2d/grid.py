"""Likelihood grids for correlative scan matching (Olson 2009), and their max-pooled pyramids.

A likelihood grid holds, per cell, how likely a laser return is to land there given a set of reference
points: exp(−d²/2σ²) with d the distance to the nearest reference point, stamped around every point
(not a distance transform over the whole grid: scans reach 50 m, and the cells near points are all we
read). `max_pyramid` gives, for each level h, the max over the 2^h × 2^h cells starting at each cell,
which bounds the score of every translation inside a coarse cell (the branch-and-bound of Hess et al.
2016).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.errors import MapExtentError

FloatArray = NDArray[np.float64]
Window = tuple[int, int, int, int]

MAX_LIKELIHOOD_CELLS = 40_000_000
"""A likelihood grid takes 8 bytes a cell (values, pairing): this bounds one at ~0.3 GB. Local maps and
loop-closure submaps cover tens of metres (≤ 1 M cells at 5 cm); only absurd poses or settings reach this."""
STAMP_WIDTH = 16
"""Stamps up to this many cells wide run a loop of this fixed count per row (`_stamp`)."""


@dataclass(frozen=True, eq=False)
class LikelihoodGrid:
    """values[iy, ix] is the likelihood at the centre of cell (ix, iy); cell (0, 0) starts at `origin`.

    pairing[iy, ix] is 1 + the index of the reference point nearest the cell's centre within the stamping
    radius (0 where none), the pairing ICP uses instead of a KD-tree query. Offset by one, a fresh grid is
    zeros the allocator hands over untouched, where −1 everywhere cost a write of every cell (UAL: 0.06 s).
    """

    origin: FloatArray
    resolution: float
    values: NDArray[np.float32]
    pairing: NDArray[np.int32]
    stamped_window: Window | None = None
    """(row start, row stop, column start, column stop): a window holding every cell a point was stamped in,
    beyond which the grid reads zeros as past its edges (None: not known, the whole grid)."""
    _pyramids: dict[tuple[int, Window], list[NDArray[np.float32]]] = field(default_factory=dict, repr=False)

    def pyramid(self, levels: int, window: Window | None = None) -> list[NDArray[np.float32]]:
        """`max_pyramid` of the values, or of the cells `window` = (row start, row stop, column start,
        column stop) of them; built once per grid and window: every scan matched against a local map, and
        both searches of a loop-closure verification, share it (grids are not modified once built)."""
        height, width = self.values.shape
        window = window or (0, height, 0, width)
        for (built, built_window), pyramid in self._pyramids.items():
            if built >= levels and built_window == window:
                return pyramid[: levels + 1]
        top, bottom, left, right = window
        values = self.values if window == (0, height, 0, width) else self.values[top:bottom, left:right]
        pyramid = max_pyramid(np.ascontiguousarray(values), levels)
        self._pyramids[(levels, window)] = pyramid
        return pyramid

    @property
    def nearest(self) -> NDArray[np.int32]:
        """The index of the reference point nearest each cell's centre (−1 where none): `pairing` − 1."""
        return self.pairing - 1

    def cell_of(self, xy: FloatArray) -> NDArray[np.int64]:
        return np.floor((np.asarray(xy) - self.origin) / self.resolution).astype(np.int64)


def build_likelihood_grid(
    points: FloatArray, resolution: float, sigma: float, margin: float, pairing_distance: float = 0.0
) -> LikelihoodGrid:
    """A grid covering `points` plus `margin` on every side, each point stamped with a Gaussian of σ and
    its index within max(3σ, `pairing_distance`)."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    # numpy's reductions along axis 0 of an (N, 2) array cost ~0.1 ms each, as much as a tenth of the stamping
    points_low, points_high = _bounds(points) if len(points) else (points.min(axis=0), points.max(axis=0))
    low = points_low - margin
    high = points_high + margin
    cells = np.ceil((high - low) / resolution) + 1
    if not np.all(np.isfinite(cells)) or float(cells[0]) * float(cells[1]) > MAX_LIKELIHOOD_CELLS:
        raise MapExtentError(
            f"a likelihood grid of {(high - low)[0]:.4g} × {(high - low)[1]:.4g} m at {resolution} m "
            f"would need more than {MAX_LIKELIHOOD_CELLS} cells"
        )
    shape = cells.astype(np.int64)
    # Zeroed by the allocator (pages untouched by a stamp stay free); `values` holds squared distances
    # while the points are stamped, then the Gaussian of them.
    values = np.zeros((int(shape[1]), int(shape[0])), dtype=np.float32)
    pairing = np.zeros(values.shape, dtype=np.int32)
    radius = _stamp_radius(sigma, pairing_distance, resolution)
    _stamp(points, low, resolution, sigma, radius, values, pairing)
    stamped = _stamped(points_low, points_high, low, resolution, radius, values.shape)
    return LikelihoodGrid(low, resolution, values, pairing, stamped)


def _stamped(low: FloatArray, high: FloatArray, origin: FloatArray, resolution: float, radius: int,
             shape: tuple[int, ...]) -> Window | None:
    """The window of the cells that stamps reach (`radius` cells around each point's) from points within
    the box `low`–`high` (m), within a grid of `shape` = (rows, columns); None where the box is not
    finite."""
    x0, y0, x1, y1 = float(low[0]), float(low[1]), float(high[0]), float(high[1])
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        return None
    # A cell more on each side than the stamps reach: the cells are rounded here as in the stamping.
    left = max(math.floor((x0 - origin[0]) / resolution) - radius - 1, 0)
    top = max(math.floor((y0 - origin[1]) / resolution) - radius - 1, 0)
    right = min(math.floor((x1 - origin[0]) / resolution) + radius + 2, shape[1])
    bottom = min(math.floor((y1 - origin[1]) / resolution) + radius + 2, shape[0])
    return (top, bottom, left, right) if top < bottom and left < right else (0, 0, 0, 0)


@njit(cache=True, nogil=True)
def _bounds(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Column minima and maxima of (N ≥ 1, 2) points, NaN when a column holds one (as numpy's)."""
    low = points[0].copy()
    high = points[0].copy()
    for i in range(1, points.shape[0]):
        for axis in range(2):
            value = points[i, axis]
            if value != value:
                low[axis] = value
                high[axis] = value
            elif value < low[axis]:
                low[axis] = value
            elif value > high[axis]:
                high[axis] = value
    return low, high


@njit(cache=True, nogil=True)
def _stamp(
    points: FloatArray,
    origin: FloatArray,
    resolution: float,
    sigma: float,
    radius: int,
    values: NDArray[np.float32],
    pairing: NDArray[np.int32],
) -> None:
    """Stamp every point within `radius` cells: each cell gets its nearest point (the first one on a tie;
    1 + its index in `pairing`) and the Gaussian of the distance to it. Points along a wall stamp the same
    cells dozens of times; the Gaussian is evaluated once per cell afterwards, over the columns the stamps
    reached in each row.

    A stamp's rows are short (13 cells at the default settings): looping over a variable count of them
    costs the vectorized loop's set-up and its scalar tail on every row. Stamps up to `STAMP_WIDTH` cells
    wide away from the grid's right edge run a loop of that fixed count instead, the columns past the
    stamp given an infinite distance, which no cell takes (16 % less time on CSAIL's local maps)."""
    height, width = values.shape
    inverse_two_sigma2 = 1.0 / (2.0 * sigma * sigma)
    row_start = np.full(height, width, dtype=np.int64)
    row_stop = np.zeros(height, dtype=np.int64)
    dx_squared = np.empty(max(2 * radius + 1, STAMP_WIDTH))
    # Each point's position in cells, kept for the Gaussian pass (the same values, not divided again).
    cells_x = np.empty(points.shape[0])
    cells_y = np.empty(points.shape[0])
    for k in range(points.shape[0]):
        fx = (points[k, 0] - origin[0]) / resolution
        fy = (points[k, 1] - origin[1]) / resolution
        cells_x[k] = fx
        cells_y[k] = fy
        cx = int(math.floor(fx))
        cy = int(math.floor(fy))
        low_x = max(cx - radius, 0)
        columns = min(cx + radius + 1, width) - low_x
        for j in range(columns):
            dx = (low_x + j + 0.5 - fx) * resolution
            dx_squared[j] = dx * dx
        fixed_width = 2 * radius + 1 <= STAMP_WIDTH and low_x + STAMP_WIDTH <= width
        if fixed_width:
            dx_squared[columns:STAMP_WIDTH] = np.inf
        for iy in range(max(cy - radius, 0), min(cy + radius + 1, height)):
            dy = (iy + 0.5 - fy) * resolution
            dy_squared = dy * dy
            row_start[iy] = min(row_start[iy], low_x)
            row_stop[iy] = max(row_stop[iy], low_x + columns)
            value_row = values[iy]
            pairing_row = pairing[iy]
            # Selects, not branches: the compiler vectorizes the row.
            if fixed_width:
                for j in range(STAMP_WIDTH):
                    squared = dx_squared[j] + dy_squared
                    old_value = value_row[low_x + j]
                    old_pairing = pairing_row[low_x + j]
                    closer = (squared < np.inf) & ((old_pairing == 0) | (squared < old_value))
                    value_row[low_x + j] = np.float32(squared) if closer else old_value
                    pairing_row[low_x + j] = k + 1 if closer else old_pairing
            else:
                for j in range(columns):
                    squared = dx_squared[j] + dy_squared
                    old_value = value_row[low_x + j]
                    old_pairing = pairing_row[low_x + j]
                    closer = (old_pairing == 0) | (squared < old_value)
                    value_row[low_x + j] = np.float32(squared) if closer else old_value
                    pairing_row[low_x + j] = k + 1 if closer else old_pairing
    for iy in range(height):
        for ix in range(row_start[iy], row_stop[iy]):
            k = pairing[iy, ix] - 1
            if k >= 0:
                # The same arithmetic as above: the value the winning point's own distance gives.
                dy = (iy + 0.5 - cells_y[k]) * resolution
                dx = (ix + 0.5 - cells_x[k]) * resolution
                values[iy, ix] = math.exp(-(dx * dx + dy * dy) * inverse_two_sigma2)


def _stamp_radius(sigma: float, pairing_distance: float, resolution: float) -> int:
    """How many cells around its own a point stamps: max(3σ, `pairing_distance`), at least one."""
    return max(1, math.ceil(max(3.0 * sigma, pairing_distance) / resolution))


def stamp_more(grid: LikelihoodGrid, points: FloatArray, first_new: int, sigma: float,
               pairing_distance: float = 0.0) -> LikelihoodGrid:
    """`grid`, built by `build_likelihood_grid` from `points[:first_new]` with the same `sigma` and
    `pairing_distance`, with `points[first_new:]` stamped too: each cell they reach takes the nearest of its
    old and new points (the old one on a tie), as a grid built from all of them would. The arrays are
    changed in place and returned in a new grid (its pyramids are those of the new values): `grid` must
    not be used again. Points are stamped where they fall inside the grid only."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    radius = _stamp_radius(sigma, pairing_distance, grid.resolution)
    _stamp_more(points, first_new, grid.origin, grid.resolution, sigma, radius, grid.values, grid.pairing)
    # A local map grown in place is never cropped (`crop_pyramid`): its stamped window is not kept.
    return LikelihoodGrid(grid.origin, grid.resolution, grid.values, grid.pairing)


@njit(cache=True, nogil=True)
def _stamp_more(
    points: FloatArray,
    first_new: int,
    origin: FloatArray,
    resolution: float,
    sigma: float,
    radius: int,
    values: NDArray[np.float32],
    pairing: NDArray[np.int32],
) -> None:
    """`_stamp` of points[first_new:] onto cells holding the Gaussian of their nearest old point: the
    old point's squared distance is computed again, with `_stamp`'s arithmetic, where a new point
    competes; cells a new point wins take its index and Gaussian."""
    height, width = values.shape
    inverse_two_sigma2 = 1.0 / (2.0 * sigma * sigma)
    # Every point's position in cells, divided once (the old ones are read wherever a new point competes).
    cells_x = (points[:, 0] - origin[0]) / resolution
    cells_y = (points[:, 1] - origin[1]) / resolution
    for k in range(first_new, points.shape[0]):
        fx = cells_x[k]
        fy = cells_y[k]
        cx = int(math.floor(fx))
        cy = int(math.floor(fy))
        for iy in range(max(cy - radius, 0), min(cy + radius + 1, height)):
            dy = (iy + 0.5 - fy) * resolution
            for ix in range(max(cx - radius, 0), min(cx + radius + 1, width)):
                dx = (ix + 0.5 - fx) * resolution
                squared = dx * dx + dy * dy
                old = pairing[iy, ix] - 1
                if old >= 0:
                    old_dx = (ix + 0.5 - cells_x[old]) * resolution
                    old_dy = (iy + 0.5 - cells_y[old]) * resolution
                    if not squared < np.float32(old_dx * old_dx + old_dy * old_dy):
                        continue
                pairing[iy, ix] = k + 1
                values[iy, ix] = math.exp(-squared * inverse_two_sigma2)


def max_pyramid(values: NDArray[np.float32], levels: int) -> list[NDArray[np.float32]]:
    """[values, M1, M2, …]: M_h[y, x] = max of values[y : y + 2^h, x : x + 2^h] (0 past the edge)."""
    return [values, *_coarse_levels(values, levels)] if levels > 0 else [values]


@njit(cache=True, nogil=True)
def _coarse_levels(values: NDArray[np.float32], levels: int) -> list[NDArray[np.float32]]:
    pyramid = []
    finer = values
    for level in range(1, levels + 1):
        finer = _doubled_max(finer, 1 << (level - 1))
        pyramid.append(finer)
    return pyramid


@njit(cache=True, nogil=True)
def _doubled_max(values: NDArray[np.float32], shift: int) -> NDArray[np.float32]:
    """max of values[y : y + 2·shift, x : x + 2·shift] from values holding the max over shift × shift;
    branch-free inner loops (the compiler vectorizes them), edges copied."""
    height, width = values.shape
    along_x = np.empty_like(values)
    inner_width = max(width - shift, 0)
    for y in range(height):
        for x in range(inner_width):
            along_x[y, x] = max(values[y, x], values[y, x + shift])
        for x in range(inner_width, width):
            along_x[y, x] = values[y, x]
    out = np.empty_like(values)
    for y in range(max(height - shift, 0)):
        for x in range(width):
            out[y, x] = max(along_x[y, x], along_x[y + shift, x])
    for y in range(max(height - shift, 0), height):
        for x in range(width):
            out[y, x] = along_x[y, x]
    return out
