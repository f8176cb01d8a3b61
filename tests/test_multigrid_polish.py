"""The block (BSR) normal equations and the multigrid-preconditioned polish, against dense algebra and the
direct solver."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp

from optimizer.block_normal_equations import (
    BlockPattern,
    add_to_diagonal,
    assemble_blocks,
    block_diagonal,
    scale_blocks,
)
from optimizer.cost import chi2
from optimizer.damped_solvers import DirectSolver, preconditioned_cg
from optimizer.gridworld import generate_grid_world
from optimizer.normal_equations import UpperPattern
from optimizer.polish import _linearise, gauss_newton
from tests.conftest import MULTIGRID_STACK
from tests.optimizer_fixtures import dense_system, run, scaled_system, tangled_graph

pytest.importorskip("pyamg")

import pyamg  # needs pyamg: after the skip
from pyamg.relaxation.smoothing import setup_block_gauss_seidel

from optimizer import multigrid_solver
from optimizer.multigrid_solver import MultigridPCGSolver, _hierarchy, _v_cycle

pytestmark = MULTIGRID_STACK  # one worker compiles the multigrid polish's kernels (conftest)


def assembled(graph_seed: int) -> tuple[BlockPattern, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    graph = tangled_graph(graph_seed)
    hessian, gradient = dense_system(graph)
    pattern = BlockPattern.of(graph)
    blocks = np.empty((pattern.num_blocks, 3, 3))
    assembled_gradient = np.empty(3 * pattern.free)
    assemble_blocks(graph.poses, graph.edge_from, graph.edge_to, graph.measurements,
                    graph.information, pattern.edge_blocks, blocks, assembled_gradient)
    return pattern, blocks, assembled_gradient, hessian, gradient


def test_block_assembly_matches_the_dense_normal_equations() -> None:
    # Reversed edges, a duplicate and edges at the anchor: every block lands where the dense H has it.
    pattern, blocks, assembled_gradient, hessian, gradient = assembled(1)
    matrix = sp.bsr_matrix((blocks, pattern.indices, pattern.indptr), shape=hessian.shape).toarray()
    np.testing.assert_allclose(matrix, hessian, atol=1e-9)
    np.testing.assert_allclose(assembled_gradient, gradient, atol=1e-9)
    np.testing.assert_allclose(block_diagonal(blocks, pattern.diagonal_block), np.diag(hessian), atol=1e-9)
    for row in range(pattern.free):  # columns strictly increase in every block row (CSR order)
        assert np.all(np.diff(pattern.indices[pattern.indptr[row]:pattern.indptr[row + 1]]) > 0)
        assert pattern.indices[pattern.diagonal_block[row]] == row


def test_scaled_blocks_are_the_jacobi_scaled_damped_matrix() -> None:
    pattern, blocks, _, hessian, _ = assembled(2)
    scale = 1.0 / np.sqrt(np.diag(hessian))
    damping = 0.25
    scale_blocks(blocks, pattern.indptr, pattern.indices, scale)
    add_to_diagonal(blocks, pattern.diagonal_block, damping)
    matrix = sp.bsr_matrix((blocks, pattern.indices, pattern.indptr), shape=hessian.shape).toarray()
    expected = np.diag(scale) @ hessian @ np.diag(scale) + damping * np.eye(len(scale))
    np.testing.assert_allclose(matrix, expected, atol=1e-12)


def test_multigrid_steps_match_the_direct_steps_for_every_damping() -> None:
    # A second damping on the same linearisation re-uses the blocks scaled in place: λ alone changes
    # (the hierarchy may be rebuilt when the kept one needs too many iterations for forcing 1e-10).
    graph = generate_grid_world(600, seed=7).graph
    upper = UpperPattern.of(graph)
    direct_solver = DirectSolver(upper)
    pattern = BlockPattern.of(graph)
    solver = MultigridPCGSolver(pattern)
    solver.forcing = 1e-10
    linearisation = _linearise(graph, pattern, graph.poses)
    for damping in (1e-4, 3e-2):
        direct = direct_solver.step(_linearise(graph, upper, graph.poses), damping)
        step = solver.step(linearisation, damping)
        assert direct is not None and step is not None
        assert solver.last_converged
        np.testing.assert_allclose(step, direct, rtol=1e-6, atol=1e-8 * np.abs(direct).max())


def test_multigrid_polish_reaches_the_direct_optimum() -> None:
    graph = generate_grid_world(400, seed=4).graph
    direct, direct_status = run(gauss_newton(graph, linear_solver="direct"))
    multigrid, multigrid_status = run(gauss_newton(graph, linear_solver="multigrid"))
    assert direct_status.converged and multigrid_status.converged, (direct_status, multigrid_status)
    assert multigrid[-1].chi2 == pytest.approx(direct[-1].chi2, rel=1e-7)
    assert direct[-1].chi2 < 1e-2 * chi2(graph)  # the polish did real work from the dead reckoning


def test_multigrid_steps_are_reproducible_and_follow_every_damping_with_one_hierarchy() -> None:
    # Two fresh solvers on the same linearisation give the same step to the last bit. The hierarchy's
    # finest level shares H's blocks: other λ on the same linearisation, with that one hierarchy kept,
    # still give the direct steps.
    graph = generate_grid_world(500, seed=3).graph
    pattern = BlockPattern.of(graph)
    steps = []
    for _ in range(2):
        solver = MultigridPCGSolver(pattern)
        solver.forcing = 1e-10
        step = solver.step(_linearise(graph, pattern, graph.poses), 1e-3)
        assert step is not None
        steps.append(step)
    np.testing.assert_array_equal(steps[0], steps[1])
    linearisation = _linearise(graph, pattern, graph.poses)
    solver = MultigridPCGSolver(pattern, rebuild_growth=1e6)  # keep the first hierarchy
    solver.forcing = 1e-10
    upper = UpperPattern.of(graph)
    direct_solver = DirectSolver(upper)
    for damping in (1e-3, 0.5, 1e-6):
        step = solver.step(linearisation, damping)
        direct = direct_solver.step(_linearise(graph, upper, graph.poses), damping)
        assert step is not None and direct is not None
        np.testing.assert_allclose(step, direct, rtol=1e-6, atol=1e-8 * np.abs(direct).max())
    assert solver.builds == 1


def test_every_linearisation_gets_a_new_hierarchy_and_its_dampings_share_it() -> None:
    graph = generate_grid_world(300, seed=5).graph
    pattern = BlockPattern.of(graph)
    solver = MultigridPCGSolver(pattern)
    linearisation = _linearise(graph, pattern, graph.poses)
    assert solver.step(linearisation, 1e-3) is not None
    assert solver.step(linearisation, 4e-3) is not None  # a rejected step's retry at a larger λ
    assert solver.builds == 1
    solver.accepted_step()
    assert solver.step(_linearise(graph, pattern, graph.poses), 1e-3) is not None
    assert solver.builds == 2


def scaled_hierarchy(num_poses: int) -> pyamg.MultilevelSolver:
    """The multigrid hierarchy of `scaled_system`."""
    return _hierarchy(*scaled_system(num_poses))


@pytest.mark.parametrize(("num_poses", "middle_level"), [(20000, True), (60, False)])
def test_the_v_cycle_is_pyamgs_with_block_gauss_seidel(num_poses: int, middle_level: bool) -> None:
    # 20 000 poses: the recursion passes a middle level; 60: the coarse solver alone solves the system.
    # The reference: pyamg's own V-cycle with its own block Gauss–Seidel smoothers (forward before, backward
    # after) on the same levels; ours fuses the first sweep with the residual, which changes only rounding.
    hierarchy = scaled_hierarchy(num_poses)
    assert len(hierarchy.levels) >= 3 if middle_level else len(hierarchy.levels) == 1
    rhs = np.random.default_rng(0).normal(size=hierarchy.levels[0].A.shape[0])
    ours = _v_cycle(hierarchy, 0, rhs)
    for level in hierarchy.levels[:-1]:
        level.R = sp.bsr_matrix(level.P.T)
        level.presmoother = setup_block_gauss_seidel(level, sweep="forward", Dinv=level.inverse_diagonal)
        level.postsmoother = setup_block_gauss_seidel(level, sweep="backward", Dinv=level.inverse_diagonal)
    reference = hierarchy.aspreconditioner(cycle="V") @ rhs
    assert np.abs(ours - reference).max() <= 1e-12 * np.abs(reference).max()


def test_the_inexact_polish_converges_on_what_the_model_promises_not_on_the_step_norm() -> None:
    # With no step-norm or gradient test left, only the model's predicted decrease can end the inexact
    # polish; it must end converged at the direct optimum, not at the iteration cap.
    graph = generate_grid_world(2000, seed=3).graph
    optimum, status = run(gauss_newton(graph, linear_solver="direct"))
    assert status.converged, status
    iterations, status = run(gauss_newton(graph, linear_solver="multigrid", step_tolerance=0.0,
                                          gradient_tolerance=0.0, max_iterations=50))
    assert status.converged, status
    assert "relative χ² change" in status.reason
    assert iterations[-1].chi2 == pytest.approx(optimum[-1].chi2, rel=1e-9)


def spd_system(size: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    factor = rng.normal(size=(size, size))
    return factor @ factor.T + 0.1 * np.diag(rng.uniform(1.0, 100.0, size)), rng.normal(size=size)


def jacobi(matrix: np.ndarray) -> Callable[[np.ndarray, np.ndarray], None]:
    inverse = 1.0 / np.diag(matrix)

    def precondition(residual: np.ndarray, out: np.ndarray) -> None:
        out[:] = inverse * residual

    return precondition


def test_cg_from_a_partial_solution_ends_at_the_cold_starts_solution() -> None:
    matrix, rhs = spd_system(60, seed=1)
    cold, _, cold_converged = preconditioned_cg(matrix.dot, jacobi(matrix), rhs, 1e-10, 1000)
    partial, partial_iterations, partial_converged = preconditioned_cg(matrix.dot, jacobi(matrix), rhs,
                                                                       1e-10, 5)
    assert cold_converged and not partial_converged and partial_iterations == 5
    warm, _, warm_converged = preconditioned_cg(matrix.dot, jacobi(matrix), rhs, 1e-10, 1000, start=partial)
    assert warm_converged
    # The target is relative to the right-hand side, as from zero, not to the partial solution's residual.
    assert np.linalg.norm(rhs - matrix @ warm) <= 1e-10 * np.linalg.norm(rhs)
    np.testing.assert_allclose(warm, cold, rtol=1e-6, atol=1e-9 * np.abs(cold).max())


def test_cg_from_a_start_that_already_solves_the_system_takes_no_iteration() -> None:
    matrix, rhs = spd_system(20, seed=2)
    exact = np.linalg.solve(matrix, rhs)
    solution, iterations, converged = preconditioned_cg(matrix.dot, jacobi(matrix), rhs, 1e-8, 100,
                                                        start=exact)
    assert (iterations, converged) == (0, True)
    np.testing.assert_array_equal(solution, exact)


def test_a_rebuilt_hierarchy_goes_on_from_where_the_kept_one_stopped(monkeypatch: pytest.MonkeyPatch) -> None:
    graph = generate_grid_world(2000, seed=5).graph
    pattern = BlockPattern.of(graph)
    solver = MultigridPCGSolver(pattern)
    linearisation = _linearise(graph, pattern, graph.poses)
    assert solver.step(linearisation, 1e-3) is not None
    calls: list[tuple[np.ndarray | None, np.ndarray, int]] = []

    def recorded(*args: Any, **kwargs: Any) -> tuple[np.ndarray, int, bool]:
        result = preconditioned_cg(*args, **kwargs)
        start = args[5] if len(args) > 5 else kwargs.get("start")
        calls.append((None if start is None else start.copy(), result[0].copy(), result[1]))
        return result

    monkeypatch.setattr(multigrid_solver, "preconditioned_cg", recorded)
    solver.forcing = 1e-12  # more than the kept hierarchy's budget of 20 iterations reaches at this λ
    assert solver.step(linearisation, 1e-9) is not None
    assert solver.last_converged
    assert solver.builds == 2
    (kept_start, kept_end, kept_iterations), (rebuilt_start, _, _) = calls
    assert kept_start is None and kept_iterations == 20
    assert rebuilt_start is not None
    np.testing.assert_array_equal(rebuilt_start, kept_end)


def test_a_kept_hierarchy_close_to_its_target_goes_on_instead_of_being_rebuilt() -> None:
    graph = generate_grid_world(2000, seed=5).graph
    pattern = BlockPattern.of(graph)
    solver = MultigridPCGSolver(pattern, rebuild_growth=0.1)
    linearisation = _linearise(graph, pattern, graph.poses)
    assert solver.step(linearisation, 1e-3) is not None
    # As if its build's first solve had taken 200 iterations: its budget (20) runs out far short of what a
    # new hierarchy would cost, and the rate it has shown reaches the target well within that.
    solver._iterations_after_build = 200
    solver.forcing = 1e-12
    assert solver.step(linearisation, 1e-9) is not None
    assert solver.last_converged and solver.last_iterations > 20
    assert solver.builds == 1
