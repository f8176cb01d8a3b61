"""The relations metric of Kümmerle et al. 2009, "On measuring the accuracy of SLAM algorithms".

A relations file lists ground-truth relative motions δ*_ij between pairs of sensor stamps (Freiburg format,
`t1 t2 x y z roll pitch yaw` per line: the pose at t2 in the frame of the pose at t1). A trajectory is
judged by how well its own relative motions δ_ij = x_i⁻¹·x_j agree: per relation the error e = δ*⁻¹·δ, its
translational part |e_t| in metres and rotational part |e_θ| in degrees, then the mean and standard
deviation of these absolute errors and of their squares, as the paper's tables report them.

Comparing relative motions rather than absolute poses makes the score independent of the map's frame and
charges each error only to the relations that span it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from optimizer import se2
from pipeline.errors import PipelineError
from pipeline.trajectory_io import DataFileError, ReadOnlyRows, read_rows, read_tum

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_TOLERANCE_NS = 1_000_000
"""How far (1 ms) a relation stamp may be from the nearest trajectory stamp and still pair with it."""

_PLANAR_TOLERANCE = 1e-9
"""z, roll and pitch of a 2D relation are 0; anything beyond rounding means a 3D file."""


class RelationsFileError(DataFileError):
    """A relations file is missing, unreadable, empty or has a malformed line."""


class EvaluationError(PipelineError):
    """A trajectory cannot be evaluated against the relations (e.g. no relation pairs with its stamps)."""


@dataclass(frozen=True, eq=False)
class Relations(ReadOnlyRows):
    """Ground-truth relative motions: `motion[k]` (x, y, θ) is the pose at `second_ns[k]` in the frame of
    the pose at `first_ns[k]`. Arrays (R,) int64 and (R,3), in file order, read-only."""

    first_ns: IntArray
    second_ns: IntArray
    motion: FloatArray


@dataclass(frozen=True, eq=False)
class RelationsResult:
    """The relations metric of one trajectory.

    `count` relations paired with trajectory poses and were scored; `unmatched` had no pose within the
    tolerance at one or both ends. Means and standard deviations (population, ddof = 0) are over the
    scored relations: of |e_t| (m) and |e_θ| (deg), and of their squares (m², deg²).
    `matched` (R,) marks the scored relations in file order; `translation_errors` and
    `rotation_errors_deg` (count,) are their errors, in the same order.
    """

    count: int
    unmatched: int
    translation_mean: float
    translation_std: float
    rotation_mean_deg: float
    rotation_std_deg: float
    translation_squared_mean: float
    translation_squared_std: float
    rotation_squared_mean: float
    rotation_squared_std: float
    matched: NDArray[np.bool_]
    translation_errors: FloatArray
    rotation_errors_deg: FloatArray

    def summary(self) -> dict[str, Any]:
        """The scalar fields, for JSON."""
        return {name: value for name, value in vars(self).items() if not isinstance(value, np.ndarray)}


def read_relations(path: str | Path) -> Relations:
    """Read a Freiburg relations file (`t1 t2 x y z roll pitch yaw`, whitespace-separated, `#` comments);
    stamps are parsed exactly to nanoseconds. Only planar relations are accepted (z = roll = pitch = 0):
    the metric here is the 2D one. Raises `RelationsFileError` naming `file:line`, or the file when empty.
    """
    stamps, values = read_rows(path, RelationsFileError, stamp_columns=2,
                               value_names=("x", "y", "z", "roll", "pitch", "yaw"),
                               layout="'t1 t2 x y z roll pitch yaw'",
                               nothing="no relations (expected lines 't1 t2 x y z roll pitch yaw')",
                               check=_planar)
    return Relations(stamps[:, 0].copy(), stamps[:, 1].copy(), values[:, [0, 1, 5]].copy())


def _planar(values: list[float]) -> None:
    """`read_relations`' check of a row's values (x y z roll pitch yaw): z, roll and pitch are 0."""
    if any(abs(value) > _PLANAR_TOLERANCE for value in values[2:5]):
        raise ValueError("a 3D relation (z, roll or pitch not 0): only planar relations are supported")


def relations_error(
    stamps_ns: ArrayLike,
    planar_poses: ArrayLike,
    relations: Relations,
    *,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
) -> RelationsResult:
    """Score planar poses (S,3) at `stamps_ns` (S,) against ground-truth relations.

    Each relation stamp pairs with the trajectory pose of the same stamp, else with the nearest one within
    `tolerance_ns` (inclusive; the earlier on a tie; the first in file order among equal stamps). Relations
    with an end that pairs with nothing are counted in `unmatched`. Raises `EvaluationError` when no
    relation pairs at all, ValueError on arrays of the wrong shape.
    """
    stamps = np.asarray(stamps_ns)
    poses = np.asarray(planar_poses, dtype=np.float64)
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise ValueError(f"stamps_ns must be a 1-D integer array, got {stamps.dtype} {stamps.shape}")
    if poses.shape != (len(stamps), 3):
        raise ValueError(f"planar_poses must be ({len(stamps)}, 3), one per stamp, got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("planar_poses must be finite")
    if tolerance_ns < 0:
        raise ValueError("tolerance_ns must be non-negative")
    if len(relations) == 0:
        raise EvaluationError("no relations to evaluate against")
    stamps = stamps.astype(np.int64)
    first = nearest_pose(stamps, relations.first_ns, tolerance_ns)
    second = nearest_pose(stamps, relations.second_ns, tolerance_ns)
    matched = (first >= 0) & (second >= 0)
    count = int(matched.sum())
    if count == 0:
        span = f"{stamps.min() * 1e-9:.3f}..{stamps.max() * 1e-9:.3f} s" if len(stamps) else "no poses"
        raise EvaluationError(
            f"none of the {len(relations)} relations pairs with a trajectory pose within "
            f"{tolerance_ns * 1e-6:g} ms (relations span {relations.first_ns.min() * 1e-9:.3f}.."
            f"{relations.second_ns.max() * 1e-9:.3f} s, the trajectory {span})"
        )
    estimated = se2.relative(poses[first[matched]], poses[second[matched]])
    error = se2.relative(relations.motion[matched], estimated)  # e = δ*⁻¹·δ
    translation = np.hypot(error[:, 0], error[:, 1])
    rotation = np.degrees(np.abs(se2.wrap_angle(error[:, 2])))
    return RelationsResult(
        count=count,
        unmatched=len(relations) - count,
        translation_mean=float(translation.mean()),
        translation_std=float(translation.std()),
        rotation_mean_deg=float(rotation.mean()),
        rotation_std_deg=float(rotation.std()),
        translation_squared_mean=float((translation**2).mean()),
        translation_squared_std=float((translation**2).std()),
        rotation_squared_mean=float((rotation**2).mean()),
        rotation_squared_std=float((rotation**2).std()),
        matched=matched,
        translation_errors=translation,
        rotation_errors_deg=rotation,
    )


def nearest_pose(stamps_ns: IntArray, wanted_ns: IntArray, tolerance_ns: int) -> IntArray:
    """Index into `stamps_ns` (any order, repeats allowed) of the nearest stamp to each wanted stamp, −1
    when none is within `tolerance_ns`. Ties go to the earlier stamp; equal stamps to the first in order."""
    if len(stamps_ns) == 0:
        return np.full(len(wanted_ns), -1, dtype=np.int64)
    order = np.argsort(stamps_ns, kind="stable")
    ordered = stamps_ns[order]
    after = np.searchsorted(ordered, wanted_ns, side="left")  # first stamp ≥ wanted
    # The last of a run of equal stamps sits just before `after`: step back to the run's first one below.
    before = np.clip(after - 1, 0, len(ordered) - 1)
    after = np.clip(after, 0, len(ordered) - 1)
    before = np.searchsorted(ordered, ordered[before], side="left")
    gap_before = _distance(wanted_ns, ordered[before])
    gap_after = _distance(ordered[after], wanted_ns)
    use_after = gap_after < gap_before
    chosen = np.where(use_after, after, before)
    gap = np.where(use_after, gap_after, gap_before)
    return np.where(gap <= tolerance_ns, order[chosen], -1)


def _distance(a: IntArray, b: IntArray) -> IntArray:
    """|a − b| of int64 stamps, the largest int64 where it does not fit (stamps centuries apart would
    otherwise wrap round to a few nanoseconds)."""
    with np.errstate(over="ignore"):
        difference = a - b
    overflowed = ((a ^ b) & (a ^ difference)) < 0
    distance = np.abs(difference)
    return np.where(overflowed | (distance < 0), np.iinfo(np.int64).max, distance)


def evaluate_files(
    trajectory_path: str | Path, relations_path: str | Path, *, tolerance_ns: int = DEFAULT_TOLERANCE_NS
) -> RelationsResult:
    """`relations_error` of a TUM trajectory file against a relations file (its poses taken as planar); an
    `EvaluationError` names both files."""
    trajectory = read_tum(trajectory_path)
    relations = read_relations(relations_path)
    try:
        return relations_error(trajectory.stamps_ns, trajectory.planar(), relations,
                               tolerance_ns=tolerance_ns)
    except EvaluationError as error:
        raise EvaluationError(f"{trajectory_path} against {relations_path}: {error}") from None
