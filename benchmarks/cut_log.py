"""Cut a ROS 2 MCAP log (laser scans or point clouds) in two at its middle scan or cloud, as two recordings
of the same place made apart: the second part's odometry (/odom and the odom → base /tf), when the log has
one, re-expressed from its own first pose.

    python benchmarks/cut_log.py ../shared/data/logs/aces/aces.mcap /tmp/aces   # aces_first/second.mcap
    replay /tmp/aces/aces_first.mcap -o /tmp/aces/rec
    replay /tmp/aces/aces_second.mcap -o /tmp/aces/rec_map --map /tmp/aces/rec/aces_first.session
    replay /tmp/aces/aces_second.mcap -o /tmp/aces/rec_cont --continue /tmp/aces/rec/aces_first.session
    python benchmarks/cut_log.py ../shared/data/logs/kitti/kitti_city.mcap /tmp/kitti   # clouds, no odometry

Messages are copied as they are (schemas, channels, stamps); /tf_static goes into both parts. Only the
odometry of the second part is decoded and written again (rosbags' CDR serializer, as the tests' logs).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests._frontends_fixtures import ros_typestore  # noqa: E402

SENSOR_SCHEMAS = ("sensor_msgs/msg/LaserScan", "sensor_msgs/msg/PointCloud2")
"""The log is cut at the middle message of its sensor topic (the first topic of one of these types)."""

Row = tuple[Any, Any, Any]
"""(schema, channel, message) as the mcap reader gives them."""


def yaw_of(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class Rebased:
    """Planar poses seen from the first one given (the second recording's odometry origin)."""

    def __init__(self) -> None:
        self.origin: tuple[float, float, float] | None = None

    def pose(self, position: Any, orientation: Any) -> tuple[Any, Any]:
        yaw = yaw_of(orientation)
        if self.origin is None:
            self.origin = (position.x, position.y, yaw)
        x0, y0, yaw0 = self.origin
        c, s = math.cos(yaw0), math.sin(yaw0)
        dx, dy = position.x - x0, position.y - y0
        turned = math.atan2(math.sin(yaw - yaw0), math.cos(yaw - yaw0))
        half = turned / 2
        return (dataclasses.replace(position, x=c * dx + s * dy, y=-s * dx + c * dy),
                dataclasses.replace(orientation, x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)))


def rebased_data(store: Any, rebased: Rebased, schema: Any, topic: str, data: bytes) -> bytes:
    """The odometry message `data` with its pose seen from the first odometry pose of the part."""
    message = store.deserialize_cdr(data, schema.name)
    if topic == "/odom":
        pose = message.pose.pose
        position, orientation = rebased.pose(pose.position, pose.orientation)
        pose = dataclasses.replace(pose, position=position, orientation=orientation)
        message = dataclasses.replace(message, pose=dataclasses.replace(message.pose, pose=pose))
    else:
        transforms = []
        for stamped in message.transforms:
            translation, rotation = rebased.pose(stamped.transform.translation, stamped.transform.rotation)
            transform = dataclasses.replace(stamped.transform, translation=translation, rotation=rotation)
            transforms.append(dataclasses.replace(stamped, transform=transform))
        message = dataclasses.replace(message, transforms=transforms)
    return bytes(store.serialize_cdr(message, schema.name))


def write_part(path: Path, rows: list[Row], rebased: Rebased | None) -> None:
    store = ros_typestore(False)
    with path.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="sgdslam benchmarks/cut_log.py")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in rows:
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id])
            data = message.data
            if rebased is not None and channel.topic in ("/odom", "/tf"):
                data = rebased_data(store, rebased, schema, channel.topic, data)
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time,
                               message.sequence)
        writer.finish()


def cut(log: Path, out: Path) -> tuple[Path, Path, str]:
    """`log` cut at its middle scan or cloud into `out`/<stem>_first.mcap and <stem>_second.mcap (the
    second's odometry seen from its first pose); returns both paths and a line describing the cut."""
    with log.open("rb") as stream:
        rows = list(make_reader(stream).iter_messages(log_time_order=True))
    sensor_topic = next(channel.topic for schema, channel, _ in rows if schema.name in SENSOR_SCHEMAS)
    scan_times = [message.log_time for _, channel, message in rows if channel.topic == sensor_topic]
    middle = scan_times[len(scan_times) // 2]
    static = [row for row in rows if row[1].topic == "/tf_static"]
    moving = [row for row in rows if row[1].topic != "/tf_static"]
    out.mkdir(parents=True, exist_ok=True)
    first, second_path = out / f"{log.stem}_first.mcap", out / f"{log.stem}_second.mcap"
    write_part(first, static + [r for r in moving if r[2].log_time < middle], None)
    second = [r for r in moving if r[2].log_time >= middle]
    # /odom and /tf carry the same odometry: both seen from the part's first /odom pose.
    rebased = Rebased()
    first_odometry = next((r for r in second if r[1].topic == "/odom"), None)
    if first_odometry is not None:
        rebased_data(ros_typestore(False), rebased, first_odometry[0], "/odom", first_odometry[2].data)
    write_part(second_path, static + second, rebased)
    described = f"{len(scan_times)} messages on {sensor_topic}; cut at {middle * 1e-9:.3f} s: "
    return first, second_path, f"{described}{first}, {second_path}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path, help="a ROS 2 MCAP with LaserScan or PointCloud2 messages "
                                               "(and optionally /odom, /tf, /tf_static)")
    parser.add_argument("out", type=Path, help="folder for <stem>_first.mcap and <stem>_second.mcap")
    args = parser.parse_args()
    print(cut(args.log, args.out)[2])


if __name__ == "__main__":
    main()
