"""The tree-parameterised SGD: its spanning tree, exact behaviour on trees, and optima on loopy graphs."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import shortest_path

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph
from optimizer.gridworld import generate_grid_world
from optimizer.polish import gauss_newton
from optimizer.sgd import sgd
from optimizer.sgd_kernels import _clamped_step, _weighted_residual
from optimizer.sgd_tree import (
    breadth_first_tree,
    incremental_tree,
    path_variance,
    settled,
    sgd_tree,
    spanning_tree,
)
from optimizer.sgd_tree_kernels import (
    parameters_from_poses,
    subtree_intervals,
    tree_sgd_iteration,
    tree_stiffness,
)
from tests.conftest import shared_file


def _reversed_every(graph: PoseGraph, every: int, truth: np.ndarray, rng: np.random.Generator,
                    noise: tuple[float, float, float]) -> PoseGraph:
    """The same pose pairs with every `every`-th constraint measured from its other end (a fresh noisy
    measurement of b→a, not the inverted one), built with the dataclass so the stored direction stays."""
    edge_from = graph.edge_from.copy()
    edge_to = graph.edge_to.copy()
    flipped = np.arange(graph.num_edges) % every == 0
    edge_from[flipped], edge_to[flipped] = graph.edge_to[flipped], graph.edge_from[flipped]
    measurements = se2.compose(se2.relative(truth[edge_from], truth[edge_to]),
                               rng.normal(0.0, noise, (graph.num_edges, 3)))
    return PoseGraph(graph.poses.copy(), edge_from, edge_to, measurements, graph.information.copy(),
                     graph.vertex_ids.copy())


def _last_chi2_of_gauss_newton(graph: PoseGraph, poses: np.ndarray) -> float:
    result = chi2(graph, poses)
    for step in gauss_newton(graph, poses, max_iterations=200):
        result = step.chi2
    return result


def test_breadth_first_tree_paths_are_shortest_hop_paths() -> None:
    graph = generate_grid_world(200, seed=3).graph
    tree = spanning_tree(graph, "breadth-first")
    adjacency = coo_matrix((np.ones(graph.num_edges), (graph.edge_from, graph.edge_to)),
                           shape=(graph.num_poses,) * 2)
    hops = shortest_path(adjacency, directed=False, unweighted=True, indices=0)
    np.testing.assert_array_equal(tree.depth, hops.astype(np.int64))
    assert tree.parent[0] == 0
    others = np.arange(1, graph.num_poses)
    np.testing.assert_array_equal(tree.depth[tree.parent[others]], tree.depth[others] - 1)
    # Each top is a common ancestor of both ends, and no child of it is (it is the lowest one).
    for k in range(graph.num_edges):
        ancestors = []
        for node in (graph.edge_from[k], graph.edge_to[k]):
            chain = [node]
            while chain[-1] != 0:
                chain.append(tree.parent[chain[-1]])
            ancestors.append(chain)
        common = [node for node in ancestors[0] if node in ancestors[1]]
        assert tree.top[k] == common[0]
        assert tree.path_length[k] == ancestors[0].index(common[0]) + ancestors[1].index(common[0])


def _six_pose_graph(loops: list[tuple[int, int]]) -> PoseGraph:
    """Odometry 0→1→…→5 plus the given loop constraints, stored as given (exact measurements of a line)."""
    pairs = [(i, i + 1) for i in range(5)] + loops
    truth = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    a = np.array([pair[0] for pair in pairs])
    b = np.array([pair[1] for pair in pairs])
    information = np.tile(np.eye(3), (len(pairs), 1, 1))
    return PoseGraph.build(np.arange(6), truth, a, b, se2.relative(truth[a], truth[b]), information)


def test_incremental_tree_hangs_each_pose_from_its_lowest_numbered_neighbour() -> None:
    # Pose 4 sees pose 1 (stored 4 → 1) and pose 5 sees pose 0: they hang from those, as in TORO.
    graph = _six_pose_graph([(4, 1), (0, 5)])
    tree = spanning_tree(graph, "incremental")
    np.testing.assert_array_equal(tree.parent, [0, 0, 1, 2, 1, 0])
    np.testing.assert_array_equal(tree.depth, [0, 1, 2, 3, 2, 1])
    # Edges in stored order: 0-1, 1-2, 2-3, 3-4 (3→2→1←4), 4-5 (4→1→0←5), 4→1, 0→5.
    np.testing.assert_array_equal(tree.top, [0, 1, 2, 1, 0, 1, 0])
    np.testing.assert_array_equal(tree.path_length, [1, 1, 1, 3, 3, 1, 1])
    # Constraints are visited by the depth of their top, ties in stored order.
    np.testing.assert_array_equal(tree.visit_order(), [0, 4, 6, 1, 3, 5, 2])


def test_no_incremental_tree_when_a_pose_has_no_lower_neighbour() -> None:
    # Pose 3 → 4 removed and pose 4 tied only to 5: pose 4 has no lower-numbered neighbour.
    pairs = [(0, 1), (1, 2), (2, 3), (5, 4), (3, 5)]
    truth = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    a = np.array([pair[0] for pair in pairs])
    b = np.array([pair[1] for pair in pairs])
    graph = PoseGraph.build(np.arange(6), truth, a, b, se2.relative(truth[a], truth[b]),
                            np.tile(np.eye(3), (5, 1, 1)))
    assert incremental_tree(graph) is None
    with pytest.raises(OptimizerError):
        spanning_tree(graph, "incremental")
    assert spanning_tree(graph).kind == "breadth-first"
    with pytest.raises(OptimizerError):
        spanning_tree(graph, "widest")  # type: ignore[arg-type]


def test_auto_takes_the_incremental_tree_only_where_its_paths_are_shorter_and_more_certain() -> None:
    # Equal information everywhere: the incremental tree's paths are 3.7 times shorter in total.
    equal = generate_grid_world(1500, seed=0, loop_sigma=(0.02, 0.02, 0.01)).graph
    assert incremental_tree(equal).total_path_length < breadth_first_tree(equal).total_path_length
    assert spanning_tree(equal).kind == "incremental"
    # The default world's loop closures are 2.5 times less certain than its odometry in x and y; the
    # incremental tree hangs revisits from them, so its paths carry more variance there.
    weak_loops = generate_grid_world(1500, seed=0).graph
    assert incremental_tree(weak_loops).total_path_length < breadth_first_tree(weak_loops).total_path_length
    assert path_variance(weak_loops, incremental_tree(weak_loops))[0] > path_variance(
        weak_loops, breadth_first_tree(weak_loops))[0]
    assert spanning_tree(weak_loops).kind == "breadth-first"


def test_path_variance_counts_each_path_edge_variance_over_the_constraint() -> None:
    graph = _six_pose_graph([(4, 1), (0, 5)])
    information = graph.information.copy()
    information[3] = np.diag([4.0, 4.0, 4.0])  # 3-4: a path of three unit variances, weighted by 4
    information[5] = np.diag([2.0, 2.0, 2.0])  # 4→1 is pose 4's tree edge: variance 1/2
    graph = PoseGraph(graph.poses, graph.edge_from, graph.edge_to, graph.measurements, information,
                      graph.vertex_ids)
    tree = incremental_tree(graph)
    # Paths: 0-1: 1; 1-2: 1; 2-3: 1; 3-4: (1 + 1 + 0.5)·4; 4-5: 0.5 + 1 + 1; 4→1: 0.5·2; 0→5: 1.
    np.testing.assert_allclose(path_variance(graph, tree), np.full(3, 1 + 1 + 1 + 10 + 2.5 + 1 + 1))


@pytest.mark.parametrize("kind", ["breadth-first", "incremental"])
def test_a_tree_of_constraints_is_solved_in_one_iteration(kind: str) -> None:
    # With α = 1/γ at t = 1 and isotropic information every step is clamped to the whole residual; a
    # constraint graph that is itself a tree is then satisfied constraint by constraint, parents first.
    rng = np.random.default_rng(4)
    n = 60
    parents = np.array([rng.integers(0, i) for i in range(1, n)])
    children = np.arange(1, n)
    z = rng.normal([1.0, 0.2, 0.1], [0.5, 0.5, 0.6], (n - 1, 3))
    info = np.tile(np.diag([20.0, 20.0, 80.0]), (n - 1, 1, 1))
    graph = PoseGraph.build(np.arange(n), rng.normal(size=(n, 3)), parents, children, z, info)
    result = next(sgd_tree(graph, 1, tree=kind))
    expected = graph.poses.copy()
    for child, parent, measurement in zip(children, parents, z, strict=True):
        expected[child] = se2.compose(expected[parent], measurement)
    difference = result.poses - expected
    difference[:, 2] = se2.wrap_angle(difference[:, 2])
    assert np.abs(difference).max() < 1e-9
    assert result.chi2 < 1e-18


def test_consistent_graph_at_its_solution_does_not_move() -> None:
    world = generate_grid_world(300, seed=1, add_noise=False)
    graph = world.graph.with_poses(world.ground_truth)
    for step in sgd_tree(graph, 3):
        difference = step.poses - world.ground_truth
        difference[:, 2] = se2.wrap_angle(difference[:, 2])
        assert np.abs(difference).max() < 1e-9


@pytest.mark.parametrize(("every", "kind"), [(2, "breadth-first"), (3, "breadth-first"), (2, "incremental")])
def test_reversed_edges_reach_the_gauss_newton_optimum(every: int, kind: str) -> None:
    rng = np.random.default_rng(every)
    world = generate_grid_world(500, seed=every)
    noise = (0.02, 0.02, 0.01)
    graph = _reversed_every(world.graph, every, world.ground_truth, rng, noise)
    assert graph.is_reversed.sum() > graph.num_edges // 4
    start = se2.compose_chain(_odometry_as_forward_steps(graph), start=world.ground_truth[0])
    graph = graph.with_poses(start)
    optimum = _last_chi2_of_gauss_newton(graph, world.ground_truth)

    steps = list(sgd_tree(graph, 100, tree=kind))
    assert [s.index for s in steps] == list(range(1, 101))
    assert all(s.stage == "sgd-tree" for s in steps)
    assert steps[-1].chi2 < 1e-2 * chi2(graph)
    assert steps[-1].chi2 < 2.0 * optimum
    # A wrong sign on reversed constraints would leave SGD in another basin; GN from it finds the optimum.
    assert _last_chi2_of_gauss_newton(graph, steps[-1].poses) == pytest.approx(optimum, rel=1e-6)
    np.testing.assert_array_equal(steps[-1].poses[0], graph.poses[0])


def _odometry_as_forward_steps(graph: PoseGraph) -> np.ndarray:
    """The odometry motions i → i+1 from the stored constraints, inverting the reversed ones."""
    odometry = np.flatnonzero(graph.is_odometry)
    low = np.minimum(graph.edge_from[odometry], graph.edge_to[odometry])
    first = odometry[np.unique(low, return_index=True)[1]]
    steps = graph.measurements[first].copy()
    backwards = graph.is_reversed[first]
    steps[backwards] = se2.inverse(steps[backwards])
    return steps


def test_beats_the_paper_sgd_on_a_grid_world() -> None:
    graph = generate_grid_world(2000, seed=5).graph
    paper = list(sgd(graph, 30))[-1].chi2
    tree = list(sgd_tree(graph, 30))[-1].chi2
    assert tree < 0.5 * paper


def test_reaches_toros_figure_on_m3500() -> None:
    from optimizer.graph_files import read_graph

    graph = read_graph(shared_file("posegraphs/2d/M3500.g2o")).graph
    assert spanning_tree(graph).kind == "incremental"
    tree = list(sgd_tree(graph, 100))[-1].chi2
    # TORO (the authors' C++ tool) reaches 248.8 from this file in 100 iterations (measured, issue 9); the
    # paper's SGD ends above 5 000.
    assert tree <= 248.8
    paper = list(sgd(graph, 100))[-1].chi2
    assert tree < 0.1 * paper


def test_continuing_the_schedule_matches_a_restart_at_that_iteration() -> None:
    graph = generate_grid_world(300, seed=2).graph
    head = list(sgd_tree(graph, 3))[-1]
    tail = list(sgd_tree(graph, 2, head.poses, first_iteration=4))
    assert tail[-1].chi2 < head.chi2


def test_bad_arguments_raise_our_error() -> None:
    graph = generate_grid_world(50, seed=0).graph
    with pytest.raises(OptimizerError):
        list(sgd_tree(graph, -1))
    with pytest.raises(OptimizerError):
        list(sgd_tree(graph, 1, first_iteration=0))
    with pytest.raises(OptimizerError):
        list(sgd_tree(graph, 1, np.zeros((2, 3))))
    with pytest.raises(OptimizerError):
        list(sgd_tree(graph, 1, learning_rate_scale=0.0))
    poses = graph.poses.copy()
    poses[3, 0] = np.nan
    with pytest.raises(OptimizerError):
        list(sgd_tree(graph, 1, poses))
    assert list(sgd_tree(graph, 0)) == []


def test_from_a_poor_start_it_leads_gauss_newton_to_the_optimum() -> None:
    # Heavy heading noise (σθ = 0.2 rad on every odometry step): Gauss–Newton from the odometry estimate
    # and after the paper's SGD ends in wrong basins; after the tree SGD it reaches the minimum that it
    # finds from the ground truth.
    world = generate_grid_world(1000, seed=0, odometry_sigma=(0.02, 0.02, 0.2))
    graph = world.graph
    optimum = _last_chi2_of_gauss_newton(graph, world.ground_truth)
    assert _last_chi2_of_gauss_newton(graph, graph.poses) > 2.0 * optimum
    paper = list(sgd(graph, 100))[-1]
    assert _last_chi2_of_gauss_newton(graph, paper.poses) > 100.0 * optimum
    tree = list(sgd_tree(graph, 100))[-1]
    assert tree.chi2 < 0.1 * paper.chi2
    assert _last_chi2_of_gauss_newton(graph, tree.poses) == pytest.approx(optimum, rel=1e-6)


def _pg1() -> PoseGraph:
    from optimizer.graph_files import read_graph

    # Its first edge's θθ information is 0; repaired (raised to 5e-4) as every benchmark reads it.
    return read_graph(shared_file("posegraphs/2d/pg1.g2o"), repair_information=True).graph


def test_never_above_the_paper_sgd_on_pg1() -> None:
    # Issue 9: never worse than the paper's SGD at 10, 30 and 100 iterations. Both approach the point
    # where their common approximate gradient vanishes (χ² 6.87e-7, the minimum is 1.54e-8); without the
    # coupled heading step sgd-tree passed it first and ended 0.3 % above the paper's SGD at 100.
    graph = _pg1()
    paper = {step.index: step.chi2 for step in sgd(graph, 100)}
    tree = {step.index: step.chi2 for step in sgd_tree(graph, 100)}
    for k in (10, 30, 100):
        assert tree[k] <= paper[k], k


def test_once_the_descent_settles_the_headings_see_the_turn_of_the_translation() -> None:
    graph = _pg1()
    optimum = _last_chi2_of_gauss_newton(graph, graph.poses)
    assert optimum < 2e-8
    paper = [step.chi2 for step in sgd(graph, 1000)]
    uncoupled = [step.chi2 for step in sgd_tree(graph, 1000, coupled_headings=False)]
    coupled = [step.chi2 for step in sgd_tree(graph, 1000)]
    # The same iterations until χ² all but stops changing (after iteration 30 here), then different ones.
    first_settled = next(k for k in range(1, 1000) if settled(uncoupled[k - 1], uncoupled[k]))
    assert 30 < first_settled < 99
    assert coupled[:first_settled + 1] == uncoupled[:first_settled + 1]
    # The paper's heading step stays where its approximate gradient vanishes, far above the minimum; the
    # coupled one goes on towards it.
    assert min(paper[500:] + uncoupled[500:]) > 30 * optimum
    assert coupled[-1] < 0.2 * min(paper[-1], uncoupled[-1])


def test_where_the_coupled_step_raises_chi2_the_paper_heading_step_returns() -> None:
    from optimizer.graph_files import read_graph

    # M3500's descent settles at iteration 683, 42 % above the minimum (137.9): coupled from there on, its
    # χ² rose to 245 by iteration 800 and was 240.9 at 1000 against 235.4 with the paper's heading step.
    graph = read_graph(shared_file("posegraphs/2d/M3500.g2o")).graph
    uncoupled = [step.chi2 for step in sgd_tree(graph, 1000, coupled_headings=False)]
    coupled = [step.chi2 for step in sgd_tree(graph, 1000)]
    assert coupled[-1] <= uncoupled[-1]
    assert max(coupled[683:]) <= coupled[683] * (1.0 + 1e-5)


def test_a_grid_world_whose_chi2_keeps_falling_is_not_changed_by_the_coupling() -> None:
    graph = generate_grid_world(500, seed=7).graph
    coupled = [step.chi2 for step in sgd_tree(graph, 30)]
    assert all(later < earlier for earlier, later in itertools.pairwise(coupled))
    assert coupled == [step.chi2 for step in sgd_tree(graph, 30, coupled_headings=False)]


def test_the_coupled_heading_step_minimises_the_constraints_own_cost_along_the_turn() -> None:
    from scipy.optimize import minimize_scalar

    from optimizer.sgd_tree_kernels import _coupled_heading_step

    rng = np.random.default_rng(11)
    z = np.array([4.0, 1.5, 0.3])
    root = rng.normal(size=(3, 3))
    information = root @ root.T + np.diag([5.0, 5.0, 0.5])  # anisotropic, with cross terms
    theta_a, share_a = 0.4, 0.6
    c, s = np.cos(theta_a), np.sin(theta_a)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    w = rotation @ information @ rotation.T
    pa = np.array([1.0, -2.0, theta_a])
    pb = se2.compose(pa, z) + np.array([0.01, -0.02, 0.003])

    def cost(beta: float) -> float:
        # The constraint's χ² (global-frame residual P_a·z − p_b) once the headings turn θ_b − θ_a by β:
        # θ_a by −β·share_a, θ_b by β·(1 − share_a); evaluated exactly, not linearised.
        a = pa + np.array([0.0, 0.0, -beta * share_a])
        b = pb + np.array([0.0, 0.0, beta * (1.0 - share_a)])
        residual = se2.compose(a, z) - b
        residual[2] = se2.wrap_angle(residual[2])
        return float(residual @ (rotation @ information @ rotation.T) @ residual)

    r = se2.compose(pa, z) - pb
    gamma = 0.1
    whole = _coupled_heading_step(theta_a, z, w, r[0], r[1], r[2], share_a, 2, gamma, 1)
    exact = minimize_scalar(cost, bracket=(-0.1, 0.1), tol=1e-12).x
    # Linearised in the turn, so equal to first order; the paper's step (r_θ, for this W not even the
    # heading residual's own minimum) is far from it.
    assert whole == pytest.approx(exact, rel=1e-2)
    assert abs(r[2] - exact) > 0.5 * abs(exact)
    # Later in the schedule it is the fraction 2ℓ·W_θθ/(γ t) of that minimum, as the paper's step is of r_θ.
    t = 1000
    assert _coupled_heading_step(theta_a, z, w, r[0], r[1], r[2], share_a, 2, gamma, t) == pytest.approx(
        whole * 2 * 2 * information[2, 2] / (gamma * t), rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_subtree_intervals_number_each_subtree_as_one_interval(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 60
    parent = np.array([0] + [int(rng.integers(0, i)) for i in range(1, n)])  # random, parents first
    if seed == 2:  # a long chain (a corridor's keyframes): the depth-first walk must not recurse
        n = 20_000
        parent = np.maximum(np.arange(n) - 1, 0)
    entry, exit_ = subtree_intervals(parent, 0)
    assert sorted(entry.tolist()) == list(range(n))
    checked = range(n) if n <= 100 else range(0, n, 997)
    if seed == 2:  # a chain: node i's subtree is i and every node after it
        expected = {i: set(range(i, n)) for i in checked}
    else:
        descendants = [{i} for i in range(n)]
        for i in range(n - 1, 0, -1):  # children after their parents
            descendants[parent[i]] |= descendants[i]
        expected = {i: descendants[i] for i in checked}
    by_entry = np.argsort(entry)
    for i, subtree in expected.items():
        assert set(by_entry[entry[i]:exit_[i]].tolist()) == subtree


def _reference_pass(graph: PoseGraph, params: np.ndarray, parent: np.ndarray, root: int, top: np.ndarray,
                    order: np.ndarray, stiffness: np.ndarray, gamma: np.ndarray, t: int) -> None:
    """One tree-SGD pass as its docstring states it, every pose summed by walking to the root."""
    def pose(node: int) -> np.ndarray:
        total = params[root].copy()
        while node != root:
            total += params[node]
            node = parent[node]
        return total

    w, r, d = np.empty((3, 3)), np.empty(3), np.empty(3)
    for k in order:
        a, b = graph.edge_from[k], graph.edge_to[k]
        _weighted_residual(pose(a), pose(b), graph.measurements[k], graph.information[k], w, r, d)
        paths = []
        for node in (a, b):
            path = []
            while node != top[k]:
                path.append(node)
                node = parent[node]
            paths.append(path)
        length = len(paths[0]) + len(paths[1])
        weight = sum(1.0 / stiffness[node] for path in paths for node in path)
        beta = [_clamped_step(length, d[j], r[j], gamma[j], t) / weight[j] for j in range(3)]
        for sign, path in zip((-1.0, 1.0), paths, strict=True):
            for node in path:
                params[node] += sign * np.array(beta) / stiffness[node]


def test_a_pass_reads_every_pose_as_updated_by_the_constraints_before_it() -> None:
    # The kernel keeps the poses in a Fenwick tree over subtree intervals; a stale or misplaced update
    # would show against walking every path to the root.
    graph = generate_grid_world(300, seed=3).graph
    tree = spanning_tree(graph, "breadth-first")
    params = np.empty_like(graph.poses)
    parameters_from_poses(graph.poses, tree.parent, tree.root, params)
    stiffness, gamma = np.empty_like(params), np.empty(3)
    tree_stiffness(graph.poses, graph.edge_from, graph.edge_to, tree.top, graph.information, tree.parent,
                   stiffness, gamma)
    order = tree.visit_order()
    expected = params.copy()
    _reference_pass(graph, expected, tree.parent, tree.root, tree.top, order, stiffness, gamma, 3)
    entry, exit_ = subtree_intervals(tree.parent, tree.root)
    tree_sgd_iteration(params, graph.edge_from, graph.edge_to, tree.top, order, graph.measurements,
                       graph.information, tree.parent, entry, exit_, np.empty((len(params) + 1, 3)),
                       stiffness, gamma, 1.0, 3, False)
    assert not np.allclose(params, graph.poses)  # the pass moved the poses
    np.testing.assert_allclose(params, expected, rtol=1e-9, atol=1e-9)
