"""The five ROS messages we read, parsed straight from CDR (ROS 2) or ROS 1 serialization.

One parser per message, written once for both wire formats: they differ only in the header's `seq` field
(ROS 1), in alignment (CDR aligns each primitive to its size, counted from after the 4-byte encapsulation
header), in the trailing NUL of CDR strings, and in CDR's choice of byte order. Arrays come out as numpy
views on the payload (no copy, no per-element Python objects); that is what makes a LaserScan or a
PointCloud2 cost a few microseconds instead of the generic deserializers' tens to hundreds.

The layouts are the standard `sensor_msgs`, `nav_msgs`, `geometry_msgs` and `tf2_msgs` definitions;
anything that does not fit them raises `WireError`.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray


class WireError(ValueError):
    """A payload does not match the message layout (too short, bad encapsulation, bad string)."""


_STRUCTS: dict[str, dict[str, struct.Struct]] = {
    endian: {
        "I": struct.Struct(endian + "I"),
        "stamp": struct.Struct(endian + "iI"),
        "cdr_header": struct.Struct(endian + "iII"),  # stamp sec, nanosec, frame_id length
        "ros1_header": struct.Struct(endian + "III"),
        "scan": struct.Struct(endian + "7fI"),
        "cloud_size": struct.Struct(endian + "II"),
        "field_tail": struct.Struct(endian + "IBxxxI"),  # offset, datatype, (pad to 4), count — CDR
        "field_tail_ros1": struct.Struct(endian + "IBI"),  # offset, datatype, count — packed
        "cloud_tail": struct.Struct(endian + "?xxxII"),  # is_bigendian, (pad to 4), point_step, row_step
        "cloud_tail_ros1": struct.Struct(endian + "?II"),
        "pose": struct.Struct(endian + "7d"),
    }
    for endian in "<>"
}


_ROS1_HEADER = struct.Struct("<IIII")  # seq, stamp secs, nsecs, frame_id length


class _Cursor:
    """Reads one payload front to back; `cdr` selects CDR alignment and strings."""

    __slots__ = ("cdr", "data", "endian", "pos", "structs")

    def __init__(self, data: bytes | memoryview, cdr: bool) -> None:
        self.data = data
        self.cdr = cdr
        if cdr:
            if len(data) < 4 or data[0] != 0 or data[1] > 1:
                raise WireError(f"unsupported CDR encapsulation {bytes(data[:2]).hex() or 'missing'}")
            self.endian = "<" if data[1] == 1 else ">"
            self.pos = 4
        else:
            self.endian = "<"
            self.pos = 0
        self.structs = _STRUCTS[self.endian]

    def align(self, size: int) -> None:
        if self.cdr:
            self.pos += -(self.pos - 4) % size

    def unpack(self, name: str, size: int, align: int = 4) -> tuple[object, ...]:
        if self.cdr:
            self.pos += -(self.pos - 4) % align
        layout = self.structs[name]
        try:
            values = layout.unpack_from(self.data, self.pos)
        except struct.error:
            raise WireError("payload ends early") from None
        self.pos += size
        return values

    def u32(self) -> int:
        (value,) = self.unpack("I", 4)
        return int(value)  # type: ignore[call-overload]

    def string(self) -> str:
        length = self.u32()
        start = self.pos
        end = start + length
        if end > len(self.data):
            raise WireError("string runs past the payload")
        self.pos = end
        if self.cdr and length:
            end -= 1  # CDR strings carry their NUL terminator in the length
        try:
            return str(self.data[start:end], "utf-8")
        except UnicodeDecodeError:
            raise WireError("string is not UTF-8") from None

    def header(self) -> tuple[int, str]:
        """std_msgs/Header → (stamp in ns, frame_id)."""
        if self.cdr:
            sec, nanosec = self.unpack("stamp", 8)
        else:
            _, sec, nanosec = self.unpack("ros1_header", 12)
        return sec * 1_000_000_000 + nanosec, self.string()  # type: ignore[operator]

    def array(self, dtype: str, itemsize: int) -> NDArray[np.generic]:
        """A sequence of primitives as a read-only numpy view on the payload."""
        count = self.u32()
        self.align(itemsize)
        end = self.pos + count * itemsize
        if end > len(self.data):
            raise WireError("array runs past the payload")
        values = np.frombuffer(self.data, dtype=self.endian + dtype, count=count, offset=self.pos)
        self.pos = end
        return values

    def pose(self) -> tuple[float, ...]:
        """Seven float64: a Point/Vector3 followed by a Quaternion."""
        return self.unpack("pose", 56, align=8)  # type: ignore[return-value]


class LaserScanFields(NamedTuple):
    stamp_ns: int
    frame_id: str
    angle_min: float
    angle_increment: float
    time_increment: float
    """Seconds between two beams (0: not given)."""
    range_min: float
    range_max: float
    ranges: NDArray[np.float32]


class PointFieldFields(NamedTuple):
    name: str
    offset: int
    datatype: int
    count: int  # type: ignore[assignment]  # ROS's name, shadowing tuple.count


class PointCloud2Fields(NamedTuple):
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    fields: tuple[PointFieldFields, ...]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: NDArray[np.uint8]


class OdometryFields(NamedTuple):
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    pose: tuple[float, ...]  # x, y, z, qx, qy, qz, qw


class TransformStampedFields(NamedTuple):
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    transform: tuple[float, ...]  # x, y, z, qx, qy, qz, qw


def _header(data: bytes | memoryview, cdr: bool) -> tuple[str, int, str, int]:
    """Encapsulation and std_msgs/Header at the start of a payload → (byte order, stamp ns, frame_id,
    position after the header). Written out flat: it is on the path of every scan."""
    if cdr:
        if len(data) < 4 or data[0] != 0 or data[1] > 1:
            raise WireError(f"unsupported CDR encapsulation {bytes(data[:2]).hex() or 'missing'}")
        endian = "<" if data[1] == 1 else ">"
        layout = _STRUCTS[endian]["cdr_header"]
    else:
        endian = "<"
        layout = _ROS1_HEADER
    try:
        sec, nanosec, length = layout.unpack_from(data, 4 if cdr else 0)[-3:]
    except struct.error:
        raise WireError("payload ends early") from None
    start = 16
    end = start + length
    if end > len(data):
        raise WireError("frame_id runs past the payload")
    try:
        frame_id = str(data[start : end - 1 if cdr and length else end], "utf-8")
    except UnicodeDecodeError:
        raise WireError("frame_id is not UTF-8") from None
    if cdr:
        end += -(end - 4) % 4  # what follows the header is 4-aligned in every message we read
    return endian, sec * 1_000_000_000 + nanosec, frame_id, end


def laser_scan(data: bytes | memoryview, cdr: bool) -> LaserScanFields:
    """sensor_msgs/LaserScan (intensities are not read)."""
    fields, endian, pos, count = _laser_scan_head(data, cdr)
    if pos + 4 * count > len(data):
        raise WireError("ranges run past the payload")
    return fields._replace(ranges=np.frombuffer(data, dtype=endian + "f4", count=count, offset=pos))


def multi_echo_laser_scan(data: bytes | memoryview, cdr: bool) -> LaserScanFields:
    """sensor_msgs/MultiEchoLaserScan read as the LaserScan of each beam's first echo, the one Cartographer
    reads (a beam without echoes has no return: inf); intensities are not read. Its fields are a
    LaserScan's up to the ranges, which are a sequence of LaserEcho (a sequence of float32 each); every
    item is 4 bytes, so CDR adds no padding inside them."""
    fields, endian, pos, count = _laser_scan_head(data, cdr)
    words = np.frombuffer(data, dtype=endian + "u4", count=(len(data) - pos) // 4, offset=pos)
    if count > len(words):  # every beam takes a word at least: a count no payload holds allocates nothing
        raise WireError("ranges run past the payload")
    words = words.astype(np.uint32, copy=False)  # native order for the kernel (a copy if big-endian)
    first = _first_echoes(words, count)
    if len(first) and first[0] == _RUNS_PAST:
        raise WireError("ranges run past the payload")
    ranges = np.full(count, np.inf, dtype=np.float32)
    has_echo = first >= 0
    ranges[has_echo] = words.view(np.float32)[first[has_echo]]
    return fields._replace(ranges=ranges)


def _laser_scan_head(data: bytes | memoryview, cdr: bool) -> tuple[LaserScanFields, str, int, int]:
    """A LaserScan's (or MultiEchoLaserScan's) fields before its ranges (`ranges` left empty), the byte
    order, where the ranges' sequence starts (past its length) and that length."""
    endian, stamp_ns, frame_id, pos = _header(data, cdr)
    try:
        angle_min, _, increment, time_increment, _, range_min, range_max, count = _STRUCTS[endian][
            "scan"
        ].unpack_from(data, pos)
    except struct.error:
        raise WireError("payload ends early") from None
    fields = LaserScanFields(stamp_ns, frame_id, angle_min, increment, time_increment, range_min, range_max,
                             np.zeros(0, dtype=np.float32))
    return fields, endian, pos + 32, count


_RUNS_PAST = -2


@njit(cache=True)
def _first_echoes(words: NDArray[np.uint32], beams: int) -> NDArray[np.int64]:
    """Index in `words` of each beam's first echo (−1: none), walking the LaserEcho sequence (each a count
    then that many floats); [`_RUNS_PAST`] when it runs past the payload."""
    first = np.full(beams, -1, dtype=np.int64)
    position: int | np.int64 = 0
    for beam in range(beams):
        if position >= len(words):
            return np.full(1, _RUNS_PAST, dtype=np.int64)
        echoes = np.int64(words[position])
        if echoes > len(words) - position - 1:
            return np.full(1, _RUNS_PAST, dtype=np.int64)
        if echoes > 0:
            first[beam] = position + 1
        position += 1 + echoes
    return first


def point_cloud2(data: bytes | memoryview, cdr: bool) -> PointCloud2Fields:
    """sensor_msgs/PointCloud2."""
    cursor = _Cursor(data, cdr)
    stamp_ns, frame_id = cursor.header()
    height, width = cursor.unpack("cloud_size", 8)
    field_count = cursor.u32()
    fields = []
    for _ in range(field_count):
        name = cursor.string()
        if cdr:
            offset, datatype, count = cursor.unpack("field_tail", 12)
        else:
            offset, datatype, count = cursor.unpack("field_tail_ros1", 9)
        fields.append(PointFieldFields(name, offset, datatype, count))  # type: ignore[arg-type]
    if cdr:
        is_bigendian, point_step, row_step = cursor.unpack("cloud_tail", 12, align=1)
    else:
        is_bigendian, point_step, row_step = cursor.unpack("cloud_tail_ros1", 9)
    points = cursor.array("u1", 1)
    return PointCloud2Fields(
        stamp_ns,
        frame_id,
        height,  # type: ignore[arg-type]
        width,  # type: ignore[arg-type]
        tuple(fields),
        bool(is_bigendian),
        point_step,  # type: ignore[arg-type]
        row_step,  # type: ignore[arg-type]
        points,  # type: ignore[arg-type]
    )


def odometry(data: bytes | memoryview, cdr: bool) -> OdometryFields:
    """nav_msgs/Odometry (pose only; covariance and twist are not read)."""
    cursor = _Cursor(data, cdr)
    stamp_ns, frame_id = cursor.header()
    child_frame_id = cursor.string()
    return OdometryFields(stamp_ns, frame_id, child_frame_id, cursor.pose())


_TF_LAYOUTS: dict[str, tuple[struct.Struct, struct.Struct, struct.Struct]] = {
    # a TransformStamped's header up to frame_id's length (→ sec, nanosec, length), a string's length, and
    # the 7 float64 of its transform; by CDR byte order, and for ROS 1 (whose header starts with `seq`)
    "<": (struct.Struct("<iII"), struct.Struct("<I"), struct.Struct("<7d")),
    ">": (struct.Struct(">iII"), struct.Struct(">I"), struct.Struct(">7d")),
    "ros1": (struct.Struct("<4xIII"), struct.Struct("<I"), struct.Struct("<7d")),
}


def _string_at(data: bytes | memoryview, start: int, length: int, nul: int) -> tuple[str, int]:
    """The string of `length` bytes at `start` (its NUL terminator left out when `nul` is 1), and where it
    ends: `_Cursor.string` after the length was read."""
    end = start + length
    if end > len(data):
        raise WireError("string runs past the payload")
    try:
        return str(data[start : end - nul if length else end], "utf-8"), end
    except UnicodeDecodeError:
        raise WireError("string is not UTF-8") from None


def tf_message(data: bytes | memoryview, cdr: bool) -> list[TransformStampedFields]:
    """tf2_msgs/TFMessage.

    Written out flat: the UAL log's odometry is 14 751 tf messages, and `_Cursor`'s call per field made this
    a tenth of its reading time. The steps, checks and errors are the cursor's, in its order (the tests
    hold the two to the same results); ROS 1 is CDR with every alignment 1 and no NUL after strings."""
    size = len(data)
    if cdr:
        if size < 4 or data[0] != 0 or data[1] > 1:
            raise WireError(f"unsupported CDR encapsulation {bytes(data[:2]).hex() or 'missing'}")
        header, word, pose = _TF_LAYOUTS["<" if data[1] == 1 else ">"]
        pos, word_align, pose_align, nul = 4, 4, 8, 1
    else:
        header, word, pose = _TF_LAYOUTS["ros1"]
        pos, word_align, pose_align, nul = 0, 1, 1, 0
    header_size = header.size
    out = []
    try:  # every read past the payload's end is the cursor's one error
        (count,) = word.unpack_from(data, pos)
        if count > size:
            raise WireError("transform count exceeds the payload")
        pos += 4
        for _ in range(count):
            pos += -(pos - 4) % word_align
            sec, nanosec, length = header.unpack_from(data, pos)
            frame_id, pos = _string_at(data, pos + header_size, length, nul)
            pos += -(pos - 4) % word_align
            (length,) = word.unpack_from(data, pos)
            child_frame_id, pos = _string_at(data, pos + 4, length, nul)
            pos += -(pos - 4) % pose_align
            transform = pose.unpack_from(data, pos)
            pos += 56
            out.append(TransformStampedFields(sec * 1_000_000_000 + nanosec, frame_id, child_frame_id,
                                              transform))
    except struct.error:
        raise WireError("payload ends early") from None
    return out
