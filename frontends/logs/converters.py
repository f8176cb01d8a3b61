"""One converter per message kind: decoded fields → `Scan2D`, `Cloud3D`, `OdometryPose`, `Transform`.

ROS messages arrive as the field tuples of `decoding.ros_wire` (the same for CDR and ROS 1 payloads);
Foxglove messages as protobuf messages or JSON objects read through `decoding.foxglove`.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.errors import LogWarning
from frontends.logs import rotations
from frontends.logs.decoding import foxglove
from frontends.logs.decoding.ros_wire import (
    LaserScanFields,
    OdometryFields,
    PointCloud2Fields,
    TransformStampedFields,
    WireError,
)
from frontends.logs.types import Cloud3D, OdometryPose, Scan2D, Transform

# sensor_msgs/PointField datatypes and foxglove.PackedElementField numeric types → numpy type codes.
ROS_POINT_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FOXGLOVE_POINT_TYPES = {1: "u1", 2: "i1", 3: "u2", 4: "i2", 5: "u4", 6: "i4", 7: "f4", 8: "f8"}
_FOXGLOVE_TYPE_NAMES = {
    "UINT8": 1,
    "INT8": 2,
    "UINT16": 3,
    "INT16": 4,
    "UINT32": 5,
    "INT32": 6,
    "FLOAT32": 7,
    "FLOAT64": 8,
}

# Per-point time fields of common drivers, in order of preference: Velodyne `time` (float32 s relative),
# Ouster `t` (uint32 ns relative), Hesai/Robosense `timestamp` (float64 s absolute), Livox `offset_time`.
POINT_TIME_FIELDS = ("time", "t", "timestamp", "time_stamp", "offset_time")


MAX_BEAMS = 32_768
"""Most beams one scan may have: planar lasers have a few hundred to a few thousand. More is a damaged
message, refused before any per-beam work (a 2-million-beam scan would take gigabytes downstream)."""
MAX_CLOUD_COORDINATE = 10_000.0
"""Cloud points farther than this along any axis (m) are dropped: no lidar sees them, and such values
would overflow the voxel keys of the 3D matching."""
_FULL_TURN = 2.0 * math.pi * (1.0 + 1e-3)
MAX_SWEEP_SECONDS = 1.0
"""A LaserScan whose beams would take longer than this (s) from first to last is read without beam times:
planar lasers sweep 5–50 times a second, so such a `time_increment` is a unit or driver error, and
motion-compensating with it would bend the scan instead of straightening it."""


@dataclass(frozen=True, slots=True)
class RangeLimits:
    """Extra limits on valid ranges, on top of a LaserScan's own [range_min, range_max] (inclusive)."""

    minimum: float = 0.0
    maximum: float = math.inf


class BearingTable:
    """Bearings and their cos/sin per beam layout: scans of one sensor share them, so compute them once."""

    def __init__(self) -> None:
        self._tables: dict[tuple[int, float, float], tuple[NDArray[np.float64], ...]] = {}

    def get(self, count: int, first: float, increment: float) -> tuple[NDArray[np.float64], ...]:
        key = (count, first, increment)
        table: tuple[NDArray[np.float64], ...] | None = self._tables.get(key)
        if table is None:
            if len(self._tables) > 64:  # a sensor whose layout changes every scan: don't grow without bound
                self._tables.clear()
            bearings = first + np.arange(count, dtype=np.float64) * increment
            table = (bearings, np.cos(bearings, dtype=np.float64), np.sin(bearings, dtype=np.float64))
            self._tables[key] = table
        return table


@njit(cache=True)
def _keep_beams(
    ranges: NDArray[np.float64],
    bearings: NDArray[np.float64],
    cos: NDArray[np.float64],
    sin: NDArray[np.float64],
    low: float,
    high: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(points, ranges, bearings) of the beams with a finite range in [low, high]. One compiled pass: a
    handful of numpy calls on a few hundred beams cost several times more in call overhead."""
    count = 0
    for i in range(ranges.shape[0]):
        r = ranges[i]
        if r >= low and r <= high and np.isfinite(r):
            count += 1
    points = np.empty((count, 2))
    kept = np.empty(count)
    kept_bearings = np.empty(count)
    j = 0
    for i in range(ranges.shape[0]):
        r = ranges[i]
        if r >= low and r <= high and np.isfinite(r):
            value = np.float64(r)
            kept[j] = value
            kept_bearings[j] = bearings[i]
            points[j, 0] = value * cos[i]
            points[j, 1] = value * sin[i]
            j += 1
    return points, kept, kept_bearings


def _scan(
    stamp_ns: int,
    log_time_ns: int,
    frame_id: str,
    ranges: NDArray[np.floating[Any]],
    table: tuple[NDArray[np.float64], ...],
    low: float,
    high: float,
) -> Scan2D:
    # One type for `_keep_beams` whatever the message held (float32 or float64, either byte order, strided;
    # limits of int or float): each other type was compiled again, seconds on a cold cache. Exact: float32
    # widens to float64 losslessly and the kernel compared and widened in float64 anyway.
    contiguous: NDArray[np.float64] = np.ascontiguousarray(ranges, dtype=np.float64)
    bearings, cos, sin = table
    points, kept, kept_bearings = _keep_beams(contiguous, bearings, cos, sin, float(low), float(high))
    return Scan2D(stamp_ns, log_time_ns, frame_id, points, kept, kept_bearings, ranges.shape[0])


def _check_beam_count(count: int) -> None:
    if count > MAX_BEAMS:
        raise WireError(f"scan has {count} beams, more than the {MAX_BEAMS} any planar laser has")


def _beam_layout_valid(count: int, first: float, increment: float) -> bool:
    """Whether beams at first + i·increment are a real sweep: finite angles, distinct beams, at most
    a full turn (a negative increment is a laser sweeping clockwise, e.g. mounted upside down)."""
    if count <= 1:
        return math.isfinite(first) and math.isfinite(increment)
    return (
        math.isfinite(first)
        and math.isfinite(increment)
        and increment != 0.0
        and abs(increment) * (count - 1) <= _FULL_TURN
    )


def _unusable(stamp_ns: int, log_time_ns: int, frame_id: str, count: int) -> Scan2D:
    """A scan whose beams cannot be placed: no valid return (the SLAM input skips and counts it)."""
    empty = np.empty(0)
    return Scan2D(stamp_ns, log_time_ns, frame_id, np.empty((0, 2)), empty, empty, count)


def ros_laser_scan(
    message: LaserScanFields, log_time_ns: int, limits: RangeLimits, bearings: BearingTable
) -> Scan2D:
    """sensor_msgs/LaserScan: beam i at angle_min + i·angle_increment; valid in [range_min, range_max].
    A scan whose angles are not a real sweep (NaN, infinite, zero or more than a turn) has no valid beam;
    ranges are never negative whatever range_min says."""
    count = message.ranges.shape[0]
    _check_beam_count(count)
    if not _beam_layout_valid(count, message.angle_min, message.angle_increment):
        return _unusable(message.stamp_ns, log_time_ns, message.frame_id, count)
    range_min = message.range_min if math.isfinite(message.range_min) else 0.0
    range_max = message.range_max if not math.isnan(message.range_max) else math.inf
    table = bearings.get(count, message.angle_min, message.angle_increment)
    low = max(range_min, limits.minimum, 0.0)
    high = min(range_max, limits.maximum)
    scan = _scan(message.stamp_ns, log_time_ns, message.frame_id, message.ranges, table, low, high)
    time_increment = message.time_increment
    if time_increment == 0.0 or not abs(time_increment) * (count - 1) <= MAX_SWEEP_SECONDS:
        return scan  # no beam times given (0), or none a laser could have (NaN, infinite, too slow)
    # Beam i was taken i·time_increment after the stamp (the first beam's time, by the message's
    # definition); the kept beams' bearings say which i they were.
    beam_index = np.rint((scan.bearings - message.angle_min) / message.angle_increment)
    return dataclasses.replace(scan, point_times=beam_index * time_increment)


def foxglove_laser_scan(
    message: Any, log_time_ns: int, limits: RangeLimits, bearings: BearingTable
) -> Scan2D:
    """foxglove.LaserScan: beams evenly from start_angle to end_angle (inclusive); no range limits of its
    own, so only non-finite, negative and out-of-`limits` ranges are dropped. A non-identity `pose` (of the
    scan origin in frame_id) is applied to the points."""
    raw_ranges = foxglove.field(message, "ranges", ())
    _check_beam_count(len(raw_ranges))
    ranges = np.asarray(raw_ranges, dtype=np.float64).reshape(-1)
    count = ranges.shape[0]
    start = float(foxglove.field(message, "start_angle", 0.0))
    end = float(foxglove.field(message, "end_angle", 0.0))
    increment = (end - start) / (count - 1) if count > 1 else 0.0
    stamp_ns = foxglove.stamp_ns(foxglove.field(message, "timestamp"))
    frame_id = str(foxglove.field(message, "frame_id", ""))
    if not _beam_layout_valid(count, start, increment):
        return _unusable(stamp_ns, log_time_ns, frame_id, count)
    table = bearings.get(count, start, increment)
    scan = _scan(stamp_ns, log_time_ns, frame_id, ranges, table, max(limits.minimum, 0.0), limits.maximum)
    position, orientation = foxglove.pose(foxglove.field(message, "pose"))
    if _is_identity(position, orientation):
        return scan
    xyz = np.zeros((scan.points.shape[0], 3))
    xyz[:, :2] = scan.points
    placed = rotations.rotate(_unit_quaternion(orientation), xyz) + np.asarray(position)
    return Scan2D(
        scan.stamp_ns,
        log_time_ns,
        scan.frame_id,
        np.ascontiguousarray(placed[:, :2]),
        scan.ranges,
        scan.bearings,
        scan.beam_count,
    )


MAX_STAMP_TO_SWEEP_S = 1.0
MAX_STAMP_TO_SWEEP_SWEEPS = 10.0
"""A cloud's stamp lies within a second and within ten sweep lengths of its points' times (sensors stamp a
sweep at its start, its end or when they publish it); times farther off are in another unit or on another
clock, and deskewing by them would carry the cloud's pose that far along the motion."""


def _point_times(raw: NDArray[Any], stamp_ns: int, field: str) -> NDArray[np.float64] | None:
    """A time field → seconds relative to the stamp. Integer fields are nanoseconds; float fields seconds,
    else nanoseconds (livox_ros_driver2's float64 `timestamp`), whichever puts the stamp within reach of
    the times (`MAX_STAMP_TO_SWEEP_S`). Times nearer the stamp than zero are absolute (since the epoch, e.g.
    Hesai) and get it subtracted; the others are already relative (Velodyne, Ouster, Livox). None, and a
    warning, when no reading fits the stamp: the cloud is read as if it had no times."""
    integer = raw.dtype.kind in "iu"
    sample = raw[:: max(1, raw.shape[0] // 64)].astype(np.float64)
    reference = float(np.nanmedian(sample)) if sample.size and not np.isnan(sample).all() else 0.0
    for seconds_per_unit in (1e-9,) if integer else (1.0, 1e-9):
        stamp = stamp_ns * 1e-9 / seconds_per_unit
        absolute = abs(reference - stamp) < abs(reference)
        if integer:
            nanoseconds = (raw.astype(np.int64) - stamp_ns) if absolute else raw.astype(np.int64)
            times = nanoseconds.astype(np.float64) * 1e-9
        else:
            values = raw.astype(np.float64)
            times = (values - stamp if absolute else values) * seconds_per_unit
        finite = times[np.isfinite(times)]
        if not finite.size:
            return times
        first, last = float(finite.min()), float(finite.max())
        reach = min(MAX_STAMP_TO_SWEEP_S, MAX_STAMP_TO_SWEEP_SWEEPS * (last - first))
        if first == last or first - reach <= 0.0 <= last + reach:  # (no span: no deskewing by them anyway)
            return times
    units = "" if integer else ", read as seconds or as nanoseconds"
    warnings.warn(f"cloud point times ({field}) lie too far from their cloud's stamp{units} (more than "
                  f"{MAX_STAMP_TO_SWEEP_S:g} s or {MAX_STAMP_TO_SWEEP_SWEEPS:g} sweeps; another clock, or a "
                  "stamp missing?): those clouds were read without them", LogWarning, stacklevel=2)
    return None


def _cloud(
    stamp_ns: int,
    log_time_ns: int,
    frame_id: str,
    data: NDArray[np.uint8],
    layout: dict[str, tuple[str, int]],
    point_step: int,
    row_step: int,
    height: int,
    width: int,
) -> Cloud3D:
    """Points of a packed buffer, read through a strided view (any field order, padding, byte order)."""
    for name in "xyz":
        if name not in layout:
            raise WireError(f"point cloud has no {name!r} field (fields: {', '.join(layout) or 'none'})")
    time_name = next((name for name in POINT_TIME_FIELDS if name in layout), None)
    used = [layout[name] for name in ("x", "y", "z", time_name) if name is not None]
    count = height * width
    if count and (
        point_step <= 0
        or row_step < width * point_step
        or data.shape[0] < (height - 1) * row_step + width * point_step
        or max(offset + np.dtype(code).itemsize for code, offset in used) > point_step
    ):
        raise WireError(
            f"point cloud layout does not fit its data ({height}×{width} points, point_step {point_step}, "
            f"row_step {row_step}, {data.shape[0]} bytes)"
        )
    if count == 0:
        return Cloud3D(stamp_ns, log_time_ns, frame_id, np.empty((0, 3), np.float32), None)
    (x_code, x_offset), (y_code, y_offset), (z_code, z_offset) = layout["x"], layout["y"], layout["z"]
    if (
        x_code == y_code == z_code
        and x_code[1:] == "f4"
        and (y_offset, z_offset) == (x_offset + 4, x_offset + 8)
    ):
        # The usual layout (x, y, z consecutive float32): one strided copy.
        xyz = np.ndarray((height, width, 3), x_code, data, x_offset, (row_step, point_step, 4))
        points = np.array(xyz, np.float32).reshape(count, 3)
    else:
        points = np.empty((height, width, 3), np.float32)
        for axis, (code, offset) in enumerate((layout["x"], layout["y"], layout["z"])):
            points[:, :, axis] = np.ndarray((height, width), code, data, offset, (row_step, point_step))
        points = points.reshape(count, 3)
    times = None
    if time_name is not None:
        code, offset = layout[time_name]
        raw = np.ndarray((height, width), code, data, offset, (row_step, point_step)).reshape(count)
        times = _point_times(raw, stamp_ns, time_name)
    finite = (np.abs(points) <= MAX_CLOUD_COORDINATE).all(axis=1)  # NaN compares False: dropped too
    if not finite.all():
        points = points[finite]
        times = times[finite] if times is not None else None
    return Cloud3D(stamp_ns, log_time_ns, frame_id, points, times)


def ros_point_cloud2(message: PointCloud2Fields, log_time_ns: int) -> Cloud3D:
    """sensor_msgs/PointCloud2: x, y, z (any numeric type) and an optional per-point time field."""
    endian = ">" if message.is_bigendian else "<"
    layout: dict[str, tuple[str, int]] = {}
    for f in message.fields:
        if f.datatype not in ROS_POINT_TYPES:
            if f.name in ("x", "y", "z"):
                raise WireError(f"point field {f.name!r} has unknown datatype {f.datatype}")
            continue
        layout.setdefault(f.name, (endian + ROS_POINT_TYPES[f.datatype], f.offset))
    return _cloud(
        message.stamp_ns,
        log_time_ns,
        message.frame_id,
        message.data,
        layout,
        message.point_step,
        message.row_step,
        message.height,
        message.width,
    )


def foxglove_point_cloud(message: Any, log_time_ns: int) -> Cloud3D:
    """foxglove.PointCloud (little-endian packed points); a non-identity `pose` is applied to the points."""
    data = np.frombuffer(foxglove.binary(foxglove.field(message, "data")), np.uint8)
    stride = int(foxglove.field(message, "point_stride", 0))
    layout: dict[str, tuple[str, int]] = {}
    for f in foxglove.field(message, "fields", ()) or ():
        numeric = foxglove.field(f, "type", 0)
        numeric = _FOXGLOVE_TYPE_NAMES.get(numeric, 0) if isinstance(numeric, str) else int(numeric)
        if numeric in FOXGLOVE_POINT_TYPES:
            layout.setdefault(
                str(foxglove.field(f, "name", "")),
                ("<" + FOXGLOVE_POINT_TYPES[numeric], int(foxglove.field(f, "offset", 0))),
            )
    if stride <= 0:
        raise WireError(f"point cloud has point_stride {stride}")
    width = data.shape[0] // stride
    cloud = _cloud(
        foxglove.stamp_ns(foxglove.field(message, "timestamp")),
        log_time_ns,
        str(foxglove.field(message, "frame_id", "")),
        data,
        layout,
        stride,
        width * stride,
        1,
        width,
    )
    position, orientation = foxglove.pose(foxglove.field(message, "pose"))
    if _is_identity(position, orientation):
        return cloud
    placed = rotations.rotate(_unit_quaternion(orientation), cloud.points) + np.asarray(position)
    return Cloud3D(cloud.stamp_ns, log_time_ns, cloud.frame_id, placed.astype(np.float32), cloud.point_times)


def ros_odometry(message: OdometryFields, log_time_ns: int) -> OdometryPose:
    """nav_msgs/Odometry: the pose of child_frame_id in header.frame_id."""
    pose = message.pose
    return OdometryPose(
        message.stamp_ns,
        log_time_ns,
        message.frame_id,
        message.child_frame_id,
        np.array(pose[:3]),
        _unit_quaternion(pose[3:]),
    )


def ros_tf_message(
    message: list[TransformStampedFields], log_time_ns: int, is_static: bool
) -> list[Transform]:
    """tf2_msgs/TFMessage: each TransformStamped maps child_frame_id into header.frame_id."""
    return [
        Transform(frame_id, child_frame_id, stamp_ns, log_time_ns, np.array(transform[:3]),
                  _unit_quaternion(transform[3:]), is_static)
        for stamp_ns, frame_id, child_frame_id, transform in message
    ]


def foxglove_frame_transform(message: Any, log_time_ns: int, is_static: bool) -> list[Transform]:
    """foxglove.FrameTransform: maps child_frame_id into parent_frame_id."""
    return [
        Transform(
            str(foxglove.field(message, "parent_frame_id", "")),
            str(foxglove.field(message, "child_frame_id", "")),
            foxglove.stamp_ns(foxglove.field(message, "timestamp")),
            log_time_ns,
            np.array(foxglove.vector3(foxglove.field(message, "translation"))),
            _unit_quaternion(foxglove.quaternion(foxglove.field(message, "rotation"))),
            is_static,
        )
    ]


def foxglove_frame_transforms(message: Any, log_time_ns: int, is_static: bool) -> list[Transform]:
    """foxglove.FrameTransforms: a list of FrameTransform."""
    return [
        transform
        for item in foxglove.field(message, "transforms", ()) or ()
        for transform in foxglove_frame_transform(item, log_time_ns, is_static)
    ]


def foxglove_pose_in_frame(message: Any, log_time_ns: int) -> list[OdometryPose]:
    """foxglove.PoseInFrame: a pose in frame_id (child_frame_id is "": the schema does not name it)."""
    position, orientation = foxglove.pose(foxglove.field(message, "pose"))
    return [
        OdometryPose(
            foxglove.stamp_ns(foxglove.field(message, "timestamp")),
            log_time_ns,
            str(foxglove.field(message, "frame_id", "")),
            "",
            np.array(position),
            _unit_quaternion(orientation),
        )
    ]


def foxglove_poses_in_frame(message: Any, log_time_ns: int) -> list[OdometryPose]:
    """foxglove.PosesInFrame: every pose, all at the message's timestamp."""
    stamp_ns = foxglove.stamp_ns(foxglove.field(message, "timestamp"))
    frame_id = str(foxglove.field(message, "frame_id", ""))
    out = []
    for pose in foxglove.field(message, "poses", ()) or ():
        position, orientation = foxglove.pose(pose)
        out.append(
            OdometryPose(
                stamp_ns, log_time_ns, frame_id, "", np.array(position), _unit_quaternion(orientation)
            )
        )
    return out


def _unit_quaternion(q: tuple[float, ...]) -> NDArray[np.float64]:
    """Normalized (x, y, z, w); an all-zero quaternion (an unset field) is the identity. Already-unit
    quaternions are kept bit for bit, so the same rotation read from two containers compares equal."""
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if norm == 0.0 or not math.isfinite(norm):
        return np.array([0.0, 0.0, 0.0, 1.0])
    if abs(norm - 1.0) < 1e-12:
        return np.array(q, dtype=np.float64)
    return np.array(q, dtype=np.float64) / norm


def _is_identity(position: tuple[float, ...], orientation: tuple[float, ...]) -> bool:
    # Any w with x = y = z = 0 is the identity (w = 0 is protobuf's unset quaternion).
    return position == (0.0, 0.0, 0.0) and tuple(orientation[:3]) == (0.0, 0.0, 0.0)
