"""Compiled kernels of the SGD of Olson, Leonard & Teller (2006).

State: global poses p (N, 3) with θ kept unwrapped, so that the incremental state x_i = p_i − p_{i−1}
is a plain difference. A constraint (a, b) is satisfied by the motions x_{lo+1..hi}, lo = min(a, b),
hi = max(a, b); its weighted residual is spread over them in proportion to 1/M (the stiffness, diag of
JᵀΣ⁻¹J). The residual is always computed in the stored direction (the frame of a, as the file measured
it); for a reversed constraint (a > b) the motions lo+1..hi carry p_a away from p_b, so the step is
applied with the opposite sign. This is exact, not a flipped approximation of the constraint.

Two implementations of one iteration, visiting constraints in their stored order:
- `sgd_iteration_linear`: Algorithm 1 of the paper, O(N) per constraint. Kept as the test oracle.
- `sgd_iteration_tree`: the same arithmetic in O(log N) per constraint (section III-F). Between two
  recomputations of M the weights w_i = 1/M_i are fixed, so the pose p_k is
      p_k = p⁰_k + Σ_{i≤k} w_i C_i,   C_i = Σ of the per-loop amounts c added on ranges covering i,
  and a segment tree with lazy range adds answers the prefix sum, the loop's total weight Σ w_i and
  the range add in O(log N) each (the paper's "binary tree whose leaves are the elements of x_incr").
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
        lo = min(a, edge_to[k])
        hi = max(a, edge_to[k])
        _rotated_information(poses[a, 2], information[k], w_global)
        for j in range(3):
            for i in range(lo + 1, hi + 1):
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
        lo = min(a, b)
        hi = max(a, b)
        sign = 1.0 if a < b else -1.0
        _weighted_residual(poses[a], poses[b], measurements[k], information[k], w_global, r, d)
        for j in range(3):
            total_weight = 0.0
            for i in range(lo + 1, hi + 1):
                total_weight += 1.0 / stiffness[i, j]
            beta = sign * _clamped_step(hi - lo, d[j], r[j], gamma[j], t)
            dpose = 0.0
            for i in range(lo + 1, n):
                if i <= hi:
                    dpose += beta / stiffness[i, j] / total_weight
                poses[i, j] += dpose


# ------------------------------------------------------------------------------------------ O(log N) tree
# A segment tree over the increments x_1..x_{N-1} (leaf size + i holds increment i). Each node stores, per
# dimension: LAZY, the amount c added to every increment of its interval by range updates that stopped at
# this node; ACCUMULATED, Σ w_i·C_i over its interval counting only updates at or below it; WEIGHT, Σ w_i over
# its interval. Every sum adds genuine contributions, never a difference of large prefix sums: the weights
# of ill-conditioned graphs (INTEL) span eleven orders of magnitude.

LAZY = 0
ACCUMULATED = 1
WEIGHT = 2


def tree_size(num_poses: int) -> int:
    """Number of leaves of the segment tree: the next power of two ≥ N."""
    return 1 << max(num_poses - 1, 1).bit_length()


@njit(cache=True)
def stiffness_tree(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, information: np.ndarray,
                   tree: np.ndarray, gamma: np.ndarray) -> None:
    """Weights w_i = 1/M_i (the tree's leaves) and the tree's interval weights, in O(M log N + N).

    M is summed with positive range adds on the tree's nodes, then pushed down to the leaves: a running
    sum of a difference array would cancel catastrophically when huge and tiny informations meet.
    """
    n = poses.shape[0]
    size = tree.shape[0] // 2
    tree[:] = 0.0
    gamma[:] = np.inf
    w_global = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        _rotated_information(poses[edge_from[k], 2], information[k], w_global)
        lo = min(edge_from[k], edge_to[k]) + 1 + size
        hi = max(edge_from[k], edge_to[k]) + size + 1
        while lo < hi:
            if lo & 1:
                for j in range(3):
                    tree[lo, LAZY, j] += w_global[j, j]
                lo += 1
            if hi & 1:
                hi -= 1
                for j in range(3):
                    tree[hi, LAZY, j] += w_global[j, j]
            lo >>= 1
            hi >>= 1
        for j in range(3):
            gamma[j] = min(gamma[j], w_global[j, j])
    for node in range(1, size):
        for j in range(3):
            tree[2 * node, LAZY, j] += tree[node, LAZY, j]
            tree[2 * node + 1, LAZY, j] += tree[node, LAZY, j]
    # Leaf i now holds M_i in LAZY; its WEIGHT becomes 1/M_i (pose 0, the anchor, and the padding
    # leaves past N keep 0). `sgd_iteration_tree` clears LAZY and ACCUMULATED before it starts.
    for i in range(1, n):
        for j in range(3):
            tree[size + i, WEIGHT, j] = 1.0 / tree[size + i, LAZY, j]
    for node in range(size - 1, 0, -1):
        for j in range(3):
            tree[node, WEIGHT, j] = tree[2 * node, WEIGHT, j] + tree[2 * node + 1, WEIGHT, j]


@njit(cache=True, inline="always")
def _tree_pose(k: int, base: np.ndarray, tree: np.ndarray, out: np.ndarray) -> None:
    """p_k = p⁰_k + Σ_{i≤k} w_i C_i, walking from the root to leaf k."""
    size = tree.shape[0] // 2
    node = 1
    lo = 0
    hi = size
    l0 = l1 = l2 = 0.0  # Σ LAZY of the ancestors of the current node, current node included
    s0 = s1 = s2 = 0.0
    while node < size:
        l0 += tree[node, LAZY, 0]
        l1 += tree[node, LAZY, 1]
        l2 += tree[node, LAZY, 2]
        mid = (lo + hi) >> 1
        left = 2 * node
        if k >= mid:  # the whole left child lies in the prefix
            s0 += tree[left, ACCUMULATED, 0] + l0 * tree[left, WEIGHT, 0]
            s1 += tree[left, ACCUMULATED, 1] + l1 * tree[left, WEIGHT, 1]
            s2 += tree[left, ACCUMULATED, 2] + l2 * tree[left, WEIGHT, 2]
            node = left + 1
            lo = mid
        else:
            node = left
            hi = mid
    out[0] = base[k, 0] + s0 + tree[node, ACCUMULATED, 0] + l0 * tree[node, WEIGHT, 0]
    out[1] = base[k, 1] + s1 + tree[node, ACCUMULATED, 1] + l1 * tree[node, WEIGHT, 1]
    out[2] = base[k, 2] + s2 + tree[node, ACCUMULATED, 2] + l2 * tree[node, WEIGHT, 2]


@njit(cache=True, inline="always")
def _tree_weight(first: int, last: int, tree: np.ndarray, out: np.ndarray) -> None:
    """Σ w_i over first..last, from the O(log N) nodes that tile the interval."""
    size = tree.shape[0] // 2
    out[:] = 0.0
    lo = first + size
    hi = last + size + 1
    while lo < hi:
        if lo & 1:
            for j in range(3):
                out[j] += tree[lo, WEIGHT, j]
            lo += 1
        if hi & 1:
            hi -= 1
            for j in range(3):
                out[j] += tree[hi, WEIGHT, j]
        lo >>= 1
        hi >>= 1


@njit(cache=True, inline="always")
def _apply(node: int, amount: np.ndarray, tree: np.ndarray) -> None:
    for j in range(3):
        tree[node, LAZY, j] += amount[j]
        tree[node, ACCUMULATED, j] += amount[j] * tree[node, WEIGHT, j]


@njit(cache=True, inline="always")
def _resum(node: int, tree: np.ndarray) -> None:
    for j in range(3):
        tree[node, ACCUMULATED, j] = (tree[2 * node, ACCUMULATED, j] + tree[2 * node + 1, ACCUMULATED, j]
                                      + tree[node, LAZY, j] * tree[node, WEIGHT, j])


@njit(cache=True, inline="always")
def _tree_add(first: int, last: int, amount: np.ndarray, tree: np.ndarray) -> None:
    """C_i += amount for i in first..last: O(log N) nodes take it, then their ancestors are re-summed."""
    size = tree.shape[0] // 2
    lo = first + size
    hi = last + size + 1
    while lo < hi:
        if lo & 1:
            _apply(lo, amount, tree)
            lo += 1
        if hi & 1:
            hi -= 1
            _apply(hi, amount, tree)
        lo >>= 1
        hi >>= 1
    # Re-sum the ancestors of both ends, level by level; once the two paths meet, only one remains.
    left = (first + size) >> 1
    right = (last + size) >> 1
    while left != right:
        _resum(left, tree)
        _resum(right, tree)
        left >>= 1
        right >>= 1
    while left >= 1:
        _resum(left, tree)
        left >>= 1


@njit(cache=True)
def sgd_iteration_tree(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray,
                       measurements: np.ndarray, information: np.ndarray,
                       tree: np.ndarray, gamma: np.ndarray, t: int) -> None:
    """One pass over all constraints in O(log N) each; `poses` is brought up to date at the end (O(N)).

    `tree` ((2·size, 3, 3), see `tree_size`) must hold the WEIGHT sums of `stiffness_tree`.
    """
    n = poses.shape[0]
    size = tree.shape[0] // 2
    tree[:, LAZY, :] = 0.0
    tree[:, ACCUMULATED, :] = 0.0
    pa = np.empty(3)
    pb = np.empty(3)
    r = np.empty(3)
    d = np.empty(3)
    total_weight = np.empty(3)
    amount = np.empty(3)
    w_global = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        _tree_pose(a, poses, tree, pa)
        _tree_pose(b, poses, tree, pb)
        _weighted_residual(pa, pb, measurements[k], information[k], w_global, r, d)
        lo = min(a, b)
        hi = max(a, b)
        sign = 1.0 if a < b else -1.0
        _tree_weight(lo + 1, hi, tree, total_weight)
        for j in range(3):
            amount[j] = sign * _clamped_step(hi - lo, d[j], r[j], gamma[j], t) / total_weight[j]
        _tree_add(lo + 1, hi, amount, tree)
    # Push every LAZY down to the leaves: C_i, then p_i += Σ_{m≤i} w_m C_m.
    for node in range(1, size):
        for j in range(3):
            tree[2 * node, LAZY, j] += tree[node, LAZY, j]
            tree[2 * node + 1, LAZY, j] += tree[node, LAZY, j]
    for j in range(3):
        moved = 0.0
        for i in range(1, n):
            moved += tree[size + i, WEIGHT, j] * tree[size + i, LAZY, j]
            poses[i, j] += moved
