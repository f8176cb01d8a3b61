"""Payload decoding and conversion, message by message: payloads serialized by rosbags (or by hand where
rosbags cannot, e.g. big-endian CDR), expectations computed here."""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np
import pytest

from frontends.errors import LogWarning
from frontends.logs import converters
from frontends.logs.converters import BearingTable, RangeLimits
from frontends.logs.decoding import ros_wire
from frontends.logs.decoding.ros_wire import WireError
from tests._frontends_fixtures import ros_typestore

STORE2 = ros_typestore(ros1=False)
STORE1 = ros_typestore(ros1=True)
NO_LIMITS = RangeLimits()


def header(store: Any, stamp_ns: int, frame_id: str) -> Any:
    stamp = store.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    if "seq" in store.types["std_msgs/msg/Header"].__dataclass_fields__:
        return store.types["std_msgs/msg/Header"](seq=7, stamp=stamp, frame_id=frame_id)
    return store.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def point_cloud(
    store: Any,
    fields: list[tuple[str, int, int]],
    data: bytes,
    width: int,
    height: int = 1,
    point_step: int = 0,
    row_step: int = 0,
    bigendian: bool = False,
) -> Any:
    field_type = store.types["sensor_msgs/msg/PointField"]
    return store.types["sensor_msgs/msg/PointCloud2"](
        header=header(store, 5 * 10**9 + 250, "velodyne"),
        height=height,
        width=width,
        fields=[field_type(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=bigendian,
        point_step=point_step,
        row_step=row_step,
        data=np.frombuffer(data, np.uint8),
        is_dense=False,
    )


def decode_cloud(store: Any, message: Any) -> Any:
    if store is STORE1:
        payload = bytes(store.serialize_ros1(message, "sensor_msgs/msg/PointCloud2"))
        return converters.ros_point_cloud2(ros_wire.point_cloud2(payload, cdr=False), 0)
    payload = bytes(store.serialize_cdr(message, "sensor_msgs/msg/PointCloud2"))
    return converters.ros_point_cloud2(ros_wire.point_cloud2(payload, cdr=True), 0)


@pytest.mark.parametrize("store", [STORE2, STORE1], ids=["cdr", "ros1"])
def test_point_cloud_any_field_order_type_and_padding(store: Any) -> None:
    # z (float64) first, then 2 bytes of padding, y and x (float32), a uint8 ring, padding to 32 bytes.
    points = [(1.5, -2.0, 3.25), (np.nan, 1.0, 2.0), (-4.0, 0.5, -1.0)]
    data = b"".join(struct.pack("<d2xffB9x", z, y, x, 3) for x, y, z in points)
    message = point_cloud(
        store, [("z", 0, 8), ("y", 10, 7), ("x", 14, 7), ("ring", 18, 2)], data, 3, point_step=28, row_step=84
    )
    cloud = decode_cloud(store, message)
    assert cloud.stamp_ns == 5 * 10**9 + 250 and cloud.frame_id == "velodyne"
    np.testing.assert_array_equal(cloud.points, np.array([points[0], points[2]], np.float32))
    assert cloud.point_times is None


def test_point_cloud_big_endian_rows_with_padding() -> None:
    # 2 rows × 2 points, 12-byte points, 4 bytes of padding at the end of each row.
    rows = [[(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)], [(7.0, 8.0, 9.0), (-1.0, -2.0, -3.0)]]
    data = b"".join(b"".join(struct.pack(">fff", *p) for p in row) + b"\xff" * 4 for row in rows)
    message = point_cloud(STORE2, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], data, 2, 2, 12, 28, bigendian=True)
    cloud = decode_cloud(STORE2, message)
    np.testing.assert_array_equal(cloud.points, np.array([p for row in rows for p in row], np.float32))


@pytest.mark.parametrize(
    ("name", "datatype", "pack", "values", "seconds"),
    [
        ("time", 7, "f", [0.0, 0.05, 0.099], [0.0, 0.05, 0.099]),  # Velodyne: float32 s after the stamp
        ("t", 6, "I", [0, 50_000_000, 99_000_000], [0.0, 0.05, 0.099]),  # Ouster: uint32 ns after it
        # Hesai / Robosense: float64 s since the epoch; this cloud is stamped 5 s + 250 ns after it.
        ("timestamp", 8, "d", [5.0, 5.05, 5.1], [-250e-9, 0.05 - 250e-9, 0.1 - 250e-9]),
        # livox_ros_driver2: float64 ns since the epoch (read as seconds, the stamp would lie 5·10⁹ s off)
        ("timestamp", 8, "d", [5e9 + 250, 5.05e9 + 250, 5.099e9 + 250], [0.0, 0.05, 0.099]),
    ],
)
def test_point_times_become_seconds_after_the_stamp(
    name: str, datatype: int, pack: str, values: list[float], seconds: list[float]
) -> None:
    size = struct.calcsize(pack)
    data = b"".join(struct.pack(f"<fff{pack}", 1.0, 2.0, 3.0, v) for v in values)
    message = point_cloud(
        STORE2,
        [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), (name, 12, datatype)],
        data,
        3,
        point_step=12 + size,
        row_step=3 * (12 + size),
    )
    cloud = decode_cloud(STORE2, message)
    assert cloud.point_times is not None and cloud.point_times.dtype == np.float64
    np.testing.assert_allclose(cloud.point_times, seconds, atol=1e-6)


@pytest.mark.parametrize("values", [
    [1000.0, 1000.05, 1000.1],  # seconds since boot beside an epoch stamp (as nanoseconds: a 0.1 ns sweep)
    [1.7e9, 1.7e9 + 0.05, 1.7e9 + 0.1],  # epoch seconds, the cloud stamped 5 s after the epoch
])
def test_point_times_on_another_clock_are_dropped_with_a_warning(values: list[float]) -> None:
    """Deskewing by them would carry the cloud's pose along the motion to where the stamp seems to be:
    10⁹ s away (a trajectory 10¹⁰ m off, before)."""
    data = b"".join(struct.pack("<fffd", 1.0, 2.0, 3.0, v) for v in values)
    message = point_cloud(STORE2, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("timestamp", 12, 8)], data, 3,
                          point_step=20, row_step=60)
    with pytest.warns(LogWarning, match=r"point times \(timestamp\) lie too far from their cloud's stamp"):
        cloud = decode_cloud(STORE2, message)
    assert cloud.point_times is None and len(cloud.points) == 3


def test_point_cloud_without_xyz_is_refused() -> None:
    message = point_cloud(STORE2, [("x", 0, 7), ("y", 4, 7)], bytes(16), 2, point_step=8, row_step=16)
    with pytest.raises(WireError, match="no 'z' field"):
        decode_cloud(STORE2, message)


def test_point_cloud_data_shorter_than_declared_is_refused() -> None:
    message = point_cloud(
        STORE2, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], bytes(24), 3, point_step=12, row_step=36
    )
    with pytest.raises(WireError, match="does not fit its data"):
        decode_cloud(STORE2, message)


def laser_scan_message(
    store: Any, ranges: list[float], angle_min: float, increment: float, range_max: float,
    time_increment: float = 0.0,
) -> Any:
    return store.types["sensor_msgs/msg/LaserScan"](
        header=header(store, 1_234_567_890_123_456_789, "base_scan"),
        angle_min=angle_min,
        angle_max=angle_min + increment * (len(ranges) - 1),
        angle_increment=increment,
        time_increment=time_increment,
        scan_time=0.0,
        range_min=0.1,
        range_max=range_max,
        ranges=np.array(ranges, np.float32),
        intensities=np.array([], np.float32),
    )


def big_endian_cdr_laser_scan(
    stamp: tuple[int, int], frame: str, floats: list[float], ranges: list[float]
) -> bytes:
    """A LaserScan in big-endian CDR (encapsulation 00 00), written field by field."""
    out = b"\x00\x00\x00\x00" + struct.pack(">iI", *stamp)
    name = frame.encode() + b"\x00"
    out += struct.pack(">I", len(name)) + name
    out += b"\x00" * (-(len(out) - 4) % 4)
    out += (
        struct.pack(">7f", *floats)
        + struct.pack(">I", len(ranges))
        + struct.pack(f">{len(ranges)}f", *ranges)
    )
    return out + struct.pack(">I", 0)


def test_laser_scan_cdr_little_and_big_endian_and_ros1_agree() -> None:
    ranges = [1.0, 2.0, float("nan"), 30.0, 0.05, 4.0]
    little = bytes(
        STORE2.serialize_cdr(
            laser_scan_message(STORE2, ranges, -0.5, 0.25, 20.0), "sensor_msgs/msg/LaserScan"
        )
    )
    ros1 = bytes(
        STORE1.serialize_ros1(
            laser_scan_message(STORE1, ranges, -0.5, 0.25, 20.0), "sensor_msgs/msg/LaserScan"
        )
    )
    big = big_endian_cdr_laser_scan(
        (1_234_567_890, 123_456_789), "base_scan", [-0.5, 0.75, 0.25, 0.0, 0.0, 0.1, 20.0], ranges
    )
    scans = [
        converters.ros_laser_scan(ros_wire.laser_scan(payload, cdr), 42, NO_LIMITS, BearingTable())
        for payload, cdr in ((little, True), (big, True), (ros1, False))
    ]
    for scan in scans:
        assert scan.stamp_ns == 1_234_567_890_123_456_789
        assert scan.frame_id == "base_scan"
        assert scan.log_time_ns == 42
        assert scan.beam_count == 6
        np.testing.assert_array_equal(scan.ranges, [1.0, 2.0, 4.0])
        np.testing.assert_allclose(scan.bearings, [-0.5, -0.25, 0.75])
        np.testing.assert_allclose(
            scan.points,
            [
                [math.cos(-0.5), math.sin(-0.5)],
                [2 * math.cos(-0.25), 2 * math.sin(-0.25)],
                [4 * math.cos(0.75), 4 * math.sin(0.75)],
            ],
            atol=1e-12,
        )


def test_laser_scan_with_unbounded_range_max_drops_only_non_finite() -> None:
    message = laser_scan_message(STORE2, [1.0, float("inf"), 500.0, float("-inf")], 0.0, 0.5, float("inf"))
    payload = bytes(STORE2.serialize_cdr(message, "sensor_msgs/msg/LaserScan"))
    scan = converters.ros_laser_scan(ros_wire.laser_scan(payload, True), 0, NO_LIMITS, BearingTable())
    np.testing.assert_array_equal(scan.ranges, [1.0, 500.0])


@pytest.mark.parametrize("store", [STORE2, STORE1], ids=["cdr", "ros1"])
@pytest.mark.parametrize("increment", [0.25, -0.25], ids=["anticlockwise", "clockwise"])
def test_laser_scan_time_increment_gives_each_kept_beam_its_time(store: Any, increment: float) -> None:
    # Beam i is taken i·time_increment after the stamp (sensor_msgs/LaserScan); dropped beams (NaN, out of
    # range) leave gaps in the kept beams' times, not a renumbering.
    ranges = [1.0, float("nan"), 2.0, 30.0, 3.0, 0.01, 4.0]
    message = laser_scan_message(store, ranges, 0.5, increment, 20.0, time_increment=0.001)
    if store is STORE1:
        fields = ros_wire.laser_scan(bytes(store.serialize_ros1(message, "sensor_msgs/msg/LaserScan")), False)
    else:
        fields = ros_wire.laser_scan(bytes(store.serialize_cdr(message, "sensor_msgs/msg/LaserScan")), True)
    scan = converters.ros_laser_scan(fields, 0, NO_LIMITS, BearingTable())
    assert scan.point_times is not None
    np.testing.assert_allclose(scan.point_times, [0.0, 0.002, 0.004, 0.006], rtol=1e-6)
    np.testing.assert_allclose(scan.bearings, 0.5 + increment * np.array([0, 2, 4, 6]))


@pytest.mark.parametrize("time_increment", [0.0, float("nan"), float("inf"), 0.5, -0.5])
def test_laser_scan_without_usable_beam_times_has_none(time_increment: float) -> None:
    # 0 is "not given"; NaN, infinite, or a sweep of 3 s over 7 beams is no laser's (MAX_SWEEP_SECONDS).
    message = laser_scan_message(STORE2, [1.0] * 7, 0.0, 0.1, 5.0, time_increment=time_increment)
    payload = bytes(STORE2.serialize_cdr(message, "sensor_msgs/msg/LaserScan"))
    scan = converters.ros_laser_scan(ros_wire.laser_scan(payload, True), 0, NO_LIMITS, BearingTable())
    assert scan.point_times is None
    assert len(scan.ranges) == 7


@pytest.mark.parametrize("cut", [0, 3, 10, 40])
def test_truncated_payload_raises_wire_error(cut: int) -> None:
    payload = bytes(
        STORE2.serialize_cdr(
            laser_scan_message(STORE2, [1.0] * 8, 0.0, 0.1, 5.0), "sensor_msgs/msg/LaserScan"
        )
    )
    with pytest.raises(WireError):
        ros_wire.laser_scan(payload[:cut], True)


@pytest.mark.parametrize("store", [STORE2, STORE1], ids=["cdr", "ros1"])
def test_odometry_and_tf_payloads(store: Any) -> None:
    types = store.types
    q = (0.0, 0.0, math.sin(0.35), math.cos(0.35))
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=1.5, y=-2.5, z=0.25),
        orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    odometry = types["nav_msgs/msg/Odometry"](
        header=header(store, 77, "odom"),
        child_frame_id="base_footprint",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.arange(36.0)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
        ),
    )
    transforms = [
        types["geometry_msgs/msg/TransformStamped"](
            header=header(store, 100 + i, "map" if i == 0 else "odom"),
            child_frame_id="odom" if i == 0 else "base_link",
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=float(i), y=2.0, z=3.0),
                rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )
        for i in range(2)
    ]
    tf = types["tf2_msgs/msg/TFMessage"](transforms=transforms)
    cdr = store is STORE2
    serialize = store.serialize_cdr if cdr else store.serialize_ros1
    parsed = converters.ros_odometry(
        ros_wire.odometry(bytes(serialize(odometry, "nav_msgs/msg/Odometry")), cdr), 5
    )
    assert (parsed.stamp_ns, parsed.frame_id, parsed.child_frame_id) == (77, "odom", "base_footprint")
    np.testing.assert_array_equal(parsed.translation, [1.5, -2.5, 0.25])
    np.testing.assert_array_equal(parsed.rotation, q)
    assert parsed.yaw == pytest.approx(0.7)
    out = converters.ros_tf_message(
        ros_wire.tf_message(bytes(serialize(tf, "tf2_msgs/msg/TFMessage")), cdr), 9, False
    )
    assert [(t.parent_frame, t.child_frame, t.stamp_ns) for t in out] == [
        ("map", "odom", 100),
        ("odom", "base_link", 101),
    ]
    np.testing.assert_array_equal(out[1].translation, [1.0, 2.0, 3.0])


def test_foxglove_scan_pose_places_points_in_its_frame() -> None:
    # JSON-shaped message: the scan origin sits 1 m ahead of frame_id, turned 90° left.
    message = {
        "timestamp": {"sec": 3, "nsec": 5},
        "frame_id": "base_link",
        "pose": {
            "position": {"x": 1.0, "y": 0.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(math.pi / 4), "w": math.cos(math.pi / 4)},
        },
        "start_angle": 0.0,
        "end_angle": math.pi / 2,
        "ranges": [2.0, float("nan"), 3.0],
    }
    scan = converters.foxglove_laser_scan(message, 0, NO_LIMITS, BearingTable())
    assert scan.stamp_ns == 3_000_000_005
    np.testing.assert_allclose(scan.bearings, [0.0, math.pi / 2])
    # Beam 0: 2 m along the sensor's x (the frame's y) → (1, 2).
    # Beam 2: 3 m along the sensor's y (the frame's −x) → (−2, 0).
    np.testing.assert_allclose(scan.points, [[1.0, 2.0], [-2.0, 0.0]], atol=1e-12)


def test_foxglove_point_cloud_from_json_with_base64_data() -> None:
    import base64

    data = struct.pack("<3f4x", 1.0, 2.0, 3.0) + struct.pack("<3f4x", 4.0, float("nan"), 6.0)
    message = {
        "timestamp": {"sec": 1, "nsec": 0},
        "frame_id": "lidar",
        "point_stride": 16,
        "fields": [
            {"name": "x", "offset": 0, "type": 7},
            {"name": "y", "offset": 4, "type": "FLOAT32"},
            {"name": "z", "offset": 8, "type": 7},
        ],
        "data": base64.b64encode(data).decode(),
    }
    cloud = converters.foxglove_point_cloud(message, 0)
    np.testing.assert_array_equal(cloud.points, [[1.0, 2.0, 3.0]])


def multi_echo_message(store: Any, echoes: list[list[float]], angle_min: float, increment: float) -> Any:
    types = store.types
    return types["sensor_msgs/msg/MultiEchoLaserScan"](
        header=header(store, 1_234_567_890_123_456_789, "horizontal_laser_link"),
        angle_min=angle_min, angle_max=angle_min + increment * (len(echoes) - 1), angle_increment=increment,
        time_increment=0.0, scan_time=0.025, range_min=0.1, range_max=30.0,
        ranges=[types["sensor_msgs/msg/LaserEcho"](echoes=np.array(e, np.float32)) for e in echoes],
        intensities=[types["sensor_msgs/msg/LaserEcho"](echoes=np.array([7.0] * len(e), np.float32))
                     for e in echoes])


# Beams with one, three, no and two echoes: the first of each is read, a beam without any has no return.
ECHOES = [[1.0], [2.0, 2.5, 9.0], [], [4.0, 6.0], [0.05], [3.0]]


def big_endian_cdr_multi_echo(echoes: list[list[float]], floats: list[float]) -> bytes:
    """A MultiEchoLaserScan in big-endian CDR (encapsulation 00 00), written field by field."""
    out = b"\x00\x00\x00\x00" + struct.pack(">iI", 1_234_567_890, 123_456_789)
    name = b"horizontal_laser_link\x00"
    out += struct.pack(">I", len(name)) + name
    out += b"\x00" * (-(len(out) - 4) % 4)
    out += struct.pack(">7f", *floats) + struct.pack(">I", len(echoes))
    for beam in echoes:
        out += struct.pack(">I", len(beam)) + struct.pack(f">{len(beam)}f", *beam)
    return out + struct.pack(">I", 0)


def test_a_multi_echo_scan_is_read_as_the_scan_of_its_first_echoes() -> None:
    little = bytes(STORE2.serialize_cdr(multi_echo_message(STORE2, ECHOES, -0.5, 0.25),
                                        "sensor_msgs/msg/MultiEchoLaserScan"))
    ros1 = bytes(STORE1.serialize_ros1(multi_echo_message(STORE1, ECHOES, -0.5, 0.25),
                                       "sensor_msgs/msg/MultiEchoLaserScan"))
    big = big_endian_cdr_multi_echo(ECHOES, [-0.5, 0.75, 0.25, 0.0, 0.025, 0.1, 30.0])
    for payload, cdr in ((little, True), (big, True), (ros1, False)):
        fields = ros_wire.multi_echo_laser_scan(payload, cdr)
        np.testing.assert_array_equal(fields.ranges, np.array([1.0, 2.0, np.inf, 4.0, 0.05, 3.0], np.float32))
        scan = converters.ros_laser_scan(fields, 42, NO_LIMITS, BearingTable())
        assert scan.stamp_ns == 1_234_567_890_123_456_789 and scan.frame_id == "horizontal_laser_link"
        np.testing.assert_array_equal(scan.ranges, [1.0, 2.0, 4.0, 3.0])  # inf and below range_min dropped
        np.testing.assert_allclose(scan.bearings, [-0.5, -0.25, 0.25, 0.75])


@pytest.mark.parametrize("cut", [4, 40, 80])
def test_a_truncated_multi_echo_scan_raises_wire_error(cut: int) -> None:
    payload = bytes(STORE2.serialize_cdr(multi_echo_message(STORE2, ECHOES, -0.5, 0.25),
                                         "sensor_msgs/msg/MultiEchoLaserScan"))
    ranges_end = len(payload) - 4 - sum(4 + 4 * len(e) for e in ECHOES)  # the intensities follow the ranges
    with pytest.raises(WireError):
        ros_wire.multi_echo_laser_scan(payload[: min(cut, ranges_end - 2)], True)


def test_a_multi_echo_scan_claiming_four_billion_beams_is_refused_without_allocating() -> None:
    payload = bytearray(STORE2.serialize_cdr(multi_echo_message(STORE2, ECHOES, -0.5, 0.25),
                                             "sensor_msgs/msg/MultiEchoLaserScan"))
    count_at = payload.index(struct.pack("<I", len(ECHOES)) + struct.pack("<I", 1) + struct.pack("<f", 1.0))
    payload[count_at:count_at + 4] = struct.pack("<I", 2**32 - 1)
    with pytest.raises(WireError, match="run past the payload"):
        ros_wire.multi_echo_laser_scan(bytes(payload), True)
