"""A start that does not depend on the initial estimate: chordal initialisation, rotations first.

After Carlone, Tron, Daniilidis & Dellaert (2015), "Initialization techniques for 3D SLAM: a survey on
rotation estimation and its use in pose graph optimization" (ICRA), specialised to 2D:

1. Rotations. Each pose's rotation is relaxed to its first column r_i = (cos θ_i, sin θ_i), any 2-vector.
   Constraint (a, b, z), in its stored direction, asks R_b = R_a·R(z_θ), whose first column reads
   r_b − R(z_θ)·r_a = 0: two linear equations. Their weighted least-squares solution, pose 0 anchored,
   is one sparse linear solve; each r_i is then projected back onto SO(2), θ_i = atan2.
2. Positions. With the rotations fixed, g2o's translational error is linear in the positions, so the
   positions minimising the χ² of `optimizer.cost` given those rotations are a second sparse linear
   least-squares solve (the translational information rotated into the global frame, pose 0 anchored).

Neither step reads the graph's estimate except pose 0, the anchor (so a graph read without vertex lines
starts exactly as well as any other). Both normal-equation matrices have the same 2×2-block sparsity
(one block per pose pair joined by a constraint), so qdldl's fill-reducing ordering and symbolic analysis
are computed once and reused.

Why chordal rather than LAGO's linear least squares on θ: LAGO must first unwrap every loop's angle sum to
the right multiple of 2π along a spanning tree; with heavy heading noise a loop's accumulated error passes
±π and the unwrapping picks the wrong multiple, which no later step repairs. The chordal relaxation has no
integer ambiguity (it works on cos/sin directly) and costs one solve of the same size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import qdldl
import scipy.sparse as sp
from numba import njit
from numpy.typing import NDArray

from optimizer import se2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

INFORMATION_FLOOR = 1e-6
"""Each constraint's rotation weight, and each eigenvalue of its translational information, is raised to at
least this fraction of the graph's median. A constraint whose θθ information is 0 (pg1.g2o's first edge)
would otherwise drop out of the rotation system, and if it is the only link to some poses (a bridge) the
system becomes singular; the floor keeps it in with a weight too small to disturb the well-measured ones."""


def chordal_initialization(graph: PoseGraph) -> FloatArray:
    """(N, 3) poses x, y, θ (θ wrapped) estimated from the constraints alone; pose 0 is the graph's own.

    Handles constraints stored in either direction (a > b), duplicate constraints and singular θθ
    information (see `INFORMATION_FLOOR`). Raises OptimizerError when a linear system cannot be solved.
    """
    poses = np.array(graph.poses, dtype=np.float64, copy=True)
    poses[:, 2] = se2.wrap_angle(poses[:, 2])
    if graph.num_poses < 2:
        return poses
    pattern = _BlockPattern.of(graph)
    theta, factorisation = _estimate_rotations(graph, pattern, poses[0, 2])
    poses[1:, 2] = theta
    poses[1:, :2] = _estimate_positions(graph, pattern, poses, factorisation)
    return poses


def positions_given_headings(graph: PoseGraph, poses: FloatArray) -> FloatArray:
    """(N, 3) `poses` with every position but pose 0's replaced by those that minimise the χ² of
    `optimizer.cost` with all headings held at `poses[:, 2]` (θ wrapped); one sparse linear solve.

    Step 2 of the chordal initialisation on any headings. Separates the two halves of a basin question: on
    M3500-shaped worlds with σθ = 0.3 rad, the headings of the minimum found from the ground truth with
    these positions are that minimum's start (the polish only rounds), while every rotation-only heading
    estimate tried (chordal, SGD) leads to a basin about 4 % higher (benchmarks/strong_sgd_bench.py).
    """
    result = np.array(poses, dtype=np.float64, copy=True)
    if result.shape != graph.poses.shape:
        raise OptimizerError(f"expected poses of shape {graph.poses.shape}, got {result.shape}")
    if not np.all(np.isfinite(result)):
        raise OptimizerError("the poses contain non-finite values")
    result[:, 2] = se2.wrap_angle(result[:, 2])
    if graph.num_poses < 2:
        return result
    result[1:, :2] = _estimate_positions(graph, _BlockPattern.of(graph), result, None)
    return result


def rotation_weights(information: FloatArray) -> FloatArray:
    """(M,) weight of each constraint's rotation equations: the θ information with translation unknown.

    The rotation step sees no translations, so it weighs a measured angle by its marginal information
    1/Σ_θθ = Ω_θθ − Ω_θtΩ_tt⁻¹Ω_tθ (the Schur complement), not by Ω_θθ, which would credit a θ that is only
    sharp once the translation is known. For the diagonal information of most files the two are equal.
    """
    information = np.asarray(information, dtype=np.float64)
    translational = floored_translational(information)
    coupling = information[:, :2, 2]
    solved = np.linalg.solve(translational, coupling[:, :, None])[:, :, 0]
    marginal = information[:, 2, 2] - np.einsum("mi,mi->m", coupling, solved)
    return _floored(marginal)


# ----------------------------------------------------------------------------------------- the two steps


def _estimate_rotations(graph: PoseGraph, pattern: _BlockPattern,
                        anchor_theta: float) -> tuple[FloatArray, qdldl.Solver]:
    """θ of poses 1..N−1 from the chordal relaxation, and the factorisation (for its reusable analysis)."""
    weight = rotation_weights(graph.information)
    rotation = _rotation_matrices(graph.measurements[:, 2])
    eye = np.broadcast_to(np.eye(2), rotation.shape)
    diagonal = weight[:, None, None] * eye
    # Residual r_b − R_z·r_a: the (a, b) block of H is w·(−R_z)ᵀ·I.
    off_diagonal = -weight[:, None, None] * np.swapaxes(rotation, 1, 2)
    anchor = np.array([np.cos(anchor_theta), np.sin(anchor_theta)])
    # Moving the anchor's known r_0 to the right-hand side: w·R_z·r_0 for b when a = 0, w·R_zᵀ·r_0 for a
    # when b = 0.
    rhs_a = np.where((graph.edge_to == 0)[:, None], weight[:, None] * (anchor @ rotation), 0.0)
    rhs_b = np.where((graph.edge_from == 0)[:, None], weight[:, None] * (rotation @ anchor), 0.0)
    relaxed, factorisation = pattern.solve(graph, diagonal, off_diagonal, rhs_a, rhs_b, None)
    relaxed = relaxed.reshape(-1, 2)
    if not np.all(np.isfinite(relaxed)) or np.any(np.hypot(relaxed[:, 0], relaxed[:, 1]) == 0.0):
        raise OptimizerError("the chordal rotation estimate is degenerate (a pose's rotation is zero)")
    return np.arctan2(relaxed[:, 1], relaxed[:, 0]), factorisation


def _estimate_positions(graph: PoseGraph, pattern: _BlockPattern, poses: FloatArray,
                        factorisation: qdldl.Solver | None) -> FloatArray:
    """Positions of poses 1..N−1 minimising the χ² with every θ held at `poses[:, 2]`.

    With θ fixed, e_t = R_φᵀ(t_b − t_a) − R(z_θ)ᵀz_t with φ = θ_a + z_θ, and e_θ is a constant. Completing
    the square in eᵀΩe, the translational residual is compared against R(z_θ)ᵀz_t − Ω_tt⁻¹Ω_tθ·e_θ; in the
    global frame that is t_b − t_a − d with weight W = R_φΩ_ttR_φᵀ.
    """
    a, b = graph.edge_from, graph.edge_to
    theta = poses[:, 2]
    angle_error = se2.wrap_angle(theta[b] - theta[a] - graph.measurements[:, 2])
    translational = floored_translational(graph.information)
    shift = np.linalg.solve(translational, graph.information[:, :2, 2:3])[:, :, 0] * angle_error[:, None]
    measured_rotation = _rotation_matrices(graph.measurements[:, 2])
    local_target = np.einsum("mji,mj->mi", measured_rotation, graph.measurements[:, :2]) - shift
    frame = _rotation_matrices(theta[a] + graph.measurements[:, 2])
    target = np.einsum("mij,mj->mi", frame, local_target)
    weight = frame @ translational @ np.swapaxes(frame, 1, 2)
    weight = 0.5 * (weight + np.swapaxes(weight, 1, 2))
    weighted_target = np.einsum("mij,mj->mi", weight, target)
    anchor = poses[0, :2]
    anchored = np.einsum("mij,j->mi", weight, anchor)
    rhs_a = -weighted_target + np.where((b == 0)[:, None], anchored, 0.0)
    rhs_b = weighted_target + np.where((a == 0)[:, None], anchored, 0.0)
    positions, _ = pattern.solve(graph, weight, -weight, rhs_a, rhs_b, factorisation)
    if not np.all(np.isfinite(positions)):
        raise OptimizerError("the chordal position estimate is not finite")
    return positions.reshape(-1, 2)


# ------------------------------------------------------------------------------------------- helpers


def _rotation_matrices(theta: FloatArray) -> FloatArray:
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty((len(theta), 2, 2))
    out[:, 0, 0] = c
    out[:, 0, 1] = -s
    out[:, 1, 0] = s
    out[:, 1, 1] = c
    return out


def _floored(values: FloatArray) -> FloatArray:
    positive = values[values > 0.0]
    reference = float(np.median(positive)) if len(positive) else 1.0
    return np.maximum(values, INFORMATION_FLOOR * reference)


def floored_translational(information: FloatArray) -> FloatArray:
    """Ω_tt of every constraint, its smaller eigenvalue raised to the floor so that it can be inverted."""
    xx = information[:, 0, 0]
    yy = information[:, 1, 1]
    xy = 0.5 * (information[:, 0, 1] + information[:, 1, 0])
    half_trace = 0.5 * (xx + yy)
    spread = np.hypot(0.5 * (xx - yy), xy)
    largest = half_trace + spread
    positive = largest[largest > 0.0]
    floor = INFORMATION_FLOOR * (float(np.median(positive)) if len(positive) else 1.0)
    # Adding c·I raises both eigenvalues by c and keeps the eigenvectors.
    lift = np.maximum(floor - (half_trace - spread), 0.0)
    out = np.empty((len(information), 2, 2))
    out[:, 0, 0] = xx + lift
    out[:, 1, 1] = yy + lift
    out[:, 0, 1] = xy
    out[:, 1, 0] = xy
    return out


@dataclass(frozen=True)
class _BlockPattern:
    """Upper triangle of a (2(N−1))² matrix with one 2×2 block per pose pair joined by a constraint.

    Pose p ≥ 1 owns variables 2(p−1), 2(p−1)+1; pose 0 is the anchor and owns none. `pair_column` and
    `pair_row` are the distinct (larger, smaller) free pose pairs sorted by column then row (CSC order);
    `pair_of_edge` is each constraint's pair, −1 when it touches the anchor.
    """

    size: int
    pair_row: IntArray
    pair_column: IntArray
    pair_of_edge: IntArray
    pairs_start: IntArray
    """(N,) first pair of each block column (pose 1..N−1 → 0..N−2), plus the end."""

    @classmethod
    def of(cls, graph: PoseGraph) -> _BlockPattern:
        free_from = graph.edge_from - 1
        free_to = graph.edge_to - 1
        low = np.minimum(free_from, free_to)
        high = np.maximum(free_from, free_to)
        blocks = graph.num_poses - 1
        free = low >= 0
        keys = high[free] * blocks + low[free]
        order = np.sort(keys)
        distinct = order[np.r_[True, order[1:] != order[:-1]]] if len(order) else order
        pair_of_edge = np.full(graph.num_edges, -1, dtype=np.int64)
        pair_of_edge[free] = np.searchsorted(distinct, keys)
        pair_column = distinct // blocks
        pair_row = distinct % blocks
        pairs_start = np.zeros(blocks + 1, dtype=np.int64)
        pairs_start[1:] = np.cumsum(np.bincount(pair_column, minlength=blocks))
        return cls(2 * blocks, pair_row, pair_column, pair_of_edge, pairs_start)

    def solve(self, graph: PoseGraph, diagonal: FloatArray, off_diagonal: FloatArray, rhs_a: FloatArray,
              rhs_b: FloatArray, factorisation: qdldl.Solver | None) -> tuple[FloatArray, qdldl.Solver]:
        """Solve H·x = g assembled from per-constraint blocks.

        Constraint k adds `diagonal[k]` to the diagonal blocks of both its poses, `off_diagonal[k]` to the
        (edge_from, edge_to) block (its transpose to (edge_to, edge_from)), `rhs_a[k]` / `rhs_b[k]` to g at
        its poses; whatever falls on the anchor is dropped.
        """
        blocks = self.size // 2
        diagonal_sum = np.zeros((blocks, 2, 2))
        endpoints = ((graph.edge_from - 1, graph.edge_from > 0), (graph.edge_to - 1, graph.edge_to > 0))
        for pose, keep in endpoints:
            for i in range(2):
                for j in range(2):
                    diagonal_sum[:, i, j] += np.bincount(pose[keep], weights=diagonal[keep, i, j],
                                                         minlength=blocks)
        rhs = np.zeros((blocks, 2))
        for pose, keep, values in ((graph.edge_from - 1, graph.edge_from > 0, rhs_a),
                                   (graph.edge_to - 1, graph.edge_to > 0, rhs_b)):
            for i in range(2):
                rhs[:, i] += np.bincount(pose[keep], weights=values[keep, i], minlength=blocks)

        # The stored (row < column) block of a constraint is its (a, b) block when a < b, else its transpose.
        free = self.pair_of_edge >= 0
        ascending = (graph.edge_from < graph.edge_to)[free]
        upper_blocks = off_diagonal[free]
        upper_blocks = np.where(ascending[:, None, None], upper_blocks, np.swapaxes(upper_blocks, 1, 2))
        pair_sum = np.zeros((len(self.pair_row), 2, 2))
        for i in range(2):
            for j in range(2):
                pair_sum[:, i, j] = np.bincount(self.pair_of_edge[free], weights=upper_blocks[:, i, j],
                                                minlength=len(self.pair_row))
        del upper_blocks

        indptr, indices, data = _upper_csc(self.pairs_start, self.pair_row, pair_sum, diagonal_sum)
        matrix = sp.csc_matrix((data, indices, indptr), shape=(self.size, self.size))
        try:
            if factorisation is None:
                factorisation = qdldl.Solver(matrix, upper=True)
            else:
                factorisation.update(matrix, upper=True)
            solution = factorisation.solve(rhs.reshape(-1))
        except (ValueError, RuntimeError) as error:  # qdldl reports a zero pivot this way
            raise OptimizerError(f"the initialisation's linear system is singular: {error}") from error
        return np.asarray(solution, dtype=np.float64), factorisation


@njit(cache=True)
def _upper_csc(pairs_start: IntArray, pair_row: IntArray, pair_sum: FloatArray,
               diagonal_sum: FloatArray) -> tuple[IntArray, IntArray, FloatArray]:
    # Scalar column 2q holds each neighbour's two rows then the diagonal entry (2q, 2q); column 2q+1 the
    # neighbours' two rows then (2q, 2q+1) and (2q+1, 2q+1): rows ascending, as CSC wants.
    blocks = diagonal_sum.shape[0]
    nnz = 4 * pair_row.shape[0] + 3 * blocks
    indptr = np.empty(2 * blocks + 1, dtype=np.int64)
    indices = np.empty(nnz, dtype=np.int64)
    data = np.empty(nnz)
    position = 0
    indptr[0] = 0
    for q in range(blocks):
        for column in range(2):
            for pair in range(pairs_start[q], pairs_start[q + 1]):
                row = 2 * pair_row[pair]
                indices[position] = row
                data[position] = pair_sum[pair, 0, column]
                indices[position + 1] = row + 1
                data[position + 1] = pair_sum[pair, 1, column]
                position += 2
            for within in range(column + 1):
                indices[position] = 2 * q + within
                data[position] = diagonal_sum[q, within, column]
                position += 1
            indptr[2 * q + column + 1] = position
    return indptr, indices, data
