"""The normal equations as a full block-sparse (BSR, 3×3 blocks) matrix, for the algebraic-multigrid solver.

`optimizer.normal_equations` keeps the upper triangle in scalar CSC form, what an LDLᵀ factorisation reads.
Multigrid wants the whole symmetric matrix and works best on its natural 3×3 blocks (one per pair of
poses: aggregation then keeps a pose's x, y and θ together). Over the free poses 1..N−1 (pose 0 is the
anchor) block row r is pose r+1; a block is stored for every pose (diagonal) and for both orders of every
pair of poses that a constraint links. Memory: 72 bytes per block, about 5·10⁶ blocks at 10⁶ poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from optimizer.graph import PoseGraph
from optimizer.normal_equations import linearise_edge_into_gradient

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Int32Array = NDArray[np.int32]

NO_BLOCK = -1
"""Position of a block that is not stored: one of the edge's poses is the anchor."""


@dataclass(frozen=True, eq=False)
class BlockPattern:
    """The fixed block sparsity of H over the free poses, in CSR order (block rows, columns ascending)."""

    free: int
    """Number of free poses (block rows)."""
    indptr: Int32Array
    indices: Int32Array
    diagonal_block: IntArray
    """(free,) position of each block row's diagonal block."""
    edge_blocks: IntArray
    """(M, 4) positions of the blocks (a, a), (a, b), (b, a), (b, b) of each edge; `NO_BLOCK` where a
    pose is the anchor (and for (a, b), (b, a) when a = b)."""

    @classmethod
    def of(cls, graph: PoseGraph) -> BlockPattern:
        free = graph.num_poses - 1
        if free < 1:
            raise ValueError("a block pattern needs at least one free pose")
        row_a = graph.edge_from.astype(np.int64) - 1
        row_b = graph.edge_to.astype(np.int64) - 1
        diagonal = np.arange(free, dtype=np.int64)
        pair = (row_a >= 0) & (row_b >= 0) & (row_a != row_b)
        # Sorted row-major keys are the CSR order; the anchor's blocks share the dummy key −1, dropped.
        keys = np.concatenate([
            diagonal * free + diagonal,
            np.where(row_a >= 0, row_a * free + row_a, -1),
            np.where(pair, row_a * free + row_b, -1),
            np.where(pair, row_b * free + row_a, -1),
            np.where(row_b >= 0, row_b * free + row_b, -1),
        ])
        unique, inverse = np.unique(keys, return_inverse=True)
        inverse = inverse.reshape(-1)
        offset = 1 if unique[0] == -1 else 0
        unique = unique[offset:]
        position = np.where(keys == -1, NO_BLOCK, inverse - offset)
        del keys, inverse
        counts = np.bincount(unique // free, minlength=free)
        indptr = np.zeros(free + 1, dtype=np.int32)
        np.cumsum(counts, out=indptr[1:])
        edges = graph.num_edges
        edge_blocks = np.ascontiguousarray(position[free:].reshape(4, edges).T)
        return cls(free, indptr, (unique % free).astype(np.int32), position[:free].copy(), edge_blocks)

    @property
    def num_blocks(self) -> int:
        return int(self.indptr[-1])


@njit(cache=True)
def assemble_blocks(poses: FloatArray, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
                    information: FloatArray, edge_blocks: IntArray, blocks: FloatArray,
                    gradient: FloatArray) -> None:
    """Fill `blocks` ((num_blocks, 3, 3): H = Σ JᵀΩJ block by block) and `gradient` (g = Σ JᵀΩe)."""
    blocks[:] = 0.0
    gradient[:] = 0.0
    e = np.empty(3)
    jac_a = np.empty((3, 3))
    jac_b = np.empty((3, 3))
    omega_a = np.empty((3, 3))
    omega_b = np.empty((3, 3))
    for k in range(edge_from.shape[0]):
        a, b = edge_from[k], edge_to[k]
        linearise_edge_into_gradient(poses, a, b, measurements[k], information[k], e, jac_a, jac_b, omega_a,
                                     omega_b, gradient)
        _add_block(blocks, edge_blocks[k, 0], jac_a, omega_a)
        _add_block(blocks, edge_blocks[k, 1], jac_a, omega_b)
        _add_block(blocks, edge_blocks[k, 2], jac_b, omega_a)
        _add_block(blocks, edge_blocks[k, 3], jac_b, omega_b)


@njit(cache=True, inline="always")
def _add_block(blocks: FloatArray, position: int, jac_row: FloatArray, omega_jac_column: FloatArray) -> None:
    """blocks[position] += J_rowᵀ (Ω J_column)."""
    if position < 0:
        return
    for p in range(3):
        for q in range(3):
            blocks[position, p, q] += (jac_row[0, p] * omega_jac_column[0, q]
                                       + jac_row[1, p] * omega_jac_column[1, q]
                                       + jac_row[2, p] * omega_jac_column[2, q])


@njit(cache=True)
def block_diagonal(blocks: FloatArray, diagonal_block: IntArray) -> FloatArray:
    """diag(H) over the free variables."""
    out = np.empty(3 * diagonal_block.shape[0])
    for row in range(diagonal_block.shape[0]):
        for p in range(3):
            out[3 * row + p] = blocks[diagonal_block[row], p, p]
    return out


@njit(cache=True)
def scale_blocks(blocks: FloatArray, indptr: Int32Array, indices: Int32Array, scale: FloatArray) -> None:
    """In place: blocks of H become those of S·H·S, S = diag(scale)."""
    for row in range(indptr.shape[0] - 1):
        for position in range(indptr[row], indptr[row + 1]):
            column = indices[position]
            for p in range(3):
                for q in range(3):
                    blocks[position, p, q] *= scale[3 * row + p] * scale[3 * column + q]


@njit(cache=True)
def add_to_diagonal(blocks: FloatArray, diagonal_block: IntArray, amount: float) -> None:
    """In place: blocks of A become those of A + amount·I."""
    for row in range(diagonal_block.shape[0]):
        for p in range(3):
            blocks[diagonal_block[row], p, p] += amount
