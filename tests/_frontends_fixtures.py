"""Tiny logs for the frontends tests, written with the `mcap` and `rosbags` writers (never with our code).

Every container holds the same recording, described by the plain-Python truth below: five laser scans
(one stored after a later-stamped one, to check sorting), five odometry poses, the same poses as
odom → base_link tf, a static base_link → laser transform, and two point clouds with NaN points, padding
and a per-point time field. ROS containers carry sensor_msgs/nav_msgs/tf2_msgs; Foxglove MCAPs carry
foxglove.LaserScan / PoseInFrame / FrameTransform(s) / PointCloud in protobuf or JSON.
"""

from __future__ import annotations

import base64
import json
import math
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from frontends.logs import Scan2D

T0 = 1_700_000_000_000_000_000
MS = 1_000_000

ANGLE_MIN = -1.0
ANGLE_INCREMENT = 0.25
RANGE_MIN = 0.5
RANGE_MAX = 10.0
_BASE_RANGES = (1.0, math.nan, 0.25, 12.0, math.inf, 2.5, 10.0, 0.5, 3.75)

SCAN_FRAME = "laser"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
CLOUD_FRAME = "lidar"
LASER_MOUNT = ((0.2, 0.0, 0.1), 0.5)  # base_link → laser: translation, yaw


@dataclass(frozen=True)
class ScanTruth:
    stamp_ns: int
    log_time_ns: int
    ranges: tuple[float, ...]


@dataclass(frozen=True)
class PoseTruth:
    stamp_ns: int
    log_time_ns: int
    x: float
    y: float
    yaw: float


@dataclass(frozen=True)
class CloudTruth:
    stamp_ns: int
    log_time_ns: int
    points: tuple[tuple[float, float, float], ...]
    times: tuple[float, ...]


# In log (storage) order; the third scan is stamped after the fourth.
_SCAN_STAMPS = (0, 100, 250, 200, 300)
SCANS = tuple(
    ScanTruth(
        T0 + s * MS,
        T0 + (s + 20) * MS if i != 3 else T0 + 275 * MS,
        tuple(r + 0.125 * i for r in _BASE_RANGES),
    )
    for i, s in enumerate(_SCAN_STAMPS)
)
POSES = tuple(
    PoseTruth(T0 + (k * 100 + 50) * MS, T0 + (k * 100 + 55) * MS, 0.5 * k, 0.1 * k, 0.2 * k) for k in range(5)
)
CLOUDS = tuple(
    CloudTruth(
        T0 + (k * 100 + 50) * MS,
        T0 + (k * 100 + 90) * MS,
        ((1.0 + k, 2.0, 3.0), (math.nan, math.nan, math.nan), (4.0, 5.0 + k, 6.0), (-1.0, -2.0, -0.5 - k)),
        (0.0, 0.01, 0.02, 0.03),
    )
    for k in range(2)
)
STATIC_STAMP_NS = T0 - 1000 * MS


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def cloud_buffer(cloud: CloudTruth) -> bytes:
    """Packed points: intensity f32 @0, x @4, y @8, z @12, 4 bytes padding, time f32 @20; 24-byte step."""
    out = b""
    for i, (point, time) in enumerate(zip(cloud.points, cloud.times, strict=True)):
        out += struct.pack("<ffff4xf", 10.0 * i, *point, time)
    return out


CLOUD_FIELDS = (("intensity", 0), ("x", 4), ("y", 8), ("z", 12), ("time", 20))
CLOUD_STEP = 24


# --- ROS messages through the rosbags typestores ------------------------------------------------------

_TF_MESSAGE_DEFINITION = "geometry_msgs/TransformStamped[] transforms\n"


def ros_typestore(ros1: bool) -> Any:
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg(_TF_MESSAGE_DEFINITION, "tf2_msgs/msg/TFMessage"))
    return store


class RosMessages:
    """Builds the recording's messages as typestore objects."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.store = ros_typestore(ros1)
        self.types = self.store.types

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        stamp = self.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if self.ros1:
            return self.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def laser_scan(self, scan: ScanTruth) -> Any:
        import numpy as np

        n = len(scan.ranges)
        return self.types["sensor_msgs/msg/LaserScan"](
            header=self.header(scan.stamp_ns, SCAN_FRAME),
            angle_min=ANGLE_MIN,
            angle_max=ANGLE_MIN + (n - 1) * ANGLE_INCREMENT,
            angle_increment=ANGLE_INCREMENT,
            time_increment=0.0,
            scan_time=0.1,
            range_min=RANGE_MIN,
            range_max=RANGE_MAX,
            ranges=np.array(scan.ranges, dtype=np.float32),
            intensities=np.ones(n, dtype=np.float32),
        )

    def pose(self, x: float, y: float, z: float, q: tuple[float, ...]) -> Any:
        return self.types["geometry_msgs/msg/Pose"](
            position=self.types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=self.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    def odometry(self, pose: PoseTruth) -> Any:
        import numpy as np

        types = self.types
        zero3 = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return types["nav_msgs/msg/Odometry"](
            header=self.header(pose.stamp_ns, ODOM_FRAME),
            child_frame_id=BASE_FRAME,
            pose=types["geometry_msgs/msg/PoseWithCovariance"](
                pose=self.pose(pose.x, pose.y, 0.0, quaternion_from_yaw(pose.yaw)), covariance=np.zeros(36)
            ),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)
            ),
        )

    def transform_stamped(
        self, stamp_ns: int, parent: str, child: str, translation: tuple[float, ...], yaw: float
    ) -> Any:
        types = self.types
        q = quaternion_from_yaw(yaw)
        return types["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](
                    x=translation[0], y=translation[1], z=translation[2]
                ),
                rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

    def tf_message(self, transforms: list[Any]) -> Any:
        return self.types["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def point_cloud2(self, cloud: CloudTruth) -> Any:
        import numpy as np

        point_field = self.types["sensor_msgs/msg/PointField"]
        fields = [point_field(name=name, offset=offset, datatype=7, count=1) for name, offset in CLOUD_FIELDS]
        data = cloud_buffer(cloud)
        return self.types["sensor_msgs/msg/PointCloud2"](
            header=self.header(cloud.stamp_ns, CLOUD_FRAME),
            height=1,
            width=len(cloud.points),
            fields=fields,
            is_bigendian=False,
            point_step=CLOUD_STEP,
            row_step=CLOUD_STEP * len(cloud.points),
            data=np.frombuffer(data, dtype=np.uint8),
            is_dense=False,
        )

    def recording(self, extra_scan_topic: str | None = None) -> list[tuple[str, str, int, Any]]:
        """(topic, type, log time, message) in log order."""
        out: list[tuple[str, str, int, Any]] = [
            (
                "/tf_static",
                "tf2_msgs/msg/TFMessage",
                STATIC_STAMP_NS,
                self.tf_message(
                    [self.transform_stamped(STATIC_STAMP_NS, BASE_FRAME, SCAN_FRAME, *LASER_MOUNT)]
                ),
            )
        ]
        for scan in SCANS:
            out.append(("/scan", "sensor_msgs/msg/LaserScan", scan.log_time_ns, self.laser_scan(scan)))
            if extra_scan_topic is not None:
                out.append(
                    (extra_scan_topic, "sensor_msgs/msg/LaserScan", scan.log_time_ns, self.laser_scan(scan))
                )
        for pose in POSES:
            out.append(("/odom", "nav_msgs/msg/Odometry", pose.log_time_ns, self.odometry(pose)))
            transform = self.transform_stamped(
                pose.stamp_ns, ODOM_FRAME, BASE_FRAME, (pose.x, pose.y, 0.0), pose.yaw
            )
            out.append(("/tf", "tf2_msgs/msg/TFMessage", pose.log_time_ns, self.tf_message([transform])))
        for cloud in CLOUDS:
            out.append(
                ("/points", "sensor_msgs/msg/PointCloud2", cloud.log_time_ns, self.point_cloud2(cloud))
            )
        out.sort(key=lambda item: item[2])
        return out

    def serialize(self, message: Any, msgtype: str) -> bytes:
        if self.ros1:
            return bytes(self.store.serialize_ros1(message, msgtype))
        return bytes(self.store.serialize_cdr(message, msgtype))


# --- writers ------------------------------------------------------------------------------------------

AddMessage = Callable[[str, str, int, Any], None]
"""add(topic, message type, stamp in ns, message): log time = publish time = the stamp."""


@contextmanager
def ros2_mcap(path: Path) -> Iterator[tuple[RosMessages, AddMessage]]:
    """A ROS 2 (CDR) MCAP being written with zstd chunks: the message builder, and an `add` that registers
    each topic's schema and channel on first use."""
    messages = RosMessages(ros1=False)
    with path.open("wb") as stream:
        writer = McapWriter(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="sgdslam tests")
        channels: dict[str, int] = {}

        def add(topic: str, msgtype: str, stamp: int, message: Any) -> None:
            if topic not in channels:
                definition, _ = messages.store.generate_msgdef(msgtype, ros_version=2)
                schema = writer.register_schema(msgtype, "ros2msg", definition.encode())
                channels[topic] = writer.register_channel(topic, "cdr", schema)
            writer.add_message(channels[topic], stamp, messages.serialize(message, msgtype), stamp)

        yield messages, add
        writer.finish()



def write_mcap_ros(
    path: Path,
    ros1: bool = False,
    chunk_size: int = 1024,
    extra_scan_topic: str | None = None,
    compression: CompressionType = CompressionType.ZSTD,
) -> Path:
    """ROS 2 (CDR) or ROS 1 messages in an MCAP file with small (zstd) chunks."""
    messages = RosMessages(ros1)
    with path.open("wb") as stream:
        writer = McapWriter(stream, chunk_size=chunk_size, compression=compression)
        writer.start(profile="ros1" if ros1 else "ros2", library="frontends tests")
        channels: dict[str, int] = {}
        for topic, msgtype, log_time, message in messages.recording(extra_scan_topic):
            if topic not in channels:
                definition, _ = messages.store.generate_msgdef(msgtype, ros_version=1 if ros1 else 2)
                name = msgtype.replace("/msg/", "/") if ros1 else msgtype
                schema = writer.register_schema(name, "ros1msg" if ros1 else "ros2msg", definition.encode())
                channels[topic] = writer.register_channel(topic, "ros1" if ros1 else "cdr", schema)
            writer.add_message(channels[topic], log_time, messages.serialize(message, msgtype), log_time)
        writer.finish()
    return path


def write_rosbag1(path: Path, compression: str | None = None, split: int | None = None) -> list[Path]:
    """A ROS 1 bag (one chunk per few messages); with `split`, the first `split` messages go to
    `<stem>_0.bag` and the rest to `<stem>_1.bag`."""
    messages = RosMessages(ros1=True)
    recording = messages.recording()
    parts = [recording] if split is None else [recording[:split], recording[split:]]
    paths = [path] if split is None else [path.with_name(f"{path.stem}_{i}.bag") for i in range(len(parts))]
    for part, part_path in zip(parts, paths, strict=True):
        writer = Rosbag1Writer(part_path)
        if compression is not None:
            writer.set_compression(Rosbag1Writer.CompressionFormat[compression.upper()])
        writer.chunk_threshold = 600
        writer.open()
        connections: dict[str, Any] = {}
        for topic, msgtype, log_time, message in part:
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic, msgtype, typestore=messages.store, latching=1 if topic == "/tf_static" else None
                )
            writer.write(connections[topic], log_time, messages.serialize(message, msgtype))
        writer.close()
    return paths


def write_rosbag2(path: Path, storage: str = "sqlite3", compression: str | None = None) -> Path:
    """A ROS 2 bag directory (metadata.yaml + one .db3 or .mcap), optionally zstd-compressed per "file"
    or per "message"."""
    messages = RosMessages(ros1=False)
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    writer = Rosbag2Writer(path, version=8, storage_plugin=plugin)
    if compression is not None:
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    writer.open()
    connections: dict[str, Any] = {}
    for topic, msgtype, log_time, message in messages.recording():
        if topic not in connections:
            connections[topic] = writer.add_connection(topic, msgtype, typestore=messages.store)
        writer.write(connections[topic], log_time, messages.serialize(message, msgtype))
    writer.close()
    return path


# --- Foxglove ---------------------------------------------------------------------------------------


def _foxglove_file() -> descriptor_pb2.FileDescriptorProto:
    """The Foxglove schemas we read, with Foxglove's field numbers, as one .proto file."""
    f = descriptor_pb2.FieldDescriptorProto
    proto = descriptor_pb2.FileDescriptorProto(
        name="foxglove/test_schemas.proto", package="foxglove", syntax="proto3"
    )
    proto.dependency.append("google/protobuf/timestamp.proto")

    def message(
        name: str, fields: list[tuple[str, int, int, str | None, bool]]
    ) -> descriptor_pb2.DescriptorProto:
        described = proto.message_type.add(name=name)
        for field_name, number, kind, type_name, repeated in fields:
            entry = described.field.add(name=field_name, number=number, type=kind)
            entry.label = f.LABEL_REPEATED if repeated else f.LABEL_OPTIONAL
            if type_name is not None:
                entry.type_name = type_name
        return described

    double, string, message_kind, fixed32, bytes_kind, enum = (
        f.TYPE_DOUBLE,
        f.TYPE_STRING,
        f.TYPE_MESSAGE,
        f.TYPE_FIXED32,
        f.TYPE_BYTES,
        f.TYPE_ENUM,
    )
    stamp = ".google.protobuf.Timestamp"
    message(
        "Vector3",
        [("x", 1, double, None, False), ("y", 2, double, None, False), ("z", 3, double, None, False)],
    )
    message(
        "Quaternion",
        [
            ("x", 1, double, None, False),
            ("y", 2, double, None, False),
            ("z", 3, double, None, False),
            ("w", 4, double, None, False),
        ],
    )
    message(
        "Pose",
        [
            ("position", 1, message_kind, ".foxglove.Vector3", False),
            ("orientation", 2, message_kind, ".foxglove.Quaternion", False),
        ],
    )
    message(
        "LaserScan",
        [
            ("timestamp", 1, message_kind, stamp, False),
            ("frame_id", 2, string, None, False),
            ("pose", 3, message_kind, ".foxglove.Pose", False),
            ("start_angle", 4, double, None, False),
            ("end_angle", 5, double, None, False),
            ("ranges", 6, double, None, True),
            ("intensities", 7, double, None, True),
        ],
    )
    packed = message(
        "PackedElementField",
        [
            ("name", 1, string, None, False),
            ("offset", 2, fixed32, None, False),
            ("type", 3, enum, ".foxglove.PackedElementField.NumericType", False),
        ],
    )
    numeric = packed.enum_type.add(name="NumericType")
    for number, name in enumerate(
        ("UNKNOWN", "UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "FLOAT32", "FLOAT64")
    ):
        numeric.value.add(name=name, number=number)
    message(
        "PointCloud",
        [
            ("timestamp", 1, message_kind, stamp, False),
            ("frame_id", 2, string, None, False),
            ("pose", 3, message_kind, ".foxglove.Pose", False),
            ("point_stride", 4, fixed32, None, False),
            ("fields", 5, message_kind, ".foxglove.PackedElementField", True),
            ("data", 6, bytes_kind, None, False),
        ],
    )
    message(
        "FrameTransform",
        [
            ("timestamp", 1, message_kind, stamp, False),
            ("parent_frame_id", 2, string, None, False),
            ("child_frame_id", 3, string, None, False),
            ("translation", 4, message_kind, ".foxglove.Vector3", False),
            ("rotation", 5, message_kind, ".foxglove.Quaternion", False),
        ],
    )
    message("FrameTransforms", [("transforms", 1, message_kind, ".foxglove.FrameTransform", True)])
    message(
        "PoseInFrame",
        [
            ("timestamp", 1, message_kind, stamp, False),
            ("frame_id", 2, string, None, False),
            ("pose", 3, message_kind, ".foxglove.Pose", False),
        ],
    )
    return proto


def foxglove_classes() -> tuple[bytes, dict[str, Any]]:
    """(serialized FileDescriptorSet, message classes by full name)."""
    timestamp_file = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(timestamp_file)
    foxglove_file = _foxglove_file()
    pool = descriptor_pool.DescriptorPool()
    pool.Add(timestamp_file)
    pool.Add(foxglove_file)
    classes = message_factory.GetMessageClassesForFiles([timestamp_file.name, foxglove_file.name], pool)
    descriptor_set = descriptor_pb2.FileDescriptorSet(file=[timestamp_file, foxglove_file])
    return descriptor_set.SerializeToString(), dict(classes)


def _foxglove_recording() -> list[tuple[str, str, int, dict[str, Any]]]:
    """(topic, schema, log time, message as a JSON-shaped dict) in log order."""

    def stamp(ns: int) -> dict[str, int]:
        return {"sec": ns // 10**9, "nsec": ns % 10**9}

    def quaternion(yaw: float) -> dict[str, float]:
        x, y, z, w = quaternion_from_yaw(yaw)
        return {"x": x, "y": y, "z": z, "w": w}

    out: list[tuple[str, str, int, dict[str, Any]]] = []
    (mx, my, mz), myaw = LASER_MOUNT
    out.append(
        (
            "/tf_static",
            "foxglove.FrameTransform",
            STATIC_STAMP_NS,
            {
                "timestamp": stamp(STATIC_STAMP_NS),
                "parent_frame_id": BASE_FRAME,
                "child_frame_id": SCAN_FRAME,
                "translation": {"x": mx, "y": my, "z": mz},
                "rotation": quaternion(myaw),
            },
        )
    )
    for scan in SCANS:
        n = len(scan.ranges)
        out.append(
            (
                "/scan",
                "foxglove.LaserScan",
                scan.log_time_ns,
                {
                    "timestamp": stamp(scan.stamp_ns),
                    "frame_id": SCAN_FRAME,
                    "pose": {
                        "position": {"x": 0.0, "y": 0.0, "z": 0.0},
                        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    },
                    "start_angle": ANGLE_MIN,
                    "end_angle": ANGLE_MIN + (n - 1) * ANGLE_INCREMENT,
                    "ranges": list(scan.ranges),
                    "intensities": [],
                },
            )
        )
    for pose in POSES:
        out.append(
            (
                "/pose",
                "foxglove.PoseInFrame",
                pose.log_time_ns,
                {
                    "timestamp": stamp(pose.stamp_ns),
                    "frame_id": ODOM_FRAME,
                    "pose": {
                        "position": {"x": pose.x, "y": pose.y, "z": 0.0},
                        "orientation": quaternion(pose.yaw),
                    },
                },
            )
        )
        out.append(
            (
                "/tf",
                "foxglove.FrameTransforms",
                pose.log_time_ns,
                {
                    "transforms": [
                        {
                            "timestamp": stamp(pose.stamp_ns),
                            "parent_frame_id": ODOM_FRAME,
                            "child_frame_id": BASE_FRAME,
                            "translation": {"x": pose.x, "y": pose.y, "z": 0.0},
                            "rotation": quaternion(pose.yaw),
                        }
                    ]
                },
            )
        )
    for cloud in CLOUDS:
        out.append(
            (
                "/points",
                "foxglove.PointCloud",
                cloud.log_time_ns,
                {
                    "timestamp": stamp(cloud.stamp_ns),
                    "frame_id": CLOUD_FRAME,
                    "point_stride": CLOUD_STEP,
                    "fields": [{"name": name, "offset": offset, "type": 7} for name, offset in CLOUD_FIELDS],
                    "data": cloud_buffer(cloud),
                },
            )
        )
    out.sort(key=lambda item: item[2])
    return out


def _fill(message: Any, values: dict[str, Any]) -> Any:
    """A JSON-shaped dict into a protobuf message."""
    for key, value in values.items():
        if key == "timestamp":
            getattr(message, key).seconds = value["sec"]
            getattr(message, key).nanos = value["nsec"]
        elif isinstance(value, dict):
            _fill(getattr(message, key), value)
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            for item in value:
                _fill(getattr(message, key).add(), item)
        elif isinstance(value, list):
            getattr(message, key).extend(value)
        else:
            setattr(message, key, value)
    return message


def write_mcap_foxglove(path: Path, encoding: str = "protobuf") -> Path:
    """The recording in Foxglove schemas, protobuf (schemas as a FileDescriptorSet) or JSON."""
    descriptor_set, classes = foxglove_classes()
    serialize: Callable[[str, dict[str, Any]], bytes]
    if encoding == "protobuf":

        def serialize(schema: str, values: dict[str, Any]) -> bytes:
            return _fill(classes[schema](), values).SerializeToString()

    else:

        def serialize(schema: str, values: dict[str, Any]) -> bytes:
            def default(value: Any) -> Any:
                if isinstance(value, bytes):
                    return base64.b64encode(value).decode()
                raise TypeError(value)

            # Python's json writes NaN / Infinity for non-finite ranges, as Foxglove's JSON encoders do.
            return json.dumps(values, default=default).encode()

    with path.open("wb") as stream:
        writer = McapWriter(stream, chunk_size=2048, compression=CompressionType.LZ4)
        writer.start(profile="", library="frontends tests")
        channels: dict[str, int] = {}
        for topic, schema, log_time, values in _foxglove_recording():
            if topic not in channels:
                schema_data = descriptor_set if encoding == "protobuf" else b"{}"
                schema_id = writer.register_schema(
                    schema, "protobuf" if encoding == "protobuf" else "jsonschema", schema_data
                )
                channels[topic] = writer.register_channel(topic, encoding, schema_id)
            writer.add_message(channels[topic], log_time, serialize(schema, values), log_time)
        writer.finish()
    return path


class ScanListLog:
    """The part of a `LogReader` that `scans_in_base_frame` reads: the scans of a topic, and a path."""

    path = Path("list.log")

    def __init__(self, scans: list[Scan2D]) -> None:
        self._scans = scans

    def scans(self, topic: str) -> list[Scan2D]:
        return self._scans
