"""The final optimization of a frontend's keyframe graph, recorded iteration by iteration.

The chosen method optimizes the graph from two starts, both recorded: the odometry-only estimate (what the
robot believed before any loop closure), so the recording shows the map straightening out, and the online
estimate (loop closures applied as they came). The lower final χ² wins; the written poses are the recorded
last iteration.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.solve import OptimizationResult, optimize
from pipeline import recording

IterationCallback = Callable[[Iteration], None]


class IterationSink(Protocol):
    """More per-iteration recording beside the 2D trajectory (e.g. 3D keyframe poses)."""

    def add(self, step: int, iteration: Iteration) -> None: ...

    def flush(self) -> None: ...


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


def optimize_keyframes(
    stream: Any,
    from_odometry: PoseGraph,
    online: PoseGraph,
    method: str,
    iterations: int | None,
    on_iteration: IterationCallback | None = None,
    sink: IterationSink | None = None,
    robust: str | None = None,
) -> KeyframeOptimization:
    """Optimize `from_odometry`'s constraints with `method` from the odometry and the online estimates,
    logging every iteration of both to `stream`; the lower final χ² wins. The two graphs hold the same
    constraints around different estimates."""
    record_started = time.perf_counter()
    loops = ~from_odometry.is_odometry
    recording.log_styles(stream)
    recording.log_initial_trajectory(stream, from_odometry.poses)
    recorder = recording.IterationRecorder(
        stream, from_odometry.edge_from[loops], from_odometry.edge_to[loops]
    )
    record_seconds = time.perf_counter() - record_started
    trace: list[tuple[str, int, float]] = []
    final = from_odometry.poses
    optimization = optimize(from_odometry, method=method, iterations=iterations,
                            starts={"odometry": from_odometry.poses, "online": online.poses}, robust=robust)
    for iteration in optimization:
        record_started = time.perf_counter()
        step = recorder.add(iteration)
        if sink is not None:
            sink.add(step, iteration)
        record_seconds += time.perf_counter() - record_started
        trace.append((iteration.stage, iteration.index, float(iteration.chi2)))
        final = iteration.poses
        if on_iteration is not None:
            on_iteration(iteration)
    record_started = time.perf_counter()
    recorder.flush()
    if sink is not None:
        sink.flush()
    record_seconds += time.perf_counter() - record_started
    return KeyframeOptimization(tuple(trace), np.array(final), optimization.result, record_seconds)
