"""The optimizer's entry point: stage chaining, and the exact minima of real benchmark graphs."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from optimizer.errors import OptimizerError
from optimizer.graph_files import read_graph
from optimizer.solve import METHODS, optimize
from tests.conftest import shared_file
from tests.test_sgd import _square_loop


@pytest.mark.parametrize("method", METHODS)
def test_every_method_starts_from_the_initial_estimate_and_lowers_chi2(method: str) -> None:
    graph, _ = _square_loop(noise=0.05, seed=4)
    steps = list(optimize(graph, method, iterations=20))
    assert (steps[0].stage, steps[0].index) == ("initial", 0)
    np.testing.assert_array_equal(steps[0].poses, graph.poses)
    assert len(steps) > 1
    assert steps[-1].chi2 < 0.1 * steps[0].chi2
    for previous, step in itertools.pairwise(steps):
        assert step.index == (previous.index + 1 if step.stage == previous.stage else 1)


def test_stages_come_in_order() -> None:
    graph, _ = _square_loop(noise=0.05, seed=4)
    stages = [s.stage for s in optimize(graph, "sgd+gn", iterations=7)]
    assert stages[:8] == ["initial"] + ["sgd"] * 7
    assert set(stages[8:]) == {"gauss-newton"}
    assert [s.stage for s in optimize(graph, "sgd", iterations=3)] == ["initial", "sgd", "sgd", "sgd"]


def test_unknown_method_and_negative_iterations_are_errors() -> None:
    graph, _ = _square_loop(noise=0.0)
    with pytest.raises(OptimizerError, match="unknown method 'lu'"):
        list(optimize(graph, "lu"))
    with pytest.raises(OptimizerError, match="iterations"):
        list(optimize(graph, "sgd", iterations=-2))


# Optima published for these graphs (g2o's χ² convention); the figures.
REFERENCE_CHI2 = {
    "posegraphs/2d/M3500.g2o": 137.913,
    "posegraphs/2d/CSAIL.g2o": 40.555,
    "posegraphs/2d/FR079.g2o": 37.598,
    "posegraphs/2d/pose2example.txt": 1.0989,
}


@pytest.mark.parametrize(("relative", "expected"), REFERENCE_CHI2.items())
def test_default_method_reaches_the_published_optimum(relative: str, expected: float) -> None:
    graph = read_graph(shared_file(relative)).graph
    final = list(optimize(graph))[-1]
    assert final.chi2 == pytest.approx(expected, rel=1e-3)


def test_intel_with_its_ill_conditioned_information_stays_finite_and_reaches_the_optimum() -> None:
    graph = read_graph(shared_file("posegraphs/2d/INTEL.g2o")).graph
    steps = list(optimize(graph))
    assert all(np.isfinite(s.chi2) and np.all(np.isfinite(s.poses)) for s in steps)
    assert steps[-1].chi2 <= 216.0
