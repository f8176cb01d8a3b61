"""Robust kernels against false loop closures, as wrappers around the SGD and the polish.

A kernel replaces each constraint's χ² term u_k = e_kᵀ Ω_k e_k by ρ(u_k). Both kernels here are concave in
u, so iteratively reweighted least squares is a majorize–minimize scheme: with the weights w_k = ρ'(u_k)
frozen at the current poses, ρ(u) ≤ ρ(u⁰) + w·(u − u⁰), so whatever lowers the weighted χ² Σ w_k u_k also
lowers the robust cost Σ ρ(u_k). Both optimizers are therefore run unchanged on the graph with
information w_k·Ω_k, and the weights are recomputed from the poses they reach.

- "cauchy": ρ(u) = c²·log(1 + u/c²), ρ'(u) = 1/(1 + u/c²).
- "dcs": dynamic covariance scaling (Agarwal et al., ICRA 2013): s = min(1, 2Φ/(Φ + u)) and the
  information is scaled by s²; the M-estimator it minimizes is ρ(u) = u for u ≤ Φ, Φ(3u − Φ)/(Φ + u)
  beyond, whose derivative is s².

Only loop closures are robustified (by default): outliers come from loop closing, and a kernel on the
odometry chain lets the optimizer tear the trajectory apart at a few odometry constraints to satisfy a
false loop (seen on M3500 with 100 false loops).

DCS's weight 4Φ²/u² gives a true loop closure that dead reckoning left far off no pull at all, so the
SGD stage weighs with Cauchy (weight c²/u) in `robust_optimize` whichever kernel the polish minimizes.
Annealing the scale (graduated non-convexity, from a scale that keeps every weight near 1 down to the
kernel's) was tried and is not used: while the scale is large the false loops bend the map, and the SGD's
decaying learning rate cannot undo it (M3500 + 100 false loops after 100 iterations: χ² on the true
edges 2.9e3× the optimum annealed over 30 iterations from c² = 1000, 2.5e2× at a fixed c² = 7.8).
"""

from __future__ import annotations

from collections.abc import Generator, Iterator
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from optimizer.cost import edge_chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.polish import PolishStatus, gauss_newton
from optimizer.sgd import sgd

FloatArray = NDArray[np.float64]
Kernel = Literal["cauchy", "dcs"]
KERNELS: tuple[str, ...] = ("cauchy", "dcs")

DEFAULT_SCALES: dict[str, float] = {"cauchy": 1.0, "dcs": 1.0}
"""In χ² units (u = eᵀΩe). DCS uses Φ = 1, the value of Agarwal et al., who found the result insensitive
to Φ over orders of magnitude. Cauchy uses c² = 1 (g2o's default too): a rejected constraint still costs
c²·log(1 + u/c²), so a larger c² makes bending the map onto a false loop the cheaper minimum. With
c² = 7.815 (the 95 % quantile of a 3-dof χ², what honest information would suggest) two of M3500's 100
false loops were satisfied at a cost of 40 % on the true edges; real graphs' information is often
pessimistic (M3500's true edges average u = 0.025 at the optimum), which a small scale tolerates."""

WEIGHT_TOLERANCE = 1e-3
"""The robust polish stops reweighting once no weight changes by more than this."""
MAX_REWEIGHTS = 30
"""Cap on the robust polish's reweighting rounds (each one a converged Levenberg–Marquardt run)."""


class Descent(Protocol):
    """An SGD: `iterations` iterations on `graph` from `poses`, continuing its learning-rate schedule."""

    def __call__(self, graph: PoseGraph, iterations: int, poses: FloatArray, *,
                 first_iteration: int) -> Iterator[Iteration]: ...


def check_kernel(kernel: str, scale: float | None) -> float:
    """The kernel's scale (its default when None), or an OptimizerError for an unknown kernel or bad scale."""
    if kernel not in KERNELS:
        raise OptimizerError(f"unknown robust kernel {kernel!r}; choose one of {', '.join(KERNELS)}")
    value = DEFAULT_SCALES[kernel] if scale is None else float(scale)
    if not (np.isfinite(value) and value > 0.0):
        raise OptimizerError(f"the robust kernel's scale must be positive and finite, got {scale}")
    return value


def kernel_cost(kernel: str, chi2_terms: FloatArray, scale: float) -> FloatArray:
    """ρ(u) of every χ² term u."""
    u = np.asarray(chi2_terms, dtype=np.float64)
    if kernel == "cauchy":
        return scale * np.log1p(u / scale)
    if kernel == "dcs":
        return np.where(u <= scale, u, scale * (3.0 * u - scale) / (scale + u))
    raise OptimizerError(f"unknown robust kernel {kernel!r}; choose one of {', '.join(KERNELS)}")


def kernel_weight(kernel: str, chi2_terms: FloatArray, scale: float) -> FloatArray:
    """ρ'(u) of every χ² term u: the factor the constraint's information is scaled by, in (0, 1]."""
    u = np.asarray(chi2_terms, dtype=np.float64)
    if kernel == "cauchy":
        return 1.0 / (1.0 + u / scale)
    if kernel == "dcs":
        return np.minimum(1.0, 2.0 * scale / (scale + u)) ** 2
    raise OptimizerError(f"unknown robust kernel {kernel!r}; choose one of {', '.join(KERNELS)}")


def robust_cost(graph: PoseGraph, poses: FloatArray | None, kernel: str, scale: float | None = None, *,
                protect_odometry: bool = True) -> float:
    """Σ ρ(u_k) over the constraints at `poses` (default: the graph's estimate); see `robust_weights`."""
    scale = check_kernel(kernel, scale)
    terms = edge_chi2(graph, poses)
    robust = _robust_mask(graph, protect_odometry)
    return float(terms[~robust].sum() + kernel_cost(kernel, terms[robust], scale).sum())


def robust_weights(graph: PoseGraph, poses: FloatArray | None, kernel: str, scale: float | None = None, *,
                   protect_odometry: bool = True) -> FloatArray:
    """(M,) weights ρ'(u_k) of the constraints at `poses`.

    With `protect_odometry` (the default) the odometry chain (`graph.is_odometry`) keeps weight 1 and
    ρ(u) = u: outliers come from loop closing, and a kernel on the chain lets the optimizer tear the
    trajectory apart at a few odometry constraints to satisfy a false loop (seen on M3500).
    """
    scale = check_kernel(kernel, scale)
    return _weights(graph, edge_chi2(graph, poses), kernel, scale, _robust_mask(graph, protect_odometry))


def _robust_mask(graph: PoseGraph, protect_odometry: bool) -> NDArray[np.bool_]:
    return ~graph.is_odometry if protect_odometry else np.ones(graph.num_edges, dtype=bool)


def _weights(graph: PoseGraph, chi2_terms: FloatArray, kernel: str, scale: float,
             robust: NDArray[np.bool_]) -> FloatArray:
    weights = np.ones(graph.num_edges)
    weights[robust] = kernel_weight(kernel, chi2_terms[robust], scale)
    return weights


def weighted_graph(graph: PoseGraph, weights: FloatArray) -> PoseGraph:
    """The graph with information w_k·Ω_k (same poses, constraints and ids)."""
    information = graph.information * np.asarray(weights, dtype=np.float64)[:, None, None]
    return PoseGraph(graph.poses, graph.edge_from, graph.edge_to, graph.measurements, information,
                     graph.vertex_ids)


def _weakest_stiffness(graph: PoseGraph, poses: FloatArray, weights: FloatArray) -> FloatArray:
    """(3,) per-dimension minimum over constraints of w_k·diag(R Ω_k Rᵀ), R = Rot(θ_a): the SGD's γ."""
    theta = poses[graph.edge_from, 2]
    c, s = np.cos(theta), np.sin(theta)
    info = graph.information
    cross = info[:, 0, 1] + info[:, 1, 0]
    diagonal = np.stack([c * c * info[:, 0, 0] - c * s * cross + s * s * info[:, 1, 1],
                         s * s * info[:, 0, 0] + c * s * cross + c * c * info[:, 1, 1],
                         info[:, 2, 2]], axis=1)
    return (weights[:, None] * diagonal).min(axis=0)


def robust_sgd(
    graph: PoseGraph,
    iterations: int,
    poses: FloatArray | None = None,
    *,
    kernel: str,
    scale: float | None = None,
    descent: Descent = sgd,
    first_iteration: int = 1,
    protect_odometry: bool = True,
) -> Iterator[Iteration]:
    """`iterations` SGD iterations on the robust cost, yielding Iteration("sgd", k, poses, robust cost).

    Before every iteration the weights ρ'(u_k) are recomputed from the current poses and one iteration
    of `descent` runs on the graph with information w_k·Ω_k. The paper's learning rate 1/(γ t) takes γ
    from the weakest constraint, which a weight of 1e-4 would make 1e4 times weaker, and the step of every
    other constraint as much larger (the map then scatters: χ² ×3e6 on M3500 + 100 false loops); so t is
    advanced by the factor γ/γ_weighted, which keeps the unweighted graph's learning rate. `descent` must
    therefore take α = 1/(γ t) with γ its weakest constraint, as `optimizer.sgd.sgd` does.
    """
    if iterations < 0:
        raise OptimizerError(f"iterations must be >= 0, got {iterations}")
    if first_iteration < 1:
        raise OptimizerError(f"first_iteration must be >= 1, got {first_iteration}")
    scale = check_kernel(kernel, scale)
    current = _starting_poses(graph, poses)
    robust = _robust_mask(graph, protect_odometry)
    ones = np.ones(graph.num_edges)
    for offset in range(iterations):
        weights = _weights(graph, edge_chi2(graph, current), kernel, scale, robust)
        slowdown = float(np.max(_weakest_stiffness(graph, current, ones)
                                / _weakest_stiffness(graph, current, weights)))
        t = first_iteration + offset
        steps = descent(weighted_graph(graph, weights), 1, current,
                        first_iteration=max(t, int(np.ceil(t * slowdown))))
        step = next(iter(steps), None)
        if step is None:
            raise OptimizerError("the descent yielded no iteration")
        current = step.poses
        yield Iteration("sgd", offset + 1, step.poses,
                        robust_cost(graph, current, kernel, scale, protect_odometry=protect_odometry))


def _starting_poses(graph: PoseGraph, poses: FloatArray | None) -> FloatArray:
    start = np.array(graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if start.shape != graph.poses.shape:
        raise OptimizerError(f"expected poses of shape {graph.poses.shape}, got {start.shape}")
    return start


def robust_polish(
    graph: PoseGraph,
    poses: FloatArray | None = None,
    *,
    kernel: str,
    scale: float | None = None,
    max_iterations: int = 300,
    weight_tolerance: float = WEIGHT_TOLERANCE,
    max_reweights: int = MAX_REWEIGHTS,
    protect_odometry: bool = True,
) -> Generator[Iteration, None, PolishStatus]:
    """Iteratively reweighted Levenberg–Marquardt on the robust cost.

    Reweight, run `gauss_newton` on the weighted graph to its convergence, reweight, … until no weight
    changes by more than `weight_tolerance`. Yields every accepted step as Iteration("gauss-newton", k,
    poses, robust cost), k counting on across the rounds; `max_iterations` caps the accepted steps of all
    rounds together. Returns a PolishStatus that has converged only when the last round's LM converged and
    the weights it was run with are those of the poses it reached.
    """
    scale = check_kernel(kernel, scale)
    if max_iterations < 0:
        raise OptimizerError(f"max_iterations must be >= 0, got {max_iterations}")
    if max_reweights < 1:
        raise OptimizerError(f"max_reweights must be >= 1, got {max_reweights}")
    current = _starting_poses(graph, poses)
    robust = _robust_mask(graph, protect_odometry)
    weights = _weights(graph, edge_chi2(graph, current), kernel, scale, robust)
    count = 0
    for _ in range(max_reweights):
        inner = gauss_newton(weighted_graph(graph, weights), current, max_iterations=max_iterations - count)
        while True:
            try:
                step = next(inner)
            except StopIteration as stop:
                status: PolishStatus = stop.value
                break
            count += 1
            current = step.poses
            yield Iteration("gauss-newton", count, step.poses, robust_cost(graph, step.poses, kernel, scale,
                                                                         protect_odometry=protect_odometry))
        new_weights = _weights(graph, edge_chi2(graph, current), kernel, scale, robust)
        change = float(np.max(np.abs(new_weights - weights), initial=0.0))
        weights = new_weights
        if change <= weight_tolerance:
            if status.converged:
                return PolishStatus(True, f"weights stable (largest change {change:.2g}); {status.reason}",
                                    count)
            return PolishStatus(False, f"weights stable but the last LM did not converge: {status.reason}",
                                count)
        if count >= max_iterations:
            return PolishStatus(False, f"{max_iterations} iterations reached while reweighting "
                                f"(largest weight change {change:.2g})", count)
    return PolishStatus(False, f"{max_reweights} reweighting rounds and the weights still change "
                        f"(largest change {change:.2g})", count)


def robust_optimize(
    graph: PoseGraph,
    kernel: str,
    iterations: int = 100,
    poses: FloatArray | None = None,
    *,
    scale: float | None = None,
    descent: Descent = sgd,
    polish_iterations: int = 300,
    protect_odometry: bool = True,
) -> Generator[Iteration, None, PolishStatus]:
    """The robust default method: `robust_sgd` with Cauchy weights, then `robust_polish` with `kernel`.

    Both at `scale` (default: the kernel's). The SGD weighs with Cauchy even for "dcs" (see the module
    docstring); the polish then minimizes the chosen kernel's cost. Returns the polish's status.
    """
    sgd_scale = check_kernel(kernel, scale) if scale is not None else DEFAULT_SCALES["cauchy"]
    current = _starting_poses(graph, poses)
    for step in robust_sgd(graph, iterations, current, kernel="cauchy", scale=sgd_scale, descent=descent,
                           protect_odometry=protect_odometry):
        current = step.poses
        # Reported in the polish's kernel, so that every stage's figure is the same objective.
        yield Iteration(step.stage, step.index, step.poses,
                        robust_cost(graph, current, kernel, scale, protect_odometry=protect_odometry))
    return (yield from robust_polish(graph, current, kernel=kernel, scale=scale,
                                     max_iterations=polish_iterations, protect_odometry=protect_odometry))
