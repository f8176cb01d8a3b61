"""What a log replay needs of a SLAM frontend, whatever its sensor: the interface both `frontends.slam2d`
(laser scans) and `frontends.slam3d` (point clouds) implement, so that one replay drives either, and the
part of it both implementations share (`LogFrontendBase`).

A frontend is built on an open log and its sensor topic; the replay streams `measurements()` through
`add`, each giving an `Estimate` (for progress and the recording), then calls `finish` once. After that
the keyframe graph, every measurement's final pose and the map follow from optimized keyframe poses.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError, LogFileError, LogWarning, MapPlacementError
from frontends.logs import LogReader, TransformTree, tf_frame
from optimizer.graph import PoseGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

DEFAULT_BASE_FRAME = "base_link"


SessionArrays = tuple[dict[str, NDArray[Any]], Sequence[NDArray[Any]]]
"""Named arrays and each keyframe's points, what a session file keeps (`LogFrontend.session_content`)."""


@dataclass(frozen=True)
class FrontendOptions:
    """What the user may choose beside the frontend's own settings."""

    base_frame: str | None = None
    """The vehicle frame poses are of, named as tf2 names it (`tf_frame`: "/base_link" is "base_link");
    None: from the log (see `default_base_frame`)."""
    odometry_topic: str | None = None
    """The odometry topic (when the log has several)."""
    base_frame_origin: str = ""
    """Where `base_frame` comes from when not from the user (said in the error when tf does not link it)."""

    def __post_init__(self) -> None:
        if self.base_frame is not None:
            object.__setattr__(self, "base_frame", tf_frame(self.base_frame))


def default_base_frame(tree: TransformTree, sensor_frame: str) -> str:
    """The frame that carries the sensor, for laser and LiDAR logs alike: walking up the sensor's tf chain
    over static edges, the first frame whose edge to its parent is dynamic (REP 105's odom → base_link:
    the frame that moves); a chain of static edges only ends at `base_link` when it passes through it, else
    at its root. A sensor frame tf does not know is its own base."""
    frame = sensor_frame
    chain = [frame]
    while tree.parent(frame) is not None and tree.is_static(frame):
        frame = tree.parent(frame)  # type: ignore[assignment]
        if frame in chain:
            raise FrontendError(f"the transform tree has a cycle through {frame!r}")
        chain.append(frame)
    moving = tree.parent(frame) is not None  # stopped at a dynamic edge: `frame` is what moves
    if not moving and DEFAULT_BASE_FRAME in chain:
        return DEFAULT_BASE_FRAME
    return frame


class Estimate(Protocol):
    """What a frontend concluded about one measurement when it processed it (read-only: the frontends'
    estimates are frozen)."""

    @property
    def index(self) -> int: ...

    @property
    def stamp_ns(self) -> int: ...

    @property
    def keyframe(self) -> int: ...

    @property
    def new_loop_closures(self) -> tuple[tuple[int, int], ...]: ...


class StreamedFrontend(Protocol):
    """What mapping and localizing frontends share: the log's measurements streamed through `add`."""

    def measurements(self) -> Iterator[Any]:
        """The log's measurements, in sensor-time order, as `add` takes them."""
        ...

    def add(self, measurement: Any) -> Estimate: ...

    def finish(self) -> None:
        """The end of the stream: the last online optimization (mapping); the results need it."""
        ...


class LogFrontend(StreamedFrontend, Protocol):
    """A SLAM frontend fed from a log (see the module docstring for the order of calls)."""

    sensor_frame: str
    """The frame of the sensor's data ("" until the first measurement)."""
    base_frame: str | None
    """The frame poses are of; None when tf does not mount the sensor on it (poses of the sensor)."""
    odometry_topic: str | None
    """The odometry topic read, `tf <odom> -> <child>` when the odometry came from tf's odom edge, None
    without odometry."""

    def keyframe_graph(self, planar_poses: FloatArray | None = None) -> PoseGraph:
        """The SE(2) keyframe graph the backend optimizes, at the online estimate unless `planar_poses`."""
        ...

    @property
    def odometry_chain(self) -> FloatArray:
        """(K, 3) keyframe poses from odometry alone: the start that shows the map straighten out."""
        ...

    @property
    def stamps_ns(self) -> IntArray:
        """The stamp of every measurement with a pose (`estimates`)."""
        ...

    def session_content(self, planar_poses: FloatArray) -> SessionArrays:
        """What a session file keeps to localize in this map or continue it later: named arrays (keyframe
        poses at `planar_poses`, constraints, how every measurement hangs off its keyframe) and each
        keyframe's points in its own frame."""
        ...

    def keyframe_wheel_odometry(self) -> FloatArray | None:
        """(K, 3) the wheel-odometry pose (in the odometry's own frame) at each keyframe's first
        measurement, or None without odometry covering every keyframe: the paper's poor start."""
        ...

    def estimates(self, planar_poses: FloatArray) -> FloatArray:
        """Every measurement's pose given optimized keyframe poses: (S, 3), or (S, 4, 4) in 3D."""
        ...

    def map_export(self, planar_poses: FloatArray) -> Any:
        """The map at optimized keyframe poses: an occupancy grid (2D) or points (3D)."""
        ...

    def counts(self) -> dict[str, int]:
        """What was read, used, skipped and made (measurements, keyframes, constraints, …)."""
        ...

    def loop_closures(self) -> dict[str, Any]:
        """{"accepted", "rejected", "candidates": how candidate verifications ended}."""
        ...

    def settings(self) -> dict[str, Any]:
        """The frontend's configuration, as plain data."""
        ...


class ContinuingFrontend(LogFrontend, Protocol):
    """A frontend mapping on from a saved session."""

    def placement(self) -> dict[str, Any]:
        """Where the new run joined the saved map (measurement index, stamp, pose, match quality); {}
        when no measurement was placed in it."""
        ...


ON_SAVED_PATH = 1.0
"""A scan or cloud placed within this distance (m) of a saved keyframe is where the mapping robot was: the
saved map saw its surroundings from there and should match it."""
ON_PATH_MIN_MEASUREMENTS = 20
OFF_MAP_ON_PATH = 0.2
"""When more than this share of the measurements placed on the saved path (at least
`ON_PATH_MIN_MEASUREMENTS`) did not match the saved map, the placement is suspect: a log of another building
can match one corridor of the map well enough for a global fix, then drives "through" the map's walls,
tracked on its own scans. Correct localizations leave few of them unmatched: the second halves of the
shared logs and of FR079 and Intel in their first halves' maps 0–13 % (ACES 154 of 1 220: its half map lies
0.67 m from the full run's), each log in its own map 0 %. Logs placed in another building's map leave
39–70 %: ACES in CSAIL's map 58 % (39 % in a map of CSAIL 0.07 m from it, made by a trial change of the
loop closing), Intel in ACES's 51 %, in CSAIL's 70 %. The share was one half until ACES went unwarned in
that other map of CSAIL. `benchmarks/sessions_bench.py` prints both counts of each localization."""


def on_saved_path(positions: FloatArray, keyframe_positions: FloatArray) -> BoolArray:
    """Which of `positions` (S, 2) lie within `ON_SAVED_PATH` of a saved keyframe's position (K, 2); NaN
    rows (no pose) do not."""
    from scipy.spatial import cKDTree  # here: scipy.spatial costs every laser replay's start-up otherwise

    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    placed = np.all(np.isfinite(positions), axis=1)
    distance, _ = cKDTree(np.asarray(keyframe_positions, dtype=np.float64)).query(positions[placed], k=1)
    near = np.zeros(len(positions), dtype=bool)
    near[placed] = distance <= ON_SAVED_PATH
    return near


def unmatched_on_saved_path(positions: FloatArray, matched: BoolArray,
                            keyframe_positions: FloatArray) -> tuple[int, int]:
    """How many of the measurements at `positions` (S, 2; NaN rows skipped) lie on the saved path
    (`on_saved_path`), and how many of those were not `matched` to the saved map."""
    on_path = on_saved_path(positions, keyframe_positions)
    return int(on_path.sum()), int((on_path & ~np.asarray(matched, dtype=bool)).sum())


def checked_on_saved_path(log_path: object, what: str, positions: FloatArray, matched: BoolArray,
                          keyframe_positions: FloatArray) -> tuple[int, int]:
    """`unmatched_on_saved_path` of a localized log's `what` ("scans", "clouds"), with a `LogWarning` naming
    `log_path` when more than `OFF_MAP_ON_PATH` of those on the saved path did not match the map, or when none
    of those placed matched it at all: their poses were tracked on the log's own measurements from where
    the run was started (an `--initial-pose` far from the truth, outside the map, stays there)."""
    placed = len(np.asarray(matched))
    if placed and not np.any(matched):
        warnings.warn(f"{log_path}: none of the {placed} {what} placed in the saved map matched it: their "
                      f"poses were tracked on the log's own {what}, not in the map (is the log's start, or "
                      "--initial-pose, in the mapped place?)", LogWarning, stacklevel=3)
    on_path, unmatched = unmatched_on_saved_path(positions, matched, keyframe_positions)
    if on_path >= ON_PATH_MIN_MEASUREMENTS and unmatched > OFF_MAP_ON_PATH * on_path:
        warnings.warn(f"{log_path}: {unmatched} of the {on_path} {what} placed on the saved run's path "
                      f"(within {ON_SAVED_PATH:g} m of a keyframe) did not match the saved map: the log "
                      "may be of another place than the map, or the place changed (see the recording)",
                      LogWarning, stacklevel=3)
    return on_path, unmatched


@dataclass(frozen=True, eq=False)
class LocalizedMeasurement:
    """What a localizer in a saved map concluded about one measurement (scan or cloud) when it processed it;
    each sensor's record adds its own fields after these."""

    index: int
    stamp_ns: int
    pose: FloatArray
    """In the map frame: (x, y, θ), or the base's 4×4 pose in 3D; NaN while not localized."""
    localized: bool
    matched: bool
    """It matched the saved map (False: the pose is the odometry's prediction, or unknown)."""
    score: float
    """How well it matched, in [0, 1] (NaN when not matched)."""
    inlier_fraction: float
    """Share of its points paired with the map (0 when not matched)."""
    rms: float
    """Residual of the paired points (m); inf when none."""


@dataclass(frozen=True, eq=False)
class ScanLocalizations:
    """How every scan of a localized log ended, in log order (the 3D frontend's `CloudLocalizations` adds
    to it; here rather than in `frontends.slam2d` so that the 3D frontend never imports the 2D one)."""

    stamps_ns: IntArray
    poses: FloatArray
    """(S, 3) in the map frame; NaN for a scan never placed."""
    localized: BoolArray
    """Placed when processed (tracking, or the global fix at this scan)."""
    matched: BoolArray
    """Matched the map when processed (else its pose is the odometry's prediction, or none)."""
    recovered: BoolArray
    """Not placed when processed; a later global fix gave its pose back."""
    score: FloatArray
    """Correlative score of the match in [0, 1] (NaN when not matched)."""
    inlier_fraction: FloatArray
    rms: FloatArray
    """ICP residual (m) of the paired points (inf when none)."""
    global_fixes: IntArray
    """The scans at which a global localization was accepted."""
    tracked: BoolArray | None = None
    """Not matched to the saved map but to the rolling local map (recent scans at their tracked poses with
    the saved keyframes nearby: outside the saved map); `score`/`inlier_fraction`/`rms` are that match's.
    None: all False."""
    online_poses: FloatArray | None = None
    """The poses as given when each scan was processed (or recovered), before the offline smoothing made
    `poses`; None: `poses` are those."""
    smoothed: BoolArray | None = None
    """The scans whose pose the smoothing gave (None: none)."""
    between: BoolArray | None = None
    """A fast laser's scans between two the localizer was given (`frontends.slam2d.cadence`): posed between
    them, not matched themselves (`localized` True). None: all False."""

    @property
    def posed_between(self) -> BoolArray:
        return np.zeros(len(self.stamps_ns), dtype=bool) if self.between is None else self.between

    @property
    def tracked_outside(self) -> BoolArray:
        return np.zeros(len(self.stamps_ns), dtype=bool) if self.tracked is None else self.tracked

    @property
    def has_pose(self) -> BoolArray:
        return self.localized | self.recovered

    @property
    def placed_stamps_ns(self) -> IntArray:
        """The stamps of the measurements placed in the map (the others have no pose)."""
        return self.stamps_ns[self.has_pose]

    @property
    def placed_poses(self) -> FloatArray:
        """The map-frame pose of every measurement at `placed_stamps_ns`."""
        return self.poses[self.has_pose]

    def counts(self) -> dict[str, int]:
        """The JSON summary's localization counts (named "scans" for clouds too, as in 2D)."""
        return {"scans_localized": int(self.has_pose.sum()),
                "scans_localized_when_processed": int(self.localized.sum()),
                "scans_matched": int(self.matched.sum()),
                "scans_tracked_outside_map": int(self.tracked_outside.sum()),
                "scans_between": int(self.posed_between.sum()),
                "scans_recovered": int(self.recovered.sum()),
                "scans_never_localized": int((~self.has_pose).sum()),
                "global_fixes": len(self.global_fixes)}


class _PlacedMeasurements(Protocol):
    @property
    def placed_stamps_ns(self) -> IntArray: ...

    @property
    def placed_poses(self) -> FloatArray: ...


LocalizationsT = TypeVar("LocalizationsT", bound=_PlacedMeasurements)


class SavedMapLocalization(Generic[LocalizationsT]):
    """What a frontend localizing in a saved map has whatever its sensor (put before its `LogFrontendBase`
    subclass): after `finish`, `localizations` says how every measurement ended, and `stamps_ns` /
    `localized_poses` are the measurements with a pose."""

    _localizations: LocalizationsT | None = None

    @property
    def localizations(self) -> LocalizationsT:
        if self._localizations is None:
            raise FrontendError("the frontend has not finished")
        return self._localizations

    @property
    def stamps_ns(self) -> IntArray:
        """The stamps of the measurements placed in the map (the others have no pose)."""
        return self.localizations.placed_stamps_ns

    def localized_poses(self) -> FloatArray:
        """The map-frame pose of every measurement at `stamps_ns`: (S, 3), or (S, 4, 4) in 3D."""
        return self.localizations.placed_poses


class _SlamResult(Protocol):
    @property
    def odometry_chain(self) -> FloatArray: ...


ConfigT = TypeVar("ConfigT")
ResultT = TypeVar("ResultT", bound=_SlamResult)


class LogFrontendBase(Generic[ConfigT, ResultT]):
    """What both `LogFrontend`s hold: the log and topic, its tf, the odometry topic chosen, the frames
    (`base_frame` the one requested until the first measurement tells), and the SLAM's result once
    `finish` set `_result`."""

    def __init__(self, log: LogReader, topic: str, config: ConfigT, options: FrontendOptions | None) -> None:
        options = options or FrontendOptions()
        self.config = config
        self._log = log
        self._topic = topic
        self.odometry_topic = log.odometry_topic(options.odometry_topic)
        self._tree = log.transform_tree()
        self.sensor_frame = ""
        self.base_frame: str | None = options.base_frame
        self._requested_base_frame = options.base_frame
        self._base_frame_origin = options.base_frame_origin
        self._result: ResultT | None = None

    def _odometry_read(self, parent_frame: str, child_frame: str) -> None:
        """The log's odometry was read: from tf's `parent_frame` → `child_frame` edge when the log has no
        odometry topic (`LogReader.odometry`), which `odometry_topic` then says."""
        if self.odometry_topic is None:
            self.odometry_topic = f"tf {parent_frame} -> {child_frame}"

    def _finished(self, finish: Callable[[], ResultT]) -> ResultT:
        """`finish()` (the SLAM's), its `MapPlacementError` (a continued run that never matched the saved
        map) naming the log."""
        try:
            return finish()
        except MapPlacementError as error:
            raise MapPlacementError(f"{self._log.path}: {error}") from None

    def _warn_if_odometry_covered_nothing(self, odometry_stamps_ns: IntArray, stamps_ns: IntArray, used: int,
                                          measurements: str, done: str, source: str = "") -> None:
        """Odometry that covers none of the measurements' stamps (stamped on another clock: time since boot
        beside the sensor's epoch time) was not used at all (`used` of them got it): a warning, not a silent
        run without it. `measurements` ("scans"), what was `done` to them without it, the odometry's
        `source` (" on /odom")."""
        if used or not len(odometry_stamps_ns) or not len(stamps_ns):
            return
        odometry, own = odometry_stamps_ns * 1e-9, stamps_ns * 1e-9
        warnings.warn(f"{self._log.path}: the odometry{source} covers none of the {len(own)} {measurements}' "
                      f"stamps (it runs from {odometry[0]:.3f} to {odometry[-1]:.3f} s, the {measurements} "
                      f"from {own[0]:.3f} to {own[-1]:.3f} s; another clock?): the {measurements} were "
                      f"{done} without it", LogWarning, stacklevel=3)

    def _unlinked_base_frame(self, sensor_frame: str, sensor: str) -> LogFileError:
        """The error for a base frame the user named that tf does not link to the sensor's frame: poses of
        the sensor given as poses of a misspelt base would be silently wrong."""
        known = ", ".join(sorted(self._tree.frames)) or "none"
        base = repr(self._requested_base_frame) + (f" ({self._base_frame_origin})" if self._base_frame_origin
                                                   else "")
        return LogFileError(self._log.path, f"tf does not link base frame {base} to the {sensor} frame "
                                            f"{sensor_frame!r} (frames in tf: {known})")

    @property
    def result(self) -> ResultT:
        if self._result is None:
            raise FrontendError("the frontend has not finished")
        return self._result

    @property
    def odometry_chain(self) -> FloatArray:
        return self.result.odometry_chain

    def keyframe_wheel_odometry(self) -> FloatArray | None:
        return None

    def settings(self) -> dict[str, Any]:
        return dataclasses.asdict(self.config)  # type: ignore[call-overload]
