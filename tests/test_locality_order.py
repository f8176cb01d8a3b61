"""The multigrid polish's renumbering of poses: the same problem, poses in another order."""

from __future__ import annotations

import numpy as np

from optimizer.cost import chi2
from optimizer.gridworld import generate_grid_world
from optimizer.locality_order import locality_order, renumbered


def test_renumbering_keeps_every_constraint_and_the_anchor() -> None:
    graph = generate_grid_world(2000, seed=4).graph
    order = locality_order(graph)
    assert order[0] == 0
    np.testing.assert_array_equal(np.sort(order), np.arange(graph.num_poses))
    local = renumbered(graph, order)
    # Constraint k joins the same two poses, in the same direction, with the same numbers.
    np.testing.assert_array_equal(order[local.edge_from], graph.edge_from)
    np.testing.assert_array_equal(order[local.edge_to], graph.edge_to)
    assert local.measurements is graph.measurements and local.information is graph.information
    np.testing.assert_array_equal(local.poses, graph.poses[order])
    # The same poses have the same χ², to the bit: the constraints are summed in the same order.
    assert chi2(local, local.poses) == chi2(graph, graph.poses)


def test_renumbering_brings_loop_closures_near_in_memory() -> None:
    graph = generate_grid_world(20_000, seed=5).graph
    local = renumbered(graph, locality_order(graph))
    spread = np.abs(graph.edge_from - graph.edge_to)
    local_spread = np.abs(local.edge_from - local.edge_to)
    assert np.percentile(local_spread, 99) < 0.1 * np.percentile(spread, 99)
