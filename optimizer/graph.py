"""The pose graph: N poses and M relative-pose constraints held in flat numpy arrays.

Poses are indexed 0..N-1 in trajectory order. Every constraint is stored with `edge_from < edge_to`
(a < b), which is what the incremental state space of Olson et al. (2006) needs: constraint (a, b) is
satisfied by the motions a+1..b.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from optimizer import se2
from optimizer.errors import GraphError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """A 2D pose graph. Build it with `PoseGraph.build`, which validates and normalises the input."""

    poses: FloatArray
    """(N, 3) initial estimate x, y, θ."""
    edge_from: IntArray
    """(M,) index a of each constraint, always < edge_to."""
    edge_to: IntArray
    """(M,) index b of each constraint."""
    measurements: FloatArray
    """(M, 3) z_ab: the pose of b measured in the frame of a."""
    information: FloatArray
    """(M, 3, 3) symmetric positive definite information Ω_ab of each measurement (x, y, θ order)."""
    vertex_ids: IntArray
    """(N,) the ids the poses had in their source (file ids), in index order."""

    def __post_init__(self) -> None:
        for array in (self.poses, self.edge_from, self.edge_to, self.measurements, self.information,
                      self.vertex_ids):
            array.setflags(write=False)

    @property
    def num_poses(self) -> int:
        return int(self.poses.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edge_from.shape[0])

    @property
    def is_odometry(self) -> NDArray[np.bool_]:
        """Mask of the constraints between consecutive poses (the odometry chain)."""
        return self.edge_to - self.edge_from == 1

    def with_poses(self, poses: FloatArray) -> PoseGraph:
        """The same constraints around another estimate (e.g. the optimized one)."""
        poses = np.array(poses, dtype=np.float64, copy=True)
        if poses.shape != self.poses.shape:
            raise GraphError(f"expected poses of shape {self.poses.shape}, got {poses.shape}")
        return PoseGraph(poses, self.edge_from, self.edge_to, self.measurements, self.information,
                         self.vertex_ids)

    @classmethod
    def build(
        cls,
        vertex_ids: NDArray[np.integer],
        poses: FloatArray,
        edge_from_ids: NDArray[np.integer],
        edge_to_ids: NDArray[np.integer],
        measurements: FloatArray,
        information: FloatArray,
    ) -> PoseGraph:
        """Validate and normalise a graph given with arbitrary (possibly sparse) vertex ids.

        - ids are remapped to 0..N-1 in increasing id order;
        - constraints given as a > b are reversed (inverse measurement, information carried over
          through the adjoint so that the first-order cost is unchanged);
        - duplicate constraints are kept;
        - self-loops, unknown ids, non-finite values and disconnected graphs are errors.
        """
        vertex_ids = np.asarray(vertex_ids, dtype=np.int64).reshape(-1)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        edge_from_ids = np.asarray(edge_from_ids, dtype=np.int64).reshape(-1)
        edge_to_ids = np.asarray(edge_to_ids, dtype=np.int64).reshape(-1)
        measurements = np.asarray(measurements, dtype=np.float64).reshape(-1, 3)
        information = np.asarray(information, dtype=np.float64).reshape(-1, 3, 3)
        if len(vertex_ids) != len(poses):
            raise GraphError(f"{len(vertex_ids)} vertex ids for {len(poses)} poses")
        if not (len(edge_from_ids) == len(edge_to_ids) == len(measurements) == len(information)):
            raise GraphError("constraint arrays differ in length")
        if len(vertex_ids) == 0:
            raise GraphError("the graph has no poses")
        for name, values in (("poses", poses), ("measurements", measurements), ("information", information)):
            if not np.all(np.isfinite(values)):
                raise GraphError(f"non-finite values in {name}")

        order = np.argsort(vertex_ids, kind="stable")
        sorted_ids = vertex_ids[order]
        if np.any(sorted_ids[1:] == sorted_ids[:-1]):
            raise GraphError("duplicate vertex ids")
        poses = poses[order].copy()
        poses[:, 2] = se2.wrap_angle(poses[:, 2])
        edge_from = _index_of(sorted_ids, edge_from_ids)
        edge_to = _index_of(sorted_ids, edge_to_ids)
        if np.any(edge_from == edge_to):
            first = int(np.flatnonzero(edge_from == edge_to)[0])
            raise GraphError(f"constraint {first} joins pose {edge_from_ids[first]} to itself")

        measurements = measurements.copy()
        information = information.copy()
        reversed_ = edge_from > edge_to
        if np.any(reversed_):
            measurements[reversed_], information[reversed_] = reverse_constraints(
                measurements[reversed_], information[reversed_]
            )
            edge_from, edge_to = (np.where(reversed_, edge_to, edge_from),
                                  np.where(reversed_, edge_from, edge_to))
        measurements[:, 2] = se2.wrap_angle(measurements[:, 2])
        _check_connected(len(sorted_ids), edge_from, edge_to)
        return cls(poses, edge_from.astype(np.int64), edge_to.astype(np.int64), measurements,
                   information, sorted_ids.copy())


def reverse_constraints(measurements: FloatArray, information: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Turn constraints a→b into b→a: z' = z⁻¹ and Ω' = Ad(z)ᵀ Ω Ad(z).

    With e = t2v(z⁻¹·a⁻¹·b), the reversed error is e' ≈ −Ad(z)·e to first order, so
    e'ᵀ Ω' e' = eᵀ Ω e requires Ω' = Ad(z)⁻ᵀ Ω Ad(z)⁻¹ = Ad(z⁻¹)ᵀ Ω Ad(z⁻¹).
    """
    inverse = se2.inverse(measurements)
    ad_inv = se2.adjoint(inverse)
    info = np.einsum("mji,mjk,mkl->mil", ad_inv, information, ad_inv)
    info = 0.5 * (info + np.swapaxes(info, 1, 2))
    return inverse, info


def _index_of(sorted_ids: IntArray, ids: IntArray) -> IntArray:
    index = np.searchsorted(sorted_ids, ids)
    index = np.minimum(index, len(sorted_ids) - 1)
    unknown = sorted_ids[index] != ids
    if np.any(unknown):
        raise GraphError(f"constraint refers to unknown pose id {int(ids[np.flatnonzero(unknown)[0]])}")
    return index.astype(np.int64)


def _check_connected(num_poses: int, edge_from: IntArray, edge_to: IntArray) -> None:
    adjacency = coo_matrix(
        (np.ones(len(edge_from), dtype=np.int8), (edge_from, edge_to)), shape=(num_poses, num_poses)
    )
    count, labels = connected_components(adjacency, directed=False)
    if count > 1:
        sizes = np.sort(np.bincount(labels))[::-1]
        shown = ", ".join(str(int(s)) for s in sizes[:10]) + (", ..." if count > 10 else "")
        raise GraphError(f"the graph is not connected: {count} components of sizes {shown}")
