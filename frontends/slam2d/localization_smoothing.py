"""Offline smoothing of a localized run: a log replay knows the whole run before it writes the trajectory.

Online, a scan the saved map cannot place is tracked on the rolling local map (or predicted by odometry)
and drifts; the first map match after such a stretch corrects the pose at once, and the jump stays in the
trajectory. Offline the drift can be spread back over the stretch, as an offline localizer would: a small
pose graph whose pose 0 is the map's origin (held fixed), one pose per localized scan, consecutive scans
tied by the motion measured locally between them (`LocalizedScan.motion`: odometry, or the rolling map's
match), map-matched scans tied to the origin by their map pose with the information the map's match alone
gave (`LocalizedScan.map_information`), solved by the project's Gauss–Newton polish.

The map pose of an anchor is the online pose, the map's match fused with the prediction (the match alone is
not kept): in a corridor the map constrains nothing along, the prediction's share stays in it, and the
anchor's information says the map does not hold it there, so the chain decides.

The tracked scans' motions are not weighed by the rolling map's match: it tells how well the scan sits on the
recent scans, which were placed by the tracking itself, so consecutive tracked poses share the rolling map's
error and their motion is far better known than either pose (weighed as independent steps, the chain bent:
0.2° of heading noise per step where the synthetic tracks drift 0.03–0.11°, and a track that barely drifted
came out worse). The run measures the drift itself: at each re-entry (the first map match after a stretch
tracked from a map match) the map's match shows how far the track drifted over the stretch's steps. A random
walk of variance q per step in x, y and heading drifts by a variance N q over N steps (per step, not per
metre: each scan's match error stays in the rolling map the next is matched on, and a robot standing still
needs no floor), so the pooled estimate q = Σ J² / Σ N over the re-entries' jumps J gives every tracked step
of the run the information 1 / q (the jump holds the map match's own error too: the drift is rather
overestimated, the chain kept loose enough to follow the map). A run without such a re-entry keeps the match's
information.

A stretch of scans with no map match at either end (never placed by the map) has nothing to be pulled
towards and keeps its online poses, as do scans placed by a global fix's recovery (no local motion kept).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontends.protocol import FloatArray
from frontends.slam2d.localization import LocalizedScan
from optimizer import se2
from optimizer.graph import PoseGraph
from optimizer.solve import optimize

__all__ = ["SmoothedTrajectory", "smooth_localized", "smooth_scans", "tracking_drift"]

BoolArray = NDArray[np.bool_]

CONDITION_FLOOR = 1e-9
"""An information's eigenvalues are raised to this share of its largest: a map match along a corridor
constrains nothing along it (a zero eigenvalue), which the graph's check of positive definiteness refuses;
at this share the direction weighs nothing against the chain."""


@dataclass(frozen=True, eq=False)
class SmoothedTrajectory:
    poses: FloatArray
    """(S, 3) every scan's pose: smoothed where `smoothed`, else the online one (NaN where none)."""
    smoothed: BoolArray
    """The scans whose pose the smoothing gave (in a stretch tied to at least one map match)."""
    converged: bool
    """The Gauss–Newton polish met its convergence test (if not, `poses` are the online ones and
    `smoothed` is all False: an unconverged result is not given as the smoothed trajectory)."""


def _conditioned(information: FloatArray) -> FloatArray:
    """(M, 3, 3) symmetric informations with their eigenvalues floored (see `CONDITION_FLOOR`)."""
    symmetric = 0.5 * (information + np.swapaxes(information, 1, 2))
    values, vectors = np.linalg.eigh(symmetric)
    values = np.maximum(values, CONDITION_FLOOR * values[:, -1:])
    return np.einsum("mij,mj,mkj->mik", vectors, values, vectors)


def tracking_drift(poses: FloatArray, linked: BoolArray, tracked: BoolArray, anchored: BoolArray,
                   motions: FloatArray) -> FloatArray | None:
    """(3,) the tracking's drift per tracked step, the variance of x, y and heading (see the module
    docstring), pooled over the re-entries: a run of tracked scans linked to a map match before it and
    to one after it; None without any re-entry (or with jumps of exactly zero: nothing measured)."""
    before = np.concatenate([[False], tracked[:-1]])
    after = np.concatenate([tracked[1:], [False]])
    first = np.flatnonzero(tracked & ~before)
    reentry = np.flatnonzero(tracked & ~after) + 1  # the scan after each run of tracked scans
    unlinked = np.cumsum(~linked)
    measured = (first > 0) & (reentry < len(tracked))
    first, reentry = first[measured], reentry[measured]
    measured = (anchored[first - 1] & anchored[reentry]
                & (unlinked[reentry] == unlinked[first - 1]))  # every step from the map match linked
    first, reentry = first[measured], reentry[measured]
    steps = int(np.sum(reentry + 1 - first))
    if steps == 0:
        return None
    jumps = poses[reentry] - se2.compose(poses[reentry - 1], motions[reentry])
    jumps[:, 2] = se2.wrap_angle(jumps[:, 2])
    squares = np.sum(jumps**2, axis=0)
    linear = 0.5 * (squares[0] + squares[1]) / steps
    angular = squares[2] / steps
    if linear <= 0.0 or angular <= 0.0:
        return None
    return np.array([linear, linear, angular])


def smooth_localized(poses: FloatArray, localized: BoolArray, motions: FloatArray,
                     motion_information: FloatArray, map_information: FloatArray,
                     tracked: BoolArray) -> SmoothedTrajectory:
    """The scans' poses smoothed between map matches (see the module docstring).

    `poses` (S, 3) the online map-frame poses; `localized` (S,) which of them were given when processed;
    `motions` (S, 3) each scan's locally measured motion from the previous scan (NaN: none);
    `motion_information` (S, 3, 3) its information in the previous pose's frame; `map_information`
    (S, 3, 3) the map match's own information on the pose (zeros: not map-matched); `tracked` (S,) the
    scans tracked on the rolling local map (their motions get the run's measured drift, when it has one)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    count = len(poses)
    localized = np.asarray(localized, dtype=bool) & np.all(np.isfinite(poses), axis=1)
    linked = np.zeros(count, dtype=bool)
    linked[1:] = localized[1:] & localized[:-1] & np.all(np.isfinite(motions[1:]), axis=1)
    largest = np.linalg.eigvalsh(0.5 * (map_information + np.swapaxes(map_information, 1, 2)))[:, -1]
    anchored = localized & (largest > 0.0)
    tracked = np.asarray(tracked, dtype=bool) & localized & ~anchored
    drift = tracking_drift(poses, linked, tracked, anchored, motions)
    if drift is not None:
        motion_information = np.array(motion_information, dtype=np.float64)
        motion_information[tracked] = np.diag(1.0 / drift)
    # Chains: runs of localized scans each linked to the one before; only those with an anchor are solved.
    chain = np.cumsum(localized & ~linked)
    kept_chains = np.unique(chain[anchored])
    kept = localized & np.isin(chain, kept_chains)
    unchanged = SmoothedTrajectory(poses.copy(), np.zeros(count, dtype=bool), True)
    if not kept.any():
        return unchanged
    node = np.full(count, -1, dtype=np.int64)
    node[kept] = np.arange(1, int(kept.sum()) + 1)
    links = np.flatnonzero(kept & linked)
    anchors = np.flatnonzero(kept & anchored)
    edge_from = np.concatenate([node[links - 1], np.zeros(len(anchors), dtype=np.int64)])
    edge_to = np.concatenate([node[links], node[anchors]])
    measurements = np.concatenate([motions[links], poses[anchors]])
    information = _conditioned(np.concatenate([motion_information[links], map_information[anchors]]))
    start = np.vstack([np.zeros((1, 3)), poses[kept]])
    graph = PoseGraph.build(np.arange(len(start)), start, edge_from, edge_to, measurements, information)
    run = optimize(graph, method="gn", starts={"online": start})
    for _ in run:
        pass
    result = run.result
    if not result.converged:
        return SmoothedTrajectory(poses.copy(), np.zeros(count, dtype=bool), False)
    smoothed = poses.copy()
    smoothed[kept] = result.poses[1:]
    return SmoothedTrajectory(smoothed, kept, True)


def smooth_scans(scans: Sequence[LocalizedScan], poses: FloatArray | None = None) -> SmoothedTrajectory:
    """`smooth_localized` of a run's `LocalizedScan`s, in log order; `poses` (default: theirs) may hold the
    poses a global fix recovered for scans not localized when processed (kept as they are)."""
    online = np.array([s.pose for s in scans]) if poses is None else np.asarray(poses, dtype=np.float64)
    return smooth_localized(online.reshape(-1, 3), np.array([s.localized for s in scans], dtype=bool),
                            np.array([s.motion for s in scans]).reshape(-1, 3),
                            np.array([s.motion_information for s in scans]).reshape(-1, 3, 3),
                            np.array([s.map_information for s in scans]).reshape(-1, 3, 3),
                            np.array([s.tracked for s in scans], dtype=bool))
