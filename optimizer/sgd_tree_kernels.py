"""Compiled kernels of the tree-parameterised SGD (TORO's idea, Grisetti et al. 2007, on our state).

State: for every pose i other than the root, the parameter q_i = p_i − p_parent(i) (global frame, θ not
wrapped), and q_root = p_root. A pose is the sum of the parameters on its path to the root, so a constraint
(a, b) is satisfied by the parameters on the tree path a → top → b (top = lowest common ancestor): moving
the parameters on b's side by +δ and those on a's side by −δ changes p_b − p_a by the sum of the δ. The
residual is computed in the stored direction (the frame of a, as the file measured it), so reversed edges
need no special case. Poses are summed exactly from the root at every visit, never read stale: in O(log N)
from a Fenwick tree over the poses in depth-first order (`subtree_intervals`), where a parameter's change is
added to its whole subtree's interval. Walking to the root instead cost the depth at every visit: O(N) a
constraint on a long corridor's chain (the Freiburg clinic's 3 502 keyframes, depth 2 475: 16 ms an
iteration, its final optimization's largest share).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from optimizer.se2 import wrap_scalar
from optimizer.sgd_kernels import _clamped_step, _rotated_information, _weighted_residual


@njit(cache=True)
def tree_depths(order: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Depth of every node, given a breadth-first order (parents before children) and the parents."""
    depth = np.zeros(order.shape[0], dtype=np.int64)
    for position in range(1, order.shape[0]):
        node = order[position]
        depth[node] = depth[parent[node]] + 1
    return depth


@njit(cache=True)
def lowest_common_ancestors(edge_from: np.ndarray, edge_to: np.ndarray, parent: np.ndarray,
                            depth: np.ndarray) -> np.ndarray:
    """The top node of every constraint's tree path (O(path length) each)."""
    top = np.empty(edge_from.shape[0], dtype=np.int64)
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        while depth[a] > depth[b]:
            a = parent[a]
        while depth[b] > depth[a]:
            b = parent[b]
        while a != b:
            a = parent[a]
            b = parent[b]
        top[k] = a
    return top


@njit(cache=True)
def parameters_from_poses(poses: np.ndarray, parent: np.ndarray, root: int, params: np.ndarray) -> None:
    """q_i = p_i − p_parent(i) with the angle difference wrapped, so that sums along paths are consistent."""
    for i in range(poses.shape[0]):
        if i == root:
            params[i, 0] = poses[i, 0]
            params[i, 1] = poses[i, 1]
            params[i, 2] = poses[i, 2]
        else:
            q = parent[i]
            params[i, 0] = poses[i, 0] - poses[q, 0]
            params[i, 1] = poses[i, 1] - poses[q, 1]
            params[i, 2] = wrap_scalar(poses[i, 2] - poses[q, 2])


@njit(cache=True)
def poses_from_parameters(params: np.ndarray, parent: np.ndarray, order: np.ndarray,
                          poses: np.ndarray) -> None:
    """p_i = p_parent(i) + q_i, parents first (θ left unwrapped)."""
    root = order[0]
    for j in range(3):
        poses[root, j] = params[root, j]
    for position in range(1, order.shape[0]):
        node = order[position]
        q = parent[node]
        for j in range(3):
            poses[node, j] = poses[q, j] + params[node, j]


@njit(cache=True)
def subtree_intervals(parent: np.ndarray, root: int) -> tuple[np.ndarray, np.ndarray]:
    """(entry, exit): the poses numbered in depth-first order from `root`, so that the subtree of pose i is
    the interval [entry[i], exit[i]) of that numbering."""
    n = parent.shape[0]
    children_count = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        if i != root:
            children_count[parent[i] + 1] += 1
    start = np.cumsum(children_count)
    children = np.empty(max(n - 1, 0), dtype=np.int64)
    filled = start[:-1].copy()
    for i in range(n):
        if i != root:
            children[filled[parent[i]]] = i
            filled[parent[i]] += 1
    entry = np.empty(n, dtype=np.int64)
    exit_ = np.empty(n, dtype=np.int64)
    stack = np.empty(n, dtype=np.int64)
    next_child = start[:-1].copy()
    depth = 0
    stack[0] = root
    entry[root] = 0
    counter = 1
    while depth >= 0:
        node = stack[depth]
        if next_child[node] < start[node + 1]:
            child = children[next_child[node]]
            next_child[node] += 1
            entry[child] = counter
            counter += 1
            depth += 1
            stack[depth] = child
        else:
            exit_[node] = counter
            depth -= 1
    return entry, exit_


@njit(cache=True)
def _fenwick_of(params: np.ndarray, entry: np.ndarray, exit_: np.ndarray, sums: np.ndarray) -> None:
    """`sums` (N + 1, 3): the Fenwick tree whose prefix sum at entry[i] is pose i, the sum of the parameters
    of i and its ancestors (each parameter +q at its subtree's entry, −q at its exit)."""
    n = params.shape[0]
    sums[:] = 0.0
    for i in range(n):
        for j in range(3):
            sums[entry[i] + 1, j] += params[i, j]
            if exit_[i] < n:
                sums[exit_[i] + 1, j] -= params[i, j]
    for i in range(1, n + 1):
        up = i + (i & -i)
        if up <= n:
            for j in range(3):
                sums[up, j] += sums[i, j]


@njit(cache=True, inline="always")
def _fenwick_add(sums: np.ndarray, position: int, d0: float, d1: float, d2: float) -> None:
    """Add (d0, d1, d2) at `position` (N, one past the last pose: nothing)."""
    i = position + 1
    n = sums.shape[0] - 1
    while i <= n:
        sums[i, 0] += d0
        sums[i, 1] += d1
        sums[i, 2] += d2
        i += i & -i


@njit(cache=True, inline="always")
def _pose_of(node: int, entry: np.ndarray, sums: np.ndarray, out: np.ndarray) -> None:
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    i = entry[node] + 1
    while i > 0:
        out[0] += sums[i, 0]
        out[1] += sums[i, 1]
        out[2] += sums[i, 2]
        i -= i & -i


@njit(cache=True)
def tree_stiffness(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, top: np.ndarray,
                   information: np.ndarray, parent: np.ndarray, stiffness: np.ndarray,
                   gamma: np.ndarray) -> None:
    """M_i = Σ diag(W) over the constraints whose tree path moves q_i; γ = min diag(W) over constraints.

    Summed by walking each path (positive terms only): a subtree sum of +W at the ends and −2W at the top
    would cancel catastrophically where huge and tiny informations meet (INTEL).
    """
    stiffness[:] = 0.0
    gamma[:] = np.inf
    w = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        _rotated_information(poses[edge_from[k], 2], information[k], w)
        for j in range(3):
            gamma[j] = min(gamma[j], w[j, j])
        for side in range(2):
            node = edge_from[k] if side == 0 else edge_to[k]
            while node != top[k]:
                for j in range(3):
                    stiffness[node, j] += w[j, j]
                node = parent[node]


@njit(cache=True)
def tree_sgd_iteration(params: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, top: np.ndarray,
                       visit_order: np.ndarray, measurements: np.ndarray, information: np.ndarray,
                       parent: np.ndarray, entry: np.ndarray, exit_: np.ndarray, sums: np.ndarray,
                       stiffness: np.ndarray, gamma: np.ndarray, learning_rate_scale: float, t: int,
                       coupled_headings: bool) -> None:
    """One pass over the constraints in `visit_order`, updating the parameters in place (`entry`, `exit_`:
    `subtree_intervals`; `sums`: (N + 1, 3) room for the Fenwick tree of the poses).

    Per constraint: the residual r = (P_a·z) − p_b (θ wrapped) and d = 2 W r with W = R Ω Rᵀ in the global
    frame; the step β_j = ℓ d_j /(s γ_j t) (ℓ = path length, s = `learning_rate_scale`), clamped to r_j so
    it never overshoots, is split over the path's parameters in proportion to 1/M_i.
    With `coupled_headings` the heading step is `_coupled_heading_step` instead: it sees the turn of the
    measured translation by θ_a, which the paper's step ignores.
    """
    pa = np.empty(3)
    pb = np.empty(3)
    r = np.empty(3)
    d = np.empty(3)
    total_weight = np.empty(3)
    beta = np.empty(3)
    w = np.empty((3, 3))
    _fenwick_of(params, entry, exit_, sums)
    for position in range(visit_order.shape[0]):
        k = visit_order[position]
        a = edge_from[k]
        b = edge_to[k]
        _pose_of(a, entry, sums, pa)
        _pose_of(b, entry, sums, pb)
        _weighted_residual(pa, pb, measurements[k], information[k], w, r, d)
        length = 0
        total_weight[:] = 0.0
        heading_weight_a = 0.0
        for side in range(2):
            node = a if side == 0 else b
            while node != top[k]:
                length += 1
                for j in range(3):
                    total_weight[j] += 1.0 / stiffness[node, j]
                if coupled_headings and side == 0:
                    heading_weight_a += 1.0 / stiffness[node, 2]
                node = parent[node]
        for j in range(3):
            beta[j] = _clamped_step(length, d[j], r[j], learning_rate_scale * gamma[j], t) / total_weight[j]
        if coupled_headings:
            beta[2] = _coupled_heading_step(pa[2], measurements[k], w, r[0] - beta[0] * total_weight[0],
                                            r[1] - beta[1] * total_weight[1], r[2],
                                            heading_weight_a / total_weight[2], length,
                                            learning_rate_scale * gamma[2], t) / total_weight[2]
        for side in range(2):
            node = a if side == 0 else b
            sign = -1.0 if side == 0 else 1.0
            while node != top[k]:
                d0 = sign * beta[0] / stiffness[node, 0]
                d1 = sign * beta[1] / stiffness[node, 1]
                d2 = sign * beta[2] / stiffness[node, 2]
                params[node, 0] += d0
                params[node, 1] += d1
                params[node, 2] += d2
                _fenwick_add(sums, entry[node], d0, d1, d2)
                _fenwick_add(sums, exit_[node], -d0, -d1, -d2)  # no-op past the last pose (the root's)
                node = parent[node]


@njit(cache=True, inline="always")
def _coupled_heading_step(theta_a: float, z: np.ndarray, w: np.ndarray, rx: float, ry: float, rtheta: float,
                          share_a: float, length: int, gamma: float, t: int) -> float:
    """The change β of θ_b − θ_a that the path's heading parameters make, seeing that θ_a turns the
    measured translation R(θ_a)·z.

    The step moves θ_a by −β·`share_a`, so the constraint's residual (rx, ry: the translation residual the
    translation step left; rθ) moves by −β·u with u = (g, 1), g = share_a·∂(R(θ_a)·z)/∂θ_a. β is the
    constraint's own minimum along u, uᵀW r / uᵀW u, times the fraction min(1, 2ℓ W_θθ/(γ t)) of it that
    the paper's heading step takes (for a diagonal W its step is that fraction of r_θ, its minimum when g
    is ignored). The paper's rate applied to uᵀW r instead would keep the steps whole for hundreds of
    iterations where the lever |z| is long and the headings' γ small: INTEL's χ² then rose from 9·10³ to
    1.8·10⁴ between iterations 20 and 34.
    """
    c = math.cos(theta_a)
    s = math.sin(theta_a)
    g0 = -share_a * (s * z[0] + c * z[1])
    g1 = share_a * (c * z[0] - s * z[1])
    wr0 = w[0, 0] * rx + w[0, 1] * ry + w[0, 2] * rtheta
    wr1 = w[1, 0] * rx + w[1, 1] * ry + w[1, 2] * rtheta
    wr2 = w[2, 0] * rx + w[2, 1] * ry + w[2, 2] * rtheta
    along = g0 * wr0 + g1 * wr1 + wr2
    curvature = (g0 * (w[0, 0] * g0 + w[0, 1] * g1 + w[0, 2]) + g1 * (w[1, 0] * g0 + w[1, 1] * g1 + w[1, 2])
                 + w[2, 0] * g0 + w[2, 1] * g1 + w[2, 2])
    if not curvature > 0.0:
        return 0.0
    return along / curvature * min(1.0, 2.0 * length * w[2, 2] / (gamma * t))


@njit(cache=True)
def path_variance_ratios(parent: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, top: np.ndarray,
                         information: np.ndarray, out: np.ndarray) -> None:
    """out_j = Σ over constraints k of (Σ over the tree edges e on k's path of 1/Ω_e,jj) · Ω_k,jj.

    How uncertain, per dimension, the path a constraint's residual is spread over is compared with the
    constraint itself. A tree edge's variance is that of the most certain constraint joining the pose to
    its parent, with 1/Ω_jj standing in for the variance. Paths are walked (O(total path length), as one
    SGD pass): differences of sums from the root would cancel where variances span many magnitudes.
    """
    n = parent.shape[0]
    variance = np.full((n, 3), np.inf)
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        b = edge_to[k]
        child = b if parent[b] == a else (a if parent[a] == b else -1)
        if child >= 0 and child != parent[child]:
            for j in range(3):
                if information[k, j, j] > 0.0:  # a direction without information adds no certainty
                    variance[child, j] = min(variance[child, j], 1.0 / information[k, j, j])
    out[:] = 0.0
    for k in range(edge_from.shape[0]):
        for side in range(2):
            node = edge_from[k] if side == 0 else edge_to[k]
            while node != top[k]:
                for j in range(3):
                    if information[k, j, j] > 0.0:
                        out[j] += variance[node, j] * information[k, j, j]
                node = parent[node]
