"""TUM trajectory files: `timestamp tx ty tz qx qy qz qw`, one pose per line (the format evo reads).

Timestamps are kept as integer nanoseconds end to end: written exactly as decimal seconds with nine digits
and parsed back from the decimal text without passing through a float, because a float64 cannot hold a
nanosecond epoch stamp exactly (2⁵³ ns is only 104 days) and the evaluation pairs poses by exact stamp.
Pose numbers are written with 17 significant digits, which a float64 reads back bit for bit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
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
NS_PER_S = 10**9
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
_DECIMAL = re.compile(r"([+-]?)(\d*)(?:\.(\d*))?(?:[eE]([+-]?\d+))?")


class DataFileError(FileLineError, PipelineError):
    """An input text file could not be read (`FileLineError`: the file, and the line at fault)."""


class TrajectoryFileError(DataFileError):
    """A TUM trajectory file is missing, unreadable, empty or has a malformed line."""


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses of a TUM file in file order: `stamps_ns` (S,) int64, `positions` (S,3), `quaternions` (S,4)
    in (x, y, z, w) order as written (not renormalised). The arrays are read-only."""

    stamps_ns: IntArray
    positions: FloatArray
    quaternions: FloatArray

    def __post_init__(self) -> None:
        count = len(self.stamps_ns)
        if (
            self.stamps_ns.shape != (count,)
            or self.positions.shape != (count, 3)
            or self.quaternions.shape != (count, 4)
        ):
            raise ValueError("Trajectory needs stamps_ns (S,), positions (S,3) and quaternions (S,4)")
        for array in (self.stamps_ns, self.positions, self.quaternions):
            array.flags.writeable = False

    def __len__(self) -> int:
        return len(self.stamps_ns)

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
    stamp_ns = int(stamp_ns)
    sign = "-" if stamp_ns < 0 else ""
    seconds, nanoseconds = divmod(abs(stamp_ns), NS_PER_S)
    return f"{sign}{seconds}.{nanoseconds:09d}"


def parse_stamp_ns(text: str) -> int:
    """Integer nanoseconds of a decimal number of seconds ("90.239599", "1.3e9", "-0.5"), computed on the
    digits, never through a float. Digits beyond the nanosecond round to the nearest (ties to even), as
    for files written from float seconds. Raises ValueError on anything else or outside int64."""
    match = _DECIMAL.fullmatch(text)
    if match is None or not (match[2] or match[3]):
        raise ValueError(f"not a decimal number of seconds: {text!r}")
    sign, whole, fraction, exponent_text = match[1], match[2], match[3] or "", match[4]
    digits = (whole + fraction).lstrip("0")
    # The value in nanoseconds is digits · 10^exponent.
    exponent = (int(exponent_text) if exponent_text else 0) + 9 - len(fraction)
    if not digits:
        return 0
    if len(digits) + exponent > 20:  # at least 10^19 ns: beyond int64, and keeps 10**exponent small
        raise ValueError(f"timestamp out of range: {text}")
    if exponent >= 0:
        value = int(digits) * 10**exponent
    elif -exponent > len(digits):  # below 0.1 ns
        value = 0
    else:
        quotient, remainder = divmod(int(digits), 10**-exponent)
        half = 10**-exponent // 2  # 10^k is even for k ≥ 1, so exactly half is remainder == half
        value = quotient + (remainder > half or (remainder == half and quotient % 2 == 1))
    value = -value if sign == "-" else value
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
        rows = np.zeros((len(poses), 7))
        rows[:, :2] = poses[:, :2]
        half = 0.5 * poses[:, 2]
        rows[:, 5] = np.sin(half)
        rows[:, 6] = np.cos(half)
        return rows
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


def read_data_lines(path: Path, error: type[DataFileError]) -> list[tuple[int, list[str]]]:
    """The non-blank lines of a text file split on whitespace, with their 1-based numbers; `#` starts a
    comment (whole-line or trailing). Raises `error` naming the file when it cannot be read."""
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
    rows = []
    # split("\n"), not splitlines(): line numbers must agree with editors (no splitting on \f, \x1c, …).
    for number, line in enumerate(text.split("\n"), start=1):
        fields = line.split("#", 1)[0].split()
        if fields:
            rows.append((number, fields))
    return rows


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


@dataclass(frozen=True)
class DataRows:
    """The rows of a data file: the 1-based `lines` they stand on, their stamps (R, stamp columns) in
    exact nanoseconds, and their other fields (R, value columns) as finite floats."""

    lines: IntArray
    stamps_ns: IntArray
    values: FloatArray


def read_rows(path: str | Path, error: type[DataFileError], *, stamp_columns: int,
              value_names: tuple[str, ...], layout: str, nothing: str) -> DataRows:
    """Read a whitespace-separated data file (`#` comments) whose every line holds `stamp_columns` stamps,
    then the values named `value_names`. Raises `error` naming `file:line` for a malformed line (wrong
    field count, described by `layout`; a stamp or number that does not parse or is not finite), and
    naming the file, with `nothing`, when it holds no row."""
    path = Path(path)
    lines = read_data_lines(path, error)
    if not lines:
        raise error(path, nothing)
    width = stamp_columns + len(value_names)
    stamps = np.empty((len(lines), stamp_columns), dtype=np.int64)
    values = np.empty((len(lines), len(value_names)))
    for index, (number, fields) in enumerate(lines):
        if len(fields) != width:
            raise error(path, f"expected {width} fields {layout}, found {len(fields)}", number)
        try:
            stamps[index] = [parse_stamp_ns(text) for text in fields[:stamp_columns]]
            values[index] = parse_floats(fields[stamp_columns:], value_names)
        except ValueError as exc:
            raise error(path, str(exc), number) from None
    return DataRows(np.array([number for number, _ in lines], dtype=np.int64), stamps, values)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file (space-separated `timestamp tx ty tz qx qy qz qw`, `#` comments).

    Raises `TrajectoryFileError` naming `file:line` for a malformed line (wrong field count, a number that
    does not parse or is not finite, a zero quaternion) and naming the file when it holds no pose.
    """
    rows = read_rows(path, TrajectoryFileError, stamp_columns=1,
                     value_names=("tx", "ty", "tz", "qx", "qy", "qz", "qw"),
                     layout="'timestamp tx ty tz qx qy qz qw'",
                     nothing="no poses (expected lines 'timestamp tx ty tz qx qy qz qw')")
    values = rows.values
    zero = np.flatnonzero(~np.any(values[:, 3:] != 0.0, axis=1))
    if len(zero):
        raise TrajectoryFileError(path, "the quaternion is zero", int(rows.lines[zero[0]]))
    return Trajectory(rows.stamps_ns[:, 0].copy(), values[:, :3].copy(), values[:, 3:].copy())


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
    rows = read_rows(path, TrajectoryFileError, stamp_columns=0,
                     value_names=("r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33",
                                  "tz"),
                     layout="(a 3×4 matrix)",
                     nothing="no poses (expected lines of 12 numbers: a 3×4 matrix row-major)")
    out = np.zeros((len(rows.values), 4, 4))
    out[:, 3, 3] = 1.0
    out[:, :3, :] = rows.values.reshape(-1, 3, 4)
    return out
