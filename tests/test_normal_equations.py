"""The compiled normal-equation kernels and the damped solvers, against dense linear algebra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from optimizer import se2
from optimizer.cost import chi2
from optimizer.damped_solvers import (
    ChainPCGSolver,
    DirectSolver,
    _block_tridiagonal_factorise,
    _block_tridiagonal_solve,
)
from optimizer.graph import PoseGraph
from optimizer.gridworld import generate_grid_world
from optimizer.normal_equations import (
    UpperPattern,
    assemble,
    hessian_diagonal,
    hessian_product,
    quadratic_form,
)
from optimizer.polish import _linearise, gauss_newton
from tests.optimizer_fixtures import dense_system, random_information, run, tangled_graph


def test_assembly_matches_the_dense_normal_equations() -> None:
    graph = tangled_graph(1)
    hessian, gradient = dense_system(graph)
    pattern = UpperPattern.of(graph)
    data = np.empty(pattern.nnz)
    assembled_gradient = np.empty(pattern.size)
    assemble(graph.poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information,
             pattern.edge_block, pattern.indptr, pattern.block_count, data, assembled_gradient)
    upper = sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=hessian.shape).toarray()
    np.testing.assert_allclose(upper, np.triu(hessian), atol=1e-9)
    np.testing.assert_allclose(assembled_gradient, gradient, atol=1e-9)
    # Column indices strictly increase inside every column (the CSC order qdldl expects).
    for column in range(pattern.size):
        assert np.all(np.diff(pattern.indices[pattern.indptr[column]:pattern.indptr[column + 1]]) > 0)


def test_matrix_free_products_match_the_dense_hessian() -> None:
    graph = tangled_graph(2)
    hessian, gradient = dense_system(graph)
    vector = np.random.default_rng(3).normal(size=len(gradient))
    product = np.empty_like(vector)
    arrays = (graph.poses, graph.edge_from, graph.edge_to, graph.measurements, graph.information)
    hessian_product(*arrays, vector, product)
    np.testing.assert_allclose(product, hessian @ vector, atol=1e-9)
    assert quadratic_form(*arrays, vector) == pytest.approx(vector @ hessian @ vector, rel=1e-12)
    diagonal, matrix_free_gradient = np.empty_like(vector), np.empty_like(vector)
    hessian_diagonal(*arrays, diagonal, matrix_free_gradient)
    np.testing.assert_allclose(diagonal, np.diag(hessian), atol=1e-9)
    np.testing.assert_allclose(matrix_free_gradient, gradient, atol=1e-9)


def test_block_tridiagonal_solve_matches_a_dense_solve() -> None:
    rng = np.random.default_rng(4)
    count = 6
    factors = rng.normal(size=(3 * count, 3 * count))
    dense = factors @ factors.T + 3 * count * np.eye(3 * count)
    band = np.kron(np.eye(count) + np.eye(count, k=1) + np.eye(count, k=-1), np.ones((3, 3)))
    dense *= band  # keep the diagonal and first off-diagonal blocks (diagonally dominant: still SPD)
    diagonal_blocks = np.array([dense[3 * j:3 * j + 3, 3 * j:3 * j + 3] for j in range(count)])
    chain_blocks = np.array([dense[3 * j:3 * j + 3, 3 * j + 3:3 * j + 6] for j in range(count - 1)])
    assert _block_tridiagonal_factorise(diagonal_blocks, chain_blocks)
    rhs = rng.normal(size=3 * count)
    solution = np.empty_like(rhs)
    _block_tridiagonal_solve(diagonal_blocks, chain_blocks, rhs, solution)
    np.testing.assert_allclose(solution, np.linalg.solve(dense, rhs), rtol=1e-10)


def test_chain_preconditioner_is_exact_on_a_pure_chain() -> None:
    # Odometry only: the system is the chain's block-tridiagonal matrix, so one CG iteration solves it.
    rng = np.random.default_rng(5)
    count = 30
    measurements = np.column_stack([rng.uniform(0.5, 1.5, count - 1), rng.normal(0, 0.2, count - 1),
                                    rng.normal(0, 0.3, count - 1)])
    poses = se2.compose_chain(measurements, start=np.zeros(3)) + rng.normal(0, 0.1, (count, 3))
    graph = PoseGraph.build(np.arange(count), poses, np.arange(count - 1), np.arange(1, count), measurements,
                            random_information(rng, count - 1))
    linearisation = _linearise(graph, UpperPattern.of(graph), graph.poses)
    direct = DirectSolver(UpperPattern.of(graph)).step(linearisation, 1e-3)
    iterative = ChainPCGSolver(graph)
    iterative.forcing = 1e-12
    step = iterative.step(linearisation, 1e-3)
    assert iterative.last_iterations == 1 and iterative.last_converged
    assert direct is not None and step is not None
    np.testing.assert_allclose(step, direct, rtol=1e-8, atol=1e-12)


def test_conjugate_gradients_reach_the_direct_optimum() -> None:
    graph = generate_grid_world(300, seed=4).graph
    direct, direct_status = run(gauss_newton(graph, linear_solver="direct"))
    iterative, iterative_status = run(gauss_newton(graph, linear_solver="cg"))
    assert direct_status.converged and iterative_status.converged, (direct_status, iterative_status)
    assert iterative[-1].chi2 == pytest.approx(direct[-1].chi2, rel=1e-7)
    assert direct[-1].chi2 < chi2(graph)
