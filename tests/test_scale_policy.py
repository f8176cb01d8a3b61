"""The default method above `LARGEST_FOR_EXTRA_STAGES` poses: the paper's SGD until an iteration stops
paying, then the polish (tested on small graphs with the size limit lowered)."""

from __future__ import annotations

import pytest

from optimizer import solve
from optimizer.cost import chi2
from optimizer.gridworld import generate_grid_world
from optimizer.polish import gauss_newton
from optimizer.sgd import sgd


def _expected_handover(graph_seed: int, cap: int) -> int:
    """The first iteration of the plain paper SGD whose χ² decrease is in [0, 1 %) of the χ² before it."""
    graph = generate_grid_world(400, seed=graph_seed).graph
    previous = chi2(graph, graph.poses)
    for iteration in sgd(graph, cap):
        if 0.0 <= previous - iteration.chi2 < 0.01 * previous:
            return iteration.index
        previous = iteration.chi2
    return cap


@pytest.mark.parametrize("seed", [1, 2])
def test_large_graphs_hand_sgd_over_to_the_polish_once_an_iteration_stops_paying(
        seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    graph = generate_grid_world(400, seed=seed).graph
    monkeypatch.setattr(solve, "LARGEST_FOR_EXTRA_STAGES", 100)
    optimization = solve.optimize(graph)
    iterations = list(optimization)
    stages = [iteration.stage for iteration in iterations]
    sgd_count = stages.count("sgd")
    assert sgd_count == _expected_handover(seed, solve.DEFAULT_ITERATIONS)
    assert sgd_count < solve.DEFAULT_ITERATIONS
    # No tree SGD and no chordal candidate above the limit: SGD, then the polish, one candidate.
    assert set(stages) == {"initial", "sgd", "gauss-newton"}
    assert stages.index("gauss-newton") == 1 + sgd_count
    # The polish still ends at the minimum the polish reaches from the file's estimate directly.
    *_, last_direct = gauss_newton(graph)
    assert optimization.result.converged
    assert optimization.result.chi2 == pytest.approx(last_direct.chi2, rel=1e-6)


def test_the_iteration_count_caps_the_handover(monkeypatch: pytest.MonkeyPatch) -> None:
    graph = generate_grid_world(400, seed=1).graph
    monkeypatch.setattr(solve, "LARGEST_FOR_EXTRA_STAGES", 100)
    monkeypatch.setattr(solve, "SGD_HANDOVER_DECREASE", 0.0)  # never stalls: the cap decides
    stages = [iteration.stage for iteration in solve.optimize(graph, iterations=3)]
    assert stages.count("sgd") == 3
