"""The pose graph: N poses and M relative-pose constraints held in flat numpy arrays.

Poses are indexed 0..N-1 in trajectory order. Every constraint is kept exactly as its source states it:
`edge_from` may be larger than `edge_to` (a "reversed" edge, measured from the later pose), and its
measurement and information stay in the frame of `edge_from`. Turning such an edge around is only a
first-order equivalent (with large or anisotropic information the turned problem has another minimum), so
the cost, the optimizers and the written files all use the stored direction; the incremental state space
of Olson et al. (2006) walks the motions `edge_low`+1..`edge_high` with the sign of the direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from optimizer import se2
from optimizer.errors import GraphError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def read_only(poses: FloatArray) -> FloatArray:
    """A read-only view of `poses` (no copy), for compiled kernels that also get a graph's own (read-only)
    poses: numba compiles a kernel once per argument type, and a writable array is another type, compiled
    again on first use (seconds per kernel in a fresh cache)."""
    view = poses.view()
    view.setflags(write=False)
    return view


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """A 2D pose graph. Build it with `PoseGraph.build`, which validates and normalises the input."""

    poses: FloatArray
    """(N, 3) initial estimate x, y, θ."""
    edge_from: IntArray
    """(M,) index a of each constraint, as stored (a > b is allowed)."""
    edge_to: IntArray
    """(M,) index b of each constraint."""
    measurements: FloatArray
    """(M, 3) z_ab: the pose of b measured in the frame of a, exactly as given (θ not wrapped)."""
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
    def edge_low(self) -> IntArray:
        """(M,) the earlier pose of each constraint, min(a, b)."""
        return np.minimum(self.edge_from, self.edge_to)

    @property
    def edge_high(self) -> IntArray:
        """(M,) the later pose of each constraint, max(a, b)."""
        return np.maximum(self.edge_from, self.edge_to)

    @property
    def is_reversed(self) -> NDArray[np.bool_]:
        """Mask of the constraints stored from the later to the earlier pose."""
        return self.edge_from > self.edge_to

    @property
    def is_odometry(self) -> NDArray[np.bool_]:
        """Mask of the constraints between consecutive poses (the odometry chain), in either direction."""
        return np.abs(self.edge_to - self.edge_from) == 1

    def with_poses(self, poses: FloatArray) -> PoseGraph:
        """The same constraints around another estimate (e.g. the optimized one)."""
        poses = np.array(poses, dtype=np.float64, copy=True)
        if poses.shape != self.poses.shape:
            raise GraphError(f"expected poses of shape {self.poses.shape}, got {poses.shape}")
        return PoseGraph(poses, self.edge_from, self.edge_to, self.measurements, self.information,
                         self.vertex_ids)

    def from_pose(self, first: int) -> PoseGraph:
        """The poses from `first` on, with the constraints among them (renumbered from 0)."""
        if first == 0:
            return self
        kept = (self.edge_from >= first) & (self.edge_to >= first)
        return PoseGraph(self.poses[first:], self.edge_from[kept] - first, self.edge_to[kept] - first,
                         self.measurements[kept], self.information[kept], self.vertex_ids[first:])

    @classmethod
    def build(
        cls,
        vertex_ids: NDArray[np.integer],
        poses: FloatArray,
        edge_from_ids: NDArray[np.integer],
        edge_to_ids: NDArray[np.integer],
        measurements: FloatArray,
        information: FloatArray,
        *,
        check_information: bool = True,
    ) -> PoseGraph:
        """Validate a graph given with arbitrary (possibly sparse) vertex ids.

        - ids are remapped to 0..N-1 in increasing id order; pose angles are wrapped;
        - every constraint keeps its direction, measurement and information as given;
        - duplicate constraints are kept;
        - self-loops, unknown ids, non-finite values, information matrices that are not symmetric
          positive definite and disconnected graphs are errors (`check_information=False` skips the
          information check, for callers that have just made it themselves with better messages).
        """
        vertex_ids = _integer_ids(vertex_ids, "vertex ids")
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        edge_from_ids = _integer_ids(edge_from_ids, "constraint ends")
        edge_to_ids = _integer_ids(edge_to_ids, "constraint ends")
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

        if check_information:
            _check_information(information, edge_from_ids, edge_to_ids)
        _check_connected(len(sorted_ids), edge_from, edge_to)
        return cls(poses, edge_from.astype(np.int64), edge_to.astype(np.int64), measurements.copy(),
                   information.copy(), sorted_ids.copy())


def _integer_ids(ids: ArrayLike, what: str) -> IntArray:
    """`ids` as int64; `GraphError` for one that is not a whole number (1.7 would become 1 unnoticed)."""
    given = np.asarray(ids).reshape(-1)
    if given.dtype.kind not in "iub":
        try:
            values = given.astype(np.float64)
        except (TypeError, ValueError):
            raise GraphError(f"{what} must be integers, got {given.dtype}") from None
        whole = np.isfinite(values) & (values == np.round(values))
        if not whole.all():
            raise GraphError(f"{what} must be integers, got {given[np.argmin(whole)]!r}")
    return given.astype(np.int64)


SPD_TOLERANCE = 16.0 * np.finfo(np.float64).eps
"""An information matrix counts as positive definite when its smallest eigenvalue exceeds this fraction
of its largest: anything smaller is singular up to the rounding of the eigenvalue computation. The
INTEL graph's condition numbers (up to 2.4e11) pass comfortably."""


def not_positive_definite(information: FloatArray) -> NDArray[np.bool_]:
    """Mask of the (M, n, n) information matrices that are not symmetric positive definite."""
    if len(information) == 0:
        return np.zeros(0, dtype=bool)
    asymmetric = np.abs(information - np.swapaxes(information, 1, 2)).max(axis=(1, 2)) > (
        SPD_TOLERANCE * np.abs(information).max(axis=(1, 2)))
    eigenvalues = np.linalg.eigvalsh(information)  # ascending, batched over constraints
    return asymmetric | ~(eigenvalues[:, 0] > SPD_TOLERANCE * eigenvalues[:, -1])


def _check_information(information: FloatArray, edge_from_ids: IntArray, edge_to_ids: IntArray) -> None:
    bad = not_positive_definite(information)
    if bad.any():
        first = int(np.argmax(bad))
        eigenvalues = np.linalg.eigvalsh(0.5 * (information[first] + information[first].T))
        raise GraphError(
            f"constraint {first} ({int(edge_from_ids[first])} → {int(edge_to_ids[first])}): its information "
            "matrix is not symmetric positive definite (eigenvalues "
            f"{', '.join(f'{value:.6g}' for value in eigenvalues)})")


def reverse_constraints(measurements: FloatArray, information: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The first-order equivalent of constraints a→b stored as b→a: z' = z⁻¹, Ω' = Ad(z)ᵀ Ω Ad(z).

    Not used to solve graphs (edges are solved as stored); benchmarks use it to make reversed variants.
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
