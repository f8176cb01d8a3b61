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
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.errors import MapExtentError

FloatArray = NDArray[np.float64]

MAX_LIKELIHOOD_CELLS = 40_000_000
"""A likelihood grid takes 12 bytes a cell while it is built (values, nearest, best distance): this
bounds one at ~0.5 GB. Local maps and loop-closure submaps cover tens of metres (≤ 1 M cells at 5 cm);
only absurd poses or settings reach this."""


@dataclass(frozen=True, eq=False)
class LikelihoodGrid:
    """values[iy, ix] is the likelihood at the centre of cell (ix, iy); cell (0, 0) starts at `origin`.

    nearest[iy, ix] is the index of the reference point nearest the cell's centre within the stamping
    radius (−1 where none), the pairing ICP uses instead of a KD-tree query.
    """

    origin: FloatArray
    resolution: float
    values: NDArray[np.float32]
    nearest: NDArray[np.int32]

    def cell_of(self, xy: FloatArray) -> NDArray[np.int64]:
        return np.floor((np.asarray(xy) - self.origin) / self.resolution).astype(np.int64)


def build_likelihood_grid(
    points: FloatArray, resolution: float, sigma: float, margin: float, pairing_distance: float = 0.0
) -> LikelihoodGrid:
    """A grid covering `points` plus `margin` on every side, each point stamped with a Gaussian of σ and
    its index within max(3σ, `pairing_distance`)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    low = points.min(axis=0) - margin
    high = points.max(axis=0) + margin
    cells = np.ceil((high - low) / resolution) + 1
    if not np.all(np.isfinite(cells)) or float(cells[0]) * float(cells[1]) > MAX_LIKELIHOOD_CELLS:
        raise MapExtentError(
            f"a likelihood grid of {(high - low)[0]:.4g} × {(high - low)[1]:.4g} m at {resolution} m "
            f"would need more than {MAX_LIKELIHOOD_CELLS} cells"
        )
    shape = cells.astype(np.int64)
    values = np.zeros((int(shape[1]), int(shape[0])), dtype=np.float32)
    nearest = np.full(values.shape, -1, dtype=np.int32)
    radius_cells = max(1, math.ceil(max(3.0 * sigma, pairing_distance) / resolution))
    _stamp(points, low, resolution, sigma, radius_cells, values, nearest)
    return LikelihoodGrid(low, resolution, values, nearest)


@njit(cache=True)
def _stamp(
    points: FloatArray,
    origin: FloatArray,
    resolution: float,
    sigma: float,
    radius: int,
    values: NDArray[np.float32],
    nearest: NDArray[np.int32],
) -> None:
    height, width = values.shape
    inverse_two_sigma2 = 1.0 / (2.0 * sigma * sigma)
    best = np.full(values.shape, np.inf, dtype=np.float32)
    for k in range(points.shape[0]):
        fx = (points[k, 0] - origin[0]) / resolution
        fy = (points[k, 1] - origin[1]) / resolution
        cx = int(math.floor(fx))
        cy = int(math.floor(fy))
        for iy in range(max(cy - radius, 0), min(cy + radius + 1, height)):
            dy = (iy + 0.5 - fy) * resolution
            for ix in range(max(cx - radius, 0), min(cx + radius + 1, width)):
                dx = (ix + 0.5 - fx) * resolution
                squared = dx * dx + dy * dy
                if squared < best[iy, ix]:
                    best[iy, ix] = squared
                    nearest[iy, ix] = k
                    values[iy, ix] = math.exp(-squared * inverse_two_sigma2)


def max_pyramid(values: NDArray[np.float32], levels: int) -> list[NDArray[np.float32]]:
    """[values, M1, M2, …]: M_h[y, x] = max of values[y : y + 2^h, x : x + 2^h] (0 past the edge)."""
    pyramid = [values]
    for level in range(1, levels + 1):
        pyramid.append(_doubled_max(pyramid[-1], 1 << (level - 1)))
    return pyramid


@njit(cache=True)
def _doubled_max(values: NDArray[np.float32], shift: int) -> NDArray[np.float32]:
    height, width = values.shape
    along_x = np.zeros_like(values)
    for y in range(height):
        for x in range(width):
            v = values[y, x]
            if x + shift < width and values[y, x + shift] > v:
                v = values[y, x + shift]
            along_x[y, x] = v
    out = np.zeros_like(values)
    for y in range(height):
        for x in range(width):
            v = along_x[y, x]
            if y + shift < height and along_x[y + shift, x] > v:
                v = along_x[y + shift, x]
            out[y, x] = v
    return out
