"""Foxglove schemas (`foxglove.LaserScan`, `foxglove.PointCloud`, ...) in protobuf or JSON encoding.

Protobuf payloads are parsed with classes built from the schema the file carries (`mcap_protobuf`); JSON
payloads with `json`. The converters read both through the accessors below, which hide the two encodings'
differences (JSON timestamps are `{"sec", "nsec"}`, bytes are base64 text, absent fields are absent).

`mcap_protobuf` (and protobuf's descriptors behind it, 0.1 s of a replay's start-up) is imported only once a
protobuf channel is decoded: logs of ROS messages never need it.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Callable
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Schema

from frontends.logs.containers.base import Channel


class FoxgloveDecodeError(ValueError):
    """A Foxglove payload or schema cannot be decoded."""


def payload_decoder(channel: Channel) -> Callable[[bytes | memoryview], Any]:
    """bytes → protobuf message or JSON object, for a protobuf or JSON channel."""
    if channel.encoding == "protobuf":
        from google.protobuf.message import DecodeError
        from mcap_protobuf.decoder import DecoderFactory

        try:
            decode = DecoderFactory().decoder_for(
                "protobuf",
                Schema(
                    id=1, data=channel.schema_data, encoding=channel.schema_encoding, name=channel.schema_name
                ),
            )
        except (McapError, DecodeError, TypeError, KeyError) as err:
            raise FoxgloveDecodeError(f"unusable protobuf schema {channel.schema_name!r}: {err}") from None
        if decode is None:
            raise FoxgloveDecodeError(
                f"channel has no protobuf schema (schema encoding {channel.schema_encoding!r})"
            )

        def decode_protobuf(data: bytes | memoryview) -> Any:
            try:
                return decode(bytes(data))
            except DecodeError as err:
                raise FoxgloveDecodeError(f"bad protobuf payload: {err}") from None

        return decode_protobuf

    def decode_json(data: bytes | memoryview) -> Any:
        try:
            message = json.loads(bytes(data))
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise FoxgloveDecodeError(f"bad JSON payload: {err}") from None
        if not isinstance(message, dict):
            raise FoxgloveDecodeError("JSON payload is not an object")
        return message

    return decode_json


def field(message: Any, name: str, default: Any = None) -> Any:
    """A field of a protobuf message or JSON object (protobuf gives its own defaults for unset fields)."""
    if isinstance(message, dict):
        return message.get(name, default)
    return getattr(message, name)


def stamp_ns(timestamp: Any) -> int:
    """google.protobuf.Timestamp or JSON {"sec", "nsec"} → ns; absent → 0."""
    if timestamp is None:
        return 0
    if isinstance(timestamp, dict):
        return int(timestamp.get("sec", 0)) * 1_000_000_000 + int(timestamp.get("nsec", 0))
    return int(timestamp.seconds) * 1_000_000_000 + int(timestamp.nanos)


def vector3(vector: Any) -> tuple[float, float, float]:
    """foxglove.Vector3 (or a position) → (x, y, z); absent components are 0."""
    if vector is None:
        return (0.0, 0.0, 0.0)
    return (float(field(vector, "x", 0.0)), float(field(vector, "y", 0.0)), float(field(vector, "z", 0.0)))


def quaternion(rotation: Any) -> tuple[float, float, float, float]:
    """foxglove.Quaternion → (x, y, z, w). An absent quaternion is the identity; an all-zero one (protobuf's
    unset default) is normalized to the identity by the converters."""
    if rotation is None:
        return (0.0, 0.0, 0.0, 1.0)
    if isinstance(rotation, dict):
        return (
            float(rotation.get("x", 0.0)),
            float(rotation.get("y", 0.0)),
            float(rotation.get("z", 0.0)),
            float(rotation.get("w", 1.0)),
        )
    return (float(rotation.x), float(rotation.y), float(rotation.z), float(rotation.w))


def pose(message: Any) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """The `pose` (foxglove.Pose) of a message, or of a Pose itself → (position, orientation)."""
    if message is None:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)
    return vector3(field(message, "position")), quaternion(field(message, "orientation"))


def binary(value: Any) -> bytes:
    """A bytes field: raw in protobuf, base64 text in JSON."""
    if value is None:
        return b""
    if isinstance(value, str):
        try:
            return base64.b64decode(value, validate=True)
        except ValueError as err:
            raise FoxgloveDecodeError(f"bad base64 data: {err}") from None
    return bytes(value)
