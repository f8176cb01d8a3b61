"""Settings of the 3D LiDAR SLAM frontend (KISS-ICP odometry, keyframes, loop closures).

The odometry settings are KISS-ICP's own, each mapped onto one field of its `KISSConfig` in
`frontends.slam3d.odometry.kiss_config`; the defaults are KISS-ICP's but one: the ICP stops once an update
is below 1e-3 (1 mm, 1 mrad) instead of 1e-4, which takes 1.5–1.7× less CPU for the same trajectory
within 0.02 % of the path on kitti_city (see `OdometryConfig.convergence_criterion`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from frontends.loop_search import LoopClosureSwitch, LoopSearchRadius


@dataclass(frozen=True)
class OdometryConfig:
    max_range: float = 100.0
    """Points farther from the sensor are dropped (m). KISSConfig.data.max_range."""
    min_range: float = 0.0
    """Points nearer the sensor are dropped: the vehicle itself (m). KISSConfig.data.min_range."""
    deskew: bool = True
    """Motion-compensate each cloud under KISS-ICP's constant-velocity model. KISSConfig.data.deskew."""
    azimuth_times: bool = True
    """A cloud without a per-point time field is deskewed with times from its points' azimuths (a
    spinning LiDAR sweeps at a constant rate; see `spin_clockwise`, `sweep_start_angle`); False: such
    a cloud is not deskewed. A cloud with a time field always uses it."""
    spin_clockwise: bool = True
    """Seen from above (sensor z up): Velodyne, Hesai and KITTI's HDL-64E spin clockwise, Ouster
    counter-clockwise (in its sensor frame)."""
    sweep_start_angle: float = math.pi
    """Azimuth (rad about the sensor's z, from +x; 2π for +x itself) where a sweep starts and ends:
    behind the sensor for Velodyne/KITTI."""
    stamp_at_sweep_end: bool = True
    """With times from azimuths: the cloud's stamp is the sweep's end (Velodyne's ROS driver stamps a
    sweep with its last packet, and KISS-ICP reports that pose); False: its start (Ouster)."""
    voxel_size: float | None = None
    """Voxel of the local map (m); None: max_range / 100, KISS-ICP's rule. KISSConfig.mapping.voxel_size."""
    max_points_per_voxel: int = 20
    """KISSConfig.mapping.max_points_per_voxel."""
    initial_threshold: float = 2.0
    """Correspondence threshold before the motion statistics exist (m).
    KISSConfig.adaptive_threshold.initial_threshold."""
    min_motion_threshold: float = 0.1
    """Motions smaller than this do not update the adaptive threshold (m).
    KISSConfig.adaptive_threshold.min_motion_th."""
    fixed_threshold: float | None = None
    """A fixed correspondence threshold instead of the adaptive one (m); None: adaptive.
    KISSConfig.adaptive_threshold.fixed_threshold."""
    max_iterations: int = 500
    """ICP iterations per cloud. KISSConfig.registration.max_num_iterations."""
    convergence_criterion: float = 1e-3
    """The ICP stops when its update (tx, ty, tz, rx, ry, rz) is shorter than this (m, rad).
    KISSConfig.registration.convergence_criterion. KISS-ICP's default is 1e-4 (0.1 mm): its last
    iterations creep by fractions of a millimetre, far below what a 0.5 m voxel map resolves, and cost a
    third of the odometry's time. Measured on kitti_city (154 frames, 71.5 m): 1.5–1.7× less CPU, final
    position 0.014 m from KISS-ICP's default run; on the synthetic town loop the same ATE within 3 mm.
    `benchmarks/slam3d_stages.py` measures it."""
    max_threads: int = 0
    """Threads of the registration; 0: all cores. KISSConfig.registration.max_num_threads."""
    min_points: int = 100
    """(Ours) a cloud with fewer points is not registered: its pose stays the previous one and the motion
    model is left alone (an empty cloud would feed KISS-ICP's threshold a zero motion)."""

    @property
    def map_voxel_size(self) -> float:
        """The voxel size KISS-ICP runs with."""
        return self.voxel_size if self.voxel_size is not None else self.max_range / 100.0


@dataclass(frozen=True)
class KeyframeConfig:
    distance: float = 1.0
    """A cloud this far (m) from the last keyframe becomes a keyframe …"""
    angle: float = math.radians(10.0)
    """… or one turned this much (rad)."""
    cloud_voxel: float = 0.3
    """Keyframe clouds (maps, loop closures) keep one point per voxel of this size (m)."""
    odometry_sigma_linear: float = 0.02
    """KISS-ICP reports no uncertainty: a keyframe step's σ is this + `odometry_sigma_per_metre` × its
    length (m) …"""
    odometry_sigma_per_metre: float = 0.01
    odometry_sigma_angular: float = math.radians(0.1)
    """… and this + `odometry_sigma_per_radian` × its rotation (rad)."""
    odometry_sigma_per_radian: float = 0.01
    odometry_sigma_per_metre_angular: float = math.radians(0.05)
    """Heading drift per metre driven (rad/m): LiDAR odometry's yaw drifts with distance, not only turns."""


@dataclass(frozen=True)
class LoopSearchCadence(LoopClosureSwitch):
    """Which keyframes search for loops, and how far back (keys that come before the search radius)."""

    every_keyframes: int = 2
    """Search at every n-th keyframe (neighbouring keyframes see the same place)."""
    min_travel: float = 25.0
    """Candidates are keyframes at least this far back along the driven path (m): not the local map."""


@dataclass(frozen=True)
class LoopClosureConfig(LoopSearchRadius, LoopSearchCadence):
    search_radius: float = 5.0
    max_search_radius: float = 30.0
    candidates_per_keyframe: int = 2
    travel_between_closures: float = 10.0
    """After a keyframe closes a loop, keyframes search again once the vehicle has travelled this far (m;
    0: every searching keyframe). A revisited street otherwise closes at every other keyframe, each
    closure registered against nearly the submap the last one used (`submap_keyframes` on each side): one
    closure per stretch corrects the drift, and each verification costs tens of milliseconds of GICP.
    Three laps of the town loop: 117 closures and 34 of 52 s in verification without it."""
    descriptor_rings: int = 20
    """Scan Context descriptor: rings × sectors polar bins holding the highest point above the ground."""
    descriptor_sectors: int = 60
    descriptor_radius: float = 50.0
    """The descriptor covers points up to this distance (m)."""
    descriptor_max_distance: float = 0.45
    """Candidates whose descriptor distance (1 − mean column cosine, best over rotations) exceeds this are
    not verified: the place does not look the same."""
    submap_keyframes: int = 8
    """The candidate's submap (registration target): this many keyframes on each side of it."""
    registration_voxel: float = 0.5
    """GICP downsamples source and target to this voxel (m)."""
    max_correspondence_distance: float = 1.5
    registration_iterations: int = 30
    threads: int = 0
    """OpenMP threads of small_gicp's registrations; 0: every core this process may run on (as the
    odometry's `max_threads`). Verification runs between two frames' odometry, so the cores are otherwise
    idle then: three laps of the town loop, 2 cores, 2 threads against 1: verification 3.6 → 2.0 s, the
    replay 13.0 → 11.1 s, process CPU +3 %."""
    inlier_distance: float = 0.4
    """After registration, source points within this distance of the target are inliers (m)."""
    min_inlier_fraction: float = 0.55
    max_rms: float = 0.1
    """RMS distance of the inliers to the target's surface (point to plane, m)."""
    ambiguity_offset: float = 3.0
    """The registration is repeated from starts this far (m) from the match, ahead, behind, left and right,
    and from ± `ambiguity_angle` …"""
    ambiguity_angle: float = math.radians(30.0)
    ambiguity_distance: float = 1.0
    ambiguity_ratio: float = 0.9
    """… a start converging to a pose at least `ambiguity_distance` (m) away (or turned by half
    `ambiguity_angle`) with an inlier fraction of at
    least `ambiguity_ratio` × the match's makes the match ambiguous (a uniform street, a row of
    look-alike buildings): it is rejected."""
    information_scale: float = 1e-3
    """The GICP Hessian treats point errors as independent; they are not. The fit's information is scaled
    by this …"""
    min_sigma_linear: float = 0.05
    min_sigma_angular: float = math.radians(0.3)
    """… and its covariance gets these floors (m, rad) added: what the fit does not see (map blur)."""
    small_correction_linear: float = 0.5
    small_correction_angular: float = math.radians(2.0)
    """A loop closure moving the current estimate less than this agrees with the map: accepted at once.
    A larger correction is a hypothesis until another loop closure agrees with it (within the same
    bounds), which a false match seldom finds."""
    hypothesis_keyframes: int = 10
    """A hypothesis not confirmed within this many keyframes is dropped."""
    chi2_threshold: float = 30.0
    """After optimizing, a loop closure whose planar error exceeds this χ² (3 dof) is rejected."""
    optimize_every_loop_closures: int = 1
    """Re-optimize the graph after this many new loop closures (and at the end). One: with
    `travel_between_closures` they come at most once per stretch of that length, and the map (and every
    later loop search) should stand corrected from the first."""


@dataclass(frozen=True)
class Se3PolishConfig:
    enabled: bool = True
    """After the planar SGD, polish the keyframe graph in full SE(3) (`frontends.slam3d.pose_graph3d`):
    loop closures then correct height, roll and pitch drift too."""
    max_iterations: int = 20
    """Levenberg–Marquardt iterations (it starts at the planar optimum: a few are enough)."""


@dataclass(frozen=True)
class Slam3DConfig:
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    se3_polish: Se3PolishConfig = field(default_factory=Se3PolishConfig)
