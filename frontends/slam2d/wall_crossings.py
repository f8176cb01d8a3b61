"""Whether a run localized in a saved 2D map drives through the map's walls: the sign of a log placed in
the map of another place, which the saved map matched along one stretch only.

A robot's path never crosses a wall it saw; a run placed by a look-alike corridor, and tracked on its own
scans from there, crosses the saved map's walls wherever its own corridors run. The check needs nothing but
the placed positions and the saved map's occupancy grid, so it also holds where the run matched the map
throughout the few scans that lie on the mapping robot's own path (`frontends.protocol.OFF_MAP_ON_PATH`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from frontends.errors import LogWarning
from frontends.protocol import FloatArray
from frontends.slam2d.occupancy import OccupancyGrid

MIN_WALL_CROSSINGS = 10
MAX_CROSSINGS_PER_METRE = 0.1
"""A placed run is suspect when it crosses the saved map's walls at least `MIN_WALL_CROSSINGS` times and
more than once per 10 m of its path over the mapped place. Correct localizations crossed them 0–4 times,
at most 0.034 per metre (each shared log and FR079 and Intel in its own map 0–1; the lidar-only second
halves of ACES, CSAIL, FR079 and Intel in their first halves' maps 0–4, ACES's 4 over 116 m in a half map
0.9 m from the full run's); logs placed in another building's map 14–28 times, 0.38–0.61 per metre (ACES in
CSAIL's map, Intel in ACES's, CSAIL in the mumble loop's: the last matched the map on all of its 39
scans on the mapping robot's path)."""
MAX_STEP = 1.0
"""Steps longer than this (m) between consecutive placed scans are not a path: a global fix or a
re-acquisition moved the run there."""


@dataclass(frozen=True)
class WallCrossings:
    crossings: int
    """How many times the path entered an occupied cell of the map (a run of steps through walls is one)."""
    path_over_map: float
    """The length (m) of the steps that pass over cells the map knows (free or occupied)."""

    @property
    def suspect(self) -> bool:
        return (self.crossings >= MIN_WALL_CROSSINGS
                and self.crossings > MAX_CROSSINGS_PER_METRE * self.path_over_map)


def wall_crossings(positions: FloatArray, grid: OccupancyGrid) -> WallCrossings:
    """The wall crossings of the path through `positions` (S, 2, in order; rows with NaN are left out) on
    `grid`, each step sampled every half cell."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    positions = positions[np.all(np.isfinite(positions), axis=1)]
    steps = np.diff(positions, axis=0)
    lengths = np.hypot(steps[:, 0], steps[:, 1])
    walked = np.flatnonzero(lengths <= MAX_STEP)
    if len(walked) == 0:
        return WallCrossings(0, 0.0)
    samples = np.ceil(lengths[walked] / (0.5 * grid.resolution)).astype(np.int64) + 1
    step_of_sample = np.repeat(np.arange(len(walked)), samples)
    first_sample = np.cumsum(samples) - samples
    fraction = (np.arange(len(step_of_sample)) - first_sample[step_of_sample]) / (samples - 1)[step_of_sample]
    points = positions[walked][step_of_sample] + fraction[:, None] * steps[walked][step_of_sample]
    cells = np.floor((points - grid.origin) / grid.resolution).astype(np.int64)
    height, width = grid.log_odds.shape
    inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < width) & (cells[:, 1] < height)
    occupied, known = np.zeros(len(points), dtype=bool), np.zeros(len(points), dtype=bool)
    ix, iy = cells[inside, 0], cells[inside, 1]
    occupied[inside] = grid.occupied_cells()[iy, ix]
    known[inside] = occupied[inside] | grid.free_cells()[iy, ix]
    through_wall = np.zeros(len(walked), dtype=bool)
    through_wall[step_of_sample[occupied]] = True
    over_map = np.zeros(len(walked), dtype=bool)
    over_map[step_of_sample[known]] = True
    # Consecutive steps through walls are one crossing (a step that was not walked breaks the run).
    consecutive = np.concatenate([[False], np.diff(walked) == 1])
    entered = through_wall & ~(consecutive & np.concatenate([[False], through_wall[:-1]]))
    return WallCrossings(int(entered.sum()), float(lengths[walked][over_map].sum()))


def checked_wall_crossings(log_path: object, what: str, positions: FloatArray,
                           grid: OccupancyGrid) -> WallCrossings:
    """`wall_crossings`, with a `LogWarning` naming `log_path` when the run is suspect."""
    found = wall_crossings(positions, grid)
    if found.suspect:
        warnings.warn(f"{log_path}: the {what} placed in the saved map cross its walls {found.crossings} "
                      f"times over {found.path_over_map:.0f} m of the mapped place: the log may be of "
                      "another place than the map, or the place changed (see the recording)", LogWarning,
                      stacklevel=3)
    return found
