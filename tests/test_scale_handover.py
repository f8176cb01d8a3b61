"""At scale: the paper's SGD hands over to the polish once it stalls, and inexact polish steps are shortened
before another linear solve is paid for."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np
import pytest

from optimizer import polish, solve
from optimizer.cost import chi2
from optimizer.damped_solvers import DirectSolver, Linearisation
from optimizer.gridworld import generate_grid_world
from optimizer.iteration import Iteration
from optimizer.normal_equations import UpperPattern
from optimizer.solve import until_stalled


def _iterations(values: list[float]) -> list[Iteration]:
    poses = np.zeros((2, 3))
    return [Iteration("sgd", index, poses, value) for index, value in enumerate(values, start=1)]


def _chi2s(iterations: list[Iteration]) -> list[float]:
    return [float(iteration.chi2) for iteration in iterations]


def test_sgd_stops_at_the_first_iteration_that_gains_less_than_the_handover_fraction() -> None:
    # 80 → 79.5 gains 0.6 % < 1 %: that iteration is the last one yielded.
    values = [100.0, 90.0, 80.0, 79.5, 70.0]
    assert _chi2s(list(until_stalled(iter(_iterations(values)), gain=0.01))) == values[:4]


def test_an_unchanged_chi2_before_sgd_begins_to_fall_is_not_a_stall() -> None:
    # The first iteration's drop does not count (the schedule's clamped steps may then pause, as SGD's
    # iterations 2–8 do on grid worlds); the stall is judged once a later iteration has lowered χ².
    values = [50.0, 50.0, 50.0, 45.0, 40.0, 39.9, 30.0]
    assert _chi2s(list(until_stalled(iter(_iterations(values)), gain=0.01))) == values[:6]


def test_a_descent_whose_chi2_never_falls_runs_to_its_end() -> None:
    values = [10.0, 10.0, 10.0, 10.0]
    assert _chi2s(list(until_stalled(iter(_iterations(values)), gain=0.01))) == values


def test_a_rising_chi2_after_the_descent_began_stops_it() -> None:
    values = [100.0, 80.0, 81.0, 60.0]
    assert _chi2s(list(until_stalled(iter(_iterations(values)), gain=0.01))) == values[:3]


def _sgd_iterations(run: solve.Optimization) -> int:
    return sum(1 for iteration in run if iteration.stage == "sgd")


def test_the_default_hands_over_early_only_where_sgd_alone_precedes_the_polish(
        monkeypatch: pytest.MonkeyPatch) -> None:
    graph = generate_grid_world(400, seed=3).graph
    assert _sgd_iterations(solve.optimize(graph)) == solve.DEFAULT_ITERATIONS  # tree SGD follows: all 100
    monkeypatch.setattr(solve, "LARGEST_FOR_EXTRA_STAGES", 100)  # as if the graph were past the extra stages
    run = solve.optimize(graph)
    handed_over = _sgd_iterations(run)
    assert 2 <= handed_over < solve.DEFAULT_ITERATIONS
    assert run.result.converged
    assert _sgd_iterations(solve.optimize(graph, iterations=40)) == 40  # given iterations run as given


def test_a_descent_handed_over_is_let_go_before_the_polish(monkeypatch: pytest.MonkeyPatch) -> None:
    # Suspended, the paper's SGD would hold its weights, tree and poses through the whole polish (115 MB
    # at 10⁶ poses): it must be finished by the time the polish yields its first iteration.
    finished: list[bool] = []
    paper_sgd = solve.sgd

    def tracked_sgd(*args: object, **kwargs: object) -> Iterator[Iteration]:
        try:
            yield from paper_sgd(*args, **kwargs)  # type: ignore[arg-type]
        finally:
            finished.append(True)

    monkeypatch.setattr(solve, "sgd", tracked_sgd)
    monkeypatch.setattr(solve, "LARGEST_FOR_EXTRA_STAGES", 100)  # as if the graph were past the extra stages
    stages, finished_at_polish = [], []
    for iteration in solve.optimize(generate_grid_world(400, seed=3).graph):
        stages.append(iteration.stage)
        if iteration.stage == "gauss-newton":
            finished_at_polish = list(finished)
            break
    assert 2 <= stages.count("sgd") < solve.DEFAULT_ITERATIONS  # handed over, not run to its end
    assert finished_at_polish == [True]


class _OvershootingSolver:
    """An inexact solver whose steps are three times the exact ones: each full step overshoots a quadratic
    minimum (χ² excess × 4), its half lowers χ² (× 0.25)."""

    exact = False

    def __init__(self, pattern: UpperPattern) -> None:
        self._direct = DirectSolver(pattern)
        self.forcing = 1e-2
        self.last_converged = True
        self.solves = 0

    def step(self, linearisation: Linearisation, damping: float) -> np.ndarray | None:
        self.solves += 1
        exact = self._direct.step(linearisation, damping)
        return None if exact is None else 3.0 * exact

    def accepted_step(self) -> None:
        pass


def test_a_rejected_inexact_step_is_shortened_before_another_solve(monkeypatch: pytest.MonkeyPatch) -> None:
    world = generate_grid_world(200, seed=4)
    graph = world.graph
    pattern = UpperPattern.of(graph)
    solver = _OvershootingSolver(pattern)
    monkeypatch.setattr(polish, "_solver_for",
                        lambda graph, linear_solver, aggregation_order=None: (pattern, solver))
    accepted = list(polish.gauss_newton(graph, world.ground_truth, max_iterations=6))
    assert len(accepted) == 6
    assert solver.solves == len(accepted)  # every overshooting step was halved, never re-solved
    values = [chi2(graph, world.ground_truth)] + [float(step.chi2) for step in accepted]
    assert all(later < earlier for earlier, later in itertools.pairwise(values))
