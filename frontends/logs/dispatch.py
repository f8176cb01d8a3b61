"""The one message-dispatch layer: which channels we can read, and raw messages → typed items.

Every container produces the same `RawMessage`s; here a channel's (encoding, type) picks a wire decoder
and the converter of its message kind, and decoding failures become one-line `LogFileError`s naming the
file, topic and message index.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from frontends.errors import LogFileError
from frontends.logs import converters
from frontends.logs.containers.base import Channel, RawMessage
from frontends.logs.converters import BearingTable, RangeLimits
from frontends.logs.decoding import foxglove, ros_wire
from frontends.logs.types import Cloud3D, OdometryPose, Scan2D, Transform

Kind = Literal["scan", "cloud", "odometry", "transform"]
Item = Scan2D | Cloud3D | OdometryPose | Transform
Decoder = Callable[[bytes | memoryview, int], list[Item]]

ROS_TYPES: dict[str, Kind] = {
    "sensor_msgs/msg/LaserScan": "scan",
    "sensor_msgs/msg/MultiEchoLaserScan": "scan",  # its beams' first echoes (Cartographer's 2D bags)
    "sensor_msgs/msg/PointCloud2": "cloud",
    "nav_msgs/msg/Odometry": "odometry",
    "tf2_msgs/msg/TFMessage": "transform",
    "tf/msg/tfMessage": "transform",  # ROS 1 before tf2 (Groovy and older bags): the same layout
}
FOXGLOVE_TYPES: dict[str, Kind] = {
    "foxglove.LaserScan": "scan",
    "foxglove.PointCloud": "cloud",
    "foxglove.PoseInFrame": "odometry",
    "foxglove.PosesInFrame": "odometry",
    "foxglove.FrameTransform": "transform",
    "foxglove.FrameTransforms": "transform",
}
_ROS_ENCODINGS = {"cdr": True, "ros1": False}  # message encoding → is CDR
_FOXGLOVE_ENCODINGS = ("protobuf", "json")

# Errors a payload that does not fit its declared type can raise while decoding or converting.
_DECODE_ERRORS = (ValueError, struct.error, TypeError, AttributeError, KeyError, IndexError, OverflowError)


def message_kind(channel: Channel) -> Kind | None:
    """What a channel's messages become, or None when we cannot read them."""
    if channel.encoding in _ROS_ENCODINGS:
        return ROS_TYPES.get(channel.type)
    if channel.encoding in _FOXGLOVE_ENCODINGS:
        return FOXGLOVE_TYPES.get(channel.type)
    return None


def is_static_topic(topic: str) -> bool:
    """Transforms on `/tf_static` (or a namespaced `…/tf_static`) hold at all times."""
    return topic.rstrip("/").endswith("tf_static")


@dataclass(frozen=True, slots=True)
class DecodeOptions:
    """Choices that change what the converters keep."""

    range_limits: RangeLimits = field(default_factory=RangeLimits)


def make_decoder(channel: Channel, options: DecodeOptions) -> Decoder:
    """payload, log time → items, for a channel `message_kind` accepts."""
    kind = message_kind(channel)
    static = is_static_topic(channel.topic)
    if channel.encoding in _ROS_ENCODINGS:
        cdr = _ROS_ENCODINGS[channel.encoding]
        if kind == "scan":
            bearings = BearingTable()
            limits = options.range_limits
            fields = (ros_wire.multi_echo_laser_scan if channel.type.endswith("MultiEchoLaserScan")
                      else ros_wire.laser_scan)

            def scan(data: bytes | memoryview, log_time_ns: int) -> list[Item]:
                return [converters.ros_laser_scan(fields(data, cdr), log_time_ns, limits, bearings)]

            return scan
        if kind == "cloud":
            return lambda data, log_time_ns: [
                converters.ros_point_cloud2(ros_wire.point_cloud2(data, cdr), log_time_ns)
            ]
        if kind == "odometry":
            return lambda data, log_time_ns: [
                converters.ros_odometry(ros_wire.odometry(data, cdr), log_time_ns)
            ]
        if kind == "transform":
            return lambda data, log_time_ns: list(
                converters.ros_tf_message(ros_wire.tf_message(data, cdr), log_time_ns, static)
            )
    elif kind is not None:
        parse = foxglove.payload_decoder(channel)
        if kind == "scan":
            bearings = BearingTable()
            limits = options.range_limits
            return lambda data, log_time_ns: [
                converters.foxglove_laser_scan(parse(data), log_time_ns, limits, bearings)
            ]
        if kind == "cloud":
            return lambda data, log_time_ns: [converters.foxglove_point_cloud(parse(data), log_time_ns)]
        if channel.type == "foxglove.FrameTransform":
            return lambda data, log_time_ns: list(
                converters.foxglove_frame_transform(parse(data), log_time_ns, static)
            )
        if channel.type == "foxglove.FrameTransforms":
            return lambda data, log_time_ns: list(
                converters.foxglove_frame_transforms(parse(data), log_time_ns, static)
            )
        if channel.type == "foxglove.PoseInFrame":
            return lambda data, log_time_ns: list(converters.foxglove_pose_in_frame(parse(data), log_time_ns))
        if channel.type == "foxglove.PosesInFrame":
            return lambda data, log_time_ns: list(
                converters.foxglove_poses_in_frame(parse(data), log_time_ns)
            )
    raise ValueError(f"no decoder for {channel.type!r} in {channel.encoding!r} encoding")


def build_decoders(path: Path, channels: Iterable[Channel], options: DecodeOptions) -> dict[int, Decoder]:
    """Decoders of these channels; a channel whose schema is unusable is a `LogFileError`."""
    decoders = {}
    for channel in channels:
        try:
            decoders[channel.id] = make_decoder(channel, options)
        except (foxglove.FoxgloveDecodeError, ValueError) as err:
            raise LogFileError(path, f"cannot read {channel.type} on {channel.topic}: {err}") from None
    return decoders


def decode(path: Path, messages: Iterable[RawMessage], decoders: Mapping[int, Decoder]) -> Iterator[Item]:
    """Typed items of the messages, in the messages' order."""
    counts: dict[int, int] = dict.fromkeys(decoders, 0)
    for message in messages:
        channel = message.channel
        index = counts[channel.id]
        counts[channel.id] = index + 1
        try:
            items = decoders[channel.id](message.data, message.log_time_ns)
        except _DECODE_ERRORS as err:
            raise LogFileError(
                path, f"cannot decode {channel.type} on {channel.topic}: {err}; in message", index
            ) from None
        yield from items
