"""The Rerun recording of a replay. The only module of the project that imports rerun.

In the style of evo's rerun_bridge: names of timelines and entities are constants, there is one `log_*` /
`send_*` function per concept, and the recording stream is always passed explicitly (never rerun's global
one), so several recordings can be written side by side.

Layout of a recording (the 2D view looks at `/`, where `world` is mirrored in y so that the world is
drawn y up, north up, like `<stem>_map.png`):
- `world` (static): that mirror;
- `world/initial_trajectory` (static, faint): the trajectory before optimization;
- `world/trajectory` and `world/loop_closures` on the timeline `iteration`: the trajectory and the
  loop-closure constraints (|b − a| > 1) after every iteration, drawn on top of everything else (thinned
  on huge graphs, except the final iteration: see `IterationRecorder`);
- log replays add `world/keyframes/kNNNNNN/scan` and the occupancy grid (`pipeline.recording.map2d`);
- `optimizer/log10_chi2` on `iteration`: the one χ² plot, on a log scale (Rerun 0.41 plots have no log
  axis, so the series is log10 χ²); `optimizer/chi2` keeps the plain values for readers of the data;
- `optimizer/stage` on `iteration`: a text log naming the stage and its iteration number, without the
  repeats of an iteration that did not change χ²;
- `legend` (static): what each colour is.

Recordings hold only our own timelines: the SDK's automatic `log_time` and `log_tick` are switched off.

The timeline `iteration` is one counter across all stages: 0 is the initial estimate, then 1, 2, … for
every iteration the optimizer yields (SGD, then the polish). Per-iteration data is sent in columns
(`send_columns`), a batch of iterations at a time, which is what keeps large recordings compact and fast.
"""

from __future__ import annotations

import contextlib
import itertools
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Protocol

# rerun's Rust side logs straight to stderr, in colour (a WARN when an encoder cannot finish, an ERROR when
# the disk fills); what matters of it reaches us as exceptions, which we word ourselves in one line. Set
# before rerun is first imported, since that is when it reads the filter; RUST_LOG set by the user wins.
os.environ.setdefault("RUST_LOG", "off")

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings
from numpy.typing import NDArray
from rerun.components import LineStrip2DBatch
from rerun.encodings import Vec2DBatch

from optimizer.iteration import ESTIMATE, Iteration
from pipeline.errors import OutputError, PipelineError
from pipeline.recording.stillness import finite_extent, moved_within

if TYPE_CHECKING:
    from frontends.protocol import ScanLocalizations

APPLICATION_ID = "sgdslam"
ITERATION_TIMELINE = "iteration"
SCAN_TIMELINE = "scan"
TIME_TIMELINE = "time"

WORLD_ENTITY = "world"
INITIAL_TRAJECTORY_ENTITY = "world/initial_trajectory"
TRAJECTORY_ENTITY = "world/trajectory"
LOOP_CLOSURES_ENTITY = "world/loop_closures"
KEYFRAMES_ENTITY = "world/keyframes"
CHI2_ENTITY = "optimizer/chi2"
MATCH_QUALITY_ENTITY = "localization"
LOG10_CHI2_ENTITY = "optimizer/log10_chi2"
STAGE_ENTITY = "optimizer/stage"
LEGEND_ENTITY = "legend"
RUN_PROPERTY = "replay"
OPTIMIZATION_PROPERTY = "optimization"

VIEWER_BACKGROUND = (13, 13, 13)
"""The 2D view's background, set in the blueprint (the viewer's own dark grey, made explicit so that the
colours below keep their contrast against it)."""
TRAJECTORY_COLOR = (64, 170, 255, 255)
INITIAL_TRAJECTORY_COLOR = (150, 150, 150, 90)
LOOP_CLOSURE_COLOR = (255, 80, 220, 200)
MAP_COLOR = (235, 235, 225, 255)


def ui_points(size: float) -> float:
    """A radius or line width in UI points (pixels at 100 % UI scaling), not scene units: rerun's
    `Radius.ui_points` of one size, which it stores as a negative radius."""
    return float(rr.Radius.ui_points(size))  # type: ignore[arg-type]  # one number in, one number out


LINE_WIDTH = ui_points(1.25)
MAP_POINT_RADIUS = ui_points(1.25)

# 2D draw order (higher on top): the occupancy grid under the walls, the animated estimate above all.
OCCUPANCY_DRAW_ORDER = -20.0
INITIAL_TRAJECTORY_DRAW_ORDER = 10.0
MAP_DRAW_ORDER = 20.0
LOOP_CLOSURE_DRAW_ORDER = 30.0
TRAJECTORY_DRAW_ORDER = 40.0

DEFAULT_BATCH_BYTES = 32 * 1024 * 1024
"""How much per-iteration geometry `IterationRecorder` buffers before sending it as one column batch."""

DEFAULT_MAX_POINTS_PER_ITERATION = 100_000
"""Above this many poses (or half as many loop closures) `IterationRecorder` thins each iteration's
geometry, except the final iteration's."""

STILL_FRACTION = 1e-3
"""A graph replay redraws an iteration only when a pose moved more than this fraction of the map's extent
since the last drawn one: about one pixel of a 1000-pixel view framing the map, so nothing visible is
left out, while the many iterations that only polish the last digits cost no geometry."""

VIEW_MARGIN = 0.05
"""The default 2D view frames the final map with this fraction of its extent around it."""

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Bounds = tuple[float, float, float, float]
"""(x_min, y_min, x_max, y_max) in world metres."""


class IterationSink(Protocol):
    """More per-iteration recording beside the 2D trajectory (e.g. 3D keyframe poses)."""

    def add(self, step: int, iteration: Iteration) -> None: ...

    def flush(self) -> None: ...


class PoseBatches:
    """An `IterationSink` that buffers every iteration's keyframe poses (as float32) and sends them in
    column batches of about `DEFAULT_BATCH_BYTES`: `_send_batch(steps, poses (T, K, …), final)`, `final`
    once the run is over."""

    def __init__(self, recording: rr.RecordingStream) -> None:
        self._recording = recording
        self._steps: list[int] = []
        self._poses: list[NDArray[np.float32]] = []
        self._buffered_bytes = 0

    def add(self, step: int, iteration: Iteration) -> None:
        """Buffer the keyframe poses of the iteration logged at `step`."""
        self._steps.append(step)
        self._poses.append(np.asarray(self._keyframe_poses(iteration), dtype=np.float32))
        self._buffered_bytes += self._poses[-1].nbytes
        if self._buffered_bytes >= DEFAULT_BATCH_BYTES:
            self.flush(final=False)

    def flush(self, *, final: bool = True) -> None:
        """Send what is buffered (`final`: the run is over, which is when the sinks are flushed)."""
        if self._steps:
            self._send_batch(np.asarray(self._steps, dtype=np.int64), np.stack(self._poses), final=final)
        self._steps, self._poses = [], []
        self._buffered_bytes = 0

    def _keyframe_poses(self, iteration: Iteration) -> NDArray[np.floating]:
        return iteration.poses

    def _send_batch(self, steps: IntArray, poses: NDArray[np.float32], *, final: bool) -> None:
        raise NotImplementedError


def create_recording(path: Path, *, name: str, with_map: bool = False) -> rr.RecordingStream:
    """A new recording stream that saves to `path` (with the default blueprint; `with_map` adds the views
    of a log replay: the scan playback tab), the world mirrored to y up, and no automatic timelines.
    Once the final map is known, `send_blueprint` replaces the blueprint by one that frames it. Raises
    `OutputError` naming `path` and why when it cannot be written there."""
    # rerun's save() never returns when its file writer fails on the first bytes (seen with a full disk):
    # make sure there is room for them first.
    reason = _write_probe_failure(path, sync=False)
    if reason is not None:
        raise OutputError(f"{path}: cannot write the recording: {reason}")
    recording = rr.RecordingStream(APPLICATION_ID)
    # RERUN=off in the environment: the SDK would drop everything silently. (rerun's stub types
    # is_enabled unbound.)
    if not recording.is_enabled():  # type: ignore[misc]
        raise OutputError(f"{path}: cannot write the recording: Rerun logging is disabled by the environment "
                          f"(RERUN={os.environ.get('RERUN', '')}); unset RERUN to replay")
    if with_map:
        from pipeline.recording import scans  # the scans module builds on this one

        blueprint = scans.log_replay_blueprint()
    else:
        blueprint = default_blueprint()
    try:
        recording.save(path)
        # What `save(path, default_blueprint=...)` does, without its leaked stream (see `send_blueprint`).
        send_blueprint(recording, blueprint, make_active=False)
    except (OSError, RuntimeError) as error:
        raise OutputError(f"{path}: cannot write the recording: {_write_failure(path, error)}") from error
    _saved_to[id(recording)] = path
    # Only our timelines (`iteration`, `scan`, `time`): the SDK would add `log_time`/`log_tick` to every
    # temporal `log` call, a timeline a user would pick and find nearly empty.
    recording.set_log_time_enabled(False)
    recording.set_log_tick_enabled(False)
    recording.send_recording_name(name)
    # Rerun's 2D views point y down (image rows); mirroring `world` once draws every map y up.
    recording.log(WORLD_ENTITY, rr.Transform3D(mat3x3=np.diag([1.0, -1.0, 1.0])), static=True)
    return recording


_saved_to: dict[int, Path] = {}
"""The file each open recording saves to (by the stream's id), to name it when closing it fails."""


_FLUSH_WAIT_S = 2.0
"""How long `close_recording` waits for the flush before it checks the disk is still writable."""


def close_recording(recording: rr.RecordingStream) -> None:
    """Flush everything to the file and close it (the file is complete only after this). Raises
    `OutputError` naming the file, and why (disk full, read-only …), when it could not be written."""
    path = _saved_to.pop(id(recording), None)
    where = "the recording" if path is None else str(path)
    try:
        while True:
            try:
                recording.flush(timeout_sec=_FLUSH_WAIT_S)
                break
            except RuntimeError as error:
                if path is None or "timed out" not in str(error):
                    raise
                # When its file writer dies on a full disk, rerun's flush sometimes waits for ever rather
                # than failing: a flush that takes long is only waited for while the disk takes data.
                reason = _write_probe_failure(path, sync=True)
                if reason is not None:
                    raise OutputError(f"{where}: cannot write the recording: {reason}") from error
        recording.disconnect()
        # The blueprint streams `send_blueprint` disconnected are only freed by this sweep.
        rerun_bindings.flush_and_cleanup_orphaned_recordings()
    except RuntimeError as error:  # rerun's file writer stopped; it says only that, not why
        reason = " ".join(str(error).split()) if path is None else _write_failure(path, error)
        raise OutputError(f"{where}: cannot write the recording: {reason}") from error


_PROBE_BYTES = 64 * 1024
"""What a write probe writes: more than the recording's header and blueprint."""


def _write_failure(path: Path, error: BaseException) -> str:
    """Why `path` could not be written: the OS's reason (disk full, read-only, quota), found by writing a
    probe beside it; rerun's own message when the probe goes through."""
    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    return _write_probe_failure(path, sync=True) or " ".join(str(error).split())


def _write_probe_failure(path: Path, *, sync: bool) -> str | None:
    """The OS's reason a file of `_PROBE_BYTES` cannot be written beside `path` now, None when it can."""
    probe = path.with_name(f".{path.name}.probe")
    try:
        descriptor = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            remaining = memoryview(bytes(_PROBE_BYTES))
            while remaining:  # a nearly full disk takes part of a write; the next one fails with ENOSPC
                remaining = remaining[os.write(descriptor, remaining):]
            if sync:
                os.fsync(descriptor)
        finally:
            os.close(descriptor)
    except OSError as error:
        return error.strerror or str(error)
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()
    return None


def visual_bounds(bounds: Bounds | None) -> rrb.VisualBounds2D | None:
    """What a 2D view looking at `/` shows to frame `bounds` (world metres) with a margin."""
    if bounds is None:
        return None
    x_min, y_min, x_max, y_max = bounds
    margin = VIEW_MARGIN * max(x_max - x_min, y_max - y_min, 1.0)
    # In the view's space y is mirrored: world y ∈ [y_min, y_max] is drawn at −y.
    return rrb.VisualBounds2D(x_range=[x_min - margin, x_max + margin],
                              y_range=[-y_max - margin, -y_min + margin])


def map_view(
    *, bounds: Bounds | None = None, hidden: Sequence[str] = (), excluded: Sequence[str] = ()
) -> rrb.Spatial2DView:
    """The world seen from `/` (so the y mirror of `world` applies), framing `bounds` with a margin;
    the entities in `hidden` start switched off (a user turns them on in the blueprint tree), those in
    `excluded` belong to other views."""
    return rrb.Spatial2DView(
        origin="/",
        contents=[f"/{WORLD_ENTITY}/**", *(f"- /{path}" for path in excluded)],
        name="map and pose graph",
        background=VIEWER_BACKGROUND,
        visual_bounds=visual_bounds(bounds),
        overrides={f"/{path}": rrb.EntityBehavior(visible=False) for path in hidden},
    )


def default_blueprint(
    *, bounds: Bounds | None = None, hidden: Sequence[str] = (), extra_tabs: Sequence[rrb.View] = (),
    excluded: Sequence[str] = (), timeline: str = ITERATION_TIMELINE,
    side: Sequence[rrb.View | rrb.Tabs] | None = None,
) -> rrb.Blueprint:
    """The map and graph in 2D (tabs: `extra_tabs` beside it) beside the `side` views (by default the χ²
    plot and the stage log) and the legend; the time panel on `timeline`."""
    main: rrb.View | rrb.Tabs = map_view(bounds=bounds, hidden=hidden, excluded=excluded)
    if extra_tabs:
        main = rrb.Tabs(main, *extra_tabs)
    side = chi2_views() if side is None else side
    return layout(main, side, row_shares=[2] * len(side) + [1], timeline=timeline)


def chi2_views() -> list[rrb.View]:
    """The χ² plot (log10) and the stage log."""
    return [rrb.TimeSeriesView(origin=LOG10_CHI2_ENTITY, name="χ² (log10)"),
            rrb.TextLogView(origin=STAGE_ENTITY, name="stages")]


def layout(main: rrb.View | rrb.Tabs, side: Sequence[rrb.View | rrb.Tabs], *, row_shares: Sequence[int],
           column_shares: Sequence[int] = (3, 1), timeline: str = ITERATION_TIMELINE,
           play_state: Literal["following", "paused", "playing"] | None = "following") -> rrb.Blueprint:
    """`main` beside a column of the `side` views over the legend; the time panel on `timeline`, the side
    panels collapsed so the views have the room."""
    return rrb.Blueprint(
        rrb.Horizontal(
            main,
            rrb.Vertical(*side, rrb.TextDocumentView(origin=LEGEND_ENTITY, name="legend"),
                         row_shares=list(row_shares)),
            column_shares=list(column_shares),
        ),
        # Following: the viewer opens on the final (straight) map; play restarts from iteration 0.
        rrb.TimePanel(timeline=timeline, state="collapsed", play_state=play_state),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def send_blueprint(recording: rr.RecordingStream, blueprint: rrb.Blueprint, *,
                   make_active: bool = True) -> None:
    """Make `blueprint` the recording's default (replacing the one `create_recording` sent, once the final
    map, hence the framing, is known): rerun's `send_blueprint`, without its leak.

    rerun 0.41 builds a blueprint in a stream of its own (`create_in_memory_blueprint`) that is never
    freed: its memory sink and the stream keep each other alive, with two threads and the replay's data
    they reference, 13-19 MB a replay in a batch script (benchmarks/batch_memory.py). Built in a stream
    we disconnect, it is freed. The private names used here are pinned by the rerun-sdk bound in
    pyproject.toml."""
    stream = rr.RecordingStream._from_native(rerun_bindings.new_blueprint(
        application_id=APPLICATION_ID, make_default=False, make_thread_default=False, default_enabled=True))
    try:
        stream.set_time("blueprint", sequence=0)
        blueprint._log_to_stream(stream)
        rerun_bindings.send_blueprint(stream.memory_recording().storage, make_active, True,
                                      recording=recording.to_native())
    finally:
        stream.disconnect()


def world_bounds(*point_sets: NDArray[np.floating]) -> Bounds:
    """The (x_min, y_min, x_max, y_max) of the finite 2D points in all `point_sets`."""
    arrays = [np.asarray(s, dtype=np.float64) for s in point_sets]
    # (a keyframe scan may hold no point: numpy cannot infer the width of an empty array's rows)
    points = np.concatenate([a.reshape(len(a), -1)[:, :2] for a in arrays if a.size] + [np.zeros((0, 2))])
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) == 0:
        points = np.zeros((1, 2))
    low, high = points.min(axis=0), points.max(axis=0)
    return float(low[0]), float(low[1]), float(high[0]), float(high[1])


def log_run_properties(recording: rr.RecordingStream, properties: Mapping[str, str | int | float], *,
                       name: str = RUN_PROPERTY) -> None:
    """What was replayed and how (input file, method, counts), as a recording property `name`."""
    values = {key: [value] for key, value in properties.items()}
    recording.send_property(name, rr.AnyValues(**values))  # type: ignore[arg-type]  # its stub's first keyword


def log_note(recording: rr.RecordingStream, text: str) -> None:
    """A warning at the top of the stage log (at iteration 0): what a reader must know about the plot."""
    recording.set_time(ITERATION_TIMELINE, sequence=0)
    recording.log(STAGE_ENTITY, rr.TextLog(text, level="WARN"))
    recording.reset_time()


NO_LOOP_CLOSURES_NOTE = ("no loop closures: the constraints form a chain that holds exactly, so the optimum "
                         "is χ² = 0 and χ² at round-off is left out of the log10 plot")


LEGEND_ROWS: dict[str, tuple[tuple[int, ...], str]] = {
    "estimate": (TRAJECTORY_COLOR, "the trajectory at the selected iteration (drawn on top)"),
    "loop closures": (LOOP_CLOSURE_COLOR, "loop-closure constraints at that iteration"),
    "start": (INITIAL_TRAJECTORY_COLOR, "the starting estimate (faint)"),
    "map": (MAP_COLOR, "each keyframe's scan at its pose of that iteration (log replays)"),
}


LEGEND_NOTE = ("\nThe time panel's `iteration` is one counter over every optimized start; "
               "the final trajectory and wheel odometry are off by default (blueprint tree).")
Legend = Mapping[str, tuple[tuple[int, ...], str]]
"""Legend rows: name → (colour, what it shows)."""


def log_legend(recording: rr.RecordingStream, extra: Legend | None = None, *, rows: Legend = LEGEND_ROWS,
               note: str = LEGEND_NOTE) -> None:
    """A static markdown table naming every colour of the map view (Rerun's spatial views have no
    legend of their own): `rows` and `extra`, then `note`."""
    lines = ["| colour | what |", "|---|---|"]
    lines += [f"| {name} `#{color[0]:02x}{color[1]:02x}{color[2]:02x}` | {text} |"
              for name, (color, text) in {**rows, **(extra or {})}.items()]
    recording.log(LEGEND_ENTITY, rr.TextDocument("\n".join([*lines, note] if note else lines),
                                                 media_type=rr.MediaType.MARKDOWN), static=True)


def log_styles(recording: rr.RecordingStream) -> None:
    """Static colours, widths, draw order, labels and series names; the per-iteration columns then carry
    geometry only."""
    for entity, color, draw_order in ((TRAJECTORY_ENTITY, TRAJECTORY_COLOR, TRAJECTORY_DRAW_ORDER),
                                      (LOOP_CLOSURES_ENTITY, LOOP_CLOSURE_COLOR, LOOP_CLOSURE_DRAW_ORDER)):
        recording.log(entity, rr.LineStrips2D.from_fields(colors=[color], radii=[LINE_WIDTH],
                                                          draw_order=draw_order), static=True)
    recording.log(CHI2_ENTITY, rr.SeriesLines(names="χ²"), static=True)
    recording.log(LOG10_CHI2_ENTITY, rr.SeriesLines(names="log10 χ²"), static=True)


def log_initial_trajectory(recording: rr.RecordingStream, poses: FloatArray) -> None:
    """The starting estimate, static, drawn faintly under the optimised one."""
    log_static_trajectory(recording, INITIAL_TRAJECTORY_ENTITY, poses, INITIAL_TRAJECTORY_COLOR,
                          draw_order=INITIAL_TRAJECTORY_DRAW_ORDER)


def log_static_trajectory(recording: rr.RecordingStream, entity: str, poses: FloatArray,
                          color: tuple[int, ...], *, draw_order: float | None = None) -> None:
    """A static trajectory beside the animated estimate: the starting estimate, what wheel odometry alone
    believed, the final poses."""
    recording.log(entity, rr.LineStrips2D([poses[:, :2].astype(np.float32)], colors=[color],
                                          radii=[LINE_WIDTH], draw_order=draw_order), static=True)


def transform3d_columns(translations: NDArray[np.float32],
                        quaternions: NDArray[np.float32]) -> list[rr.ComponentColumn]:
    """`Transform3D` columns of (T, 3) translations and (T, 4) quaternions (x, y, z, w), the component
    columns built directly: `Transform3D.columns` validates every field of the archetype, many times the
    cost, and the recordings call this once per keyframe."""
    return [
        rr.ComponentColumn(rr.Transform3D.descriptor_translation(),
                           rr.components.Translation3DBatch(translations)),
        rr.ComponentColumn(rr.Transform3D.descriptor_quaternion(),
                           rr.components.RotationQuatBatch(quaternions)),
    ]


def send_strips(recording: rr.RecordingStream, entity: str, steps: IntArray,
                strips: NDArray[np.float32]) -> None:
    """(K, S, P, 2) strips: S line strips of P points per iteration, row k logged at `steps[k]` (nothing
    when S = 0): the trajectory (S = 1) or the two-point loop-closure segments."""
    count, length = strips.shape[1:3]
    if count == 0:
        return
    columns = rr.LineStrips2D.columns(strips=_equal_length_strips(strips.reshape(-1, length, 2)))
    recording.send_columns(entity, indexes=[_iteration_column(steps)],
                           columns=columns.partition(np.full(len(steps), count)))


ROUND_OFF_CHI2 = 1e-12
"""Below this, the χ² of a graph without loop closures is round-off of zero (a chain is exactly
consistent), not a cost worth a point on the log plot."""


def send_match_quality(recording: rr.RecordingStream, localizations: ScanLocalizations,
                       series: tuple[str, ...]) -> None:
    """Each matched measurement's `series` (fields of `localizations`: a localization's match quality), on
    the `scan` timeline."""
    matched = np.flatnonzero(localizations.matched & np.isfinite(localizations.score))
    if len(matched) == 0:
        return
    index = [rr.TimeColumn(SCAN_TIMELINE, sequence=matched.astype(np.int64))]
    for name in series:
        shown = np.asarray(getattr(localizations, name), dtype=np.float64)[matched]
        recording.send_columns(f"{MATCH_QUALITY_ENTITY}/{name}", indexes=index,
                               columns=rr.Scalars.columns(scalars=shown))


def _equal_length_strips(points: NDArray[np.float32]) -> pa.Array:
    """(S, P, 2) points as an Arrow array of S line strips of P points each.

    Rerun's own conversion walks the strips one by one in Python (half a second for the million segments
    of a 10,000-pose graph over 100 iterations); with equal lengths the offsets are a single arange.
    """
    count, length = points.shape[:2]
    values = Vec2DBatch(np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 2)).as_arrow_array()
    offsets = pa.array(np.arange(0, count * length + 1, length, dtype=np.int32))
    return pa.ListArray.from_arrays(offsets, values, type=_LINE_STRIP_TYPE)


_LINE_STRIP_TYPE = LineStrip2DBatch([np.zeros((2, 2), dtype=np.float32)]).as_arrow_array().type


def _iteration_column(steps: IntArray) -> rr.TimeColumn:
    return rr.TimeColumn(ITERATION_TIMELINE, sequence=np.asarray(steps, dtype=np.int64))


class IterationRecorder:
    """Logs every iteration of an optimization on the `iteration` timeline.

    Iterations are buffered (positions as float32, which is what Rerun stores) and sent in column batches
    of about `batch_bytes`, so memory stays bounded on large graphs and the file stays compact.

    Huge graphs are thinned per iteration so the recording stays bounded (at 10⁶ poses × 100 iterations
    the full trajectories alone would be gigabytes): when the graph has more than `max_points` poses, each
    iteration's trajectory is the line through every k-th pose (and the last), with the smallest k that
    keeps it to `max_points` points; when it has more than `max_points` / 2 loop closures, every k-th loop
    closure is drawn, likewise. The most recent iteration (the final one, once `flush` is called at the
    end) is always sent whole. Graphs within both limits are recorded in full at every iteration.

    With `still_move` (m), an iteration whose poses all lie within it of the last drawn iteration's gets
    no geometry row (χ² and stage only): the viewer keeps showing the last row, which is that close.
    `still_fraction` sets that distance relative to the iteration's extent instead (`STILL_FRACTION`:
    about a pixel of a view framing the whole map), for graphs whose units and size are unknown.

    Without loop closures the optimum is χ² = 0 exactly, so the log plot leaves out χ² ≤ `ROUND_OFF_CHI2`
    (the caller logs a note saying the graph is already consistent); the plain χ² keeps every value.
    """

    def __init__(
        self,
        recording: rr.RecordingStream,
        loop_from: IntArray,
        loop_to: IntArray,
        *,
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        max_points: int = DEFAULT_MAX_POINTS_PER_ITERATION,
        still_move: float | None = None,
        still_fraction: float | None = None,
    ) -> None:
        if max_points < 2:
            raise PipelineError(f"max_points must be at least 2, got {max_points}")
        self._recording = recording
        # (L, 2) the two poses of each loop closure, all of them and those a thinned iteration draws.
        self._loops = np.column_stack([loop_from, loop_to]).astype(np.int64)
        shown = _every_kth(len(self._loops), max_points // 2, keep_last=False)
        self._thinned_loops = self._loops if shown is None else self._loops[shown]
        self._chi2_floor = ROUND_OFF_CHI2 if len(self._loops) == 0 else 0.0
        self._max_points = max_points
        self._batch_bytes = batch_bytes
        self._still_move = still_move
        self._still_fraction = still_fraction
        self._last_drawn: NDArray[np.float64] | None = None
        # Per buffered iteration its trajectory and loop-closure segments, None where its geometry is not
        # sent (see `still_move`).
        self._geometry_rows: list[tuple[NDArray[np.float32], NDArray[np.float32]] | None] = []
        self._scalars: list[tuple[float, str | None]] = []
        """Per buffered iteration its χ² and stage-log line, None for a repeat (same stage, same χ² shown)."""
        self._previous_line: tuple[str, str] | None = None
        self._latest_poses: NDArray[np.float64] | None = None
        self._first_step = 0
        self._buffered_bytes = 0

    def add(self, iteration: Iteration) -> int:
        """Buffer one iteration; returns its step on the `iteration` timeline."""
        step = self._first_step + len(self._scalars)  # iterations added so far
        if self._latest_poses is not None:  # the previous iteration was not the final one: thinned
            self._buffer_geometry(self._latest_poses, thin=True)
        self._latest_poses = iteration.poses  # read-only by the optimizers' contract: no copy
        # Several starts are optimized one after another: name the start unless it is the graph's own.
        stage = iteration.stage if iteration.start == ESTIMATE else f"{iteration.start}: {iteration.stage}"
        chi2 = float(iteration.chi2)
        # A converged stage keeps yielding the same χ²: the log shows the first such line only. Round-off
        # of a zero optimum reads as zero, so a stage that only shuffles it shows one line too.
        value = f"{chi2:.6g}" if chi2 > self._chi2_floor else "0 (round-off)"
        repeat = (stage, value) == self._previous_line
        self._scalars.append((chi2, None if repeat else f"{stage} {iteration.index}: χ² = {value}"))
        self._previous_line = (stage, value)
        if self._buffered_bytes >= self._batch_bytes:
            self._send()
        return step

    def flush(self) -> None:
        """Send everything buffered, the most recent iteration whole (call it once the run is over)."""
        if self._latest_poses is not None:
            self._buffer_geometry(self._latest_poses, thin=False)
            self._latest_poses = None
        self._send()

    def _buffer_geometry(self, poses: NDArray[np.float64], *, thin: bool) -> None:
        # How far every pose may move from the last drawn row without a new one; None: always draw.
        still = self._still_move
        if self._still_fraction is not None:
            still = max(still or 0.0, self._still_fraction * finite_extent(poses))
        if (thin and still is not None and self._last_drawn is not None
                and moved_within(poses, self._last_drawn, still)):
            self._geometry_rows.append(None)
            return
        if still is not None:
            self._last_drawn = np.array(poses[:, :2])
        # The trajectory (P, 2) and loop-closure segments (L, 2, 2) of the iteration, as float32.
        shown = _every_kth(len(poses), self._max_points, keep_last=True) if thin else None
        trajectory = (poses[:, :2] if shown is None else poses[shown, :2]).astype(np.float32)
        segments = poses[self._thinned_loops if thin else self._loops, :2].astype(np.float32)
        self._geometry_rows.append((trajectory, segments))
        self._buffered_bytes += trajectory.nbytes + segments.nbytes

    def _send(self) -> None:
        """Send the buffered iterations that have their geometry row (the latest has none until the next
        `add` or `flush`): χ² and stage lines of all, the geometry of those that are drawn, runs of equally
        thinned ones as one column batch each."""
        count = len(self._geometry_rows)
        steps = np.arange(self._first_step, self._first_step + count, dtype=np.int64)
        chi2 = np.asarray([value for value, _ in self._scalars[:count]], dtype=np.float64)
        self._recording.send_columns(CHI2_ENTITY, indexes=[_iteration_column(steps)],
                                     columns=rr.Scalars.columns(scalars=chi2))
        # log10 of the values above the floor only: χ² ≤ 0 has no log, and χ² at or below the floor is
        # noise the plot would draw as a meaningless −24.
        positive = chi2 > self._chi2_floor
        if positive.any():
            self._recording.send_columns(LOG10_CHI2_ENTITY, indexes=[_iteration_column(steps[positive])],
                                         columns=rr.Scalars.columns(scalars=np.log10(chi2[positive])))
        shown = {k: line for k, (_, line) in enumerate(self._scalars[:count]) if line is not None}
        if shown:
            self._recording.send_columns(
                STAGE_ENTITY, indexes=[_iteration_column(steps[list(shown)])],
                columns=rr.TextLog.columns(text=list(shown.values()), level=["INFO"] * len(shown)))
        drawn = [(k, *row) for k, row in enumerate(self._geometry_rows[:count]) if row is not None]
        for _, group in itertools.groupby(drawn, key=lambda row: (row[1].shape, row[2].shape)):
            ks, trajectories, segments = zip(*group, strict=True)
            send_strips(self._recording, TRAJECTORY_ENTITY, steps[list(ks)], np.stack(trajectories)[:, None])
            send_strips(self._recording, LOOP_CLOSURES_ENTITY, steps[list(ks)], np.stack(segments))
        self._first_step += count
        del self._geometry_rows[:count], self._scalars[:count]
        self._buffered_bytes = 0  # every geometry row was sent


def _every_kth(count: int, limit: int, *, keep_last: bool) -> IntArray | None:
    """Indices of every k-th of `count` items, with the smallest k that keeps at most `limit` of them
    (plus the last item when `keep_last`, counted in the limit); None when all `count` fit."""
    if count <= limit:
        return None
    if keep_last:
        stride = -(-(count - 1) // (limit - 1))  # ceil: 0, k, 2k, … < count − 1, then count − 1
        return np.append(np.arange(0, count - 1, stride), count - 1)
    stride = -(-count // limit)
    return np.arange(0, count, stride)
