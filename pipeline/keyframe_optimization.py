"""The final optimization of a frontend's keyframe graph, recorded iteration by iteration.

The graph is optimized from its odometry-only estimate (what the robot believed before any loop closure),
so the recording shows the map straightening out; the online estimate (loop closures applied as they came)
is polished too, and the lower χ² wins.
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
from optimizer.polish import gauss_newton
from optimizer.solve import optimize
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
    start: str
    """"odometry" when the recorded optimization won, "online" when the polished online estimate did."""
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
) -> KeyframeOptimization:
    """Optimize `from_odometry` with `method`, logging every iteration to `stream`; polish `online`; keep
    whichever ends lower. The two graphs hold the same constraints around different estimates."""
    record_started = time.perf_counter()
    loops = ~from_odometry.is_odometry
    recording.log_styles(stream)
    recording.log_initial_trajectory(stream, from_odometry.poses)
    recorder = recording.IterationRecorder(
        stream, from_odometry.edge_from[loops], from_odometry.edge_to[loops]
    )
    record_seconds = time.perf_counter() - record_started
    trace: list[tuple[str, int, float]] = []
    final, final_chi2 = from_odometry.poses, np.inf
    for iteration in optimize(from_odometry, method=method, iterations=iterations):
        record_started = time.perf_counter()
        step = recorder.add(iteration)
        if sink is not None:
            sink.add(step, iteration)
        record_seconds += time.perf_counter() - record_started
        trace.append((iteration.stage, iteration.index, float(iteration.chi2)))
        final, final_chi2 = iteration.poses, float(iteration.chi2)
        if on_iteration is not None:
            on_iteration(iteration)
    record_started = time.perf_counter()
    recorder.flush()
    if sink is not None:
        sink.flush()
    record_seconds += time.perf_counter() - record_started
    polished, polished_chi2 = online.poses, float(np.inf)
    for iteration in gauss_newton(online, online.poses):
        polished, polished_chi2 = iteration.poses, float(iteration.chi2)
    if polished_chi2 < final_chi2 * (1.0 - 1e-9):
        return KeyframeOptimization(tuple(trace), np.array(polished), "online", record_seconds)
    return KeyframeOptimization(tuple(trace), np.array(final), "odometry", record_seconds)
