"""LiDAR odometry with KISS-ICP (Vizzo et al. 2023), through its Python API.

KISS-ICP deskews a cloud with per-point times in [0, 1] over the sweep (it rescales whatever it gets by
min and max, and a sweep whose times are all equal makes it divide by zero and abort the process), under
a constant-velocity model: the point at normalised time τ is moved by exp((τ − 1)·ω), ω the log of the
previous frame-to-frame motion, so the deskewed cloud and the registered pose are those of the sensor at
the *last* point's time. Our clouds carry times in seconds relative to their stamp (or none): the wrapper
normalises them, skips deskewing when they are missing or span no time, and reports the pose at the
cloud's stamp (moved back along the same motion model), so that every pose has the time of its message.

A cloud without a time field (KITTI, many drivers) is deskewed from its points' azimuths when
`OdometryConfig.azimuth_times`: a spinning LiDAR sweeps at a constant rate, so a point's time in the
sweep is the angle swept from `sweep_start_angle` in the spin direction (the rule KISS-ICP's own KITTI
reader uses); `stamp_at_sweep_end` says whether the stamp is the sweep's end or its start. Only clouds
that fill the circle are deskewed this way (`covers_the_circle`): a narrow field of view is no sweep.

A motion guess (the base's motion since the previous cloud from wheel or INS odometry, as a sensor
motion) replaces KISS-ICP's constant-velocity prediction for that cloud: the registration starts from
it and the deskewing uses it. KISS-ICP 1.3 has no argument for this; its `register_frame` predicts with
`last_pose @ last_delta`, so the wrapper sets `last_delta` (pinned: kiss-icp < 1.4 in pyproject.toml).

The deskewing itself is done here (`deskew`, the same motion model) and KISS-ICP gets the cloud without
times: its C++ deskewing evaluates a full SE(3) exponential (Sophus) per point, three quarters of its
preprocessing (2.4 of 3.2 ms on a town-loop sweep of 22 k points).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig
from kiss_icp.kiss_icp import KissICP
from kiss_icp.voxelization import voxel_down_sample
from numba import njit
from numpy.typing import NDArray

from frontends.slam3d import se3
from frontends.slam3d.config import OdometryConfig

FloatArray = NDArray[np.float64]

NO_TIMES = np.empty(0, dtype=np.float64)


def kiss_config(config: OdometryConfig) -> KISSConfig:
    """Our odometry settings as KISS-ICP's configuration, every field set explicitly."""
    return KISSConfig(
        data=DataConfig(max_range=config.max_range, min_range=config.min_range, deskew=config.deskew),
        mapping=MappingConfig(
            voxel_size=config.map_voxel_size, max_points_per_voxel=config.max_points_per_voxel
        ),
        registration=RegistrationConfig(
            max_num_iterations=config.max_iterations,
            convergence_criterion=config.convergence_criterion,
            max_num_threads=config.max_threads,
        ),
        adaptive_threshold=AdaptiveThresholdConfig(
            fixed_threshold=config.fixed_threshold,
            initial_threshold=config.initial_threshold,
            min_motion_th=config.min_motion_threshold,
        ),
    )


def azimuth_point_times(
    points: NDArray[np.floating], *, clockwise: bool = True, start_azimuth: float = np.pi
) -> FloatArray:
    """(N,) each point's time as a fraction of the sweep (0 at `start_azimuth`, → 1 a full turn later)
    from its azimuth about the sensor's z axis, for a sensor spinning `clockwise` seen from above."""
    azimuth = np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)
    swept = (start_azimuth - azimuth) if clockwise else (azimuth - start_azimuth)
    return np.mod(swept, 2.0 * np.pi) / (2.0 * np.pi)


AZIMUTH_BINS = 36
MIN_AZIMUTH_COVERAGE = 0.9
"""Times from azimuths need a full sweep: KISS-ICP stretches the times over the whole frame-to-frame
motion, so a 70° field of view (a solid-state sensor) would be deskewed five times too much. Clouds with
points in fewer than this fraction of 10° azimuth bins are not deskewed from azimuths."""


def covers_the_circle(sweep_fractions: FloatArray) -> bool:
    """Whether points at these sweep fractions (`azimuth_point_times`) fill the circle of a full sweep."""
    bins = np.minimum((sweep_fractions * AZIMUTH_BINS).astype(np.int64), AZIMUTH_BINS - 1)
    occupied = np.count_nonzero(np.bincount(bins, minlength=AZIMUTH_BINS))
    return bool(occupied >= MIN_AZIMUTH_COVERAGE * AZIMUTH_BINS)


def normalized_point_times(point_times: NDArray[np.float64] | None) -> tuple[FloatArray, float | None]:
    """KISS-ICP's per-point times (0 at the first point, 1 at the last), and where the cloud's stamp
    (relative time 0) falls on that scale; (empty, None) when the cloud cannot be deskewed: no times, a
    non-finite one, or a sweep spanning no time."""
    if point_times is None or len(point_times) == 0:
        return NO_TIMES, None
    first = float(np.min(point_times))
    span = float(np.max(point_times)) - first
    if not (np.isfinite(first) and np.isfinite(span)) or span <= 0.0:
        return NO_TIMES, None
    return (np.asarray(point_times, dtype=np.float64) - first) / span, -first / span


@dataclass(frozen=True, eq=False)
class OdometryStep:
    """One registered cloud."""

    pose: FloatArray
    """4×4 pose of the sensor at the cloud's stamp, in the odometry frame (the first cloud's sensor frame)."""
    points: FloatArray
    """(N, 3) the cloud as registered: range-limited and deskewed, in the frame `points_pose`."""
    points_pose: FloatArray
    """4×4 pose of the frame `points` are in: the sensor at the last point's time when deskewed."""
    deskewed: bool
    guess_overruled: bool = False
    """The motion guess was not used: registering from the constant-velocity prediction fit the map
    clearly better (`KissOdometry._guess_fits`)."""


class Odometry(Protocol):
    """What the SLAM needs of an odometry: register a cloud, or decline one with too few points."""

    def register(
        self,
        points: NDArray[np.floating],
        point_times: NDArray[np.float64] | None = None,
        motion_guess: NDArray[np.float64] | None = None,
    ) -> OdometryStep | None: ...


def _has_extent(points: NDArray[np.floating], voxel: float) -> bool:
    """Whether the points span at least one voxel of the map in some direction: every point in one spot
    (a sensor fault) holds no geometry to register, however many there are."""
    extent = np.max(points, axis=0) - np.min(points, axis=0)
    return bool(np.max(extent) >= voxel)


GUESS_OUTLIER_RATIO = 0.5
"""A motion guess far from the LiDAR's prediction is dropped when registering from the prediction leaves at
most this fraction of the points that the guess leaves unmatched (within σ of the map): a clearly better
fit, not a tie."""


class KissOdometry:
    """Feed clouds in time order with `register`."""

    def __init__(self, config: OdometryConfig | None = None) -> None:
        self.config = config or OdometryConfig()
        self._kiss = KissICP(kiss_config(self.config))
        self._pose = np.eye(4)

    @property
    def pose(self) -> FloatArray:
        """The latest registered pose (at its cloud's stamp)."""
        return self._pose.copy()

    def register(
        self,
        points: NDArray[np.floating],
        point_times: NDArray[np.float64] | None = None,
        motion_guess: NDArray[np.float64] | None = None,
    ) -> OdometryStep | None:
        """Register one cloud, (N, 3) points in the sensor frame with optional times (s, relative to the
        stamp); None (and nothing changes) when it has fewer than `min_points` points, or all of them lie
        within one voxel. `motion_guess`
        (4×4, the sensor's motion since the previous registered cloud, stamp to stamp) replaces the
        constant-velocity prediction."""
        if len(points) < self.config.min_points or not _has_extent(points, self.config.map_voxel_size):
            return None
        times, stamp_fraction = self._sweep_times(points, point_times)
        guess = None if motion_guess is None else np.array(motion_guess, dtype=np.float64)
        overruled = guess is not None and not self._guess_fits(points, guess)
        if guess is not None and not overruled:
            self._kiss.last_delta = guess
        # The motion the deskewing assumes (read before registering replaces it), as a twist.
        twist = se3.log(np.array(self._kiss.last_delta, dtype=np.float64))
        frame = np.ascontiguousarray(points, dtype=np.float64)
        if len(times):
            frame = _deskew(frame, np.ascontiguousarray(times, dtype=np.float64), twist)
        # without times KISS-ICP only drops points out of range
        deskewed, _ = self._kiss.register_frame(frame, NO_TIMES)
        end_pose = np.array(self._kiss.last_pose, dtype=np.float64)
        pose = end_pose
        if stamp_fraction is not None and stamp_fraction != 1.0:
            pose = end_pose @ se3.exp((stamp_fraction - 1.0) * twist)
        self._pose = pose
        return OdometryStep(pose, np.asarray(deskewed), end_pose, stamp_fraction is not None, overruled)

    def _guess_fits(self, points: NDArray[np.floating], motion_guess: FloatArray) -> bool:
        """Whether to register from the motion guess rather than the constant-velocity prediction.

        Wheel or INS odometry can jump (a reset, a glitch, a wrong message): a guess metres or tens of
        degrees from the LiDAR's own prediction lies beyond ICP's correspondence distance (3σ of KISS-ICP's
        adaptive threshold), where ICP cannot undo it and the trajectory keeps the jump. Only then are both
        starts tried (their ICP is rerun by `register_frame`, so the cost is that of rare disagreements):
        the guess loses when registering from the prediction leaves at most `GUESS_OUTLIER_RATIO` of its
        unmatched points. Where the scene cannot tell the two apart (a featureless corridor) both fit
        alike and the odometry is kept.
        """
        kiss = self._kiss
        if kiss.local_map.empty():
            return True
        predicted = kiss.last_pose @ kiss.last_delta
        guessed = kiss.last_pose @ motion_guess
        between = se3.relative(predicted, guessed)
        sigma = float(kiss.adaptive_threshold.get_threshold())
        reach = 3.0 * sigma  # ICP's correspondence distance
        # No point moves further than |t| + angle · range: most clouds end here, before any work on points.
        bound = np.linalg.norm(between[:3, 3]) + float(se3.rotation_angle(between)) * self.config.max_range
        if bound <= reach:
            return True
        frame = kiss.preprocessor.preprocess(np.ascontiguousarray(points, dtype=np.float64), NO_TIMES,
                                             np.eye(4))
        source, _ = kiss.voxelize(frame)  # the points ICP registers
        moved = se3.transform_points(between, source) - source
        if len(source) == 0 or float(np.median(np.linalg.norm(moved, axis=1))) <= reach:
            return True
        from scipy.spatial import cKDTree  # here: only a disagreement needs it

        map_points = cKDTree(kiss.local_map.point_cloud())
        unmatched = []
        for start in (guessed, predicted):
            pose = kiss.registration.align_points_to_map(
                points=source, voxel_map=kiss.local_map, initial_guess=start,
                max_correspondance_distance=reach, kernel=sigma,
            )
            distance, _ = map_points.query(se3.transform_points(pose, source), distance_upper_bound=sigma)
            unmatched.append(float(np.mean(~np.isfinite(distance))))
        return unmatched[1] > GUESS_OUTLIER_RATIO * unmatched[0]

    def _sweep_times(
        self, points: NDArray[np.floating], point_times: NDArray[np.float64] | None
    ) -> tuple[FloatArray, float | None]:
        """KISS-ICP's normalised times and the stamp's place among them; (empty, None): no deskewing."""
        config = self.config
        if not config.deskew:
            return NO_TIMES, None
        times, stamp_fraction = normalized_point_times(point_times)
        if point_times is not None or not config.azimuth_times:
            return times, stamp_fraction
        times = azimuth_point_times(
            points, clockwise=config.spin_clockwise, start_azimuth=config.sweep_start_angle
        )
        if not covers_the_circle(times):
            return NO_TIMES, None
        return normalized_point_times(times - (1.0 if config.stamp_at_sweep_end else 0.0))


def downsample(points: NDArray[np.floating], voxel: float) -> FloatArray:
    """One point per voxel of this size (KISS-ICP's voxel filter: the first point seen in each voxel)."""
    if len(points) == 0:
        return np.empty((0, 3))
    return np.asarray(voxel_down_sample(np.ascontiguousarray(points, dtype=np.float64), voxel))


def deskew(points: FloatArray, times: FloatArray, motion: FloatArray) -> FloatArray:
    """KISS-ICP's motion compensation: the point at normalised time τ (0 … 1 over the sweep) moved by
    exp((τ − 1)·log(motion)), `motion` the 4×4 frame-to-frame motion; the result is in the sensor frame
    at τ = 1."""
    return _deskew(
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(times, dtype=np.float64),
        se3.log(motion),
    )


@njit(cache=True)
def _deskew(points: FloatArray, times: FloatArray, twist: FloatArray) -> FloatArray:  # pragma: no cover
    """`deskew` with `twist` = log(motion) (tx, ty, tz, rx, ry, rz): R p + V t of exp(s·twist), s = τ − 1,
    through cross products (Rodrigues) instead of 4×4 matrices."""
    out = np.empty_like(points)
    for i in range(points.shape[0]):
        scale = times[i] - 1.0
        wx, wy, wz = scale * twist[3], scale * twist[4], scale * twist[5]
        ux, uy, uz = scale * twist[0], scale * twist[1], scale * twist[2]
        theta = np.sqrt(wx * wx + wy * wy + wz * wz)
        if theta < se3.SMALL_ANGLE:
            a, b, c = 1.0, 0.5, 0.0
            rotation_b = 0.0
        else:
            a = np.sin(theta) / theta
            b = (1.0 - np.cos(theta)) / (theta * theta)
            c = (1.0 - a) / (theta * theta)
            rotation_b = b
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        # w × p and w × (w × p), the same for u
        cpx, cpy, cpz = wy * pz - wz * py, wz * px - wx * pz, wx * py - wy * px
        ccpx, ccpy, ccpz = wy * cpz - wz * cpy, wz * cpx - wx * cpz, wx * cpy - wy * cpx
        cux, cuy, cuz = wy * uz - wz * uy, wz * ux - wx * uz, wx * uy - wy * ux
        ccux, ccuy, ccuz = wy * cuz - wz * cuy, wz * cux - wx * cuz, wx * cuy - wy * cux
        out[i, 0] = px + a * cpx + rotation_b * ccpx + ux + b * cux + c * ccux
        out[i, 1] = py + a * cpy + rotation_b * ccpy + uy + b * cuy + c * ccuy
        out[i, 2] = pz + a * cpz + rotation_b * ccpz + uz + b * cuz + c * ccuz
    return out
