"""`ros_wire.tf_message`, written out flat for speed, against the same message read field by field with
`ros_wire._Cursor` (the way every other message is read): random TFMessages in little- and big-endian CDR
and ROS 1 give the same fields, and truncated or corrupted payloads the same result or the same
`WireError`."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from frontends.logs.decoding import ros_wire
from frontends.logs.decoding.ros_wire import TransformStampedFields, WireError

FORMATS = [("<", True), (">", True), ("<", False)]
FORMAT_IDS = ["cdr-little", "cdr-big", "ros1"]
FRAME_NAMES = ["", "odom", "base_link", "laser", "späti_ø", "a" * 37]


def tf_message_by_cursor(data: bytes, cdr: bool) -> list[TransformStampedFields]:
    """The reference: the TFMessage layout read one field at a time."""
    cursor = ros_wire._Cursor(data, cdr)
    count = cursor.u32()
    if count > len(data):
        raise WireError("transform count exceeds the payload")
    out = []
    for _ in range(count):
        stamp_ns, frame_id = cursor.header()
        child_frame_id = cursor.string()
        out.append(TransformStampedFields(stamp_ns, frame_id, child_frame_id, cursor.pose()))
    return out


def serialize(transforms: list[TransformStampedFields], endian: str, cdr: bool) -> bytes:
    out = bytearray(b"\x00\x01\x00\x00" if endian == "<" else b"\x00\x00\x00\x00") if cdr else bytearray()
    origin = len(out)

    def align(size: int) -> None:
        if cdr:
            out.extend(b"\x00" * (-(len(out) - origin) % size))

    def string(text: str) -> None:
        raw = text.encode() + (b"\x00" if cdr else b"")
        align(4)
        out.extend(struct.pack(endian + "I", len(raw)) + raw)

    align(4)
    out.extend(struct.pack(endian + "I", len(transforms)))
    for stamp_ns, frame_id, child_frame_id, pose in transforms:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        if not cdr:
            out.extend(struct.pack(endian + "I", 7))  # seq
        align(4)
        out.extend(struct.pack(endian + ("iI" if cdr else "II"), sec, nanosec))
        string(frame_id)
        string(child_frame_id)
        align(8)
        out.extend(struct.pack(endian + "7d", *pose))
    return bytes(out)


def random_message(rng: np.random.Generator) -> list[TransformStampedFields]:
    return [
        TransformStampedFields(
            int(rng.integers(0, 2**31 - 1)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000)),
            FRAME_NAMES[int(rng.integers(len(FRAME_NAMES)))],
            FRAME_NAMES[int(rng.integers(len(FRAME_NAMES)))],
            tuple(float(v) for v in rng.normal(size=7)),
        )
        for _ in range(int(rng.integers(0, 4)))
    ]


def outcome(decode: object, data: bytes | memoryview, cdr: bool) -> object:
    """The fields read (each pose as its bytes: a corrupted one may be NaN) or the error raised."""
    try:
        message = decode(data, cdr)  # type: ignore[operator]
    except WireError as error:
        return ("WireError", str(error))
    return [(*transform[:3], struct.pack("<7d", *transform.transform)) for transform in message]


@pytest.mark.parametrize(("endian", "cdr"), FORMATS, ids=FORMAT_IDS)
def test_random_tf_messages_decode_as_the_cursor_reads_them(endian: str, cdr: bool) -> None:
    rng = np.random.default_rng(20261130)
    for _ in range(300):
        message = random_message(rng)
        payload = serialize(message, endian, cdr)
        assert ros_wire.tf_message(payload, cdr) == message
        assert ros_wire.tf_message(memoryview(payload), cdr) == tf_message_by_cursor(payload, cdr) == message


@pytest.mark.parametrize(("endian", "cdr"), FORMATS, ids=FORMAT_IDS)
def test_truncated_tf_messages_raise_the_cursors_wire_error(endian: str, cdr: bool) -> None:
    rng = np.random.default_rng(7)
    for _ in range(40):
        payload = serialize(random_message(rng), endian, cdr)
        for cut in range(len(payload)):
            fast = outcome(ros_wire.tf_message, payload[:cut], cdr)
            assert fast == outcome(tf_message_by_cursor, payload[:cut], cdr)


@pytest.mark.parametrize(("endian", "cdr"), FORMATS, ids=FORMAT_IDS)
def test_corrupted_tf_messages_give_the_cursors_result_or_error(endian: str, cdr: bool) -> None:
    rng = np.random.default_rng(11)
    for _ in range(2000):
        payload = bytearray(serialize(random_message(rng), endian, cdr))
        if not payload:
            continue
        for _ in range(int(rng.integers(1, 4))):
            payload[int(rng.integers(len(payload)))] = int(rng.integers(256))
        data = bytes(payload)
        assert outcome(ros_wire.tf_message, data, cdr) == outcome(tf_message_by_cursor, data, cdr)


def test_tf_message_errors_name_what_is_wrong() -> None:
    good = serialize([TransformStampedFields(5, "odom", "base_link", (0.0,) * 7)], "<", True)
    with pytest.raises(WireError, match="unsupported CDR encapsulation"):
        ros_wire.tf_message(b"\x01\x01" + good[2:], True)
    with pytest.raises(WireError, match="payload ends early"):
        ros_wire.tf_message(good[:6], True)
    with pytest.raises(WireError, match="transform count exceeds the payload"):
        ros_wire.tf_message(good[:4] + struct.pack("<I", 10**6) + good[8:], True)
    with pytest.raises(WireError, match="string runs past the payload"):
        ros_wire.tf_message(good[:16] + struct.pack("<I", 10**6) + good[20:], True)
    with pytest.raises(WireError, match="string is not UTF-8"):
        ros_wire.tf_message(good[:20] + b"\xff" + good[21:], True)
    with pytest.raises(WireError, match="payload ends early"):
        ros_wire.tf_message(good[:-1], True)
