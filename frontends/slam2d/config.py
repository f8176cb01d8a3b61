"""Settings of the 2D laser SLAM frontend, with defaults meant to hold on logs never seen before."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from frontends.loop_search import LoopClosureSwitch, LoopSearchRadius

# Fixed values. Each was a setting once; one value served every log we have (ACES, the CSAIL log, the two
# RPLidar bags, the simulated buildings) and none is a property of a robot or a place, so they are no
# longer asked of users (issue 12: fewer settings). A configuration file naming one gets a line saying so.

RELIABLE_ODOMETRY_INTERVAL = 0.5
"""Odometry interpolated over a longer interval between messages (s) predicts less well: the search
window and the prior's σ are then scaled by `UNRELIABLE_ODOMETRY_SCALE`."""
UNRELIABLE_ODOMETRY_SCALE = 2.5
LOOP_QUERY_KEYFRAMES = 8
"""A loop query is the current keyframe with this many previous ones, seen from it: one 180° scan of a
corridor matches the wrong stretch of many corridors; a few metres of context rarely do."""
LOOP_QUERY_THINNING = 0.1
"""Loop query points are thinned to one per cell of this size (m)."""
SMALL_CORRECTION_LINEAR = 0.3
SMALL_CORRECTION_ANGULAR = math.radians(3.0)
"""A loop closure moving the current estimate less than this agrees with the map: accepted at once.
A larger correction is a hypothesis until another loop closure agrees with it (within the same bounds),
which a false match seldom finds."""
HYPOTHESIS_KEYFRAMES = 12
"""A hypothesis not confirmed within this many keyframes is dropped."""
LOOP_CANDIDATES_PER_KEYFRAME = 2
LOOP_SEARCH_EVERY_KEYFRAMES = 2
"""Loops are searched at every n-th keyframe (neighbouring keyframes see the same place)."""
OPTIMIZE_EVERY_LOOP_CLOSURES = 3
"""The online graph is re-optimized after this many new loop closures (and at the end)."""

RETIRED_SETTINGS: dict[tuple[str, str], str] = {
    ("odometry", "reliable_interval"): f"{RELIABLE_ODOMETRY_INTERVAL:g} s",
    ("odometry", "unreliable_scale"): f"{UNRELIABLE_ODOMETRY_SCALE:g}",
    ("loop_closure", "query_keyframes"): f"{LOOP_QUERY_KEYFRAMES}",
    ("loop_closure", "query_thinning"): f"{LOOP_QUERY_THINNING:g} m",
    ("loop_closure", "small_correction_linear"): f"{SMALL_CORRECTION_LINEAR:g} m",
    ("loop_closure", "small_correction_angular"): f"{math.degrees(SMALL_CORRECTION_ANGULAR):g} degrees",
    ("loop_closure", "hypothesis_keyframes"): f"{HYPOTHESIS_KEYFRAMES}",
    ("loop_closure", "candidates_per_keyframe"): f"{LOOP_CANDIDATES_PER_KEYFRAME}",
    ("loop_closure", "every_keyframes"): f"{LOOP_SEARCH_EVERY_KEYFRAMES}",
    ("loop_closure", "optimize_every_loop_closures"): f"{OPTIMIZE_EVERY_LOOP_CLOSURES}",
}
"""(section, key) of each setting that became a fixed value, and that value as a reader would write it."""


@dataclass(frozen=True)
class MatchingConfig:
    resolution: float = 0.05
    """Cell size of the likelihood grids (m)."""
    likelihood_sigma: float = 0.06
    """Spread of a return's likelihood around a reference point (m)."""
    point_sigma: float = 0.03
    """Noise of one laser point for point-to-line ICP (m)."""
    icp_max_distance: float = 0.3
    """Pairs farther apart than this are not paired (m)."""
    max_range: float = 30.0
    """Returns beyond this are dropped before matching: sparse and noisy far away (m)."""
    min_points: int = 20
    """A scan with fewer valid points is not matched (its pose follows the prior)."""
    information_scale: float = 0.05
    """The ICP Hessian treats point errors as independent; they are not (one wall, one bias). The edge
    information is the Hessian scaled by this, which the loop-closure χ² tests rely on."""
    deskew: bool = True
    """Motion-compensate scans whose messages say when each beam was taken (LaserScan `time_increment`
    not 0), under the motion predicted for the scan (`frontends.slam2d.deskew`). Off: every beam is taken
    as if at the stamp, as for scans without beam times."""
    min_match_interval: float = 0.1
    """A fast laser's scans are matched this many seconds apart (s), in whole strides of its scans; the
    scans between are posed between the matched ones on either side (`frontends.slam2d.cadence`). 0:
    every scan is matched."""


@dataclass(frozen=True)
class OdometryConfig:
    window_linear: float = 0.2
    """± search around the prediction when wheel odometry predicts the motion (m)."""
    window_angular: float = math.radians(6.0)
    window_linear_without_odometry: float = 0.5
    window_angular_without_odometry: float = math.radians(35.0)
    angular_step: float = math.radians(0.5)
    odometry_sigma_linear: float = 0.05
    """Wheel-odometry prior: σ = this + `odometry_sigma_per_metre` × distance moved (m)."""
    odometry_sigma_per_metre: float = 0.1
    odometry_sigma_angular: float = math.radians(2.0)
    odometry_sigma_per_radian: float = 0.1
    constant_velocity_sigma_linear: float = 0.5
    """Without odometry the prior is constant velocity, weak: it only steers featureless stretches."""
    constant_velocity_sigma_angular: float = math.radians(20.0)
    min_inlier_fraction: float = 0.25
    """A match pairing fewer scan points than this is not trusted: the pose follows the prior."""


@dataclass(frozen=True)
class KeyframeConfig:
    distance: float = 0.3
    angle: float = math.radians(12.0)
    max_turn_rate: float = math.radians(60.0)
    """A scan taken while the robot turns faster than this (rad/s) is not made a keyframe: a laser
    sweeping for 0.1–0.2 s smears it by several degrees, and a smeared scan must not enter the map."""
    local_map_keyframes: int = 25
    """The local map the odometry matches against: built from this many recent keyframes, then grown in
    place by the next few (`frontends.slam2d.slam.LOCAL_MAP_GROWTH`) before it is built again."""


@dataclass(frozen=True)
class LoopClosureConfig(LoopSearchRadius, LoopClosureSwitch):
    search_radius: float = 2.0
    max_search_radius: float = 30.0
    min_separation_keyframes: int = 40
    """Candidates must be at least this many keyframes older than the current one (not the local map)."""
    submap_keyframes: int = 12
    """The candidate's submap: this many keyframes on each side of it."""
    travel_between_closures: float = 2.0
    """After a keyframe closes a loop, keyframes search again once the robot has travelled this far (m;
    0: every searching keyframe). Closures a few keyframes apart match the same walls in nearly the same
    submap: their errors are one error counted again, each with the confidence of an independent one.
    On synthetic three-lap drives with ground truth, 2 m between closures left a quarter less trajectory
    error than closing at every searching keyframe, and CSAIL's replay took 12–19 % less time
    (`benchmarks/loop_spacing2d_bench.py`). The 3D SLAM's rule of the same name."""
    angular_window: float = math.radians(25.0)
    angular_step: float = math.radians(0.75)
    min_score: float = 0.55
    """Branch-and-bound acceptance: mean likelihood of the scan's points on the submap."""
    ambiguity_ratio: float = 0.9
    ambiguity_distance: float = 1.0
    """A match is ambiguous, and rejected, when a pose at least `ambiguity_distance` (m) away scores at least
    `ambiguity_ratio` of it: two look-alike rooms, a stretch of uniform corridor."""
    min_inlier_fraction: float = 0.6
    max_rms: float = 0.08
    """ICP verification: the refined match must pair most points closely (m)."""
    chi2_threshold: float = 30.0
    """After optimizing, a loop closure whose error exceeds this χ² (3 dof) is rejected as inconsistent."""


@dataclass(frozen=True)
class DataChecksConfig:
    """What the 2D SLAM input refuses from a log, before it reaches the matcher or a map. Passed to
    `log_input.read_odometry` and `log_input.scans_in_base_frame` (not part of `Slam2DConfig`, whose
    fields are the matcher's)."""

    min_usable_scan_share: float = 0.5
    """A log where fewer scans than this share have at least `matching.min_points` valid returns is
    refused: a map made of a few good scans among garbage would look like a result and not be one."""
    max_speed: float = 30.0
    """Odometry moving faster than this between two messages (m/s) is a glitch: the message is dropped."""
    max_turn_rate: float = 20.0
    """Odometry turning faster than this between two messages (rad/s) is a glitch: dropped."""
    world_extent: float = 100_000.0
    """Odometry poses farther than this from the origin (m) are dropped: no robot log spans 100 km, and
    maps sized from such a pose would need terabytes."""


@dataclass(frozen=True)
class Slam2DConfig:
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)

    def without_loop_closures(self) -> Slam2DConfig:
        """These settings with loop closing off: a tracking of the scans alone (the localizer's)."""
        return replace(self, loop_closure=replace(self.loop_closure, enabled=False))
