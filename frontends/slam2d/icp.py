"""Point-to-line ICP in 2D with an optional Gaussian prior on the pose, compiled.

Each scan point is paired with the reference point nearest its cell (the likelihood grid's `pairing`
index: no KD-tree query per iteration) and penalised by its distance to that point's tangent line, or,
where the reference has no line (corners, clutter), by its distance to the point itself. A Cauchy
weight keeps wrong pairings from dragging the pose. The prior (the wheel-odometry or constant-velocity
prediction with its information) joins the normal equations, so a scan of a featureless corridor, which
constrains nothing along it, stays where the prior puts it, and its information says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.slam2d.grid import LikelihoodGrid
from optimizer import se2

FloatArray = NDArray[np.float64]

NORMAL_NEIGHBOURS = 7
"""Beams on each side of a point that may join its normal's neighbourhood …"""
NORMAL_RADIUS = 0.3
"""… if they lie within this distance of it (m), or within `NORMAL_SPACINGS` times the local beam spacing
when that is larger: a wall seen at a grazing angle far away has beams tens of centimetres apart."""
NORMAL_SPACINGS = 3.5
MAX_NORMAL_RADIUS = 1.0
FLATNESS = 0.3
"""A neighbourhood whose small/large spread ratio is below this is a line: walls seen with 1–2 cm noise
over 10–20 cm are near 0.1–0.2."""


@njit(cache=True, nogil=True)
def scan_normals(points: FloatArray) -> FloatArray:
    """Normals (N, 2) of a bearing-ordered scan from neighbouring beams.

    A unit vector where the neighbourhood is a line; NaN where it is clutter (neighbours, but no line:
    ICP pairs such points point-to-point); (0, 0) where the point has too few neighbours to say (ICP does
    not pair with it: sparse samples of a wall seen at a grazing angle would pin the scan along the wall).
    """
    count = points.shape[0]
    normals = np.full((count, 2), np.nan)
    for i in range(count):
        spacing = np.inf
        for j in (i - 1, i + 1):
            if 0 <= j < count:
                spacing = min(spacing, math.hypot(points[j, 0] - points[i, 0], points[j, 1] - points[i, 1]))
        radius = min(max(NORMAL_RADIUS, NORMAL_SPACINGS * spacing), MAX_NORMAL_RADIUS)
        sx = sy = 0.0
        members = 0
        for j in range(max(0, i - NORMAL_NEIGHBOURS), min(count, i + NORMAL_NEIGHBOURS + 1)):
            if (points[j, 0] - points[i, 0]) ** 2 + (points[j, 1] - points[i, 1]) ** 2 <= radius**2:
                sx += points[j, 0]
                sy += points[j, 1]
                members += 1
        if members < 4:  # three scattered points can look like a line by chance
            normals[i, 0] = 0.0
            normals[i, 1] = 0.0
            continue
        mx = sx / members
        my = sy / members
        cxx = cxy = cyy = 0.0
        for j in range(max(0, i - NORMAL_NEIGHBOURS), min(count, i + NORMAL_NEIGHBOURS + 1)):
            dx = points[j, 0] - mx
            dy = points[j, 1] - my
            if (points[j, 0] - points[i, 0]) ** 2 + (points[j, 1] - points[i, 1]) ** 2 <= radius**2:
                cxx += dx * dx
                cxy += dx * dy
                cyy += dy * dy
        # Eigen-decomposition of the 2×2 scatter: the normal is the eigenvector of the smaller eigenvalue.
        half_trace = 0.5 * (cxx + cyy)
        root = math.sqrt(max(0.25 * (cxx - cyy) ** 2 + cxy * cxy, 0.0))
        small = half_trace - root
        large = half_trace + root
        if large <= 0.0 or small > FLATNESS * FLATNESS * large:
            continue
        nx = cxy
        ny = small - cxx
        if abs(nx) + abs(ny) < 1e-15:
            nx, ny = (1.0, 0.0) if cxx < cyy else (0.0, 1.0)
        norm = math.hypot(nx, ny)
        normals[i, 0] = nx / norm
        normals[i, 1] = ny / norm
    return normals


@dataclass(frozen=True, eq=False)
class IcpResult:
    pose: FloatArray
    """(x, y, θ) of the scan in the reference frame."""
    information: FloatArray
    """(3, 3) information of the pose: the Gauss–Newton Hessian at the solution, prior included."""
    inlier_fraction: float
    """Share of scan points paired with a reference point within the pairing distance."""
    rms: float
    """Root mean square residual of the paired points (m)."""


def refine_point_to_line(
    scan: FloatArray,
    grid: LikelihoodGrid,
    reference_points: FloatArray,
    reference_normals: FloatArray,
    initial: FloatArray,
    *,
    max_distance: float,
    sigma: float,
    prior: FloatArray | None = None,
    prior_information: FloatArray | None = None,
    iterations: int = 15,
    tolerance: float = 1e-5,
) -> IcpResult:
    """Refine `initial` so the scan lies on the reference's lines; σ is the point noise (m).

    `grid.pairing` − 1 indexes `reference_points`/`reference_normals` (normals NaN where none).
    """
    has_prior = prior is not None and prior_information is not None
    pose, hessian, paired, rms = _icp(
        np.ascontiguousarray(scan, dtype=np.float64),
        grid.pairing,
        grid.origin,
        grid.resolution,
        reference_points,
        reference_normals,
        np.asarray(initial, dtype=np.float64),
        np.asarray(prior if has_prior else initial, dtype=np.float64),
        np.asarray(prior_information if has_prior else np.zeros((3, 3)), dtype=np.float64),
        max_distance,
        sigma,
        iterations,
        tolerance,
    )
    fraction = paired / len(scan) if len(scan) else 0.0
    return IcpResult(pose, hessian, float(fraction), float(rms))


@njit(cache=True, nogil=True)
def _icp(
    scan: FloatArray,
    pairing: NDArray[np.int32],
    origin: FloatArray,
    resolution: float,
    reference_points: FloatArray,
    reference_normals: FloatArray,
    initial: FloatArray,
    prior: FloatArray,
    prior_information: FloatArray,
    max_distance: float,
    sigma: float,
    iterations: int,
    tolerance: float,
) -> tuple[FloatArray, FloatArray, int, float]:
    height, width = pairing.shape
    pose = initial.copy()
    hessian = np.zeros((3, 3))
    gradient = np.zeros(3)
    row = np.zeros(3)
    regularized = np.empty((3, 3))
    step = np.empty(3)
    inverse_variance = 1.0 / (sigma * sigma)
    scale2 = (2.0 * sigma) ** 2
    paired = 0
    squared_sum = 0.0
    residual_count = 0
    for _ in range(iterations):
        c = math.cos(pose[2])
        s = math.sin(pose[2])
        for a in range(3):  # element by element: an array assignment compiles numba's shape checks (1-3 s)
            for b in range(3):
                hessian[a, b] = prior_information[a, b]
        offset_theta = se2.wrap_scalar(pose[2] - prior[2])
        for a in range(3):
            gradient[a] = (
                prior_information[a, 0] * (pose[0] - prior[0])
                + prior_information[a, 1] * (pose[1] - prior[1])
                + prior_information[a, 2] * offset_theta
            )
        paired = 0
        squared_sum = 0.0
        residual_count = 0
        for i in range(scan.shape[0]):
            px = scan[i, 0]
            py = scan[i, 1]
            wx = c * px - s * py + pose[0]
            wy = s * px + c * py + pose[1]
            ix = int(math.floor((wx - origin[0]) / resolution))
            iy = int(math.floor((wy - origin[1]) / resolution))
            if ix < 0 or iy < 0 or ix >= width or iy >= height:
                continue
            k = pairing[iy, ix] - 1
            if k < 0:
                continue
            ox = wx - reference_points[k, 0]
            oy = wy - reference_points[k, 1]
            if ox * ox + oy * oy > max_distance * max_distance:
                continue
            paired += 1
            dtx = -s * px - c * py  # ∂(R p + t)/∂θ
            dty = c * px - s * py
            nx = reference_normals[k, 0]
            ny = reference_normals[k, 1]
            if nx == 0.0 and ny == 0.0:  # too sparse to pair (see `scan_normals`)
                continue
            count = 1 if nx == nx else 2  # a line: one point-to-line row; none (NaN): two point-to-point
            for r in range(count):
                if count == 1:
                    row[0], row[1], row[2] = nx, ny, nx * dtx + ny * dty
                    residual = nx * ox + ny * oy
                elif r == 0:
                    row[0], row[1], row[2] = 1.0, 0.0, dtx
                    residual = ox
                else:
                    row[0], row[1], row[2] = 0.0, 1.0, dty
                    residual = oy
                weight = inverse_variance / (1.0 + residual * residual / scale2)  # Cauchy
                for a in range(3):
                    gradient[a] += weight * row[a] * residual
                    for b in range(3):
                        hessian[a, b] += weight * row[a] * row[b]
                squared_sum += residual * residual
                residual_count += 1
        if paired < 3:
            break
        for a in range(3):
            for b in range(3):
                regularized[a, b] = hessian[a, b]
            regularized[a, a] += 1e-9
            step[a] = -gradient[a]
        if not _solve_3x3(regularized, step):
            break
        pose += step
        pose[2] = se2.wrap_scalar(pose[2])
        if abs(step[0]) + abs(step[1]) < tolerance and abs(step[2]) < tolerance:
            break
    rms = math.sqrt(squared_sum / residual_count) if residual_count > 0 else math.inf
    return pose, hessian, paired, rms


@njit(cache=True, nogil=True)
def _solve_3x3(matrix: FloatArray, rhs: FloatArray) -> bool:
    """Overwrite `rhs` with matrix⁻¹·rhs by LU with partial pivoting, as LAPACK's `gesv` solves it; False
    where a pivot is exactly zero (singular). Written out: `np.linalg.solve` compiles numba's LAPACK binding
    and its shape checks, half of the ICP kernel's compilation (4 of 8 s on a fresh install). Not the
    optimizer's Cholesky (`optimizer.gauss_seidel._solve_3x3_spd`): its positive-definiteness test refuses
    the nearly singular systems of a corridor (a rank-2 Hessian plus the 1e-9 regularisation), which LAPACK
    solved, and the matches there would change."""
    a = matrix  # factorised in place
    for column in range(3):
        pivot = column
        for r in range(column + 1, 3):
            if abs(a[r, column]) > abs(a[pivot, column]):
                pivot = r
        if a[pivot, column] == 0.0:
            return False
        if pivot != column:
            for k in range(3):
                a[column, k], a[pivot, k] = a[pivot, k], a[column, k]
            rhs[column], rhs[pivot] = rhs[pivot], rhs[column]
        reciprocal = 1.0 / a[column, column]
        for r in range(column + 1, 3):
            a[r, column] *= reciprocal
            for k in range(column + 1, 3):
                a[r, k] -= a[r, column] * a[column, k]
    for r in range(1, 3):  # L (unit diagonal)
        for k in range(r):
            rhs[r] -= a[r, k] * rhs[k]
    for column in range(2, -1, -1):  # U, column by column
        rhs[column] /= a[column, column]
        for r in range(column):
            rhs[r] -= rhs[column] * a[r, column]
    return True
