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
  the range add in O(log N) each (the paper's "binary tree whose leaves are the elements of x_incr",
  with a few increments per leaf). p⁰ is only read; the iteration writes its poses to a new array.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from optimizer.cost import plus_edge_chi2
from optimizer.prefetch import prefetch
from optimizer.se2 import wrap_scalar

Six = tuple[float, float, float, float, float, float]




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
    r[2] = wrap_scalar(pa[2] + z[2] - pb[2])
    _rotated_information(pa[2], info, w_global)
    for j in range(3):
        d[j] = 2.0 * (w_global[j, 0] * r[0] + w_global[j, 1] * r[1] + w_global[j, 2] * r[2])


@njit(cache=True, inline="always")
def _weighted_residual_one_rotation(ax: float, ay: float, atheta: float, bx: float, by: float, btheta: float,
                                    z: np.ndarray, info: np.ndarray) -> Six:
    """`_weighted_residual` of p_a = (ax, ay, atheta), p_b = (bx, by, btheta) as scalars (r, then d), with
    cos, sin of θ_a computed once and W = R Ω Rᵀ kept in registers: the same operations in the same order
    (so bit-identical), without the second cos, sin and the stores of W, r and d."""
    c = math.cos(atheta)
    s = math.sin(atheta)
    r0 = ax + c * z[0] - s * z[1] - bx
    r1 = ay + s * z[0] + c * z[1] - by
    r2 = wrap_scalar(atheta + z[2] - btheta)
    ro00 = c * info[0, 0] - s * info[1, 0]
    ro01 = c * info[0, 1] - s * info[1, 1]
    ro10 = s * info[0, 0] + c * info[1, 0]
    ro11 = s * info[0, 1] + c * info[1, 1]
    d0 = 2.0 * ((ro00 * c - ro01 * s) * r0 + (ro00 * s + ro01 * c) * r1
                + (c * info[0, 2] - s * info[1, 2]) * r2)
    d1 = 2.0 * ((ro10 * c - ro11 * s) * r0 + (ro10 * s + ro11 * c) * r1
                + (s * info[0, 2] + c * info[1, 2]) * r2)
    d2 = 2.0 * ((info[2, 0] * c - info[2, 1] * s) * r0 + (info[2, 0] * s + info[2, 1] * c) * r1
                + info[2, 2] * r2)
    return r0, r1, r2, d0, d1, d2


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
# The increments x_1..x_{N-1} are cut into blocks of `block` consecutive increments (increment i is in block
# i // block; increment 0, the anchor, has weight 0), and a segment tree is built over the blocks (node
# size + b is block b). Per increment: `weights` w_i and `amounts`, the part of C_i added to that increment
# alone (by a range whose end falls inside its block). Each node stores, per dimension: LAZY, the amount c
# added to every increment of its interval by range updates that stopped at this node; ACCUMULATED,
# Σ w_i·C_i over its interval counting only updates at or below it (for a block: its own LAZY and the
# per-increment amounts); WEIGHT, Σ w_i over its interval. Blocks make the tree `block` times smaller (19 MB
# instead of 151 MB at 10⁶ poses with blocks of 8) and shorten its cache-missing walks; the few increments
# at the ends of a range are handled one by one. Every sum adds genuine contributions, never a difference of
# large prefix sums: the weights of ill-conditioned graphs (INTEL) span eleven orders of magnitude.

LAZY = 0
ACCUMULATED = 1
WEIGHT = 2

TREE_BLOCK = 8
"""Increments per leaf of the tree (see above)."""


def tree_size(num_poses: int, block: int = TREE_BLOCK) -> int:
    """Number of leaves of the segment tree: the next power of two ≥ the number of blocks."""
    blocks = -(-num_poses // block)
    return 1 << max(blocks - 1, 1).bit_length()


@njit(cache=True, inline="always")
def _spans_blocks(a: int, b: int, block: int) -> bool:
    """Whether a constraint's increments min(a, b)+1..max(a, b) lie in more than one block of the tree:
    its total weight is then one row of `spans` (`stiffness_tree`)."""
    return (min(a, b) + 1) // block != max(a, b) // block


@njit(cache=True)
def spanning_count(edge_from: np.ndarray, edge_to: np.ndarray, block: int) -> int:
    """Number of constraints that span more than one block: the rows of the `spans` array of
    `stiffness_tree` and `sgd_iteration_tree`."""
    count = 0
    for k in range(edge_from.shape[0]):
        if _spans_blocks(edge_from[k], edge_to[k], block):
            count += 1
    return count


@njit(cache=True, inline="always")
def _block_end(block_index: int, block: int, n: int) -> int:
    """One past the last increment of a block."""
    return min((block_index + 1) * block, n)


@njit(cache=True, inline="always")
def _rotated_diagonal(c: float, s: float, info: np.ndarray) -> tuple[float, float, float]:
    """diag(R Ω Rᵀ) for R = Rot(θ), c = cos θ, s = sin θ: `_rotated_information`'s diagonal, the same
    operations in the same order."""
    ro00 = c * info[0, 0] - s * info[1, 0]
    ro01 = c * info[0, 1] - s * info[1, 1]
    ro10 = s * info[0, 0] + c * info[1, 0]
    ro11 = s * info[0, 1] + c * info[1, 1]
    return ro00 * c - ro01 * s, ro10 * s + ro11 * c, info[2, 2]


@njit(cache=True)
def stiffness_tree(poses: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray, information: np.ndarray,
                   weights: np.ndarray, amounts: np.ndarray, tree: np.ndarray, gamma: np.ndarray,
                   block: int, spans: np.ndarray) -> None:
    """Weights w_i = 1/M_i and the tree's interval weights, in O(M (log N + block) + N); and `spans`, the
    total weight Σ w_i of each constraint whose increments lie in more than one block, in the constraints'
    order ((`spanning_count`, 3)).

    M is summed with positive range adds (on the tree's nodes, and on `amounts` at the ends of a range),
    then pushed down to the increments: a running sum of a difference array would cancel catastrophically
    when huge and tiny informations meet. `sgd_iteration_tree` clears LAZY, ACCUMULATED and `amounts`.
    """
    n = poses.shape[0]
    size = tree.shape[0] // 2
    # The range adds go to a dense (nodes, 3) array (a third of the tree's bytes per node, so fewer cache
    # misses), laid over the tree's first third: the tree's own LAZY and ACCUMULATED are scratch until the
    # pass clears them, and its WEIGHT there is written only after the last read of `lazy`.
    lazy = tree.reshape(tree.size)[:6 * size].reshape((2 * size, 3))
    lazy[:] = 0.0
    amounts[:] = 0.0
    # `weights` is scratch until it is written at the end: cos, sin of each pose's θ, once per pose rather
    # than once per constraint.
    for i in range(n):
        weights[i, 0] = math.cos(poses[i, 2])
        weights[i, 1] = math.sin(poses[i, 2])
    gamma0 = gamma1 = gamma2 = np.inf
    for k in range(edge_from.shape[0]):
        a = edge_from[k]
        w0, w1, w2 = _rotated_diagonal(weights[a, 0], weights[a, 1], information[k])
        first = min(a, edge_to[k]) + 1
        last = max(a, edge_to[k])
        first_block = first // block
        last_block = last // block
        if first_block == last_block:
            for i in range(first, last + 1):
                amounts[i, 0] += w0
                amounts[i, 1] += w1
                amounts[i, 2] += w2
        else:
            for i in range(first, _block_end(first_block, block, n)):
                amounts[i, 0] += w0
                amounts[i, 1] += w1
                amounts[i, 2] += w2
            for i in range(last_block * block, last + 1):
                amounts[i, 0] += w0
                amounts[i, 1] += w1
                amounts[i, 2] += w2
            lo = first_block + size
            hi = last_block + size
            while lo ^ hi != 1:  # the nodes strictly between the two end blocks
                if lo & 1 == 0:
                    lazy[lo ^ 1, 0] += w0
                    lazy[lo ^ 1, 1] += w1
                    lazy[lo ^ 1, 2] += w2
                if hi & 1 == 1:
                    lazy[hi ^ 1, 0] += w0
                    lazy[hi ^ 1, 1] += w1
                    lazy[hi ^ 1, 2] += w2
                lo >>= 1
                hi >>= 1
        gamma0 = min(gamma0, w0)
        gamma1 = min(gamma1, w1)
        gamma2 = min(gamma2, w2)
    gamma[0] = gamma0
    gamma[1] = gamma1
    gamma[2] = gamma2
    for node in range(1, size):
        for j in range(3):
            lazy[2 * node, j] += lazy[node, j]
            lazy[2 * node + 1, j] += lazy[node, j]
    # M_i = amounts_i + the LAZY pushed down to its block; pose 0, the anchor, keeps weight 0.
    weights[0, :] = 0.0
    blocks = (n + block - 1) // block
    for b in range(blocks):
        for j in range(3):
            total = 0.0
            for i in range(max(b * block, 1), _block_end(b, block, n)):
                weights[i, j] = 1.0 / (amounts[i, j] + lazy[size + b, j])
                total += weights[i, j]
            tree[size + b, WEIGHT, j] = total
    tree[size + blocks:, WEIGHT, :] = 0.0
    for node in range(size - 1, 0, -1):
        for j in range(3):
            tree[node, WEIGHT, j] = tree[2 * node, WEIGHT, j] + tree[2 * node + 1, WEIGHT, j]
    # A pass would otherwise sum them from the tree for every constraint (a walk up both ends of the range,
    # out of cache for a loop closure), while they only change here. The same sums as `_tree_weight`
    # there: the same values to the bit.
    spanning = 0
    for k in range(edge_from.shape[0]):
        if _spans_blocks(edge_from[k], edge_to[k], block):
            w0, w1, w2 = _tree_weight(min(edge_from[k], edge_to[k]) + 1, max(edge_from[k], edge_to[k]),
                                      weights, tree, block)
            spans[spanning, 0] = w0
            spans[spanning, 1] = w1
            spans[spanning, 2] = w2
            spanning += 1


Walk = Six
"""A walk's state at a block's leaf: l = Σ LAZY of the leaf's ancestors, s = the prefix sum of the subtrees
left of its path (see `_walk_to_block`)."""


@njit(cache=True, inline="always")
def _walk_to_block(target: int, node: int, lo: int, hi: int, l0: float, l1: float, l2: float, s0: float,
                   s1: float, s2: float, tree: np.ndarray, pending: np.ndarray) -> Walk:
    """The tree's walk from `node` (interval lo..hi−1) down to block `target`'s leaf, with l = Σ LAZY of the
    ancestors of `node` (itself excluded) and s = the prefix sum gathered so far: (l, s) at the leaf, its own
    LAZY not yet added."""
    size = tree.shape[0] // 2
    while node < size:
        l0 += tree[node, LAZY, 0]
        l1 += tree[node, LAZY, 1]
        l2 += tree[node, LAZY, 2]
        mid = (lo + hi) >> 1
        left = 2 * node
        if target >= mid:  # the whole left child lies in the prefix
            if lo <= pending[0] < mid:
                _resum_pending(pending, tree)
            s0 += tree[left, ACCUMULATED, 0] + l0 * tree[left, WEIGHT, 0]
            s1 += tree[left, ACCUMULATED, 1] + l1 * tree[left, WEIGHT, 1]
            s2 += tree[left, ACCUMULATED, 2] + l2 * tree[left, WEIGHT, 2]
            node = left + 1
            lo = mid
        else:
            node = left
            hi = mid
    return l0, l1, l2, s0, s1, s2


@njit(cache=True, inline="always")
def _pose_in_block(k: int, walk: Walk, base: np.ndarray, weights: np.ndarray, amounts: np.ndarray,
                   tree: np.ndarray, block: int) -> tuple[float, float, float]:
    """p_k = p⁰_k + Σ_{i≤k} w_i C_i from the walk's state at the leaf of k's block: the leaf's LAZY, then
    the increments of k's block up to k."""
    l0, l1, l2, s0, s1, s2 = walk
    leaf = tree.shape[0] // 2 + k // block
    l0 += tree[leaf, LAZY, 0]
    l1 += tree[leaf, LAZY, 1]
    l2 += tree[leaf, LAZY, 2]
    for i in range((k // block) * block, k + 1):
        s0 += weights[i, 0] * (amounts[i, 0] + l0)
        s1 += weights[i, 1] * (amounts[i, 1] + l1)
        s2 += weights[i, 2] * (amounts[i, 2] + l2)
    return base[k, 0] + s0, base[k, 1] + s1, base[k, 2] + s2


@njit(cache=True, inline="always")
def _walks_to_pair(a: int, b: int, tree: np.ndarray, pending: np.ndarray, block: int) -> tuple[Walk, Walk]:
    """The walks to the blocks of a and b. The path both walks share is walked once: most constraints join
    nearby poses, whose walks part only near the leaves. Each sum adds the same terms in the same order as a
    walk of its own."""
    size = tree.shape[0] // 2
    target_a = a // block
    target_b = b // block
    node = 1
    lo = 0
    hi = size
    l0 = l1 = l2 = 0.0
    s0 = s1 = s2 = 0.0
    while node < size:
        mid = (lo + hi) >> 1
        if (target_a >= mid) != (target_b >= mid):
            break
        l0 += tree[node, LAZY, 0]
        l1 += tree[node, LAZY, 1]
        l2 += tree[node, LAZY, 2]
        left = 2 * node
        if target_a >= mid:
            if lo <= pending[0] < mid:
                _resum_pending(pending, tree)
            s0 += tree[left, ACCUMULATED, 0] + l0 * tree[left, WEIGHT, 0]
            s1 += tree[left, ACCUMULATED, 1] + l1 * tree[left, WEIGHT, 1]
            s2 += tree[left, ACCUMULATED, 2] + l2 * tree[left, WEIGHT, 2]
            node = left + 1
            lo = mid
        else:
            node = left
            hi = mid
    walk_a = _walk_to_block(target_a, node, lo, hi, l0, l1, l2, s0, s1, s2, tree, pending)
    walk_b = _walk_to_block(target_b, node, lo, hi, l0, l1, l2, s0, s1, s2, tree, pending)
    return walk_a, walk_b


@njit(cache=True, inline="always")
def _tree_weight(first: int, last: int, weights: np.ndarray, tree: np.ndarray,
                 block: int) -> tuple[float, float, float]:
    """Σ w_i over first..last: the increments of the end blocks, and the nodes that tile those between.
    Scalars rather than an output array: the compiler keeps them in registers across the tree's loads."""
    size = tree.shape[0] // 2
    n = weights.shape[0]
    w0 = w1 = w2 = 0.0
    first_block = first // block
    last_block = last // block
    if first_block == last_block:
        for i in range(first, last + 1):
            w0 += weights[i, 0]
            w1 += weights[i, 1]
            w2 += weights[i, 2]
        return w0, w1, w2
    for i in range(first, _block_end(first_block, block, n)):
        w0 += weights[i, 0]
        w1 += weights[i, 1]
        w2 += weights[i, 2]
    lo = first_block + size
    hi = last_block + size
    while lo ^ hi != 1:
        if lo & 1 == 0:
            w0 += tree[lo ^ 1, WEIGHT, 0]
            w1 += tree[lo ^ 1, WEIGHT, 1]
            w2 += tree[lo ^ 1, WEIGHT, 2]
        if hi & 1 == 1:
            w0 += tree[hi ^ 1, WEIGHT, 0]
            w1 += tree[hi ^ 1, WEIGHT, 1]
            w2 += tree[hi ^ 1, WEIGHT, 2]
        lo >>= 1
        hi >>= 1
    for i in range(last_block * block, last + 1):
        w0 += weights[i, 0]
        w1 += weights[i, 1]
        w2 += weights[i, 2]
    return w0, w1, w2


@njit(cache=True, inline="always")
def _apply(node: int, a0: float, a1: float, a2: float, tree: np.ndarray) -> None:
    tree[node, LAZY, 0] += a0
    tree[node, LAZY, 1] += a1
    tree[node, LAZY, 2] += a2
    tree[node, ACCUMULATED, 0] += a0 * tree[node, WEIGHT, 0]
    tree[node, ACCUMULATED, 1] += a1 * tree[node, WEIGHT, 1]
    tree[node, ACCUMULATED, 2] += a2 * tree[node, WEIGHT, 2]


@njit(cache=True, inline="always")
def _resum(node: int, tree: np.ndarray) -> None:
    for j in range(3):
        tree[node, ACCUMULATED, j] = (tree[2 * node, ACCUMULATED, j] + tree[2 * node + 1, ACCUMULATED, j]
                                      + tree[node, LAZY, j] * tree[node, WEIGHT, j])


@njit(cache=True)
def _resum_pending(pending: np.ndarray, tree: np.ndarray) -> None:
    """Re-sum the ancestors of the pending block, bottom up; no block is pending afterwards."""
    node = (pending[0] + tree.shape[0] // 2) >> 1
    while node >= 1:
        _resum(node, tree)
        node >>= 1
    pending[0] = -1


@njit(cache=True, inline="always")
def _add_to_increments(first: int, stop: int, a0: float, a1: float, a2: float, weights: np.ndarray,
                       amounts: np.ndarray, tree: np.ndarray, leaf: int) -> None:
    """C_i += (a0, a1, a2) for i in first..stop−1, all in the block of node `leaf`."""
    w0 = w1 = w2 = 0.0
    for i in range(first, stop):
        amounts[i, 0] += a0
        amounts[i, 1] += a1
        amounts[i, 2] += a2
        w0 += weights[i, 0]
        w1 += weights[i, 1]
        w2 += weights[i, 2]
    tree[leaf, ACCUMULATED, 0] += a0 * w0
    tree[leaf, ACCUMULATED, 1] += a1 * w1
    tree[leaf, ACCUMULATED, 2] += a2 * w2


@njit(cache=True, inline="always")
def _tree_add(first: int, last: int, a0: float, a1: float, a2: float, weights: np.ndarray,
              amounts: np.ndarray, tree: np.ndarray, pending: np.ndarray, block: int) -> None:
    """C_i += (a0, a1, a2) for i in first..last: the increments of the end blocks one by one, the nodes that
    tile the blocks between; then the ancestors of the end blocks are re-summed, except those of one end
    block, left pending (see `sgd_iteration_tree`)."""
    size = tree.shape[0] // 2
    n = weights.shape[0]
    first_block = first // block
    last_block = last // block
    if pending[0] >= 0 and pending[0] != first_block and pending[0] != last_block:
        _resum_pending(pending, tree)  # it may lie under a node of the range, or share ancestors with it
    left = first_block + size
    right = last_block + size
    # The ancestors of the pending end block (the last one, unless the first was pending already) stay
    # pending; the other end block's are re-summed up to the last one below where the two paths meet.
    keep_first = pending[0] == first_block
    if not keep_first:
        pending[0] = last_block
    if first_block == last_block:
        _add_to_increments(first, last + 1, a0, a1, a2, weights, amounts, tree, left)
        return
    _add_to_increments(first, _block_end(first_block, block, n), a0, a1, a2, weights, amounts, tree, left)
    _add_to_increments(last_block * block, last + 1, a0, a1, a2, weights, amounts, tree, right)
    # One climb from both end blocks: at each level the nodes that tile the range, then the re-summed side's
    # parent, which reads its two children, both final by then (later levels add to neither): the values of
    # all adds first and then all re-sums, in one loop.
    lo = left
    hi = right
    while lo ^ hi != 1:
        if lo & 1 == 0:
            _apply(lo ^ 1, a0, a1, a2, tree)
        if hi & 1 == 1:
            _apply(hi ^ 1, a0, a1, a2, tree)
        lo >>= 1
        hi >>= 1
        _resum(hi if keep_first else lo, tree)


PREFETCH_AHEAD = 8
"""Constraints ahead whose memory the tree pass asks for (`_prefetch_pose`)."""
PREFETCH_BELOW = 2048
"""Tree nodes numbered below this (the top 11 levels: 150 kB) stay in cache anyway and are not prefetched."""


@njit(cache=True, inline="always")
def _prefetch_pose(k: int, base: np.ndarray, weights: np.ndarray, amounts: np.ndarray, tree: np.ndarray,
                   block: int) -> None:
    """Ask for what the pass will read and write for pose k: its starting pose, the weights and amounts of
    its block, and the node pairs on its block's path below `PREFETCH_BELOW` (the walk reads a node and its
    left child; the sums, adds and re-sums touch both children). One hint per cache line (64 bytes: a
    block's 8 rows of 3 doubles span up to 4 lines, a pair of 9-double nodes up to 4)."""
    start = 3 * ((k // block) * block)
    prefetch(base, 3 * k)  # type: ignore[call-arg]  # a numba intrinsic: typed by numba, not mypy
    for line in (0, 8, 16, 23):
        prefetch(weights, start + line)
        prefetch(amounts, start + line)
    node = (k // block + tree.shape[0] // 2) | 1
    while node >= PREFETCH_BELOW:
        pair = 9 * (node - 1)
        for line in (0, 8, 16, 17):
            prefetch(tree, pair + line)
        node = (node >> 1) | 1


@njit(cache=True)
def sgd_iteration_tree(base: np.ndarray, edge_from: np.ndarray, edge_to: np.ndarray,
                       measurements: np.ndarray, information: np.ndarray, weights: np.ndarray,
                       amounts: np.ndarray, tree: np.ndarray, gamma: np.ndarray, t: int, block: int,
                       out: np.ndarray, base_chi2: bool, spans: np.ndarray) -> float:
    """One pass over all constraints in O(log N + block) each, from the poses `base` (left as they are);
    the new poses, θ wrapped, are written to `out` at the end (O(N)). Returns the χ² of `base` if
    `base_chi2` (else NaN): `optimizer.cost.chi2(graph, base)` to the bit, summed along the pass, which
    reads each constraint and its poses anyway (a separate χ² costs a third of a pass at 10⁶ poses, most of
    it in memory traffic, not arithmetic).

    `weights`, `tree` ((2·`tree_size`, 3, 3)) and `spans` must hold what `stiffness_tree` computed with
    `block`. `amounts` is scratch, and may be `out` itself: the last loop reads an increment's amounts
    before it writes that pose, and nothing else writes `out`.

    The ACCUMULATED of the ancestors of one block, `pending`, may be out of date: a range add re-sums them
    only when a walk reads one of them or a later add has no end in that block. Consecutive constraints
    mostly end in the same block (odometry, then loop closures to the current pose), so most re-sums up to
    the root are saved. A re-sum recomputes a node from its children and its own LAZY, and no node is read
    or added to while out of date, so every sum is the one an immediate re-sum gives: bit-identical poses.
    """
    n = base.shape[0]
    size = tree.shape[0] // 2
    tree[:, LAZY, :] = 0.0
    tree[:, ACCUMULATED, :] = 0.0
    amounts[:] = 0.0
    pending = np.full(1, -1)
    chi2 = 0.0 if base_chi2 else np.nan
    m = edge_from.shape[0]
    fetched_a = fetched_b = -1  # the blocks asked for last: consecutive constraints mostly share them
    spanning = 0
    kept_block = -1  # the block of the walk kept in `kept`
    kept = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for k in range(m):
        if k + PREFETCH_AHEAD < m:
            ahead_a = edge_from[k + PREFETCH_AHEAD] // block
            ahead_b = edge_to[k + PREFETCH_AHEAD] // block
            if ahead_a != fetched_a and ahead_a != fetched_b:
                _prefetch_pose(edge_from[k + PREFETCH_AHEAD], base, weights, amounts, tree, block)
            if ahead_b != ahead_a and ahead_b != fetched_a and ahead_b != fetched_b:
                _prefetch_pose(edge_to[k + PREFETCH_AHEAD], base, weights, amounts, tree, block)
            fetched_a = ahead_a
            fetched_b = ahead_b
        a = edge_from[k]
        b = edge_to[k]
        if base_chi2:
            chi2 = plus_edge_chi2(chi2, base, edge_from, edge_to, measurements, information, k)
        # The walk to the block of the later pose is kept: the next constraints mostly end there too (a pose's
        # odometry, then its loop closures), and it holds until an add changes what it read (see below).
        later = max(a, b) // block
        if later == kept_block:
            other = min(a, b) // block
            if other == kept_block:
                walk_other = kept
            else:  # the same terms in the same order as the shared walk of `_walks_to_pair`
                walk_other = _walk_to_block(other, 1, 0, size, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, tree, pending)
            walk_a, walk_b = (kept, walk_other) if a > b else (walk_other, kept)
        else:
            walk_a, walk_b = _walks_to_pair(a, b, tree, pending, block)
            kept = walk_b if b > a else walk_a
            kept_block = later
        ax, ay, atheta = _pose_in_block(a, walk_a, base, weights, amounts, tree, block)
        bx, by, btheta = _pose_in_block(b, walk_b, base, weights, amounts, tree, block)
        r0, r1, r2, d0, d1, d2 = _weighted_residual_one_rotation(ax, ay, atheta, bx, by, btheta,
                                                                 measurements[k], information[k])
        lo = min(a, b)
        hi = max(a, b)
        sign = 1.0 if a < b else -1.0
        if _spans_blocks(a, b, block):
            w0, w1, w2 = spans[spanning, 0], spans[spanning, 1], spans[spanning, 2]
            spanning += 1
        else:
            w0, w1, w2 = _tree_weight(lo + 1, hi, weights, tree, block)
        a0 = sign * _clamped_step(hi - lo, d0, r0, gamma[0], t) / w0
        a1 = sign * _clamped_step(hi - lo, d1, r1, gamma[1], t) / w1
        a2 = sign * _clamped_step(hi - lo, d2, r2, gamma[2], t) / w2
        _tree_add(lo + 1, hi, a0, a1, a2, weights, amounts, tree, pending, block)
        # A walk reads the LAZY of its block's ancestors and the sums of the subtrees left of its path (with
        # the pending block's ancestors re-summed first if it lies there). An add whose range starts in or
        # right of the kept block changes neither: its range covers no ancestor of that block, and it adds to
        # and re-sums nodes in or right of it; so the kept walk is what a new walk would give.
        if (lo + 1) // block < kept_block:
            kept_block = -1
    # Push every LAZY down to the blocks: C_i = amounts_i + its block's LAZY; p_i = p⁰_i + Σ_{m≤i} w_m C_m.
    for node in range(1, size):
        for j in range(3):
            tree[2 * node, LAZY, j] += tree[node, LAZY, j]
            tree[2 * node + 1, LAZY, j] += tree[node, LAZY, j]
    moved0 = moved1 = moved2 = 0.0
    for i in range(n):
        leaf = size + i // block
        moved0 += weights[i, 0] * (amounts[i, 0] + tree[leaf, LAZY, 0])
        moved1 += weights[i, 1] * (amounts[i, 1] + tree[leaf, LAZY, 1])
        moved2 += weights[i, 2] * (amounts[i, 2] + tree[leaf, LAZY, 2])
        out[i, 0] = base[i, 0] + moved0
        out[i, 1] = base[i, 1] + moved1
        out[i, 2] = wrap_scalar(base[i, 2] + moved2)
    return chi2
