"""One entry point that chains the optimizer's stages and yields every iteration of every stage."""

from __future__ import annotations

from collections.abc import Iterator

from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.gauss_seidel import gauss_seidel
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.polish import gauss_newton
from optimizer.sgd import sgd

METHODS: tuple[str, ...] = ("sgd+gn", "sgd", "gn", "gauss-seidel")
"""sgd+gn (default): the paper's SGD, then the exact minimum by Gauss–Newton/LM from its basin."""
DEFAULT_METHOD = "sgd+gn"
DEFAULT_ITERATIONS = 100
DEFAULT_POLISH_ITERATIONS = 300
"""Cap on polish iterations; it stops earlier on convergence (INTEL, badly conditioned, needs ~250)."""


def optimize(
    graph: PoseGraph,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    *,
    polish_iterations: int = DEFAULT_POLISH_ITERATIONS,
) -> Iterator[Iteration]:
    """Yield the initial estimate (stage "initial", index 0), then every iteration of the method's stages.

    `iterations` is the number of SGD (or Gauss–Seidel) iterations, default 100; for "gn" alone it caps
    the Gauss–Newton iterations. The polish runs until it converges or `polish_iterations`.
    """
    if method not in METHODS:
        raise OptimizerError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if iterations is not None and iterations < 0:
        raise OptimizerError(f"iterations must be >= 0, got {iterations}")
    sweeps = DEFAULT_ITERATIONS if iterations is None else iterations
    poses = graph.poses.copy()
    yield Iteration("initial", 0, poses, chi2(graph, poses))
    if method in ("sgd", "sgd+gn"):
        for step in sgd(graph, sweeps, poses):
            poses = step.poses
            yield step
    if method == "gauss-seidel":
        yield from gauss_seidel(graph, poses, iterations=sweeps)
    if method in ("sgd+gn", "gn"):
        limit = iterations if method == "gn" and iterations is not None else polish_iterations
        yield from gauss_newton(graph, poses, max_iterations=limit)
