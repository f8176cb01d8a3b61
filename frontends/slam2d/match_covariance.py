"""How far a scan match could slide: the plateau of the correlative score around it (after Olson 2009,
"Real-time correlative scan matching", which reads a match's covariance off the score surface).

The ICP Hessian says how sharply the paired points pin a pose *at* the match; in a corridor a door frame
or a few clutter points make it look sharp along the corridor, while the score, the fit of the whole scan
on the map, barely changes over a metre there. `score_plateau` samples the score over translations
around the match (at its heading) and returns the spread of the ones scoring within `PLATEAU_RATIO` of the
best: a few centimetres where the scan pins the pose, the length of the look-alike stretch where it does
not. `slide_to_prior` then lets the prediction (wheel odometry) decide the pose along such a stretch, when
the prediction lies on the plateau itself, and widens the match's covariance by the plateau, so neither
the scan's estimate nor the keyframe graph trusts a match along the direction it cannot measure.

Along a wall that bends as an arc the direction a scan cannot measure is a shift that turns (a rotation
about the arc's centre): at a fixed heading its score is sharp. Where the match's own information says so
(`heading_coupling`), the plateau is sampled along that coupled direction, and the slide moves and widens
the heading with the shift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.slam2d.grid import LikelihoodGrid

FloatArray = NDArray[np.float64]

PLATEAU_RATIO = 0.9
"""Translations scoring at least this share of the best belong to the plateau: the loop closures'
`ambiguity_ratio`, the same notion of a look-alike (a rival pose)."""
PLATEAU_REACH = 0.6
"""The plateau is sampled within ± this (m) of the match in x and y: past a corridor's typical sliding
distance per scan, short of the next room."""
PLATEAU_STEP_CELLS = 2
"""Samples every 2 grid cells (10 cm at 5 cm): a sharp match's plateau is one sample, a slide many."""
MAX_HEADING_PER_METRE = 0.5
"""Bound on the heading change per metre of a coupled slide (rad/m): a wall bending with a radius down to
5 m; a larger coupling comes from an ill-conditioned heading row, not a wall."""
COUPLED_SHARE = 0.25
"""A scan is taken to slide along a curved wall (`heading_coupling`) where eliminating its heading leaves
less than this share of its weakest translation's information: a coupled shift (along the wall, turning
with it) at least twice as uncertain (σ) as any shift at a fixed heading. Synthetic arcs of radius
15–50 m: 0.005–0.34 (most under 0.25); straight walls, the test worlds and the real logs: 0.25–1 (UAL: 1.6 %
of its matches under)."""
COUPLED_HEADING_STEP = math.radians(0.25)
"""The coupled plateau's turns are rounded to this (rad): within an eighth of a degree, 2 cm at 10 m,
under half a grid cell (the same quarter degree under which a coupling is taken as none)."""
PLATEAU_SIGMA = 0.1
"""A plateau whose spread along its long axis exceeds this σ (m) is a slide; below, the match pins the pose
and is left as ICP made it (a blob of a sample or two is the score's own width, not an ambiguity)."""


@njit(cache=True, nogil=True)
def _plateau_scores(values: NDArray[np.float32], origin: FloatArray, resolution: float, points: FloatArray,
                    pose: FloatArray, step: int, reach: int) -> FloatArray:
    """Mean likelihood of the points at `pose` shifted by (i, j)·`step` cells, i, j in [−reach, reach]:
    (2·reach + 1)² scores, rows along y.

    Point by point, each adding its patch of samples to every shift's total (as `correlative._exhaustive`):
    the grid is read a row at a time near the point instead of at scattered cells per shift, and
    consecutive points in one cell add their patch once, times their count."""
    height, width = values.shape
    count = points.shape[0]
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    side = 2 * reach + 1
    span = 2 * reach * step
    totals = np.zeros((side, side))
    cells_x = np.empty(count, dtype=np.int64)
    cells_y = np.empty(count, dtype=np.int64)
    for k in range(count):
        cells_x[k] = int(math.floor((pose[0] + c * points[k, 0] - s * points[k, 1] - origin[0]) / resolution))
        cells_y[k] = int(math.floor((pose[1] + s * points[k, 0] + c * points[k, 1] - origin[1]) / resolution))
    k = 0
    while k < count:
        # A run of consecutive points in one cell adds that cell's patch once, times the run's length.
        run = 1
        while k + run < count and cells_x[k + run] == cells_x[k] and cells_y[k + run] == cells_y[k]:
            run += 1
        left = cells_x[k] - reach * step
        bottom = cells_y[k] - reach * step
        k += run
        if left >= 0 and bottom >= 0 and left + span < width and bottom + span < height:
            for j in range(side):
                row = values[bottom + j * step]
                for i in range(side):
                    totals[j, i] += run * row[left + i * step]
        else:
            for j in range(side):
                cy = bottom + j * step
                if 0 <= cy < height:
                    for i in range(side):
                        cx = left + i * step
                        if 0 <= cx < width:
                            totals[j, i] += run * values[cy, cx]
    scores = np.empty((side, side))
    for j in range(side):
        for i in range(side):
            scores[j, i] = totals[j, i] / max(count, 1)
    return scores


@njit(cache=True, nogil=True)
def _coupled_plateau_scores(values: NDArray[np.float32], origin: FloatArray, resolution: float,
                            points: FloatArray, pose: FloatArray, step: int, reach: int,
                            heading_per_metre: FloatArray, heading_step: float) -> FloatArray:
    """`_plateau_scores` with each shift (dx, dy) turning the scan by `heading_per_metre` · (dx, dy) too:
    the translations along a curved wall, which turn with it.

    The turn is rounded to a multiple of `heading_step`; the points are placed once per distinct turn
    and each shift of that turn then reads the grid at cell offsets from the points' cells (no rotation
    per shift and point): the cost is one placement per distinct turn and one read per shift and point."""
    height, width = values.shape
    count = points.shape[0]
    side = 2 * reach + 1
    spacing = step * resolution
    totals = np.zeros((side, side))
    bins = np.empty(side * side, dtype=np.int64)
    for j in range(side):
        for i in range(side):
            turn = heading_per_metre[0] * (i - reach) * spacing + heading_per_metre[1] * (j - reach) * spacing
            bins[j * side + i] = int(round(turn / heading_step))
    order = np.argsort(bins, kind="mergesort")
    cells_x = np.empty(count, dtype=np.int64)
    cells_y = np.empty(count, dtype=np.int64)
    first = 0
    while first < side * side:
        last = first + 1
        while last < side * side and bins[order[last]] == bins[order[first]]:
            last += 1
        theta = pose[2] + bins[order[first]] * heading_step
        c = math.cos(theta)
        s = math.sin(theta)
        for k in range(count):
            x = pose[0] + c * points[k, 0] - s * points[k, 1]
            y = pose[1] + s * points[k, 0] + c * points[k, 1]
            cells_x[k] = int(math.floor((x - origin[0]) / resolution))
            cells_y[k] = int(math.floor((y - origin[1]) / resolution))
        # Every shift of the scan inside the grid (the usual case): the reads need no bounds.
        margin = reach * step
        inside = count > 0 and (cells_x.min() - margin >= 0 and cells_y.min() - margin >= 0
                                and cells_x.max() + margin < width and cells_y.max() + margin < height)
        for m in range(first, last):
            sample = order[m]
            j = sample // side
            i = sample - j * side
            offset_x = (i - reach) * step
            offset_y = (j - reach) * step
            total = 0.0
            if inside:
                for k in range(count):
                    total += values[cells_y[k] + offset_y, cells_x[k] + offset_x]
            else:
                for k in range(count):
                    cx = cells_x[k] + offset_x
                    cy = cells_y[k] + offset_y
                    if 0 <= cx < width and 0 <= cy < height:
                        total += values[cy, cx]
            totals[j, i] = total
        first = last
    scores = np.empty((side, side))
    for j in range(side):
        for i in range(side):
            scores[j, i] = totals[j, i] / max(count, 1)
    return scores


def _smallest_eigenvalue(matrix: FloatArray) -> float:
    """The smaller eigenvalue of a symmetric (2, 2) matrix."""
    half_trace = 0.5 * float(matrix[0, 0] + matrix[1, 1])
    half_gap = 0.5 * float(matrix[0, 0] - matrix[1, 1])
    return half_trace - math.hypot(half_gap, float(matrix[0, 1]))


def heading_coupling(information: FloatArray) -> FloatArray:
    """The heading change per metre (rad/m, a 2-vector g: dθ = g · (dx, dy)) that best re-fits a scan
    shifted by (dx, dy), by the (3, 3) information of its match alone: −H_θθ⁻¹ H_θ,xy, bounded by
    `MAX_HEADING_PER_METRE`. Zero along a straight wall; along a curved one, the turn per metre that keeps
    the shifted scan on it.

    Zero too where the scan's weakest direction is no coupled one: where eliminating the heading leaves
    at least `COUPLED_SHARE` of the weakest translation's information (λ_min of H_xy − H_xθ H_θθ⁻¹ H_θ,xy
    against λ_min of H_xy), a shift that turns is pinned about as well as one that does not, and the
    plain plateau (at the match's heading) sees any slide there is."""
    information = np.asarray(information, dtype=np.float64)
    if information[2, 2] <= 0.0:
        return np.zeros(2)
    translation = information[:2, :2]
    cross = information[:2, 2]
    weakest = _smallest_eigenvalue(translation)
    if weakest <= 0.0 or _smallest_eigenvalue(translation - np.outer(cross, cross) / information[2, 2]) \
            >= COUPLED_SHARE * weakest:
        return np.zeros(2)
    coupling = -information[2, :2] / information[2, 2]
    norm = float(np.hypot(*coupling))
    return coupling if norm <= MAX_HEADING_PER_METRE else coupling * (MAX_HEADING_PER_METRE / norm)


@njit(cache=True, nogil=True)
def _plateau_covariance(scores: FloatArray, threshold: float, spacing: float) -> FloatArray:
    """(2, 2) covariance (m²) of the sample offsets whose score reaches `threshold`."""
    reach = (scores.shape[0] - 1) // 2
    count = 0
    sx = sy = sxx = sxy = syy = 0.0
    for j in range(scores.shape[0]):
        for i in range(scores.shape[1]):
            if scores[j, i] >= threshold:
                x = (i - reach) * spacing
                y = (j - reach) * spacing
                count += 1
                sx += x
                sy += y
                sxx += x * x
                sxy += x * y
                syy += y * y
    covariance = np.zeros((2, 2))
    if count > 0:
        mx = sx / count
        my = sy / count
        covariance[0, 0] = sxx / count - mx * mx
        covariance[0, 1] = covariance[1, 0] = sxy / count - mx * my
        covariance[1, 1] = syy / count - my * my
    return covariance


@dataclass(frozen=True, eq=False)
class ScorePlateau:
    covariance: FloatArray
    """(2, 2) spread (m²) of the translations whose score is within `PLATEAU_RATIO` of the best sampled."""
    best_score: float
    scores: FloatArray
    """(2r + 1, 2r + 1) the sampled scores, rows along y, the sampled pose in the middle."""
    spacing: float
    """Distance between samples (m)."""
    ratio: float
    heading_per_metre: FloatArray
    """(2,) the samples' heading change per metre of shift (rad/m; zero: at the pose's heading)."""

    def holds(self, offset: FloatArray) -> bool:
        """Whether a translation `offset` (m) from the sampled pose lies on the plateau (its nearest sample
        is a member)."""
        reach = (self.scores.shape[0] - 1) // 2
        i = round(float(offset[0]) / self.spacing) + reach
        j = round(float(offset[1]) / self.spacing) + reach
        inside = 0 <= i < self.scores.shape[1] and 0 <= j < self.scores.shape[0]
        return bool(inside and self.best_score > 0.0 and self.scores[j, i] >= self.ratio * self.best_score)

    @property
    def long_axis(self) -> tuple[float, FloatArray]:
        """σ (m) along the plateau's long axis, and that axis (a unit vector in the map frame)."""
        variances, axes = np.linalg.eigh(self.covariance)
        return float(math.sqrt(max(variances[1], 0.0))), axes[:, 1]

    @property
    def is_slide(self) -> bool:
        # The long axis' variance is at most the trace: most matches are rejected without a decomposition.
        if np.trace(self.covariance) <= PLATEAU_SIGMA**2:
            return False
        return self.long_axis[0] > PLATEAU_SIGMA


def score_plateau(points: FloatArray, grid: LikelihoodGrid, pose: FloatArray, *,
                  reach: float = PLATEAU_REACH, step_cells: int = PLATEAU_STEP_CELLS,
                  ratio: float = PLATEAU_RATIO, heading_per_metre: FloatArray | None = None) -> ScorePlateau:
    """The plateau of the score of `points` (robot frame) on `grid` around `pose` (x, y, θ), over
    translations within ± `reach` m sampled every `step_cells` cells, at the pose's heading turned by
    `heading_per_metre` · shift (`heading_coupling`; None: at the pose's heading). A wall that is an arc
    fits a scan rotated about its centre, a shift along it that turns with it: at a fixed heading the
    plateau is sharp there."""
    steps = max(int(round(reach / (step_cells * grid.resolution))), 1)
    spacing = step_cells * grid.resolution
    coupling = np.zeros(2) if heading_per_metre is None else np.asarray(heading_per_metre, dtype=np.float64)
    arguments = (grid.values, np.asarray(grid.origin, dtype=np.float64), float(grid.resolution),
                 np.ascontiguousarray(points, dtype=np.float64), np.asarray(pose, dtype=np.float64),
                 step_cells, steps)
    if float(np.hypot(*coupling)) * reach < COUPLED_HEADING_STEP:  # under a rounding step at the edge
        coupling = np.zeros(2)
        scores = _plateau_scores(*arguments)
    else:
        scores = _coupled_plateau_scores(*arguments, coupling, COUPLED_HEADING_STEP)
    best = float(scores.max())
    covariance = _plateau_covariance(scores, ratio * best, spacing) if best > 0.0 else np.zeros((2, 2))
    return ScorePlateau(covariance, best, scores, spacing, ratio, coupling)


def slide_to_prior(pose: FloatArray, information: FloatArray, prior: FloatArray,
                   prior_information: FloatArray, plateau: ScorePlateau) -> tuple[FloatArray, FloatArray]:
    """The match (`pose`, `information`) with a sliding plateau taken into account: along the plateau's long
    axis the pose moves toward the prior as a Gaussian fusion of the two weighs them (the match's
    variance there being the plateau's), across it and in heading it stays; the information is that of
    the match's covariance widened by the plateau. A plateau that is no slide, or a prior off the
    plateau, changes nothing."""
    # Only a prediction the scan cannot tell from the match decides: one off the plateau (wheel odometry
    # that slipped, a constant-velocity guess at a turn) is worse than the match, which then stands.
    if not plateau.is_slide or not plateau.holds(np.asarray(prior[:2]) - np.asarray(pose[:2])):
        return pose, information
    sigma, axis = plateau.long_axis
    prior_variance = float(axis @ np.linalg.inv(prior_information)[:2, :2] @ axis)
    gap = float(axis @ (np.asarray(prior[:2]) - np.asarray(pose[:2])))
    moved = np.array(pose, dtype=np.float64)
    shift = axis * gap * sigma**2 / (sigma**2 + prior_variance)
    moved[:2] += shift
    moved[2] += float(plateau.heading_per_metre @ shift)  # along an arc the heading turns with the shift
    return moved, widened(information, plateau)


def widened(information: FloatArray, plateau: ScorePlateau) -> FloatArray:
    """The (3, 3) information of a match whose translation is also uncertain by the plateau's spread."""
    covariance = np.linalg.inv(information)
    jacobian = np.vstack([np.eye(2), plateau.heading_per_metre[None, :]])  # shift → (x, y, θ)
    covariance += jacobian @ plateau.covariance @ jacobian.T
    result = np.linalg.inv(covariance)
    return 0.5 * (result + result.T)
