"""The multigrid polish's renumbering of poses: the same problem, poses in another order."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.cost import chi2
from optimizer.gridworld import generate_grid_world
from optimizer.locality_order import inverse, locality_order, renumbered


def test_renumbering_keeps_every_constraint_and_the_anchor() -> None:
    graph = generate_grid_world(2000, seed=4).graph
    order = locality_order(graph)
    assert order[0] == 0
    np.testing.assert_array_equal(np.sort(order), np.arange(graph.num_poses))
    np.testing.assert_array_equal(inverse(order)[order], np.arange(graph.num_poses))
    local = renumbered(graph, locality_order(graph))
    np.testing.assert_array_equal(local.poses, graph.poses[order])
    # Every constraint is there once, joining the same two poses in the same direction with its numbers.
    original = {(int(a), int(b), m.tobytes(), w.tobytes()) for a, b, m, w in
                zip(graph.edge_from, graph.edge_to, graph.measurements, graph.information, strict=True)}
    moved = {(int(a), int(b), m.tobytes(), w.tobytes()) for a, b, m, w in
             zip(order[local.edge_from], order[local.edge_to], local.measurements, local.information,
                 strict=True)}
    assert len(original) == graph.num_edges and moved == original
    # Listed by their earlier pose, so the assembly walks H's rows in order.
    assert np.all(np.diff(local.edge_low) >= 0)
    assert chi2(local, local.poses) == pytest.approx(chi2(graph, graph.poses), rel=1e-12)


def test_renumbering_brings_loop_closures_near_in_memory() -> None:
    graph = generate_grid_world(20_000, seed=5).graph
    local = renumbered(graph, locality_order(graph))
    spread = np.abs(graph.edge_from - graph.edge_to)
    local_spread = np.abs(local.edge_from - local.edge_to)
    assert np.percentile(local_spread, 99) < 0.1 * np.percentile(spread, 99)
