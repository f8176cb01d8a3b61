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

The robust methods with a polish run `optimizer.robust_gnc.robust_optimize`: graduated non-convexity over
chordal solves to decide which loop closures to trust, then `robust_polish`. The robust SGD here serves the
methods without a polish. Annealing the scale inside the SGD was tried and is not used: while the scale is
large the false loops bend the map, and the SGD's decaying learning rate cannot undo it (M3500 + 100 false
loops after 100 iterations: χ² on the true edges 2.9e3× the optimum annealed over 30 iterations from
c² = 1000, 2.5e2× at a fixed c² = 7.8); the chordal solves of `robust_gnc` read no estimate, so nothing
of an earlier round's bend is left to undo.
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
from optimizer.polish import PolishStatus, _starting_poses, gauss_newton
from optimizer.sgd import sgd

FloatArray = NDArray[np.float64]
Kernel = Literal["cauchy", "dcs"]
KERNELS: tuple[str, ...] = ("cauchy", "dcs")

HONEST_MEDIAN_CHI2 = 2.366
"""Median of a χ² variable with 3 degrees of freedom."""
RELATIVE_SCALES: dict[str, float] = {"cauchy": 10.0, "dcs": 40.0}
"""The default scale, in χ² units (u = eᵀΩe), is this factor times the median χ² term of the robustified
constraints at the current poses, re-estimated every reweighting round (as the MAD scale of classic
IRLS), between MIN_SCALES and MAX_SCALES. Real graphs' information is often far from honest: M3500's
loop closures have a median u of 0.024 at the optimum, a 500-pose grid world's 2.4. A fixed scale fits
one and fails the other: with c² = 7.8 two of M3500's 100 false loops are bent onto at 40 % extra cost
on the true edges (rejecting a constraint still costs c²·log(1 + u/c²), more than bending this map);
with c² = 1 or Φ = 1 the grid world's true loops lose weight and its result is 23 % / 36 % off the clean
optimum. The median stays an inlier's as long as fewer than half of the loop closures are false.

Cauchy: its cost grows without bound, so every rejected false loop keeps a pull ∝ c²; c² must follow the
inliers down, and the factor is a compromise (M3500 after graduated non-convexity: factor 10 is 1.4 %
off without false loops and 1.3 % with 100; factor 30 0.14 % / 4.1 %; factor 100 0.01 % / 12 %).
DCS: weight 1 up to Φ and a bounded cost, so Φ can sit well above the inliers, but not so far that a
false loop can be bent onto at a cost below Φ. Measured after graduated non-convexity, ratio of χ² on the
true edges to the clean optimum (benchmarks/robust_bench.py; factor 4 was the earlier default):
factor 4: CSAIL 1.61, INTEL 1.67, FR079 1.000; M3500 + 100 / 500 false loops 1.000 (seeds 1–3).
factor 40: CSAIL 1.000, INTEL 1.042 (2 true loops weighted below 0.9), FR079 1.000; M3500 + 100 / 500
false loops 1.000 / 1.000 (seed 1: 1.00016 at 500; seeds 2 and 3 in the benchmark).
factor 100: CSAIL, INTEL, FR079 1.000, but M3500 + 500 false loops, seed 1: 1.0097, one false loop
bent onto (M3500's pessimistic information makes bending the map cheap in χ² units).
"""
MAX_SCALES: dict[str, float] = {"cauchy": 10.0 * HONEST_MEDIAN_CHI2, "dcs": 4.0 * HONEST_MEDIAN_CHI2}
"""Ceiling of the adaptive scale, for honest information (a median χ² term near 2.366): c² = 24 and
Φ = 9.5, the smallest measured to stay within 1 % of the clean grid world's optimum with 6 gross false
loops (c² = 7.8 was 2.2 % off, Φ = 7.8 0.1 %). A fixed Φ = 9.5 on M3500 (pessimistic information, so
bending the map is cheap in χ² units) lets one of 500 false loops be bent onto: 3.3 % off (seed 2)."""
MIN_SCALES: dict[str, float] = {"cauchy": 1e-6, "dcs": 1.0}
"""Floor of the adaptive scale. DCS: a constraint within one standard deviation of its own information
(u ≤ 1) is never down-weighted. Without it M3500's scale follows its pessimistic information down
(factor 4: Φ = 0.1), and DCS, whose weight falls as 4Φ²/u², then rejected true loops that were still
converging behind the robust SGD (M3500 + 100 false loops: 10 true loops rejected, 19 % off the optimum,
not converged; with the floor 0.0 %). Cauchy's weight c²/u falls gently, while every rejected constraint
keeps a pull ∝ c²: its scale may follow the median down (M3500 + 100 false loops: 1.3 % off; with the
floor of 1, 4.8 %)."""
SGD_SCALE = 1.0
"""The robust SGD's fixed default scale (`--method sgd --robust`, and the reweighted polish's first round).
It was chosen when the SGD had to bring the map into the polish's basin (the robust chain now starts from
graduated non-convexity instead, `optimizer.robust_gnc`); starting
from dead reckoning, the median χ² term says nothing about the inliers yet. Measured on M3500 with 100 /
500 false loops: c² = 1 leaves the true edges at 53× / 61× the optimum (the plain SGD: 41× without false
loops; re-measured with seed 1 of benchmarks/robust_bench.py: 54× / 1.5e3×), c² = 7.8 at 106× / 2.3e4×
(from which the polish does not recover)."""

WEIGHT_TOLERANCE = 1e-3
"""The robust polish stops reweighting once no weight changes by more than this."""
MAX_REWEIGHTS = 30
"""Cap on the robust polish's reweighting rounds (each one a converged Levenberg–Marquardt run)."""


class Descent(Protocol):
    """An SGD: `iterations` iterations on `graph` from `poses`, continuing its learning-rate schedule."""

    def __call__(self, graph: PoseGraph, iterations: int, poses: FloatArray, *,
                 first_iteration: int) -> Iterator[Iteration]: ...


def check_kernel(kernel: str, scale: float | None = None) -> None:
    """An OptimizerError for an unknown kernel or a scale that is not positive and finite."""
    if kernel not in KERNELS:
        raise OptimizerError(f"unknown robust kernel {kernel!r}; choose one of {', '.join(KERNELS)}")
    if scale is not None and not (np.isfinite(scale) and scale > 0.0):
        raise OptimizerError(f"the robust kernel's scale must be positive and finite, got {scale}")


def adaptive_scale(kernel: str, chi2_terms: FloatArray) -> float:
    """The default scale for these χ² terms of the robustified constraints (see RELATIVE_SCALES)."""
    check_kernel(kernel)
    if len(chi2_terms) == 0:
        return MAX_SCALES[kernel]
    median = float(np.median(chi2_terms))
    return float(min(MAX_SCALES[kernel], max(RELATIVE_SCALES[kernel] * median, MIN_SCALES[kernel])))


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
    check_kernel(kernel, scale)
    terms = edge_chi2(graph, poses)
    robust = robust_mask(graph, protect_odometry)
    if scale is None:
        scale = adaptive_scale(kernel, terms[robust])
    return float(terms[~robust].sum() + kernel_cost(kernel, terms[robust], scale).sum())


def robust_weights(graph: PoseGraph, poses: FloatArray | None, kernel: str, scale: float | None = None, *,
                   protect_odometry: bool = True) -> FloatArray:
    """(M,) weights ρ'(u_k) of the constraints at `poses`.

    With `protect_odometry` (the default) the odometry chain (`graph.is_odometry`) keeps weight 1 and
    ρ(u) = u: outliers come from loop closing, and a kernel on the chain lets the optimizer tear the
    trajectory apart at a few odometry constraints to satisfy a false loop (seen on M3500). The default
    scale is `adaptive_scale` of the χ² terms at `poses`.
    """
    check_kernel(kernel, scale)
    terms = edge_chi2(graph, poses)
    robust = robust_mask(graph, protect_odometry)
    if scale is None:
        scale = adaptive_scale(kernel, terms[robust])
    return masked_weights(graph, terms, kernel, scale, robust)


def robust_mask(graph: PoseGraph, protect_odometry: bool) -> NDArray[np.bool_]:
    """(M,) which constraints the kernel applies to: the loop closures, or all without `protect_odometry`."""
    return ~graph.is_odometry if protect_odometry else np.ones(graph.num_edges, dtype=bool)


def masked_weights(graph: PoseGraph, chi2_terms: FloatArray, kernel: str, scale: float,
             robust: NDArray[np.bool_]) -> FloatArray:
    """(M,) ρ'(u) at `scale` where `robust`, 1 elsewhere."""
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
    """`iterations` SGD iterations on the robust cost, yielding Iteration(stage, k, poses, robust cost) with
    the stage `descent` names ("sgd", "sgd-tree").

    The scale is fixed: `scale`, by default SGD_SCALE.
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
    check_kernel(kernel, scale)
    scale = SGD_SCALE if scale is None else scale
    current = _starting_poses(graph, poses)
    robust = robust_mask(graph, protect_odometry)
    ones = np.ones(graph.num_edges)
    for offset in range(iterations):
        weights = masked_weights(graph, edge_chi2(graph, current), kernel, scale, robust)
        slowdown = float(np.max(_weakest_stiffness(graph, current, ones)
                                / _weakest_stiffness(graph, current, weights)))
        t = first_iteration + offset
        steps = descent(weighted_graph(graph, weights), 1, current,
                        first_iteration=max(t, round(t * slowdown)))
        step = next(iter(steps), None)
        if step is None:
            raise OptimizerError("the descent yielded no iteration")
        current = step.poses
        yield Iteration(step.stage, offset + 1, step.poses,
                        robust_cost(graph, current, kernel, scale, protect_odometry=protect_odometry))


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
    the weights it was run with are those of the poses it reached. Without `scale`, every round takes
    `adaptive_scale` of the poses it starts from (the yielded robust costs use the round's scale).
    """
    check_kernel(kernel, scale)
    if max_iterations < 0:
        raise OptimizerError(f"max_iterations must be >= 0, got {max_iterations}")
    if max_reweights < 1:
        raise OptimizerError(f"max_reweights must be >= 1, got {max_reweights}")
    current = _starting_poses(graph, poses)
    robust = robust_mask(graph, protect_odometry)
    terms = edge_chi2(graph, current)
    round_scale = adaptive_scale(kernel, terms[robust]) if scale is None else scale
    if scale is None and kernel == "cauchy":
        # From an unconverged start the median χ² term is no inlier's: the first round runs at SGD_SCALE.
        # (DCS's weight is 1 up to Φ: a start where true loops lie beyond Φ is left to the later rounds.)
        round_scale = min(SGD_SCALE, round_scale)
    weights = masked_weights(graph, terms, kernel, round_scale, robust)
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
            yield Iteration("gauss-newton", count, step.poses, robust_cost(
                graph, step.poses, kernel, round_scale, protect_odometry=protect_odometry))
        terms = edge_chi2(graph, current)
        round_scale = adaptive_scale(kernel, terms[robust]) if scale is None else scale
        new_weights = masked_weights(graph, terms, kernel, round_scale, robust)
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
