"""The exact-minimum polish: sparse Levenberg–Marquardt (damped Gauss–Newton) on the χ² of `optimizer.cost`.

Poses are parameterised globally (x, y, θ) with an additive update, θ wrapped, except that a step's rotation
of the whole graph about the anchor is applied as a rotation (`moved_by`). The first pose is anchored:
its three columns are dropped from the system, so the normal equations are (3N−3)×(3N−3).

The information of real graphs (INTEL.g2o) is badly scaled — 3×3 edge informations with condition numbers
up to 2e11 — so the damped system is solved in Jacobi-scaled form: with S = diag(H)^(-1/2),
(S H S + λ·I) y = −S g, Δ = S y. This is exactly Marquardt's λ·diag(H) damping, but the matrix handed to
the factorisation has a unit diagonal. H and g are assembled edge by edge by the compiled kernels of
`optimizer.normal_equations`; the damped system is solved by `optimizer.damped_solvers` (qdldl's exact
LDLᵀ), or on graphs too large to factorise by conjugate gradients preconditioned with algebraic multigrid
(`optimizer.multigrid_solver`, on H in 3×3 blocks from `optimizer.block_normal_equations`) or, on request,
with the pose chain.

The generator's return value says whether it converged (`PolishStatus`): it never stops silently.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from optimizer import se2
from optimizer.anchor_alignment import aligned_to_anchor
from optimizer.block_normal_equations import BlockPattern, assemble_blocks, block_diagonal
from optimizer.cost import chi2, edge_errors
from optimizer.damped_solvers import ChainPCGSolver, DirectSolver, Linearisation
from optimizer.errors import GraphError, OptimizerError
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration
from optimizer.locality_order import inverse, locality_order, renumbered
from optimizer.normal_equations import UpperPattern, assemble, diagonal_of, hessian_diagonal, quadratic_form

if TYPE_CHECKING:
    from optimizer.multigrid_solver import MultigridPCGSolver

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

STAGE = "gauss-newton"
DEFAULT_MAX_ITERATIONS = 5000
"""Far above what the benchmark graphs need: INTEL, the worst, takes 270–840 steps (from paper-SGD after
100/10 iterations); M3500, CSAIL, FR079 and 10⁵-pose grid worlds 10–20."""
DIRECT_SOLVER_MAX_POSES = 200_000
"""Above this the factorisation's fill outgrows the machine: multigrid-preconditioned CG instead. At 10⁶
grid-world poses the default's polish takes 11 steps, 109–132 s wall (11 hierarchy builds, 101 CG
iterations), to χ² 3 044 220.327 (benchmarks/README.md, scale section). At 2·10⁵ poses from paper-SGD 100
multigrid took 22.3 CPU s (7 steps) where the direct solver took 56.9 (11 steps, before `moved_by`), to
the same χ² 596 032.94715: the threshold was not re-measured since."""
_INITIAL_LAMBDA = 1e-5
_MIN_LAMBDA = 1e-15
"""Floor of λ (relative to the scaled system's unit diagonal). λ·I damps every mode of S·H·S whose
eigenvalue is not far above λ, so at the floor a step leaves (λ/(μ+λ))² of the χ² excess along a mode of
eigenvalue μ: at 10⁶ grid-world poses the softest modes (the global bending) have μ of a few 1e-12. With
the floor at 1e-12 the polish's last steps each took only about 94 % of what was left (χ² lowered by 0.68,
0.039, 0.002: 10 steps to 3 044 220.328); from the same point a step at λ ≤ 1e-13 takes all but 1e-5 of
it (9 steps to 3 044 220.3273). The graphs are connected with positive definite information, so S·H·S is
positive definite and the floor only keeps λ positive, a little above the rounding of the unit diagonal."""
_MIN_SHRINK = 0.01
"""Smallest factor λ shrinks by after a step the linear model predicted well (Nielsen's rule caps it at
1/3). The slowest modes of a large graph (its global bending: eigenvalues of S·H·S near 1/N²) stay damped
until λ falls below them; at 1/3 per step that took 16 steps on a 10⁵-pose grid world, at 0.01 it takes 9,
to the same χ². M3500, CSAIL, FR079 from the file or SGD 30 take 6–13 steps instead of 10–16; INTEL ±2 %."""
INEXACT_FORCING = 1e-2
"""Inexact solvers (CG) stop at this residual relative to the right-hand side, at every step. Near the
minimum a step solved to relative residual η leaves about η² of the χ² excess above it, so the χ² test is
met within a step or two of the basin's floor; forcing that shrank with the gradient (down to 1e-10)
bought the same χ² with 1.7× the CG iterations (10⁵-pose grid world with the multigrid solver: 122
against 72, both 8 steps to χ² 294040.4325)."""
_BACKTRACKS = 3
"""An inexact step that does not lower χ² is halved up to this many times before λ is raised: at 10⁶ poses,
with λ near its floor, one step of the polish took 4 CG solves (134 CPU s), three of them rejected, where
a shorter multiple of the first costs one χ² evaluation (about 0.3 s)."""
_MAX_LAMBDA = 1e12
"""Past this the step is a vanishing gradient-descent step: no further decrease can be found."""
_DIAGONAL_FLOOR = 1e-12
"""Relative floor of diag(H) for the scaling, for variables a singular information leaves unconstrained."""


def edge_jacobians(
    graph: PoseGraph, poses: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Errors (M, 3) and their Jacobians (M, 3, 3) with respect to x_a and x_b, for every constraint.

    With e = t2v(z⁻¹·(x_a⁻¹·x_b)): e_t = R(θ_a+θ_z)ᵀ (t_b − t_a) − R(θ_z)ᵀ t_z and e_θ = θ_b − θ_a − θ_z, so
    ∂e/∂x_b is the rotation R(θ_a+θ_z)ᵀ (with a 1 for θ) and ∂e/∂x_a is its negative, plus the derivative
    of R(θ_a+θ_z)ᵀ with respect to θ_a applied to t_b − t_a in the θ column.
    """
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    errors = edge_errors(graph, poses)
    pose_a = poses[graph.edge_from]
    pose_b = poses[graph.edge_to]
    phi = pose_a[:, 2] + graph.measurements[:, 2]
    c, s = np.cos(phi), np.sin(phi)
    dx = pose_b[:, 0] - pose_a[:, 0]
    dy = pose_b[:, 1] - pose_a[:, 1]

    jac_b = np.zeros((len(phi), 3, 3))
    jac_b[:, 0, 0] = c
    jac_b[:, 0, 1] = s
    jac_b[:, 1, 0] = -s
    jac_b[:, 1, 1] = c
    jac_b[:, 2, 2] = 1.0
    jac_a = -jac_b
    jac_a[:, 0, 2] = -s * dx + c * dy
    jac_a[:, 1, 2] = -c * dx - s * dy
    return errors, jac_a, jac_b


def _gradient(graph: PoseGraph, errors: FloatArray, jac_a: FloatArray, jac_b: FloatArray) -> FloatArray:
    """g = Σ JᵀΩe over the free variables (the anchor's three entries dropped)."""
    weighted = np.einsum("mij,mj->mi", graph.information, errors)
    grad_a = np.einsum("mji,mj->mi", jac_a, weighted)
    grad_b = np.einsum("mji,mj->mi", jac_b, weighted)
    within = np.arange(3)
    index = np.concatenate([(3 * graph.edge_from[:, None] + within).reshape(-1),
                            (3 * graph.edge_to[:, None] + within).reshape(-1)])
    full = np.bincount(index, weights=np.concatenate([grad_a.reshape(-1), grad_b.reshape(-1)]),
                       minlength=3 * graph.num_poses)
    return np.asarray(full[3:], dtype=np.float64)  # weighted: floats (numpy's stubs say integers)


@dataclass(frozen=True)
class PolishStatus:
    """How the polish ended: `converged` only when its convergence test held, with the reason."""

    converged: bool
    reason: str
    iterations: int
    """Accepted steps (the iterations yielded)."""


LinearSolver = Literal["auto", "direct", "multigrid", "cg"]
LINEAR_SOLVERS: tuple[str, ...] = ("auto", "direct", "multigrid", "cg")


def _predicted_decrease(graph: PoseGraph, poses: FloatArray, linearisation: Linearisation,
                        step: FloatArray) -> float:
    """The decrease of χ² the linearised model predicts for `step`."""
    return -(2.0 * float(linearisation.gradient @ step) + quadratic_form(
        poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information, step))


def _near_newton_gain(graph: PoseGraph, poses: FloatArray, current_chi2: float,
                      linearisation: Linearisation,
                      solver: DirectSolver | ChainPCGSolver | MultigridPCGSolver) -> float:
    """The relative decrease of χ² the least-damped step promises (NaN when it cannot be solved)."""
    scaled_step = solver.step(linearisation, _MIN_LAMBDA)
    if scaled_step is None:
        return math.nan
    return _predicted_decrease(graph, poses, linearisation, linearisation.scale * scaled_step) / current_chi2


def gauss_newton(
    graph: PoseGraph,
    poses: FloatArray | None = None,
    *,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    relative_tolerance: float = 1e-9,
    step_tolerance: float = 1e-6,
    gradient_tolerance: float = 1e-18,
    linear_solver: LinearSolver = "auto",
) -> Generator[Iteration, None, PolishStatus]:
    """Levenberg–Marquardt on the χ² of `graph`, from `poses` (default: the graph's estimate).

    Yields Iteration("gauss-newton", k, poses, χ²) after every accepted step, k from 1; rejected trial
    steps (χ² did not decrease, so λ is raised and the step recomputed) are not yielded; with an inexact
    (CG) solver a step that does not lower χ² is first halved up to `_BACKTRACKS` times before λ is raised.
    Pose 0 stays fixed.
    Returns a `PolishStatus` (`status = yield from gauss_newton(...)`). It has converged when either
    - an accepted near-Gauss–Newton step (λ ≤ 1 in the scaled system; a solved, not truncated, linear
      system; taken whole, not shortened by the inexact solvers' line search) changed χ² by less than
      `relative_tolerance` of its value and, with the exact solver, moved the poses by less than
      `step_tolerance`·(‖x‖ + `step_tolerance`) (Euclidean norms over all free coordinates), with an
      inexact one, was predicted by the linear model to lower χ² by less than `relative_tolerance` of it,
      or
    - the Jacobi-scaled gradient is negligible: gᵀ·diag(H)⁻¹·g ≤ `gradient_tolerance`·χ².
    It has not converged when `max_iterations` steps were taken first, or when λ grew past 1e12 without a
    decrease while the gradient test fails (a stall, not an optimum). `linear_solver` "direct" is qdldl's
    exact LDLᵀ, "multigrid" conjugate gradients preconditioned by smoothed-aggregation multigrid (pyamg),
    "cg" conjugate gradients preconditioned by the pose chain; "auto" takes "direct" up to
    `DIRECT_SOLVER_MAX_POSES` poses and "multigrid" above. The multigrid descent runs on the graph with its
    poses renumbered for memory locality (`optimizer.locality_order`); its iterations are yielded with the
    poses in the graph's own order.
    """
    if max_iterations < 0:
        raise OptimizerError(f"max_iterations must be >= 0, got {max_iterations}")
    for name, value in (("relative_tolerance", relative_tolerance), ("step_tolerance", step_tolerance),
                        ("gradient_tolerance", gradient_tolerance)):
        if not value >= 0.0:
            raise OptimizerError(f"{name} must be >= 0, got {value}")
    if linear_solver not in LINEAR_SOLVERS:
        raise OptimizerError(f"unknown linear solver {linear_solver!r}; choose {', '.join(LINEAR_SOLVERS)}")
    start = _starting_poses(graph, poses)
    if _resolved(graph, linear_solver) == "multigrid" and graph.num_poses > 2:
        order = locality_order(graph)
        rank = inverse(order)
        # The multigrid hierarchy aggregates the free poses in the graph's own order (`rank[1:] - 1`: the
        # renumbered free pose of each in turn), as it would without the renumbering.
        renumbered_start = start[order]
        renumbered_start.setflags(write=False)  # read-only like every iterate (`_starting_poses`)
        descent = _descent(renumbered(graph, order), renumbered_start, max_iterations, relative_tolerance,
                           step_tolerance, gradient_tolerance, "multigrid", rank[1:] - 1)
        return (yield from _numbered_back(descent, rank))
    return (yield from _descent(graph, start, max_iterations, relative_tolerance, step_tolerance,
                                gradient_tolerance, linear_solver))


def _numbered_back(descent: Generator[Iteration, None, PolishStatus],
                   rank: IntArray) -> Generator[Iteration, None, PolishStatus]:
    """The iterations of a descent on the graph renumbered so that pose i is pose `rank[i]`
    (`optimizer.locality_order`), their poses in the graph's own order."""
    while True:
        try:
            iteration = next(descent)
        except StopIteration as stop:
            return stop.value
        poses = iteration.poses[rank]
        poses.setflags(write=False)
        yield Iteration(iteration.stage, iteration.index, poses, iteration.chi2, iteration.start)


def _descent(graph: PoseGraph, current: FloatArray, max_iterations: int, relative_tolerance: float,
             step_tolerance: float, gradient_tolerance: float,
             linear_solver: LinearSolver, aggregation_order: IntArray | None = None
             ) -> Generator[Iteration, None, PolishStatus]:
    """`gauss_newton` on `graph` as numbered, from `current` (`_starting_poses`: a copy of its own);
    `aggregation_order`: the order the multigrid solver's aggregation visits the free poses in."""
    current_chi2 = chi2(graph, current)
    if graph.num_poses < 2:
        return PolishStatus(True, "a single pose: nothing to optimize", 0)
    if current_chi2 == 0.0:
        return PolishStatus(True, "χ² is zero", 0)
    pattern, solver = _solver_for(graph, linear_solver, aggregation_order)
    damping = _INITIAL_LAMBDA
    growth = 2.0
    last_change = float("nan")
    rounding_chi2 = _rounding_chi2(graph, current)
    index = 0

    while True:
        if current_chi2 <= rounding_chi2:
            return PolishStatus(True, f"χ² {current_chi2:.1e} is zero up to rounding", index)
        linearisation = _linearise(graph, pattern, current)
        scaled_gradient = linearisation.scale * linearisation.gradient
        gradient_measure = float(scaled_gradient @ scaled_gradient) / current_chi2
        if gradient_measure <= gradient_tolerance:
            return PolishStatus(True, f"scaled gradient gᵀdiag(H)⁻¹g/χ² {gradient_measure:.1e} ≤ "
                                      f"{gradient_tolerance:.0e}", index)
        if index >= max_iterations:
            return PolishStatus(False, f"iteration cap {max_iterations} reached (last relative χ² change "
                                       f"{last_change:.1e})", index)
        if not solver.exact:
            solver.forcing = INEXACT_FORCING
        backtracked = False
        while True:
            scaled_step = solver.step(linearisation, damping)
            if scaled_step is not None:
                step = linearisation.scale * scaled_step
                trial, trial_chi2 = _trial(graph, current, step, realign=not solver.exact)
                if not (trial_chi2 < current_chi2) and not solver.exact:
                    # An inexact solve costs tens of products with H: before paying another at a larger
                    # λ, try shorter steps along the one found, one χ² evaluation each.
                    for _ in range(_BACKTRACKS):
                        step = 0.5 * step
                        trial, trial_chi2 = _trial(graph, current, step, realign=not solver.exact)
                        if trial_chi2 < current_chi2:
                            backtracked = True
                            break
                if trial_chi2 < current_chi2:
                    break
            damping *= growth
            growth *= 2.0
            if damping > _MAX_LAMBDA:
                near_newton_gain = _near_newton_gain(graph, current, current_chi2, linearisation, solver)
                if 0.0 <= near_newton_gain < relative_tolerance:  # (negative: a broken step, no optimum)
                    # At the optimum up to rounding: the Gauss–Newton model promises less than the χ² test
                    # asks for, and the evaluated χ² cannot show even that.
                    return PolishStatus(True, f"no step can lower χ² by a relative {relative_tolerance:.0e} "
                                              f"(Gauss–Newton predicts {near_newton_gain:.1e})", index)
                return PolishStatus(False, f"no decreasing step (λ > {_MAX_LAMBDA:.0e}) with scaled gradient "
                                           f"gᵀdiag(H)⁻¹g/χ² {gradient_measure:.1e} > "
                                           f"{gradient_tolerance:.0e}", index)
        step_damping = damping

        # Nielsen's update: shrink λ the more the linear model predicted the actual decrease.
        predicted = _predicted_decrease(graph, current, linearisation, step)
        # H is not needed past here: let it go before the next one is assembled (360 MB at 10⁶ poses); the
        # multigrid solver's hierarchy, which shares its blocks, lets go at `accepted_step`.
        del linearisation
        gain = (current_chi2 - trial_chi2) / predicted if predicted > 0.0 else 0.0
        damping = max(damping * max(_MIN_SHRINK, 1.0 - (2.0 * gain - 1.0) ** 3), _MIN_LAMBDA)
        growth = 2.0

        change = last_change = (current_chi2 - trial_chi2) / current_chi2
        solver.accepted_step()
        step_norm = float(np.linalg.norm(step))
        state_norm = float(np.linalg.norm(current[1:]))
        if solver.exact:
            settled = step_norm <= step_tolerance * (state_norm + step_tolerance)
        else:
            # A step solved to a forcing term carries CG's remaining error along the flattest modes, which
            # moves poses without changing χ²: at 10⁶ grid-world poses steps 10–14 of the default all ended
            # at χ² 3 044 220.327 (10 digits) without the norm test holding. What the linear model still
            # promises is the test there.
            settled = predicted <= relative_tolerance * current_chi2
        current, current_chi2 = trial, trial_chi2
        current.setflags(write=False)
        index += 1
        yield Iteration(STAGE, index, current, current_chi2)
        if current_chi2 == 0.0:
            return PolishStatus(True, "χ² is zero", index)
        solved = solver.exact or solver.last_converged
        if change < relative_tolerance and settled and step_damping <= 1.0 and solved and not backtracked:
            return PolishStatus(True, f"relative χ² change {change:.1e} < {relative_tolerance:.0e}, step "
                                      f"{step_norm:.1e} (‖x‖ {state_norm:.1e})", index)


def _trial(graph: PoseGraph, current: FloatArray, step: FloatArray, *,
           realign: bool) -> tuple[FloatArray, float]:
    """The poses `step` leads to from `current` (θ wrapped, see `moved_by`), with `realign` realigned to
    the anchor's constraints (`aligned_to_anchor`), and their χ² (inf when not finite).

    Realigned only after inexact (CG) steps, on the graphs too large to factorise: there the anchor's
    rigid mode is the softest of a system solved to a forcing term, while the exact steps of the smaller
    graphs are left as they were."""
    trial = moved_by(current, step)
    if realign and np.all(np.isfinite(trial)):
        trial = aligned_to_anchor(graph, trial)
    with np.errstate(over="ignore", invalid="ignore"):  # a wild trial step may overflow χ²
        trial_chi2 = chi2(graph, trial)
    return trial, float(trial_chi2) if np.isfinite(trial_chi2) else math.inf


def moved_by(poses: FloatArray, step: FloatArray) -> FloatArray:
    """`poses` after the step (3 entries per free pose), with the step's rotation of the whole graph about
    the anchor applied as a rotation.

    The additive update is exact in θ but only first-order in the rigid rotation about the anchor: turning
    everything by φ moves a pose at distance r by r·φ along the tangent instead of along the circle, which
    stretches every edge by a factor √(1 + φ²). That rotation is the graph's softest mode wherever the
    anchor has few edges (at 10⁶ grid-world poses, with 2 edges at pose 0, 99.99 % of a near-optimum step's
    norm, φ = −0.036 rad at λ = 1e-11: the additive update raised χ² by 877 where 145.7 of decrease was
    predicted; this one lowers it by 145.4). So the step's rotation φ (its least-squares fit to the rigid
    rotation field, δθ = φ, δt = φ·R(π/2)·(t − t₀)) is taken out and applied exactly, about pose 0, after
    the rest of the step; to first order the result is the additive update, so the Gauss–Newton model and
    its predicted decrease are unchanged."""
    free = step.reshape(-1, 3)
    relative = poses[1:, :2] - poses[0, :2]
    lever = np.column_stack([-relative[:, 1], relative[:, 0]])  # δt of a unit rotation about pose 0
    phi = float(np.vdot(free[:, :2], lever) + free[:, 2].sum()) / (float(np.vdot(lever, lever)) + len(free))
    moved = relative + free[:, :2] - phi * lever
    cos, sin = math.cos(phi), math.sin(phi)
    trial = poses.copy()
    trial[1:, 0] = poses[0, 0] + cos * moved[:, 0] - sin * moved[:, 1]
    trial[1:, 1] = poses[0, 1] + sin * moved[:, 0] + cos * moved[:, 1]
    trial[1:, 2] += free[:, 2]
    trial[:, 2] = se2.wrap_angle(trial[:, 2])
    return trial


def _rounding_chi2(graph: PoseGraph, poses: FloatArray) -> float:
    """The χ² that rounding alone leaves in the errors: a few ulps of the coordinates, weighted by Ω.

    Below it a relative test on χ² or the gradient only measures rounding noise.
    """
    ulps = 16.0 * np.finfo(np.float64).eps * (1.0 + float(np.abs(poses).max()))
    return ulps**2 * float(np.trace(graph.information, axis1=1, axis2=2).sum())


Pattern = UpperPattern | BlockPattern | None
"""How H is assembled: upper CSC (direct), 3×3 blocks (multigrid), or not at all (matrix-free chain CG)."""


def _resolved(graph: PoseGraph, linear_solver: LinearSolver) -> LinearSolver:
    """The solver "auto" stands for on `graph`."""
    if linear_solver == "auto":
        return "direct" if graph.num_poses <= DIRECT_SOLVER_MAX_POSES else "multigrid"
    return linear_solver


def _solver_for(graph: PoseGraph, linear_solver: LinearSolver, aggregation_order: IntArray | None = None
                ) -> tuple[Pattern, DirectSolver | ChainPCGSolver | MultigridPCGSolver]:
    """The linear solver and the pattern H is assembled in (None: matrix-free)."""
    linear_solver = _resolved(graph, linear_solver)
    if linear_solver == "direct":
        upper = UpperPattern.of(graph)
        return upper, DirectSolver(upper)
    if linear_solver == "multigrid":
        from optimizer.multigrid_solver import MultigridPCGSolver  # pyamg only where it is used

        blocks = BlockPattern.of(graph)
        return blocks, MultigridPCGSolver(blocks, aggregation_order=aggregation_order)
    return None, ChainPCGSolver(graph)


def _linearise(graph: PoseGraph, pattern: Pattern, poses: FloatArray) -> Linearisation:
    size = 3 * (graph.num_poses - 1)
    gradient = np.empty(size)
    hessian: FloatArray | None
    if isinstance(pattern, BlockPattern):
        hessian = np.empty((pattern.num_blocks, 3, 3))
        assemble_blocks(poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information,
                        pattern.edge_blocks, hessian, gradient)
        diagonal = block_diagonal(hessian, pattern.diagonal_block)
    elif pattern is not None:
        hessian = np.empty(pattern.nnz)
        assemble(poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information,
                 pattern.edge_block, pattern.indptr, pattern.block_count, hessian, gradient)
        diagonal = diagonal_of(hessian, pattern.indptr)
    else:
        hessian = None
        diagonal = np.empty(size)
        hessian_diagonal(poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information,
                         diagonal, gradient)
    floor = _DIAGONAL_FLOOR * max(float(diagonal.max(initial=0.0)), 1.0)
    scale = 1.0 / np.sqrt(np.maximum(diagonal, floor))
    return Linearisation(poses, gradient, diagonal, scale, hessian)


def _starting_poses(graph: PoseGraph, poses: FloatArray | None) -> FloatArray:
    """A checked copy of the starting poses, θ wrapped, read-only like every later iterate: numba compiles
    a kernel once per argument type, and a writable start took a second compile of the assembly and the
    quadratic form in every fresh cache (a user's first polish)."""
    start = np.array(graph.poses if poses is None else poses, dtype=np.float64, copy=True)
    if start.shape != graph.poses.shape:
        raise GraphError(f"expected poses of shape {graph.poses.shape}, got {start.shape}")
    if not np.all(np.isfinite(start)):
        raise GraphError("the starting poses contain non-finite values")
    start[:, 2] = se2.wrap_angle(start[:, 2])
    start.setflags(write=False)
    return start
