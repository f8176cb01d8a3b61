"""Compiled kernels of the SGD of Olson, Leonard & Teller (2006).

State: global poses p (N, 3) with θ kept unwrapped, so that the incremental state x_i = p_i − p_{i−1}
is a plain difference. A constraint (a, b) is satisfied by the motions x_{a+1..b}; its weighted residual
is spread over them in proportion to 1/M (the stiffness, diag of JᵀΣ⁻¹J).

Two implementations of one iteration, visiting constraints in their stored order:
- `sgd_iteration_linear`: Algorithm 1 of the paper, O(N) per constraint. Kept as the test oracle.
- `sgd_iteration_tree`: the same arithmetic in O(log N) per constraint (section III-F). Between two
  recomputations of M the weights w_i = 1/M_i are fixed, so the pose p_k is
      p_k = p⁰_k + Σ_{i≤k} w_i C_i,   C_i = Σ of the per-loop amounts c added on ranges covering i.
  With the range adds kept as a difference array D (D_l += c, D_{r+1} −= c) and W(k) = Σ_{i≤k} w_i,
      Σ_{i≤k} w_i C_i = W(k)·Σ_{m≤k} D_m − Σ_{m≤k} D_m·W(m−1),
  two prefix sums that two Fenwick trees answer and update in O(log N).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def _wrap(angle: float) -> float:
    return (angle + math.pi) % TWO_PI - math.pi


@njit(cache=True, inline="always")
def _rotated_information(theta: float, info: np.ndarray, out: np.ndarray) -> None:
    """out = R Ω Rᵀ with R = Rot(θ): the information of a constraint expressed in the global frame."""
    c = math.cos(theta)
    s = math.sin(theta)
    # rot rows: (c, -s, 0), (s, c, 0), (0, 0, 1)
    ro00 = c * info[0, 0] - s * info[1, 0]
    ro01 = c * info[0, 1] - s * info[1, 1]
    ro02 = c * info[0, 2] - s * info[1, 2]
    ro10 = s * info[0, 0] + c * info[1, 0]
    ro11 = s * info[0, 1] + c * info[1, 1]
    ro12 = s * info[0, 2] + c * info[1, 2]
    ro20, ro21, ro22 = info[2, 0], info[2, 1], info[2, 2]
    out[0, 0] = ro00 * c - ro01 * s
    out[0, 1] = ro00 * s + ro01 * c
    out[0, 2] = ro02
    out[1, 0] = ro10 * c - ro11 * s
    out[1, 1] = ro10 * s + ro11 * c
    out[1, 2] = ro12
    out[2, 0] = ro20 * c - ro21 * s
    out[2, 1] = ro20 * s + ro21 * c
    out[2, 2] = ro22


@njit(cache=True, inline="always")
def _weighted_residual(pa: np.ndarray, pb: np.ndarray, z: np.ndarray, info: np.ndarray,
                       w_global: np.ndarray, r: np.ndarray, d: np.ndarray) -> None:
    """r = p_b' − p_b with P_b' = P_a·T_ab (θ wrapped), and d = 2·W·r with W = R Ω Rᵀ."""
    c = math.cos(pa[2])
    s = math.sin(pa[2])
    r[0] = pa[0] + c * z[0] - s * z[1] - pb[0]
    r[1] = pa[1] + s * z[0] + c * z[1] - pb[1]
    r[2] = _wrap(pa[2] + z[2] - pb[2])
    _rotated_information(pa[2], info, w_global)
    for j in range(3):
        d[j] = 2.0 * (w_global[j, 0] * r[0] + w_global[j, 1] * r[1] + w_global[j, 2] * r[2])


@njit(cache=True, inline="always")
def _clamped_step(loop_length: int, d_j: float, r_j: float, gamma_j: float, t: int) -> float:
    """β = (b − a)·d_j·α with α = 1/(γ_j t), clamped so that it never overshoots the residual."""
    beta = loop_length * d_j / (gamma_j * t)
    if abs(beta) > abs(r_j):
        beta = r_j
    return beta


# ---------------------------------------------------------------------------------------------- Algorithm 1

@njit(cache=True)
def stiffness_linear(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray,
                     information: np.ndarray, stiffness: np.ndarray, gamma: np.ndarray) -> None:
    """M_i = Σ diag(W) over constraints whose loop covers i, γ = min diag(W); literal O(loop) sums."""
    stiffness[:] = 0.0
    gamma[:] = np.inf
    w_global = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        _rotated_information(poses[a, 2], information[k], w_global)
        for j in range(3):
            for i in range(a + 1, b + 1):
                stiffness[i, j] += w_global[j, j]
            gamma[j] = min(gamma[j], w_global[j, j])


@njit(cache=True)
def sgd_iteration_linear(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray,
                         measurements: np.ndarray, information: np.ndarray, stiffness: np.ndarray,
                         gamma: np.ndarray, t: int) -> None:
    """One pass of Algorithm 1 over all constraints, updating `poses` in place (O(N) per constraint)."""
    n = poses.shape[0]
    r = np.empty(3)
    d = np.empty(3)
    w_global = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        _weighted_residual(poses[a], poses[b], measurements[k], information[k], w_global, r, d)
        for j in range(3):
            total_weight = 0.0
            for i in range(a + 1, b + 1):
                total_weight += 1.0 / stiffness[i, j]
            beta = _clamped_step(b - a, d[j], r[j], gamma[j], t)
            dpose = 0.0
            for i in range(a + 1, n):
                if i <= b:
                    dpose += beta / stiffness[i, j] / total_weight
                poses[i, j] += dpose


# ------------------------------------------------------------------------------------------ O(log N) tree

@njit(cache=True)
def stiffness_tree(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, information: np.ndarray,
                   weights: np.ndarray, prefix_weights: np.ndarray, gamma: np.ndarray) -> None:
    """Weights w_i = 1/M_i and their prefix sums W(k), in O(N + M) through a difference array."""
    n = poses.shape[0]
    difference = np.zeros((n + 1, 3))
    gamma[:] = np.inf
    w_global = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        _rotated_information(poses[a, 2], information[k], w_global)
        for j in range(3):
            difference[a + 1, j] += w_global[j, j]
            difference[b + 1, j] -= w_global[j, j]
            gamma[j] = min(gamma[j], w_global[j, j])
    for j in range(3):
        running = 0.0
        prefix = 0.0
        weights[0, j] = 0.0  # pose 0 is the anchor: no loop covers it
        prefix_weights[0, j] = 0.0
        for i in range(1, n):
            running += difference[i, j]
            weights[i, j] = 1.0 / running
            prefix += weights[i, j]
            prefix_weights[i, j] = prefix


@njit(cache=True, inline="always")
def _tree_pose(k: int, base: np.ndarray, prefix_weights: np.ndarray, tree_d: np.ndarray,
               tree_dw: np.ndarray, out: np.ndarray) -> None:
    """p_k = p⁰_k + W(k)·Σ_{m≤k} D_m − Σ_{m≤k} D_m W(m−1), from the two Fenwick trees."""
    s0 = s1 = s2 = 0.0
    q0 = q1 = q2 = 0.0
    i = k + 1
    while i > 0:
        s0 += tree_d[i, 0]
        s1 += tree_d[i, 1]
        s2 += tree_d[i, 2]
        q0 += tree_dw[i, 0]
        q1 += tree_dw[i, 1]
        q2 += tree_dw[i, 2]
        i -= i & -i
    out[0] = base[k, 0] + prefix_weights[k, 0] * s0 - q0
    out[1] = base[k, 1] + prefix_weights[k, 1] * s1 - q1
    out[2] = base[k, 2] + prefix_weights[k, 2] * s2 - q2


@njit(cache=True, inline="always")
def _tree_add(k: int, amount: np.ndarray, weight_before: np.ndarray, sign: float, tree_d: np.ndarray,
              tree_dw: np.ndarray) -> None:
    """D_k += sign·amount in both trees (the second weighted by W(k−1))."""
    n = tree_d.shape[0] - 1
    v0 = sign * amount[0]
    v1 = sign * amount[1]
    v2 = sign * amount[2]
    u0 = v0 * weight_before[0]
    u1 = v1 * weight_before[1]
    u2 = v2 * weight_before[2]
    i = k + 1
    while i <= n:
        tree_d[i, 0] += v0
        tree_d[i, 1] += v1
        tree_d[i, 2] += v2
        tree_dw[i, 0] += u0
        tree_dw[i, 1] += u1
        tree_dw[i, 2] += u2
        i += i & -i


@njit(cache=True)
def sgd_iteration_tree(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray,
                       measurements: np.ndarray, information: np.ndarray, weights: np.ndarray,
                       prefix_weights: np.ndarray, gamma: np.ndarray, t: int, tree_d: np.ndarray,
                       tree_dw: np.ndarray) -> None:
    """One pass over all constraints in O(log N) each; `poses` is brought up to date at the end (O(N)).

    `tree_d` and `tree_dw` ((N+1, 3)) are scratch buffers owned by the caller.
    """
    n = poses.shape[0]
    tree_d[:] = 0.0
    tree_dw[:] = 0.0
    pa = np.empty(3)
    pb = np.empty(3)
    r = np.empty(3)
    d = np.empty(3)
    amount = np.empty(3)
    w_global = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        _tree_pose(a, poses, prefix_weights, tree_d, tree_dw, pa)
        _tree_pose(b, poses, prefix_weights, tree_d, tree_dw, pb)
        _weighted_residual(pa, pb, measurements[k], information[k], w_global, r, d)
        for j in range(3):
            total_weight = prefix_weights[b, j] - prefix_weights[a, j]
            amount[j] = _clamped_step(b - a, d[j], r[j], gamma[j], t) / total_weight
        _tree_add(a + 1, amount, prefix_weights[a], 1.0, tree_d, tree_dw)
        if b + 1 < n:
            _tree_add(b + 1, amount, prefix_weights[b], -1.0, tree_d, tree_dw)
    _fenwick_to_array(tree_d)
    for j in range(3):
        covering = 0.0
        moved = 0.0
        for i in range(1, n):
            covering += tree_d[i + 1, j]
            moved += weights[i, j] * covering
            poses[i, j] += moved


@njit(cache=True)
def _fenwick_to_array(tree: np.ndarray) -> None:
    """Undo the Fenwick summation in place, O(N): each node loses its children's partial sums.

    Descending order matters: a node's own value must still be its partial sum when it is taken from
    its parent.
    """
    n = tree.shape[0] - 1
    for i in range(n, 0, -1):
        parent = i + (i & -i)
        if parent <= n:
            for j in range(3):
                tree[parent, j] -= tree[i, j]
