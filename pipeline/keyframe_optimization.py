"""The final optimization of a frontend's keyframe graph, recorded iteration by iteration.

The chosen method optimizes the graph from two or three starts, all recorded: the wheel-odometry chain
when the log has wheel odometry (the paper's setting: a poor initial estimate, so what a person sees
straighten out is real), the odometry-only estimate (the scan-matched chain, what the robot believed before
any loop closure) and the online estimate (loop closures applied as they came). The lowest final χ² wins;
the written poses are the recorded last iteration.

With the keyframe scans (2D), the recording draws the walls moving with every iteration
(`pipeline.recording.map2d`) and frames the final map in its blueprint.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from optimizer import se2
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.solve import DEFAULT_METHOD, OptimizationResult, optimize
from pipeline import recording
from pipeline.recording import IterationSink
from pipeline.replay_graph import optimization_recorder, record_optimization

if TYPE_CHECKING:
    from frontends.slam2d.held_map import HeldMapProblem, HeldMapSolution, HeldMapSolver

IterationCallback = Callable[[Iteration], None]


@dataclass(frozen=True, eq=False)
class KeyframeOptimization:
    trace: tuple[tuple[str, int, float], ...]
    """(stage, index, χ²) of every recorded iteration, the starting estimate first."""
    poses: NDArray[np.float64]
    """(K, 3) the final keyframe poses."""
    result: OptimizationResult
    """How the optimization ended; `result.winner` is "odometry" or "online"."""
    record_seconds: float
    """Of the time spent here, the part spent writing to the recording."""


WHEEL_ODOMETRY_START = "wheel odometry"
"""The name of the wheel-odometry start (`optimize_keyframes`' `wheel_odometry`)."""


def optimize_keyframes(
    stream: Any,
    from_odometry: PoseGraph,
    online: PoseGraph,
    method: str,
    iterations: int | None,
    on_iteration: IterationCallback | None = None,
    sink: IterationSink | None = None,
    robust: str | None = None,
    keyframe_scans: Sequence[NDArray[np.float64]] | None = None,
    wheel_odometry: NDArray[np.float64] | None = None,
    on_final: Callable[[NDArray[np.float64]], None] | None = None,
    first_recorded: int = 0,
    walls_color: tuple[int, ...] = recording.MAP_COLOR,
) -> KeyframeOptimization:
    """Optimize `from_odometry`'s constraints with `method` from the odometry and the online estimates
    (and first from `wheel_odometry`, (K, 3) keyframe poses, when given), logging every iteration of each
    to `stream`; the lowest final χ² wins. The graphs hold the same constraints around different
    estimates. With `keyframe_scans` (each keyframe's 2D points in its own frame) the walls are recorded
    moving with the keyframes, and the blueprint frames the final map. `on_final` gets the final poses
    before the recording of the iterations is flushed (sending the moving walls: 0.2 s on UAL), so that
    the map can be made meanwhile. Poses before `first_recorded` are optimized but neither recorded nor
    returned (a held map's origin, `held_map_solver`); the walls are drawn in `walls_color`."""
    started = time.perf_counter()
    first_start = from_odometry.poses if wheel_odometry is None else wheel_odometry
    recording.log_run_properties(stream, {
        "method": method,
        "keyframes": from_odometry.num_poses - first_recorded,
        "constraints": from_odometry.num_edges,
        "loop_closures": int((~from_odometry.is_odometry).sum()),
    }, name=recording.OPTIMIZATION_PROPERTY)
    sinks: list[IterationSink] = [] if sink is None else [sink]
    legend, still_move = None, None
    if keyframe_scans is not None:
        # Imported here: the 2D map's recording builds on the laser frontend, which clouds never load.
        from pipeline.recording import map2d, scans

        keyframe_scans = keyframe_scans[first_recorded:]
        # Log replays draw the trajectory only when it moved as much as the walls must to be redrawn.
        legend, still_move = scans.LEGEND_ROWS, map2d.SHOWN_MOVE
        sinks.append(map2d.KeyframeMapRecorder(stream, keyframe_scans, walls_color))
    recorder = optimization_recorder(stream, from_odometry.from_pose(first_recorded),
                                     first_start[first_recorded:], legend=legend, still_move=still_move)
    starts = {"odometry": from_odometry.poses, "online": online.poses}
    if wheel_odometry is not None:
        starts = {WHEEL_ODOMETRY_START: np.asarray(wheel_odometry, dtype=np.float64), **starts}
    # One odometry chain (K − 1 constraints, each between consecutive poses): composing it is the optimum
    # (χ² = 0), so descending from it (SGD: 400 iterations on KITTI) proves nothing; the polish's
    # convergence test proves the start optimal in one or two steps.
    chain = from_odometry.num_edges == from_odometry.num_poses - 1 and bool(from_odometry.is_odometry.all())
    if chain:
        recording.log_note(stream, f"{CHAIN_REASON}; {method} was not run")
        method, iterations, robust = CHAIN_METHOD, None, None
    optimization = optimize(from_odometry, method=method, iterations=iterations, starts=starts,
                            robust=robust)
    run = record_optimization(optimization, recorder, sinks, on_iteration, on_final, first_recorded)
    if keyframe_scans is not None:
        bounds = map2d.placed_bounds(keyframe_scans, run.final_poses)
        recording.send_blueprint(stream, scans.log_replay_blueprint(bounds))
    record_seconds = time.perf_counter() - started - sum(run.optimize_time.values())
    trace = tuple((record.stage, record.index, record.chi2) for record in run.trace)
    result = run.result
    if chain:
        result = dataclasses.replace(result, reason=f"{CHAIN_REASON} ({result.reason})")
    return KeyframeOptimization(trace, run.final_poses, result, record_seconds)


def held_map_solver(stream: Any, on_iteration: IterationCallback | None = None) -> HeldMapSolver:
    """A `frontends.slam2d.held_map.HeldMapSolver` that optimizes as a replay's keyframe graph is
    optimized, from the odometry chain and the online estimate, and records every iteration of the new
    keyframes: their walls (in the new run's colour) moving into the saved map (its origin, pose 0, left
    out). The default optimizer, whatever [optimizer] says: that section is the map's, which --map does not
    change; this solve is a step of the localization (its convergence decides which trajectory is written)."""

    def solve(problem: HeldMapProblem) -> HeldMapSolution:
        # The laser frontend and the 2D recording: clouds never load them.
        from frontends.slam2d.held_map import HeldMapSolution
        from pipeline.recording.scans import NEW_RUN_WALLS_COLOR

        optimized = optimize_keyframes(
            stream, problem.graph.with_poses(problem.odometry_start), problem.graph, DEFAULT_METHOD, None,
            on_iteration, keyframe_scans=problem.keyframe_scans, first_recorded=1,
            walls_color=NEW_RUN_WALLS_COLOR)
        return HeldMapSolution(optimized.poses, optimized.result.converged)

    return solve


CHAIN_METHOD = "gn"
"""What optimizes a keyframe graph without loop closures, whatever the method asked for."""
CHAIN_REASON = "no loop closures: the odometry chain is the optimum, the polish alone confirmed it"
"""The stop reason's prefix then (the JSON summary's `stop_reason`)."""


def wheel_odometry_start(
    keyframe_odometry: NDArray[np.float64] | None, first_pose: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """The keyframe poses wheel odometry alone gives, (K, 3), from the wheel-odometry pose at each
    keyframe's first scan (NaN where odometry did not cover it), anchored at `first_pose` (the first
    keyframe's pose in the map frame); None without odometry or when it misses a keyframe."""
    if keyframe_odometry is None or len(keyframe_odometry) == 0 or not np.all(np.isfinite(keyframe_odometry)):
        return None
    keyframe_odometry = np.asarray(keyframe_odometry, dtype=np.float64)
    return se2.compose(np.asarray(first_pose, dtype=np.float64),
                       se2.relative(keyframe_odometry[0], keyframe_odometry))
