"""One entry point that runs a method's stages from one or more starting estimates, yielding every iteration.

A method is a descent (the paper's SGD, the stronger tree-parameterised SGD, or Gauss–Seidel) optionally
followed by the polish (Levenberg–Marquardt to the exact minimum). Every starting estimate ("candidate") is
optimized in turn and recorded; the result is the candidate with the lowest final χ², and it is converged
only when its polish's own convergence test held. Methods without a polish stop after a fixed number of
iterations and are never reported as converged.

The default, "sgd+gn", is built for the paper's case, a poor initial estimate: the paper's SGD, then the
tree-parameterised SGD from where it ended, then the polish; and, as another candidate, the chordal
initialisation polished directly. A first polish that runs long (`PEEK_AFTER` iterations) has the chordal
candidate optimized beside it, unrecorded and a tenth as far (`_Aside`; it runs again, recorded, in its
turn), so that a polish crawling far above it is abandoned (`crawl_verdict`) instead of running for
thousands of iterations; when candidates end in the same minimum the graph's own estimate (the SGD path)
is the one kept. Measured on M3500-shaped worlds whose odometry headings carry σθ = 0.2
rad of noise, the paper's SGD alone leaves the polish 240–530 times above the minimum; after the tree SGD
(or from the chordal start) it reaches it (benchmarks/optimizer_bench.py, best-known section). When those
two candidates end in different minima (several basins within reach), a third: headings from the planar
SE-Sync relaxation, which uses the translations (`optimizer.planar_sync`), positions solved for them,
polished; at σθ = 0.3 only that one reaches the best-known minimum. A start at which the polish's
convergence test holds at once (a keyframe graph's online estimate, optimized as it came) is only polished:
the descent would climb out of the minimum for the polish to come back. Above `LARGEST_FOR_EXTRA_STAGES` poses
the default is the paper's SGD, handed over to the polish once its χ² stalls (`until_stalled`), then the
polish.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.gauss_seidel import gauss_seidel
from optimizer.graph import PoseGraph
from optimizer.initialization import chordal_initialization
from optimizer.iteration import ESTIMATE, Iteration
from optimizer.planar_sync import sync_initialization
from optimizer.polish import DEFAULT_MAX_ITERATIONS, DIRECT_SOLVER_MAX_POSES, PolishStatus, gauss_newton
from optimizer.polish import STAGE as POLISH_STAGE
from optimizer.robust import KERNELS, check_kernel, robust_sgd
from optimizer.robust_gnc import robust_optimize
from optimizer.sgd import sgd
from optimizer.sgd_tree import sgd_tree

FloatArray = NDArray[np.float64]
Descent = Callable[[PoseGraph, int, FloatArray], Iterator[Iteration]]

LARGEST_FOR_EXTRA_STAGES = 200_000
"""The tree SGD's iteration and the chordal start's factorisation grow faster than linearly on large
graphs (the tree's depth, the factor's fill): above this many poses the default runs the paper's SGD and
the polish only."""
CHORDAL = "chordal"
"""Name of the chordal initialisation among the starts."""
SYNC = "sync"
"""Name of the planar SE-Sync start among the starts."""
LARGEST_FOR_SYNC = 5_000
"""The sync start's low-rank solve takes thousands of products with the reduced form (each a pair of
triangular solves of the translation Laplacian): several seconds at 3 500 poses (benchmarks/
strong_sgd_bench.py --only basin). Above this many poses it is skipped: measured only up to 3 500."""
SAME_MINIMUM = 1e-9
"""Candidates whose final χ² differ by less than this fraction (the polish's own relative convergence
tolerance) ended in the same minimum: the earliest of the starts as the caller or the method lists them
(the graph's estimate before the chordal and sync starts) is kept, whichever ran first."""
ABANDON_FACTOR = 10
"""A candidate's polish is abandoned (`crawl_verdict`) only after this many times the polish iterations of
the lowest converged candidate before it. Measured on the 22 graphs of benchmarks/optimizer_bench.py's
best-known table: a polish that reaches a minimum takes at most 2.1× the iterations of the lowest one
(INTEL 44 against 22, CSAIL 19 against 9, the σθ = 0.3 world seed 1 3 688 against 1 976), while the one
that crawls (the reversed anisotropic σθ = 0.1 world, SGD path) takes 4 363 against 19 and ends 3.2× above;
with fewer SGD iterations the polish may have more to do (INTEL after 1, 3, 10, 30: 118, 45, 48, 46
against 22, at most 5.4×; M3500 and CSAIL at most 2.3×), still below the factor."""
PEEK_AFTER = 100
"""Polish iterations of the first candidate after which the chordal one is optimized beside it (`_Aside`)
as its reference. The polishes from the SGD path of the shared graphs take 9–44: they never pay for it."""
SYNC_DISAGREEMENT = 1e-3
"""The sync start runs only when the earlier candidates' final χ² differ by more than this fraction: when
the SGD path and the chordal start polish into the same minimum, a third start has not been seen to find a
lower one, and it would cost more than both."""
BUILT_STARTS: dict[str, Callable[[PoseGraph], FloatArray]] = {CHORDAL: chordal_initialization,
                                                              SYNC: sync_initialization}
"""The starts the default builds from the graph alone, by name."""
HANDOVER_GAIN = 0.01
"""Where the paper's SGD hands straight to the polish (the default above `LARGEST_FOR_EXTRA_STAGES` poses,
when `iterations` is not given), it stops once an iteration, after its χ² has begun to fall, lowers χ² by
less than this fraction of its value: SGD's steps shrink as 1/t, and its χ² then falls by about c/t per
iteration (c ≈ 0.4 on the 10⁶-pose grid world), far slower than the polish's steps, each of which takes the
whole linearised problem at once. Its first iterations may leave χ² unchanged (all steps clamped to the
residuals: the 10⁶-pose grid world's iterations 2–8); that plateau is not a stall (`until_stalled`)."""


def until_stalled(iterations: Iterator[Iteration], gain: float = HANDOVER_GAIN) -> Iterator[Iteration]:
    """`iterations` (of one descent, from its first) until one lowers χ² by less than `gain` of the χ²
    before it, that iteration included, counting only once an iteration after the first has lowered χ² by
    at least `gain` (SGD's χ² has begun to fall). A descent whose χ² never begins to fall runs to its end."""
    previous = math.inf
    descending = False
    for count, iteration in enumerate(iterations, start=1):
        yield iteration
        value = float(iteration.chi2)
        lowered = previous - value >= gain * previous if math.isfinite(previous) else False
        if descending and not lowered:
            return
        descending = descending or (count >= 2 and lowered)
        previous = value


def _paper_sgd(graph: PoseGraph, iterations: int, poses: FloatArray) -> Iterator[Iteration]:
    return sgd(graph, iterations, poses)


def _paper_then_tree_sgd(graph: PoseGraph, iterations: int, poses: FloatArray) -> Iterator[Iteration]:
    last = poses
    for iteration in sgd(graph, iterations, poses):
        last = iteration.poses
        yield iteration
    if graph.num_poses <= LARGEST_FOR_EXTRA_STAGES:
        yield from sgd_tree(graph, iterations, last)


def _tree_sgd(graph: PoseGraph, iterations: int, poses: FloatArray) -> Iterator[Iteration]:
    return sgd_tree(graph, iterations, poses)


def _gauss_seidel(graph: PoseGraph, iterations: int, poses: FloatArray) -> Iterator[Iteration]:
    return gauss_seidel(graph, poses, iterations=iterations)


@dataclass(frozen=True)
class Method:
    """A descent (None: none) followed, or not, by the polish; `chordal_start` adds the chordal
    initialisation as a second candidate (polished directly: SGD's first, large steps would undo it)."""

    descent: Descent | None
    polish: bool
    chordal_start: bool = False
    sync_start: bool = False
    """Adds the planar SE-Sync start (polished directly) when the other candidates disagree."""
    handover_when_stalled: bool = False
    """Where the paper's SGD is the descent's only stage (above `LARGEST_FOR_EXTRA_STAGES` poses) and
    `iterations` was not given, it hands over to the polish once it stalls (`until_stalled`)."""


METHOD_TABLE: dict[str, Method] = {
    "sgd+gn": Method(_paper_then_tree_sgd, polish=True, chordal_start=True, sync_start=True,
                     handover_when_stalled=True),
    "sgd": Method(_paper_sgd, polish=False),
    "sgd-tree+gn": Method(_tree_sgd, polish=True),
    "sgd-tree": Method(_tree_sgd, polish=False),
    "gn": Method(None, polish=True),
    "gauss-seidel": Method(_gauss_seidel, polish=False),
}
METHODS: tuple[str, ...] = tuple(METHOD_TABLE)
"""sgd+gn (default): the paper's SGD, the tree SGD, then the exact minimum by Gauss–Newton/LM; sgd: the
paper's SGD exactly; sgd-tree: SGD on a spanning tree's paths (TORO's parameterisation), alone or
polished; gn: the polish alone; gauss-seidel: the paper's baseline."""
ROBUST_METHODS = ("sgd+gn", "sgd")
"""The methods a robust kernel applies to: with "sgd+gn" graduated non-convexity over chordal solves, then
the reweighted polish (`optimizer.robust_gnc`); with "sgd" the paper's SGD, reweighted. Not "sgd-tree":
reweighted iteration by iteration the tree SGD hardly moves (M3500: χ² 1.8e4× the optimum after 100
iterations, benchmarks/robust_bench.py)."""
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
                 polish_iterations: int = DEFAULT_POLISH_ITERATIONS, robust: str | None = None) -> None:
        if method not in METHOD_TABLE:
            raise OptimizerError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        if robust is not None:
            check_kernel(robust)
            if method not in ROBUST_METHODS:
                raise OptimizerError(f"a robust kernel ({', '.join(KERNELS)}) works with the methods "
                                     f"{', '.join(ROBUST_METHODS)}, not {method}")
        self._robust = robust
        if iterations is not None and not 0 <= iterations <= MAX_ITERATIONS:
            raise OptimizerError(f"iterations must be between 0 and {MAX_ITERATIONS}, got {iterations}")
        if not 0 <= polish_iterations <= MAX_ITERATIONS:
            raise OptimizerError(f"polish iterations must be between 0 and {MAX_ITERATIONS}, "
                                 f"got {polish_iterations}")
        self._graph = graph
        self._method = METHOD_TABLE[method]
        self._sweeps = DEFAULT_ITERATIONS if iterations is None else iterations
        # Given iterations are run as given; the default count is a cap once SGD alone precedes the polish.
        self._until_stalled = (self._method.handover_when_stalled and iterations is None
                               and graph.num_poses > LARGEST_FOR_EXTRA_STAGES)
        # A start already at a minimum is not descended from (`_converged_at_once`): the default iterations
        # only (given iterations are run as given), and within the direct solver's reach (a multigrid step
        # on 10⁶ poses takes seconds).
        self._probe_minimum = (self._method.polish and robust is None and iterations is None
                               and graph.num_poses <= DIRECT_SOLVER_MAX_POSES)
        # With the polish alone, `iterations` caps the polish.
        self._polish_cap = (iterations if self._method.descent is None and iterations is not None
                            else polish_iterations)
        self._starts: dict[str, FloatArray] = {}
        for name, poses in ({ESTIMATE: graph.poses} if starts is None else starts).items():
            poses = np.asarray(poses, dtype=np.float64)
            if poses.shape != graph.poses.shape:
                raise OptimizerError(f"start {name!r}: expected poses of shape {graph.poses.shape}, "
                                     f"got {poses.shape}")
            if not np.all(np.isfinite(poses)):
                raise OptimizerError(f"start {name!r}: non-finite poses")
            self._starts[name] = poses
        if not self._starts:
            raise OptimizerError("no starting estimate given")
        if robust is not None and self._method.polish:
            # The robust chain reads no estimate (its rounds are chordal solves): one candidate is enough.
            first = next(iter(self._starts))
            self._starts = {first: self._starts[first]}
        # Only when the caller left the starts to the method: given starts are the candidates wanted.
        self._with_chordal = (self._method.chordal_start and robust is None and starts is None
                              and 2 <= graph.num_poses <= LARGEST_FOR_EXTRA_STAGES)
        self._with_sync = (self._with_chordal and self._method.sync_start
                           and graph.num_poses <= LARGEST_FOR_SYNC)
        self._built: dict[str, FloatArray] = {}
        self._result: OptimizationResult | None = None

    @property
    def result(self) -> OptimizationResult:
        if self._result is None:
            raise OptimizerError("the optimization has not run to its end yet")
        return self._result

    def __iter__(self) -> Iterator[Iteration]:
        candidates: list[Candidate] = []
        finals: dict[str, Iteration] = {}
        references: list[_Reference] = []  # every candidate that converged: what a crawl is judged by
        abandoned: set[str] = set()
        plans: list[tuple[str, FloatArray | None, bool]] = [
            (name, start, True) for name, start in self._starts.items()]
        if self._with_chordal:
            plans.append((CHORDAL, None, False))
        for name, start, descend in self._with_sync_plan(plans, candidates):
            if start is None:
                start = self._built_start(name)
            last = Iteration("initial", 0, start, chi2(self._graph, start), start=name)
            yield last
            count = 0
            converged, reason = False, f"{self._sweeps} iterations of a method without a convergence test"
            reference = min(references, key=lambda converged: converged.chi2, default=None)
            polish_chi2: list[float] = []
            status: PolishStatus | None = None
            stages = self._stages(last.poses, descend)
            aside: _Aside | None = None
            while True:
                try:
                    iteration = next(stages)
                except StopIteration as stop:
                    status = stop.value
                    break
                last = dataclasses.replace(iteration, start=name)
                count += 1
                yield last
                if iteration.stage != POLISH_STAGE:
                    continue
                polish_chi2.append(float(last.chi2))
                if aside is None and len(polish_chi2) == PEEK_AFTER and not candidates and self._with_chordal:
                    aside = _Aside(self._stages(self._built_start(CHORDAL), descend=False))
                if reference is None and aside is not None:
                    reference = aside.advance_to(len(polish_chi2) // ABANDON_FACTOR)
                if reference is not None:
                    verdict = crawl_verdict(polish_chi2, reference.chi2, reference.polish_iterations,
                                            reference.start)
                    if verdict is not None:
                        stages.close()
                        abandoned.add(name)
                        status = PolishStatus(False, verdict, len(polish_chi2))
                        break
            del aside  # its polish state, as large as the graph's
            if status is not None:
                converged, reason = status.converged, status.reason
                if converged:
                    references.append(_Reference(name, float(last.chi2), status.iterations))
            candidates.append(Candidate(name, float(last.chi2), converged, reason, count))
            finals[name] = last
        preference = [*self._starts, CHORDAL, SYNC]
        winner = _same_minimum_first([c for c in candidates if c.start not in abandoned], preference)
        best = finals[winner.start]
        if len(candidates) > 1:
            yield Iteration("selected", 0, best.poses, best.chi2, start=best.start)
        self._result = OptimizationResult(np.array(best.poses), float(best.chi2), winner.converged,
                                          winner.reason, winner.start, tuple(candidates))

    def _built_start(self, name: str) -> FloatArray:
        """The start `name` builds from the graph (the chordal or sync initialisation), built once."""
        if name not in self._built:
            self._built[name] = BUILT_STARTS[name](self._graph)
        return self._built[name]

    def _with_sync_plan(self, plans: list[tuple[str, FloatArray | None, bool]],
                        candidates: list[Candidate]) -> Iterator[tuple[str, FloatArray | None, bool]]:
        """`plans`, then the sync start if wanted and the candidates that ran (filled in meanwhile)
        disagree."""
        yield from plans
        if not self._with_sync:
            return
        # An abandoned candidate's χ² (where it was abandoned, above the others) counts as a disagreement:
        # it did not reach their minimum, and several basins may be within reach.
        finals = [candidate.chi2 for candidate in candidates]
        if min(finals) < max(finals) * (1.0 - SYNC_DISAGREEMENT):
            yield SYNC, None, False

    def _stages(self, poses: FloatArray, descend: bool) -> Generator[Iteration, None, PolishStatus | None]:
        """The method's iterations from `poses` (the descent skipped unless `descend`); returns the polish's
        status, or None without a polish."""
        if self._robust is not None:
            if self._method.polish:
                return (yield from robust_optimize(self._graph, self._robust,
                                                   polish_iterations=self._polish_cap))
            yield from robust_sgd(self._graph, self._sweeps, poses, kernel=self._robust)
            return None
        if descend and self._method.descent is not None:
            if self._probe_minimum:
                probe = _converged_at_once(self._graph, poses)
                if probe is not None:
                    yield from probe[0]
                    return probe[1]
            descent = self._method.descent(self._graph, self._sweeps, poses)
            for iteration in until_stalled(descent) if self._until_stalled else descent:
                poses = iteration.poses
                yield iteration
            # A descent handed over before its last iteration is suspended, not finished: it would hold its
            # state through the polish (SGD's weights, tree and two sets of poses: 115 MB at 10⁶ poses).
            del descent
        if not self._method.polish:
            return None
        return (yield from gauss_newton(self._graph, poses, max_iterations=self._polish_cap))


AT_ONCE_STEPS = 1
"""A start at which the polish's convergence test holds within this many steps is at a minimum already."""


def _converged_at_once(graph: PoseGraph, poses: FloatArray) -> tuple[list[Iteration], PolishStatus] | None:
    """The polish's iterations and status from `poses` when its convergence test holds within
    `AT_ONCE_STEPS` steps (the start is a minimum already), else None.

    A keyframe graph's online estimate is such a start: its last optimization converged and the keyframes
    since follow the odometry chain (UAL, ACES, CSAIL and FR079 all). The paper's SGD from a minimum only
    climbs out of it (UAL: χ² 10.57 → 84 in its 100 iterations) for the polish to come back down, which
    costs a third of the final optimization and of its recording on such logs. The probe costs one
    polish step where the start is not a minimum (UAL's poor starts: 1 ms against SGD's 20 ms)."""
    polish = gauss_newton(graph, poses, max_iterations=AT_ONCE_STEPS)
    steps: list[Iteration] = []
    while True:
        try:
            steps.append(next(polish))
        except StopIteration as stop:
            status: PolishStatus = stop.value
            return (steps, status) if status.converged else None


@dataclass(frozen=True)
class _Reference:
    """A converged candidate, as `crawl_verdict` judges a later polish against it."""

    start: str
    chi2: float
    polish_iterations: int


class _Aside:
    """The chordal candidate optimized beside a running polish, step by step and unrecorded, so that it can
    serve as the reference of `crawl_verdict` (which needs a converged candidate). A polish that has taken
    n iterations can only be abandoned against a reference that converged within n / `ABANDON_FACTOR`, so
    the aside is advanced no further: at most a tenth of the running polish's cost."""

    def __init__(self, stages: Generator[Iteration, None, PolishStatus | None]) -> None:
        self._stages = stages
        self._steps = 0
        self._chi2 = math.inf
        self._finished = False
        self._result: _Reference | None = None

    def advance_to(self, steps: int) -> _Reference | None:
        """Advance to `steps` iterations (or its end): the candidate once its polish converged, else None."""
        while not self._finished and self._steps < steps:
            try:
                self._chi2 = float(next(self._stages).chi2)
                self._steps += 1
            except StopIteration as stop:
                self._finished = True
                status: PolishStatus | None = stop.value
                if status is not None and status.converged:
                    self._result = _Reference(CHORDAL, self._chi2, status.iterations)
        return self._result


def crawl_verdict(polish_chi2: Sequence[float], reference_chi2: float, reference_iterations: int,
                  reference: str) -> str | None:
    """Why a polish whose χ² after each of its iterations so far is `polish_chi2` is abandoned, or None to
    carry on. `reference` is the lowest candidate that converged before it, at `reference_chi2` after
    `reference_iterations` polish iterations.

    Abandoned when both hold: it has taken more than `ABANDON_FACTOR` times the reference's iterations, and
    at the rate its χ² fell over the second half of them it would still be above the reference's after as
    many iterations again (a crawl: each step takes a tiny fraction of what separates it from the
    reference). A polish that is still falling fast, or that has reached the reference's χ², carries on."""
    done = len(polish_chi2)
    if done <= ABANDON_FACTOR * max(reference_iterations, 1):
        return None
    half = done // 2
    current = polish_chi2[-1]
    rate = (polish_chi2[done - 1 - half] - current) / half
    if not current - done * rate > reference_chi2:
        return None
    return (f"abandoned after {done} polish iterations ({ABANDON_FACTOR}× the {reference_iterations} of the "
            f"{reference!r} candidate): χ² {current:.6g} falling by {rate:.3g} per iteration would still be "
            f"above its {reference_chi2:.6g} after as many again")


def _same_minimum_first(candidates: Sequence[Candidate], preference: Sequence[str]) -> Candidate:
    """The candidate with the lowest final χ²; among those within `SAME_MINIMUM` of it (the same minimum),
    the earliest in `preference`."""
    lowest = min((c.chi2 for c in candidates if not math.isnan(c.chi2)), default=math.inf)
    tied = [candidate for candidate in candidates if candidate.chi2 <= lowest + SAME_MINIMUM * abs(lowest)]
    return min(tied or candidates, key=lambda candidate: preference.index(candidate.start))


def optimize(
    graph: PoseGraph,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    *,
    starts: Mapping[str, FloatArray] | None = None,
    polish_iterations: int = DEFAULT_POLISH_ITERATIONS,
    robust: str | None = None,
) -> Optimization:
    """The optimization of `graph` by `method` from `starts` (name → poses; default: the graph's own
    estimate, named "estimate", and for the default method the chordal initialisation after it), each
    in turn, the lowest final χ² winning (the earliest start given when several end in the same minimum). A
    candidate whose polish crawls far above an earlier converged one is abandoned (`crawl_verdict`): listed
    with its χ² there, not converged, its reason saying so.

    `iterations` is the number of SGD (or Gauss–Seidel) iterations, default 100; for "gn" alone it caps
    the Gauss–Newton iterations. The polish runs until its convergence test holds (or `polish_iterations`,
    reported as not converged). `robust` ("cauchy" or "dcs") puts a robust kernel into the SGD's step
    weights and the polish (`optimizer.robust`; the objective becomes Σ ρ(χ²ₖ) over the loop closures and
    the χ² reported is that cost). Iterate over the returned object for every iteration; `.result` after.
    """
    return Optimization(graph, method, iterations, starts=starts, polish_iterations=polish_iterations,
                        robust=robust)
