"""Loop closures for 3D LiDAR: place recognition by a Scan Context descriptor, verification by GICP.

1. Place recognition (Kim & Kim 2018, "Scan Context"): a keyframe's cloud, levelled, becomes a polar grid
   of rings × sectors holding the highest point above the ground in each bin. Two places compare column
   by column (cosine), at every rotation of one against the other: the best rotation gives the distance
   and a heading guess that does not depend on the drifted estimate.
2. Verification (`verify_loop`): GICP (small_gicp, Koide 2024) of the current keyframe's cloud onto the
   candidate's submap, from the estimate's guess and the descriptor's; accepted when most points land
   close to the map. The information is the fit's Hessian, scaled, with floors on the covariance.
3. Ambiguity: the registration is repeated from starts a few metres and tens of degrees away; if one
   converges elsewhere with nearly as good a fit, the place is self-similar (a uniform street) and the
   match is rejected — the 3D counterpart of the 2D frontend's rival search. The rivals are registered
   coarse first (a source with a third of the points, a third of the iterations); only one that ends
   elsewhere with a fit that could compete is registered again at full resolution.

Hypothesis confirmation and the χ² test after optimization live in `frontends.slam3d.slam`, as in 2D.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.slam3d import se3
from frontends.slam3d.config import LoopClosureConfig
from frontends.threads import usable_cores

# small_gicp's own libgomp reads the wait policy once, when it is loaded. By default its threads spin at
# every barrier for a while before sleeping: beside another busy process (a batch's second job) a replay of
# three town laps then took 41–51 s instead of 21–22 s. Passive threads sleep at once, and cost a single
# replay on idle cores almost nothing. Only that import sees the setting; the user's own choice wins.
_USER_WAIT_POLICY = os.environ.get("OMP_WAIT_POLICY")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
try:
    import small_gicp
finally:
    if _USER_WAIT_POLICY is None:
        os.environ.pop("OMP_WAIT_POLICY", None)

FloatArray = NDArray[np.float64]

GROUND_PERCENTILE = 5.0
"""Descriptor heights are measured from this percentile of the cloud's z: the ground, seen all around."""
COVARIANCE_NEIGHBOURS = 10
_ROTATION_FIRST_TO_TRANSLATION_FIRST = np.array([3, 4, 5, 0, 1, 2])
"""small_gicp orders its Hessian (rx, ry, rz, tx, ty, tz); ours is translation first."""
RIVAL_VOXEL_FACTOR = 2.0
"""The ambiguity test registers its rival starts with the source downsampled at this many times the
registration voxel (a third of the points, a third of the cost): where a start leads needs no fine detail."""
RIVAL_ITERATIONS = 10
"""The coarse rival registrations stop after this many iterations (the match gets `registration_iterations`):
where a start leads shows early, and a rival stopped on its way is scored where it stopped, then registered
finely from there if it could compete. Three town laps: 180 rival starts, the 41 that went back to the match
took 9 iterations at the median; rival tests 2.16 → 1.36 s. Over 76 places (town blocks of four seeds,
streets with poles 2–8 m apart) the verdicts were those of 30 iterations but one, made ambiguous instead of
accepted (poles every 8 m, jittered)."""
COMPETING_SHARE = 0.75
"""A coarse rival that ended elsewhere is registered again at full resolution when the fine source's inlier
fraction at its pose is at least this share of the ambiguity threshold (`ambiguity_ratio` × the match's);
the others are taken as unable to compete. Measured on the town loop's 24 rival starts: refined at full
resolution, a coarse rival that stayed elsewhere changed its score by at most 0.05 of the threshold (0.25
is the margin); the one that gained more went back to the match, and no decision differed from registering
every start finely."""


def registration_threads(config: LoopClosureConfig) -> int:
    """small_gicp's threads: `config.threads`, or with 0 every core this process may run on."""
    return config.threads or usable_cores()


# ------------------------------------------------------------------------------------------ descriptor


def scan_context(points: NDArray[np.floating], rings: int, sectors: int, radius: float) -> FloatArray:
    """(rings, sectors) descriptor of a levelled cloud (z up, in its own frame): the highest point above
    the ground in each polar bin, 0 for empty bins. Sector 0 starts at bearing −π."""
    points = np.asarray(points, dtype=np.float64)
    descriptor = np.zeros(rings * sectors)
    if len(points) == 0:
        return descriptor.reshape(rings, sectors)
    distance = np.hypot(points[:, 0], points[:, 1])
    height = points[:, 2] - np.percentile(points[:, 2], GROUND_PERCENTILE)
    keep = (distance < radius) & (distance > 0.0)
    ring = (distance[keep] * (rings / radius)).astype(np.int64)
    bearing = np.arctan2(points[keep, 1], points[keep, 0])
    sector = np.floor((bearing + np.pi) * (sectors / (2.0 * np.pi))).astype(np.int64) % sectors
    _raise_to_maxima(descriptor, ring * sectors + sector, np.maximum(height[keep], 0.0))
    return descriptor.reshape(rings, sectors)


@njit(cache=True)
def _raise_to_maxima(
    bins: FloatArray, indices: NDArray[np.int64], values: FloatArray
) -> None:  # pragma: no cover
    """bins[i] = max(bins[i], every value at index i): `np.maximum.at`, which is unbuffered and ten times
    slower on a keyframe's tens of thousands of points."""
    for k in range(indices.shape[0]):
        if values[k] > bins[indices[k]]:
            bins[indices[k]] = values[k]


def descriptor_distances(query: FloatArray, candidates: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Scan Context distance of `query` (R, S) to each of `candidates` (K, R, S) at the best rotation,
    and that rotation as the heading of the query's frame in the candidate's (rad).

    Distance = 1 − mean cosine similarity of the columns (sectors) occupied in both; 1 when none are.
    """
    candidates = np.asarray(candidates, dtype=np.float64).reshape(-1, *query.shape)
    sectors = query.shape[1]
    # rolled[h][:, c] = query[:, c − h]: the query turned by h sectors
    rolled = np.stack([np.roll(query, shift, axis=1) for shift in range(sectors)])
    dots = np.einsum("hrc,krc->khc", rolled, candidates)
    query_norms = np.linalg.norm(rolled, axis=1)  # (H, C)
    candidate_norms = np.linalg.norm(candidates, axis=1)  # (K, C)
    norms = query_norms[None, :, :] * candidate_norms[:, None, :]
    valid = norms > 0.0
    similarity = np.where(valid, dots / np.where(valid, norms, 1.0), 0.0).sum(axis=2)
    counts = valid.sum(axis=2)
    mean = np.where(counts > 0, similarity / np.maximum(counts, 1), 0.0)
    best = np.argmax(mean, axis=1)
    distance = 1.0 - mean[np.arange(len(candidates)), best]
    heading = np.angle(np.exp(1j * best * (2.0 * np.pi / sectors)))
    return distance, heading


# ---------------------------------------------------------------------------------------- registration


@dataclass(frozen=True, eq=False)
class RegistrationFit:
    transform: FloatArray
    """4×4 pose of the source's frame in the target's (T_target_source)."""
    inlier_fraction: float
    rms: float
    """RMS distance (m) of the inliers to the surface (tangent plane) at their nearest target point."""
    hessian: FloatArray
    """6×6 GICP Hessian at the solution, (tx, ty, tz, rx, ry, rz), perturbation in the source frame."""


@dataclass(frozen=True, eq=False)
class LoopMatch:
    relative: FloatArray
    """4×4 pose of the current keyframe in the candidate's frame."""
    information: FloatArray
    """6×6 information of `relative`, (tx, ty, tz, rx, ry, rz), error in the current keyframe's frame."""
    inlier_fraction: float
    rms: float


@dataclass(frozen=True, eq=False)
class LoopVerdict:
    match: LoopMatch | None
    reason: str
    """"accepted", "poor fit" or "ambiguous"."""


class RegistrationTarget:
    """A target cloud prepared once (downsampled, covariances, k-d tree) for several registrations."""

    def __init__(self, points: NDArray[np.floating], config: LoopClosureConfig) -> None:
        self.config = config
        self.cloud, self.tree = small_gicp.preprocess_points(
            np.ascontiguousarray(points, dtype=np.float64),
            downsampling_resolution=config.registration_voxel,
            num_neighbors=COVARIANCE_NEIGHBOURS,
            num_threads=registration_threads(config),
        )
        self._points = self.cloud.points()[:, :3]
        self._normals = self.cloud.normals()[:, :3]

    def register(self, source: small_gicp.PointCloud, guess: FloatArray) -> RegistrationFit:
        result = self._align(source, guess)
        transform = np.array(result.T_target_source, dtype=np.float64)
        inlier_fraction, rms = self.score(source, transform)
        order = _ROTATION_FIRST_TO_TRANSLATION_FIRST
        return RegistrationFit(
            transform, inlier_fraction, rms, np.array(result.H, dtype=np.float64)[np.ix_(order, order)]
        )

    def align(self, source: small_gicp.PointCloud, guess: FloatArray, iterations: int) -> FloatArray:
        """The 4×4 T_target_source GICP reaches from `guess` in at most `iterations`, without scoring it."""
        return np.array(self._align(source, guess, iterations).T_target_source, dtype=np.float64)

    def _align(
        self, source: small_gicp.PointCloud, guess: FloatArray, iterations: int | None = None
    ) -> small_gicp.RegistrationResult:
        config = self.config
        return small_gicp.align(
            self.cloud,
            source,
            self.tree,
            init_T_target_source=np.asarray(guess, dtype=np.float64),
            registration_type="GICP",
            max_correspondence_distance=config.max_correspondence_distance,
            num_threads=registration_threads(config),
            max_iterations=config.registration_iterations if iterations is None else iterations,
        )

    def score(self, source: small_gicp.PointCloud, transform: FloatArray) -> tuple[float, float]:
        """Inlier fraction of the source placed at `transform` (T_target_source), and the RMS distance of
        its inliers to the target's surface (m; inf without inliers)."""
        config = self.config
        placed = se3.transform_points(transform, source.points()[:, :3])
        threads = registration_threads(config)
        nearest, squared = self.tree.batch_nearest_neighbor_search(placed, num_threads=threads)
        nearest = np.asarray(nearest, dtype=np.int64)
        inliers = (np.asarray(squared, dtype=np.float64) <= config.inlier_distance**2) & (nearest >= 0)
        count = int(inliers.sum())
        # Point-to-plane distances: the distance to the nearest target *point* mostly measures how
        # sparsely the sensor sampled a surface, not how well the two clouds agree.
        offsets = placed[inliers] - self._points[nearest[inliers]]
        residuals = np.einsum("ij,ij->i", offsets, self._normals[nearest[inliers]])
        rms = float(np.sqrt(np.mean(residuals**2))) if count else np.inf
        return count / max(len(placed), 1), rms


def prepare_source(
    points: NDArray[np.floating], config: LoopClosureConfig, voxel: float | None = None
) -> small_gicp.PointCloud:
    """The source downsampled (at `voxel`, default the registration voxel) with its covariances."""
    cloud, _ = small_gicp.preprocess_points(
        np.ascontiguousarray(points, dtype=np.float64),
        downsampling_resolution=config.registration_voxel if voxel is None else voxel,
        num_neighbors=COVARIANCE_NEIGHBOURS,
        num_threads=registration_threads(config),
    )
    return cloud


def fit_information(hessian: FloatArray, config: LoopClosureConfig) -> FloatArray:
    """6×6 information of a fit: the inverse of (the scaled Hessian's inverse + floor variances). Directions
    the fit does not constrain (a straight tunnel along its axis) keep the Hessian's low information."""
    scaled = config.information_scale * 0.5 * (hessian + hessian.T)
    covariance = np.linalg.inv(scaled + 1e-9 * np.eye(6))
    floors = np.array([config.min_sigma_linear] * 3 + [config.min_sigma_angular] * 3) ** 2
    information = np.linalg.inv(covariance + np.diag(floors))
    return 0.5 * (information + information.T)


def rival_starts(transform: FloatArray, config: LoopClosureConfig) -> list[FloatArray]:
    """Starts away from a match: shifted ahead, behind, left and right (in the target frame) and turned
    either way about the source's origin."""
    starts = []
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        start = transform.copy()
        start[:2, 3] += config.ambiguity_offset * np.array([dx, dy])
        starts.append(start)
    for sign in (1.0, -1.0):
        turn = np.eye(4)
        c, s = np.cos(sign * config.ambiguity_angle), np.sin(sign * config.ambiguity_angle)
        turn[:2, :2] = [[c, -s], [s, c]]
        starts.append(transform @ turn)
    return starts


def verify_loop(
    target: RegistrationTarget,
    source_points: NDArray[np.floating],
    guesses: Sequence[FloatArray],
    config: LoopClosureConfig,
) -> LoopVerdict:
    """Register the source (current keyframe, its own frame) onto the target (candidate submap, in the
    candidate's frame) from each guess of T_target_source; accept the best fit if it is good and
    unambiguous."""
    source = prepare_source(source_points, config)
    if source.size() == 0:
        return LoopVerdict(None, "poor fit")
    best = max((target.register(source, guess) for guess in guesses), key=lambda fit: fit.inlier_fraction)
    if best.inlier_fraction < config.min_inlier_fraction or best.rms > config.max_rms:
        return LoopVerdict(None, "poor fit")
    if has_rival(target, source, source_points, best, config):
        return LoopVerdict(None, "ambiguous")
    return LoopVerdict(
        LoopMatch(best.transform, fit_information(best.hessian, config), best.inlier_fraction, best.rms),
        "accepted",
    )


def has_rival(
    target: RegistrationTarget,
    source: small_gicp.PointCloud,
    source_points: NDArray[np.floating],
    best: RegistrationFit,
    config: LoopClosureConfig,
) -> bool:
    """Whether a registration from one of the `rival_starts` converges elsewhere (a pose
    `ambiguity_distance` away or turned by half `ambiguity_angle`) with an inlier fraction of at least
    `ambiguity_ratio` × the match's. `source` is `source_points` prepared at the registration voxel."""
    threshold = config.ambiguity_ratio * best.inlier_fraction
    coarse = prepare_source(source_points, config, RIVAL_VOXEL_FACTOR * config.registration_voxel)
    for start in rival_starts(best.transform, config):
        rough = target.align(coarse, start, RIVAL_ITERATIONS)
        # back at the match: this start leads there, no rival
        if not _elsewhere(best.transform, rough, config):
            continue
        if target.score(source, rough)[0] < COMPETING_SHARE * threshold:
            continue
        rival = target.register(source, rough)
        if _elsewhere(best.transform, rival.transform, config) and rival.inlier_fraction >= threshold:
            return True
    return False


def _elsewhere(match: FloatArray, rival: FloatArray, config: LoopClosureConfig) -> bool:
    away = float(np.linalg.norm(rival[:3, 3] - match[:3, 3]))
    turned = float(se3.rotation_angle(se3.relative(match, rival)))
    return away >= config.ambiguity_distance or turned >= 0.5 * config.ambiguity_angle
