"""Whether a cloud constrains the vehicle's horizontal motion in every direction.

ICP finds a translation only along directions the scene's surfaces face: between two long flat walls (a
featureless road, a tunnel) every position along them fits equally well, and LiDAR odometry measures
little or none of the motion along them; the trajectory comes out short with nothing else to tell. The
measure is that of point-to-plane ICP's information on the horizontal translation, Σ n nᵀ over the surface
normals n (the normals' x, y parts): the share of its weakest direction in its strongest.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

UNDERCONSTRAINED_SHARE = 0.02
"""A cloud whose weakest horizontal direction gets less than this share of the strongest's information
is taken as unable to measure motion along it. Keyframes between two flat walls (and the ground) measure
0.0004-0.0012 (normal noise); a simulated town 0.41-0.82, the same town seen by a LiDAR pitched 60 deg
0.05-0.43 and kitti_city 0.24-0.39 (each keyframe's, lowest to median)."""

SAMPLE_POINTS = 1000
"""Points whose normals are estimated (an even subsample: the share is a ratio, a sample estimates it)."""
NEIGHBOURS = 10
PLANAR = 0.1
"""A point's normal counts when its neighbourhood is flat: least variance under this share of the middle."""


def weakest_horizontal_share(points: NDArray[np.floating]) -> float:
    """The share of the weakest horizontal direction in point-to-plane information, 0 … 1 (`points`: (N, 3)
    in a frame whose z is up; 1.0 when there are too few points to tell)."""
    from scipy.spatial import cKDTree  # here: laser replays never need it

    sample = np.asarray(points, dtype=np.float64)[:: max(1, len(points) // SAMPLE_POINTS)]
    if len(sample) <= NEIGHBOURS:
        return 1.0
    _, neighbours = cKDTree(sample).query(sample, k=NEIGHBOURS)
    neighbourhoods = sample[neighbours]
    around = neighbourhoods - neighbourhoods.mean(axis=1, keepdims=True)
    variances, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", around, around))
    normals = axes[variances[:, 0] < PLANAR * variances[:, 1], :2, 0]
    weakest, strongest = np.linalg.eigvalsh(normals.T @ normals)
    return float(weakest / strongest) if strongest > 0.0 else 1.0
