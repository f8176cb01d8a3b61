"""Wide-window matches that are accepted only when unambiguous, and the query scans they match.

The loop closures' test (`LaserSlam2D._verify_loop`): the branch-and-bound optimum is kept only when no
pose at least `ambiguity_distance` away scores `ambiguity_ratio` of it, and when point-to-line ICP from it
pairs most points closely. Global localization in a saved map asks the same question over the whole map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontends.slam2d.config import LoopClosureConfig, MatchingConfig
from frontends.slam2d.correlative import (
    SearchWindow,
    branch_and_bound_levels,
    match_exhaustive,
    prepare_branch_and_bound,
)
from frontends.slam2d.grid import LikelihoodGrid, build_likelihood_grid
from frontends.slam2d.icp import IcpResult, refine_point_to_line
from frontends.slam2d.local_map import Submap, one_per_cell, place
from optimizer import se2

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class VerifiedMatch:
    pose: FloatArray
    """(x, y, θ) of the query's frame in the submap's frame, after ICP."""
    score: float
    """Branch-and-bound score of the coarse optimum (mean likelihood, in [0, 1])."""
    icp: IcpResult


def match_unambiguous(
    query: FloatArray,
    submap: Submap,
    center: FloatArray,
    window: SearchWindow,
    *,
    matching: MatchingConfig,
    acceptance: LoopClosureConfig,
    levels: int,
    search_grid: LikelihoodGrid | None = None,
    crop_pyramid: bool = False,
) -> VerifiedMatch | None:
    """The pose of `query` (points in its own frame) in `submap` within `window` around `center`, or None
    when it scores below `acceptance.min_score`, has a distinct rival, or fails the ICP verification.

    `search_grid` (default: the submap's) is the grid the branch and bound searches: a coarser one makes
    a whole-map search affordable, ICP on the submap's points then brings the pose to its resolution."""
    grid = submap.grid if search_grid is None else search_grid
    # Both searches place the same points in the same window: the second reuses the first's cells,
    # pyramid and coarsest scores.
    search = prepare_branch_and_bound(query, grid, center, window, levels=levels, crop_pyramid=crop_pyramid)
    coarse = search.best(acceptance.min_score)
    if coarse is None:
        return None
    rival = search.best(acceptance.ambiguity_ratio * coarse.score,
                        exclude=(coarse.pose[:2], acceptance.ambiguity_distance))
    if rival is not None:
        return None
    refined = refine_point_to_line(
        query,
        submap.grid,
        submap.points,
        submap.normals,
        coarse.pose,
        max_distance=matching.icp_max_distance,
        sigma=matching.point_sigma,
    )
    if refined.inlier_fraction < acceptance.min_inlier_fraction or refined.rms > acceptance.max_rms:
        return None
    return VerifiedMatch(refined.pose, coarse.score, refined)


COARSENING = 2.0
"""`match_beyond` searches on cells at least this many times the submap's: a window barely wider than the
fine one is not searched again at nearly its resolution (ACES: 21 searches of ±10.0–10.2 m on 5.0 cm cells
took 0.8 s, on 10 cm cells 0.3 s, none finding a match either way)."""


def match_beyond(
    query: FloatArray,
    submap: Submap,
    center: FloatArray,
    fine_window: SearchWindow,
    radius: float,
    *,
    matching: MatchingConfig,
    acceptance: LoopClosureConfig,
    cells: int,
    min_levels: int,
) -> VerifiedMatch | None:
    """`match_unambiguous` within ± `radius` around `center`, for a match beyond `fine_window` (the window
    a search on the submap's own grid covers), or None.

    The window is searched on a grid coarse enough to hold ± `radius` in `cells` cells (`COARSENING` times
    the submap's at least; σ at least a cell; at least `min_levels` branch-and-bound levels), as the global
    localization searches a whole map; ICP on the submap refines the match. It is kept only outside
    `fine_window`, where the fine search is the judge (it found that pose below `min_score`, or with a
    rival a coarse cell blurs: on the Freiburg clinic log a corridor 5.6 m along), and where the submap's
    own grid scores it at `min_score` within a cell and an angular step, as a fine search would have (a
    coarse cell's likelihood is wide: there, look-alike corridors 23 m apart scored 0.57–0.61 on it and
    0.39–0.43 on the submap's)."""
    resolution = max(radius / cells, COARSENING * submap.grid.resolution)
    spread = max(matching.likelihood_sigma, resolution)
    # Only the points' own neighbourhood: the search reads nothing beyond the grid, as it reads zeros.
    coarse = build_likelihood_grid(submap.points, resolution, spread, 3.0 * spread + resolution)
    window = SearchWindow(radius, fine_window.angular, fine_window.angular_step)
    levels = branch_and_bound_levels(radius, resolution, minimum=min_levels)
    verified = match_unambiguous(query, submap, center, window, matching=matching, acceptance=acceptance,
                                 levels=levels, search_grid=coarse, crop_pyramid=True)
    if verified is None or fine_window.holds(verified.icp.pose, center, submap.grid.resolution):
        return None
    around = SearchWindow(submap.grid.resolution, window.angular_step, window.angular_step)
    if match_exhaustive(query, submap.grid, verified.icp.pose, around).score < acceptance.min_score:
        return None
    return verified


def thinned_query(scans: Sequence[FloatArray], poses: Sequence[FloatArray], frame: FloatArray,
                  thinning: float) -> FloatArray:
    """Scans (each in its own frame, at `poses`) seen from `frame`, thinned to one point per cell of
    `thinning` metres: a few metres of context rarely match the wrong place, one scan often does."""
    points = np.concatenate([place(s, se2.relative(frame, p)) for s, p in zip(scans, poses, strict=True)])
    return np.ascontiguousarray(points[one_per_cell(points, thinning)])
