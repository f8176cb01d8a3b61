"""A keyframe graph without loop closures (KITTI's 154 frames) is one odometry chain: its optimum is the
chain itself, which the polish confirms without the requested descent; a graph with loops still gets it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from optimizer import se2
from optimizer.graph import PoseGraph
from pipeline import recording
from pipeline.keyframe_optimization import CHAIN_REASON, optimize_keyframes
from tests.optimizer_fixtures import square_loop_graph
from tests.pipeline_fixtures import read_recording


def _chain(count: int, seed: int) -> tuple[PoseGraph, np.ndarray]:
    rng = np.random.default_rng(seed)
    steps = np.column_stack([rng.uniform(0.5, 1.5, count - 1), rng.normal(0.0, 0.1, count - 1),
                             rng.normal(0.0, 0.2, count - 1)])
    information = np.tile(np.diag([400.0, 400.0, 900.0]), (count - 1, 1, 1))
    start = np.array([3.0, -2.0, 0.7])
    composed = se2.compose_chain(steps, start)  # every pose: its predecessor ∘ the measured step
    edges = np.arange(count - 1)
    return PoseGraph.build(np.arange(count), composed, edges, edges + 1, steps, information), composed


@pytest.mark.parametrize("method", ["sgd", "sgd+gn", "sgd-tree"])
def test_a_chain_is_confirmed_by_the_polish_alone_whatever_the_method(tmp_path: Path, method: str) -> None:
    graph, composed = _chain(40, seed=1)
    stream = recording.create_recording(tmp_path / "chain.rrd", name="chain")
    # a wheel-odometry start off the chain: the polish must bring it to the chain too
    wheel = composed + np.random.default_rng(2).normal(0.0, 0.05, composed.shape)
    wheel[0] = composed[0]
    try:
        optimized = optimize_keyframes(stream, graph, graph, method, None, wheel_odometry=wheel)
    finally:
        recording.close_recording(stream)
    stages = {stage for stage, _, _ in optimized.trace}
    assert not stages & {"sgd", "sgd-tree"}, stages
    assert optimized.result.reason.startswith(CHAIN_REASON)
    assert optimized.result.converged
    np.testing.assert_allclose(optimized.poses, composed, atol=1e-9)
    assert all(candidate.chi2 < 1e-12 for candidate in optimized.result.candidates)
    stage_log = read_recording(tmp_path / "chain.rrd")["/optimizer/stage"]
    notes = [row[0] for row in stage_log.columns["TextLog:text"]]
    assert f"{CHAIN_REASON}; {method} was not run" in notes


def test_a_graph_with_loop_closures_runs_the_requested_descent(tmp_path: Path) -> None:
    graph, _ = square_loop_graph(noise=0.05, laps=2)
    stream = recording.create_recording(tmp_path / "loops.rrd", name="loops")
    try:
        optimized = optimize_keyframes(stream, graph, graph, "sgd", 5)
    finally:
        recording.close_recording(stream)
    assert [stage for stage, _, _ in optimized.trace].count("sgd") == 2 * 5  # from each of the two starts
    assert not optimized.result.reason.startswith(CHAIN_REASON)
