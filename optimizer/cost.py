"""The χ² cost of a pose graph in g2o's convention: Σ eᵀ Ω e with e = t2v(z⁻¹ · (x_a⁻¹ · x_b)), θ wrapped."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from optimizer import se2
from optimizer.graph import PoseGraph

FloatArray = NDArray[np.float64]


def edge_errors(graph: PoseGraph, poses: FloatArray | None = None) -> FloatArray:
    """(M, 3) error vectors of every constraint at `poses` (default: the graph's estimate)."""
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    predicted = se2.relative(poses[graph.edge_from], poses[graph.edge_to])
    return se2.relative(graph.measurements, predicted)


def edge_chi2(graph: PoseGraph, poses: FloatArray | None = None) -> FloatArray:
    """(M,) χ² contribution eᵀ Ω e of every constraint."""
    errors = edge_errors(graph, poses)
    return np.einsum("mi,mij,mj->m", errors, graph.information, errors)


CHUNK_EDGES = 1 << 16
"""Edges per block when summing χ²: bounds the temporaries on million-edge graphs."""


def chi2(graph: PoseGraph, poses: FloatArray | None = None) -> float:
    """Total χ² of the graph at `poses` (default: the graph's estimate)."""
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    total = 0.0
    for start in range(0, graph.num_edges, CHUNK_EDGES):
        block = slice(start, start + CHUNK_EDGES)
        predicted = se2.relative(poses[graph.edge_from[block]], poses[graph.edge_to[block]])
        errors = se2.relative(graph.measurements[block], predicted)
        total += float(np.einsum("mi,mij,mj->", errors, graph.information[block], errors))
    return total
