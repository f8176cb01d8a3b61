"""The Rerun recording of a replay. The only module of the project that imports rerun.

In the style of evo's rerun_bridge: names of timelines and entities are constants, there is one `log_*` /
`send_*` function per concept, and the recording stream is always passed explicitly (never rerun's global
one), so several recordings can be written side by side.

Layout of a recording:
- `world/initial_trajectory` (static): the trajectory before optimization;
- `world/trajectory` and `world/loop_closures` on the timeline `iteration`: the trajectory and the
  loop-closure constraints (|b − a| > 1) after every iteration (thinned on huge graphs, except the final
  iteration: see `IterationRecorder`);
- `optimizer/chi2` and `optimizer/log10_chi2` on `iteration`: χ² as scalar series (the log is what shows
  the SGD's progress; χ² falls by orders of magnitude);
- `optimizer/stage` on `iteration`: a text log naming the stage and its iteration number.

The timeline `iteration` is one counter across all stages: 0 is the initial estimate, then 1, 2, … for
every iteration the optimizer yields (SGD, then the polish). Per-iteration data is sent in columns
(`send_columns`), a batch of iterations at a time, which is what keeps large recordings compact and fast.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

# rerun's Rust side logs straight to stderr, in colour (a WARN when an encoder cannot finish, an ERROR when
# the disk fills); what matters of it reaches us as exceptions, which we word ourselves in one line. Set
# before rerun is first imported, since that is when it reads the filter; RUST_LOG set by the user wins.
os.environ.setdefault("RUST_LOG", "off")

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray
from rerun.components import LineStrip2DBatch
from rerun.encodings import Vec2DBatch

from optimizer.iteration import ESTIMATE, Iteration
from pipeline.errors import OutputError, PipelineError

APPLICATION_ID = "sgdslam"
ITERATION_TIMELINE = "iteration"

WORLD_ENTITY = "world"
INITIAL_TRAJECTORY_ENTITY = "world/initial_trajectory"
TRAJECTORY_ENTITY = "world/trajectory"
LOOP_CLOSURES_ENTITY = "world/loop_closures"
CHI2_ENTITY = "optimizer/chi2"
LOG10_CHI2_ENTITY = "optimizer/log10_chi2"
STAGE_ENTITY = "optimizer/stage"
MAP_ENTITY = "world/map"
RUN_PROPERTY = "replay"

TRAJECTORY_COLOR = (31, 119, 180, 255)
INITIAL_TRAJECTORY_COLOR = (150, 150, 150, 110)
LOOP_CLOSURE_COLOR = (230, 85, 13, 140)
MAP_COLOR = (20, 20, 20, 255)
LINE_WIDTH = rr.Radius.ui_points(0.75)
MAP_POINT_RADIUS = rr.Radius.ui_points(1.0)
MAP_CELL = 0.05
"""The final map keeps one point per cell of this size (m): what the viewer draws smoothly."""

DEFAULT_BATCH_BYTES = 32 * 1024 * 1024
"""How much per-iteration geometry `IterationRecorder` buffers before sending it as one column batch."""

DEFAULT_MAX_POINTS_PER_ITERATION = 100_000
"""Above this many poses (or half as many loop closures) `IterationRecorder` thins each iteration's
geometry, except the final iteration's."""

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def create_recording(path: Path, *, name: str, with_map: bool = False) -> rr.RecordingStream:
    """A new recording stream that saves to `path` (with the default blueprint; `with_map` adds the views
    of a log replay: the occupancy grid, the time panel on the scans). Raises `OutputError` naming `path`
    and why when it cannot be written there."""
    # rerun's save() never returns when its file writer fails on the first bytes (seen with a full disk):
    # make sure there is room for them first.
    reason = _write_probe_failure(path, sync=False)
    if reason is not None:
        raise OutputError(f"{path}: cannot write the recording: {reason}")
    recording = rr.RecordingStream(APPLICATION_ID)
    try:
        recording.save(path, default_blueprint=default_blueprint(with_map=with_map))
    except (OSError, RuntimeError) as error:
        raise OutputError(f"{path}: cannot write the recording: {_write_failure(path, error)}") from error
    _saved_to[id(recording)] = path
    recording.send_recording_name(name)
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
            os.write(descriptor, bytes(_PROBE_BYTES))
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


def default_blueprint(*, with_map: bool = False) -> rrb.Blueprint:
    """The map and graph in 2D beside the χ² plots and the stage log, the time panel on `iteration`; with
    `with_map`, the occupancy grid as a second tab beside the map."""
    graph_view = rrb.Spatial2DView(origin=WORLD_ENTITY, name="map and pose graph")
    main = (
        rrb.Tabs(graph_view, rrb.Spatial2DView(origin="occupancy", name="occupancy grid"))
        if with_map
        else graph_view
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            main,
            rrb.Vertical(
                rrb.TimeSeriesView(origin=LOG10_CHI2_ENTITY, name="log10 χ²"),
                rrb.TimeSeriesView(origin=CHI2_ENTITY, name="χ²"),
                rrb.TextLogView(origin=STAGE_ENTITY, name="stages"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=ITERATION_TIMELINE),
        collapse_panels=False,
    )


def log_run_properties(recording: rr.RecordingStream, properties: Mapping[str, str | int | float]) -> None:
    """What was replayed and how (input file, method, counts), as a recording property."""
    recording.send_property(RUN_PROPERTY, rr.AnyValues(**{key: [value] for key, value in properties.items()}))


def log_styles(recording: rr.RecordingStream) -> None:
    """Static colours, widths and series names; the per-iteration columns then carry geometry only."""
    recording.log(
        TRAJECTORY_ENTITY,
        rr.LineStrips2D.from_fields(colors=[TRAJECTORY_COLOR], radii=[LINE_WIDTH]),
        static=True,
    )
    recording.log(
        LOOP_CLOSURES_ENTITY,
        rr.LineStrips2D.from_fields(colors=[LOOP_CLOSURE_COLOR], radii=[LINE_WIDTH]),
        static=True,
    )
    recording.log(CHI2_ENTITY, rr.SeriesLines(names="χ²"), static=True)
    recording.log(LOG10_CHI2_ENTITY, rr.SeriesLines(names="log10 χ²"), static=True)


def log_initial_trajectory(recording: rr.RecordingStream, poses: FloatArray) -> None:
    """The starting estimate, static, drawn faintly under the optimised one."""
    recording.log(
        INITIAL_TRAJECTORY_ENTITY,
        rr.LineStrips2D(
            [np.asarray(poses[:, :2], dtype=np.float32)],
            colors=[INITIAL_TRAJECTORY_COLOR],
            radii=[LINE_WIDTH],
        ),
        static=True,
    )


def log_final_map(
    recording: rr.RecordingStream, keyframe_scans: Sequence[FloatArray], keyframe_poses: FloatArray
) -> None:
    """All keyframe scans at their optimized poses, static, thinned to one point per `MAP_CELL`."""
    placed = [
        scan @ _rotation(pose[2]) + pose[:2]
        for scan, pose in zip(keyframe_scans, keyframe_poses, strict=True)
    ]
    if not placed:
        return
    points = np.concatenate(placed)
    cells = np.floor(points / MAP_CELL).astype(np.int64)
    _, first = np.unique(cells[:, 0] * 2_000_003 + cells[:, 1], return_index=True)
    recording.log(
        MAP_ENTITY,
        rr.Points2D(points[np.sort(first)].astype(np.float32), colors=[MAP_COLOR], radii=[MAP_POINT_RADIUS]),
        static=True,
    )


def _rotation(theta: float) -> FloatArray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s], [-s, c]])


def send_trajectories(recording: rr.RecordingStream, steps: IntArray, positions: NDArray[np.float32]) -> None:
    """One line strip per iteration: `positions` is (K, N, 2), row k logged at `steps[k]`."""
    recording.send_columns(
        TRAJECTORY_ENTITY,
        indexes=[_iteration_column(steps)],
        columns=rr.LineStrips2D.columns(strips=_equal_length_strips(positions)),
    )


def send_loop_segments(recording: rr.RecordingStream, steps: IntArray, segments: NDArray[np.float32]) -> None:
    """(K, L, 2, 2) segments: L two-point loop-closure segments per iteration (nothing when L = 0)."""
    count = segments.shape[1]
    if count == 0:
        return
    recording.send_columns(
        LOOP_CLOSURES_ENTITY,
        indexes=[_iteration_column(steps)],
        columns=rr.LineStrips2D.columns(strips=_equal_length_strips(segments.reshape(-1, 2, 2))).partition(
            np.full(len(steps), count)
        ),
    )


def send_chi2(recording: rr.RecordingStream, steps: IntArray, chi2: FloatArray) -> None:
    """χ² per iteration, and its log10 (non-positive χ² has no log and is left out of that series)."""
    index = [_iteration_column(steps)]
    recording.send_columns(CHI2_ENTITY, indexes=index, columns=rr.Scalars.columns(scalars=chi2))
    positive = chi2 > 0
    if positive.any():
        recording.send_columns(
            LOG10_CHI2_ENTITY,
            indexes=[_iteration_column(steps[positive])],
            columns=rr.Scalars.columns(scalars=np.log10(chi2[positive])),
        )


def send_stages(
    recording: rr.RecordingStream, steps: IntArray, stages: Sequence[str], indices: IntArray, chi2: FloatArray
) -> None:
    """A text line per iteration naming its stage and its number within the stage."""
    text = [
        f"{stage} {index}: χ² = {value:.6g}"
        for stage, index, value in zip(stages, indices.tolist(), chi2.tolist(), strict=True)
    ]
    recording.send_columns(
        STAGE_ENTITY,
        indexes=[_iteration_column(steps)],
        columns=rr.TextLog.columns(text=text, level=["INFO"] * len(text)),
    )


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
    """

    def __init__(
        self,
        recording: rr.RecordingStream,
        loop_from: IntArray,
        loop_to: IntArray,
        *,
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        max_points: int = DEFAULT_MAX_POINTS_PER_ITERATION,
    ) -> None:
        if max_points < 2:
            raise PipelineError(f"max_points must be at least 2, got {max_points}")
        self._recording = recording
        self._loop_from = np.asarray(loop_from, dtype=np.int64)
        self._loop_to = np.asarray(loop_to, dtype=np.int64)
        self._loop_shown = _every_kth(len(self._loop_from), max_points // 2, keep_last=False)
        self._max_points = max_points
        self._batch_bytes = batch_bytes
        self._trajectories: list[NDArray[np.float32]] = []
        self._loop_segments: list[NDArray[np.float32]] = []
        self._stages: list[str] = []
        self._indices: list[int] = []
        self._chi2: list[float] = []
        self._latest_poses: NDArray[np.float64] | None = None
        self._first_step = 0
        self._buffered_bytes = 0

    @property
    def steps_recorded(self) -> int:
        """How many iterations were added so far (the next one gets this step number)."""
        return self._first_step + len(self._stages)

    def add(self, iteration: Iteration) -> int:
        """Buffer one iteration; returns its step on the `iteration` timeline."""
        step = self.steps_recorded
        if self._latest_poses is not None:  # the previous iteration was not the final one: thinned
            self._buffer_geometry(self._latest_poses, thin=True)
        self._latest_poses = iteration.poses  # read-only by the optimizers' contract: no copy
        # Several starts are optimized one after another: name the start unless it is the graph's own.
        self._stages.append(iteration.stage if iteration.start == ESTIMATE else
                            f"{iteration.start}: {iteration.stage}")
        self._indices.append(iteration.index)
        self._chi2.append(float(iteration.chi2))
        if self._buffered_bytes >= self._batch_bytes:
            self._send(len(self._trajectories))
        return step

    def flush(self) -> None:
        """Send everything buffered, the most recent iteration whole (call it once the run is over)."""
        if self._latest_poses is not None:
            self._buffer_geometry(self._latest_poses, thin=False)
            self._latest_poses = None
        self._send(len(self._trajectories))

    def _buffer_geometry(self, poses: NDArray[np.float64], *, thin: bool) -> None:
        trajectory, segments = self._geometry(poses, thin=thin)
        self._trajectories.append(trajectory)
        self._loop_segments.append(segments)
        self._buffered_bytes += trajectory.nbytes + segments.nbytes

    def _geometry(self, poses: NDArray[np.float64], *, thin: bool) -> tuple[NDArray[np.float32],
                                                                           NDArray[np.float32]]:
        """The trajectory (P, 2) and loop-closure segments (L, 2, 2) of one iteration, as float32."""
        if thin:
            shown = _every_kth(len(poses), self._max_points, keep_last=True)
            trajectory = poses[shown, :2] if shown is not None else poses[:, :2]
            loop_from, loop_to = self._loop_from, self._loop_to
            if self._loop_shown is not None:
                loop_from, loop_to = loop_from[self._loop_shown], loop_to[self._loop_shown]
        else:
            trajectory = poses[:, :2]
            loop_from, loop_to = self._loop_from, self._loop_to
        segments = np.stack([poses[loop_from, :2], poses[loop_to, :2]], axis=1)
        return trajectory.astype(np.float32), segments.astype(np.float32)

    def _send(self, count: int) -> None:
        """Send the first `count` buffered iterations (the latest has no geometry until the next `add` or
        `flush`): runs of equally thinned ones as one column batch each."""
        sent = 0
        while sent < count:
            end = sent + 1
            shape = (self._trajectories[sent].shape, self._loop_segments[sent].shape)
            while end < count and (self._trajectories[end].shape, self._loop_segments[end].shape) == shape:
                end += 1
            steps = np.arange(self._first_step + sent, self._first_step + end, dtype=np.int64)
            chi2 = np.asarray(self._chi2[sent:end], dtype=np.float64)
            send_trajectories(self._recording, steps, np.stack(self._trajectories[sent:end]))
            send_loop_segments(self._recording, steps, np.stack(self._loop_segments[sent:end]))
            send_chi2(self._recording, steps, chi2)
            send_stages(self._recording, steps, self._stages[sent:end],
                        np.asarray(self._indices[sent:end], dtype=np.int64), chi2)
            sent = end
        self._first_step += count
        for buffer in (self._trajectories, self._loop_segments, self._stages, self._indices, self._chi2):
            del buffer[:count]
        self._buffered_bytes = sum(trajectory.nbytes + segments.nbytes for trajectory, segments
                                   in zip(self._trajectories, self._loop_segments, strict=True))


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
