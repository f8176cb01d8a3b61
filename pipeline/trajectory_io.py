"""TUM trajectory files: `timestamp tx ty tz qx qy qz qw`, one pose per line (the format evo reads).

Timestamps are kept as integer nanoseconds end to end: written exactly as decimal seconds with nine digits
and parsed back from the decimal text without passing through a float, because a float64 cannot hold a
nanosecond epoch stamp exactly (2⁵³ ns is only 104 days) and the evaluation pairs poses by exact stamp.
Pose numbers are written with 17 significant digits, which a float64 reads back bit for bit.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from optimizer.errors import FileLineError
from optimizer.file_input import read_bytes_bounded
from pipeline.errors import PipelineError
from pipeline.outputs import write_text

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
# Decimal seconds, with a digit before or right after the point (the lookahead): "5.", ".5", "1.3e9".
_DECIMAL = re.compile(r"[+-]?(?=\.?\d)\d*(?:\.\d*)?(?:[eE][+-]?\d+)?")
_NANOSECOND = Decimal("1e-9")


class DataFileError(FileLineError, PipelineError):
    """An input text file could not be read (`FileLineError`: the file, and the line at fault)."""


class TrajectoryFileError(DataFileError):
    """A TUM trajectory file is missing, unreadable, empty or has a malformed line."""


@dataclass(frozen=True, eq=False)
class ReadOnlyRows:
    """Rows of a data file as arrays of equal length, one per field, made read-only; its length theirs."""

    def __post_init__(self) -> None:
        for item in dataclasses.fields(self):
            getattr(self, item.name).flags.writeable = False

    def __len__(self) -> int:
        return len(getattr(self, dataclasses.fields(self)[0].name))


@dataclass(frozen=True, eq=False)
class Trajectory(ReadOnlyRows):
    """Poses of a TUM file in file order: `stamps_ns` (S,) int64, `positions` (S,3), `quaternions` (S,4)
    in (x, y, z, w) order as written (not renormalised). The arrays are read-only."""

    stamps_ns: IntArray
    positions: FloatArray
    quaternions: FloatArray

    def planar(self) -> FloatArray:
        """(S,3) planar poses (x, y, yaw): the heading about z, in [-π, π]. The formula is the ZYX yaw
        written so that it does not depend on the quaternion's norm."""
        x, y, z, w = self.quaternions.T
        yaw = np.arctan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)
        return np.column_stack((self.positions[:, 0], self.positions[:, 1], yaw))


# ------------------------------------------------------------------------------------------------ stamps


def format_stamp_ns(stamp_ns: int) -> str:
    """Decimal seconds with exactly nine digits after the point: 1700000000123456789 ns →
    "1700000000.123456789"."""
    return f"{Decimal(int(stamp_ns)).scaleb(-9):.9f}"  # exact: 19 digits fit a decimal context's 28


def parse_stamp_ns(text: str) -> int:
    """Integer nanoseconds of a decimal number of seconds ("90.239599", "1.3e9", "-0.5"), computed on the
    digits, never through a float. Digits beyond the nanosecond round to the nearest (ties to even), as
    for files written from float seconds. Raises ValueError on anything else or outside int64."""
    if _DECIMAL.fullmatch(text) is None:  # what Decimal would also take (nan, inf, 1_000) is no stamp
        raise ValueError(f"not a decimal number of seconds: {text!r}")
    try:  # Decimal rounds exactly: the input as written, to the nanosecond
        value = int(Decimal(text).quantize(_NANOSECOND, ROUND_HALF_EVEN).scaleb(9))
    except InvalidOperation:  # more digits than a decimal context holds: far beyond int64
        raise ValueError(f"timestamp out of range: {text}") from None
    if not _INT64_MIN <= value <= _INT64_MAX:
        raise ValueError(f"timestamp out of range: {text}")
    return value


# ------------------------------------------------------------------------------------------------- write


def write_tum(path: str | Path, stamps_ns: ArrayLike, poses: ArrayLike) -> None:
    """Write a TUM trajectory: one line per pose, in the given order, under a `#` header line.

    `poses` is (S,3) planar (x, y, θ: z = 0 and a rotation about z), (S,7) (tx ty tz qx qy qz qw, written
    as given) or (S,4,4) homogeneous matrices (the rotation block turned into a unit quaternion, w ≥ 0).
    Writes `path` directly (stage it with `pipeline.outputs.staged_outputs` for an atomic replace); raises
    `OutputError` when it cannot be written, ValueError on arrays of the wrong shape or non-finite poses.
    """
    stamps = np.asarray(stamps_ns)
    if stamps.ndim != 1 or not (np.issubdtype(stamps.dtype, np.integer) or stamps.size == 0):
        raise ValueError(f"stamps_ns must be a 1-D integer array, got {stamps.dtype} {stamps.shape}")
    rows = tum_rows(poses)
    if len(rows) != len(stamps):
        raise ValueError(f"{len(stamps)} stamps but {len(rows)} poses")
    lines = [f"{format_stamp_ns(stamp)} {numbers}"
             for stamp, numbers in zip(stamps.tolist(), _number_lines(rows), strict=True)]
    write_text(Path(path), "\n".join([TUM_HEADER, *lines]) + "\n")


def _number_lines(rows: FloatArray) -> list[str]:
    """Each row's numbers, space-separated, with 17 significant digits; ValueError unless all are finite."""
    if not np.isfinite(rows).all():
        raise ValueError("poses must be finite")
    return [" ".join(f"{value:.17g}" for value in row) for row in rows.tolist()]


def tum_rows(poses: ArrayLike) -> FloatArray:
    """(S,7) rows tx ty tz qx qy qz qw of planar (S,3), TUM (S,7) or homogeneous (S,4,4) poses."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2 and poses.shape[1] == 7:
        return poses
    if poses.ndim == 2 and poses.shape[1] == 3:
        from frontends.logs.rotations import from_yaw  # lazy: the log readers take seconds to import

        return np.column_stack((poses[:, :2], np.zeros(len(poses)), from_yaw(poses[:, 2])))
    if poses.ndim == 3 and poses.shape[1:] == (4, 4):
        rows = np.empty((len(poses), 7))
        rows[:, :3] = poses[:, :3, 3]
        if len(poses):
            from scipy.spatial.transform import Rotation  # only 3D poses need it: keep the import lazy

            if not np.isfinite(poses[:, :3, :3]).all():
                raise ValueError("poses must be finite")
            quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
            rows[:, 3:] = np.where(quaternions[:, 3:] < 0.0, -quaternions, quaternions)
        return rows
    raise ValueError(f"poses must be (S,3) planar, (S,7) TUM or (S,4,4) matrices, got shape {poses.shape}")


# -------------------------------------------------------------------------------------------------- read


MAX_DATA_FILE_BYTES = 256 << 20
"""Largest trajectory or relations file read (a TUM line is under 200 bytes: over a million poses)."""


def parse_floats(fields: list[str], names: tuple[str, ...]) -> list[float]:
    """Finite floats of text fields, or ValueError naming the field at fault."""
    values = []
    for text, name in zip(fields, names, strict=True):
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{name} is not a number: {text!r}") from None
        if not np.isfinite(value):
            raise ValueError(f"{name} is not finite: {text}")
        values.append(value)
    return values


def read_rows(path: str | Path, error: type[DataFileError], *, stamp_columns: int,
              value_names: tuple[str, ...], layout: str, nothing: str,
              check: Callable[[list[float]], None] | None = None) -> tuple[IntArray, FloatArray]:
    """The stamps (R, `stamp_columns`) in exact nanoseconds and the values (R, values named `value_names`)
    as finite floats of a whitespace-separated data file, one row per non-blank line (`#` starts a
    comment, whole-line or trailing). Raises `error` naming the file when it cannot be read or, with
    `nothing`, holds no row; naming `file:line` for a malformed line: a wrong field count (described by
    `layout`), a stamp or number that does not parse or is not finite, values `check` refuses (ValueError).
    """
    path = Path(path)
    try:
        data = read_bytes_bounded(path, MAX_DATA_FILE_BYTES)
    except FileNotFoundError:
        raise error(path, "no such file") from None
    except IsADirectoryError:
        raise error(path, "is a folder, not a file") from None
    except OSError as exc:
        raise error(path, f"cannot read the file: {exc.strerror or exc}") from exc
    try:
        text = data.decode("utf-8-sig")  # tolerate a byte-order mark
    except UnicodeDecodeError as exc:
        raise error(path, "not UTF-8 text", data[: exc.start].count(b"\n") + 1) from None
    width = stamp_columns + len(value_names)
    stamps: list[list[int]] = []
    values: list[list[float]] = []
    # split("\n"), not splitlines(): line numbers must agree with editors (no splitting on \f, \x1c, …).
    for number, line in enumerate(text.split("\n"), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) != width:
            raise error(path, f"expected {width} fields {layout}, found {len(fields)}", number)
        try:
            stamps.append([parse_stamp_ns(field) for field in fields[:stamp_columns]])
            values.append(parse_floats(fields[stamp_columns:], value_names))
            if check is not None:
                check(values[-1])
        except ValueError as exc:
            raise error(path, str(exc), number) from None
    if not values:
        raise error(path, nothing)
    return np.array(stamps, dtype=np.int64), np.array(values)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file (space-separated `timestamp tx ty tz qx qy qz qw`, `#` comments).

    Raises `TrajectoryFileError` naming `file:line` for a malformed line (wrong field count, a number that
    does not parse or is not finite, a zero quaternion) and naming the file when it holds no pose.
    """
    stamps, values = read_rows(path, TrajectoryFileError, stamp_columns=1,
                               value_names=("tx", "ty", "tz", "qx", "qy", "qz", "qw"),
                               layout="'timestamp tx ty tz qx qy qz qw'",
                               nothing="no poses (expected lines 'timestamp tx ty tz qx qy qz qw')",
                               check=_nonzero_quaternion)
    return Trajectory(stamps[:, 0].copy(), values[:, :3].copy(), values[:, 3:].copy())


def _nonzero_quaternion(values: list[float]) -> None:
    """`read_tum`'s check of a row's values (tx ty tz qx qy qz qw): a zero quaternion is no rotation."""
    if not any(values[3:]):
        raise ValueError("the quaternion is zero")


def write_kitti_poses(path: str | Path, transforms: ArrayLike) -> None:
    """Write poses in the KITTI odometry format: one line per (S, 4, 4) transform, the top three rows
    row-major (r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz), no stamps and no header (what KITTI's
    devkit, evo's `evo_traj kitti` and KISS-ICP's `*_poses.txt` read). Writes `path` directly; raises
    `OutputError` when it cannot be written, ValueError on arrays of the wrong shape or non-finite poses.
    """
    transforms = np.asarray(transforms, dtype=np.float64)
    if transforms.ndim != 3 or transforms.shape[1:] != (4, 4):
        raise ValueError(f"transforms must be (S, 4, 4), got {transforms.shape}")
    if not np.isfinite(transforms).all():  # the bottom rows too, which are not written
        raise ValueError("poses must be finite")
    rows = transforms[:, :3, :].reshape(-1, 12)
    write_text(Path(path), "".join(f"{line}\n" for line in _number_lines(rows)))


def read_kitti_poses(path: str | Path) -> FloatArray:
    """(S, 4, 4) poses of a KITTI-format file (12 numbers a line, `#` comments tolerated). Raises
    `TrajectoryFileError` naming `file:line` for a malformed line, and the file when it holds no pose."""
    _, rows = read_rows(path, TrajectoryFileError, stamp_columns=0,
                        value_names=("r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32",
                                     "r33", "tz"),
                        layout="(a 3×4 matrix)",
                        nothing="no poses (expected lines of 12 numbers: a 3×4 matrix row-major)")
    out = np.zeros((len(rows), 4, 4))
    out[:, 3, 3] = 1.0
    out[:, :3, :] = rows.reshape(-1, 3, 4)
    return out
