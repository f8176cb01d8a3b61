"""One entry point that runs a method's stages from one or more starting estimates, yielding every iteration.

A method is a descent stage (the paper's SGD, or Gauss–Seidel) optionally followed by the polish
(Levenberg–Marquardt to the exact minimum). Every starting estimate ("candidate") is optimized in turn and
recorded; the result is the candidate with the lowest final χ², and it is converged only when its polish's
own convergence test held. Methods without a polish stop after a fixed number of iterations and are never
reported as converged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.gauss_seidel import gauss_seidel
from optimizer.graph import PoseGraph
from optimizer.iteration import ESTIMATE, Iteration
from optimizer.polish import DEFAULT_MAX_ITERATIONS, PolishStatus, gauss_newton
from optimizer.sgd import sgd

FloatArray = NDArray[np.float64]
Descent = Callable[[PoseGraph, int, FloatArray], Iterator[Iteration]]


@dataclass(frozen=True)
class Method:
    """A descent stage (None: none) followed, or not, by the polish."""

    descent: Descent | None
    polish: bool


METHOD_TABLE: dict[str, Method] = {
    "sgd+gn": Method(lambda graph, n, poses: sgd(graph, n, poses), polish=True),
    "sgd": Method(lambda graph, n, poses: sgd(graph, n, poses), polish=False),
    "gn": Method(None, polish=True),
    "gauss-seidel": Method(lambda graph, n, poses: gauss_seidel(graph, poses, iterations=n), polish=False),
}
METHODS: tuple[str, ...] = tuple(METHOD_TABLE)
"""sgd+gn (default): the paper's SGD, then the exact minimum by Gauss–Newton/LM from its basin."""
DEFAULT_METHOD = "sgd+gn"
DEFAULT_ITERATIONS = 100
MAX_ITERATIONS = 1_000_000
"""Bound on `iterations`: far beyond any use (a 10⁶-pose SGD iteration takes about a second)."""
DEFAULT_POLISH_ITERATIONS = DEFAULT_MAX_ITERATIONS
"""Cap on polish iterations, far above what the benchmark graphs need; it stops on its convergence test."""



@dataclass(frozen=True)
class Candidate:
    """How the optimization of one starting estimate ended."""

    start: str
    chi2: float
    converged: bool
    reason: str
    iterations: int
    """Iterations after the starting estimate."""


@dataclass(frozen=True, eq=False)
class OptimizationResult:
    """The winning candidate's final poses and χ², and how every candidate ended."""

    poses: FloatArray
    chi2: float
    converged: bool
    reason: str
    """Why the winning candidate stopped (the polish's convergence test, or a fixed iteration count)."""
    winner: str
    candidates: tuple[Candidate, ...]


class Optimization:
    """Iterate over it for every `Iteration` of every candidate; `result` then says how it ended.

    The first iteration of each candidate is its starting estimate (stage "initial", index 0). When
    several candidates ran, a last iteration (stage "selected", index 0) repeats the winner's result, so
    the last iteration yielded is always the result.
    """

    def __init__(self, graph: PoseGraph, method: str = DEFAULT_METHOD, iterations: int | None = None, *,
                 starts: Mapping[str, FloatArray] | None = None,
                 polish_iterations: int = DEFAULT_POLISH_ITERATIONS) -> None:
        if method not in METHOD_TABLE:
            raise OptimizerError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        if iterations is not None and not 0 <= iterations <= MAX_ITERATIONS:
            raise OptimizerError(f"iterations must be between 0 and {MAX_ITERATIONS}, got {iterations}")
        if not 0 <= polish_iterations <= MAX_ITERATIONS:
            raise OptimizerError(f"polish iterations must be between 0 and {MAX_ITERATIONS}, "
                                 f"got {polish_iterations}")
        self._graph = graph
        self._method = METHOD_TABLE[method]
        self._sweeps = DEFAULT_ITERATIONS if iterations is None else iterations
        # With the polish alone, `iterations` caps the polish.
        self._polish_cap = (iterations if self._method.descent is None and iterations is not None
                            else polish_iterations)
        self._starts: dict[str, FloatArray] = {}
        for name, poses in (starts or {ESTIMATE: graph.poses}).items():
            poses = np.asarray(poses, dtype=np.float64)
            if poses.shape != graph.poses.shape:
                raise OptimizerError(f"start {name!r}: expected poses of shape {graph.poses.shape}, "
                                     f"got {poses.shape}")
            if not np.all(np.isfinite(poses)):
                raise OptimizerError(f"start {name!r}: non-finite poses")
            self._starts[name] = poses
        if not self._starts:
            raise OptimizerError("no starting estimate given")
        self._result: OptimizationResult | None = None

    @property
    def result(self) -> OptimizationResult:
        if self._result is None:
            raise OptimizerError("the optimization has not run to its end yet")
        return self._result

    def __iter__(self) -> Iterator[Iteration]:
        candidates: list[Candidate] = []
        best: Iteration | None = None
        for name, start in self._starts.items():
            last = Iteration("initial", 0, start, chi2(self._graph, start), start=name)
            yield last
            count = 0
            converged, reason = False, f"{self._sweeps} iterations of a method without a convergence test"
            if self._method.descent is not None:
                for iteration in self._method.descent(self._graph, self._sweeps, last.poses):
                    last = dataclasses.replace(iteration, start=name)
                    count += 1
                    yield last
            if self._method.polish:
                polish = gauss_newton(self._graph, last.poses, max_iterations=self._polish_cap)
                while True:
                    try:
                        iteration = next(polish)
                    except StopIteration as stop:
                        status: PolishStatus = stop.value
                        break
                    last = dataclasses.replace(iteration, start=name)
                    count += 1
                    yield last
                converged, reason = status.converged, status.reason
            candidates.append(Candidate(name, float(last.chi2), converged, reason, count))
            if best is None or last.chi2 < best.chi2:
                best = last
        assert best is not None
        winner = next(candidate for candidate in candidates if candidate.start == best.start)
        if len(candidates) > 1:
            yield Iteration("selected", 0, best.poses, best.chi2, start=best.start)
        self._result = OptimizationResult(np.array(best.poses), float(best.chi2), winner.converged,
                                          winner.reason, winner.start, tuple(candidates))


def optimize(
    graph: PoseGraph,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    *,
    starts: Mapping[str, FloatArray] | None = None,
    polish_iterations: int = DEFAULT_POLISH_ITERATIONS,
) -> Optimization:
    """The optimization of `graph` by `method` from `starts` (name → poses; default: the graph's own
    estimate, named "estimate"), each in turn, the lowest final χ² winning.

    `iterations` is the number of SGD (or Gauss–Seidel) iterations, default 100; for "gn" alone it caps
    the Gauss–Newton iterations. The polish runs until its convergence test holds (or `polish_iterations`,
    reported as not converged). Iterate over the returned object for every iteration; `.result` after.
    """
    return Optimization(graph, method, iterations, starts=starts, polish_iterations=polish_iterations)
