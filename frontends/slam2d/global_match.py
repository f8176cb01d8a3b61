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
from frontends.slam2d.correlative import SearchWindow, prepare_branch_and_bound
from frontends.slam2d.grid import LikelihoodGrid
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


def thinned_query(scans: Sequence[FloatArray], poses: Sequence[FloatArray], frame: FloatArray,
                  thinning: float) -> FloatArray:
    """Scans (each in its own frame, at `poses`) seen from `frame`, thinned to one point per cell of
    `thinning` metres: a few metres of context rarely match the wrong place, one scan often does."""
    points = np.concatenate([place(s, se2.relative(frame, p)) for s, p in zip(scans, poses, strict=True)])
    return np.ascontiguousarray(points[one_per_cell(points, thinning)])
