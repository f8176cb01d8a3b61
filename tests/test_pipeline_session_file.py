"""The session file format: round trip, other MCAP tools can read it, and damaged or newer files refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from pipeline.session_file import (
    HEADER_TOPIC,
    SESSION_VERSION,
    SessionError,
    read_session,
    write_session,
)


def write(path: Path, header: dict | None = None) -> tuple[dict, list[np.ndarray]]:
    rng = np.random.default_rng(1)
    arrays = {"keyframe_poses": rng.normal(size=(5, 3)), "edge_from": np.arange(4, dtype=np.int64),
              "information": rng.normal(size=(4, 3, 3)).astype(np.float32)}
    points = [rng.normal(size=(n, 2)) for n in (10, 0, 3, 7, 1)]
    with path.open("wb") as stream:
        write_session(stream, header or {"sensor_kind": "scan"}, arrays, points)
    return arrays, points


def test_round_trip_keeps_every_array_bit_for_bit(tmp_path: Path) -> None:
    path = tmp_path / "run.session"
    arrays, points = write(path)
    import pipeline

    content = pipeline.load_session(path)
    assert content.header["sensor_kind"] == "scan"
    assert content.header["version"] == SESSION_VERSION
    assert set(content.arrays) == set(arrays)
    for name, array in arrays.items():
        assert content.arrays[name].dtype == array.dtype
        np.testing.assert_array_equal(content.arrays[name], array)
    assert len(content.keyframe_points) == len(points)
    for read, written in zip(content.keyframe_points, points, strict=True):
        np.testing.assert_array_equal(read, written)


def test_the_official_mcap_reader_reads_it(tmp_path: Path) -> None:
    path = tmp_path / "run.session"
    write(path)
    with path.open("rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        assert reader.get_header().profile == "sgdslam.session"
        topics = [channel.topic for _, channel, _ in reader.iter_messages()]
    assert topics.count(HEADER_TOPIC) == 1
    assert topics.count("/session/keyframe_points") == 5


def test_a_newer_format_is_refused_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "new.session"
    write(path, {"version": SESSION_VERSION + 1})
    with pytest.raises(SessionError, match="newer sgdslam") as caught:
        read_session(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("damage", ["cut-third", "cut-two-thirds", "cut-last-byte", "flip", "empty", "json"])
def test_damaged_files_are_refused(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "run.session"
    write(path)
    data = bytearray(path.read_bytes())
    if damage.startswith("cut"):
        data = data[: {"cut-third": len(data) // 3, "cut-two-thirds": len(data) * 2 // 3}.get(damage, -1)]
    elif damage == "flip":
        data[len(data) // 2] ^= 0xFF  # inside the compressed chunk: its CRC no longer matches
    elif damage == "empty":
        data = bytearray()
    else:
        data = bytearray(json.dumps({"not": "mcap"}).encode())
    path.write_bytes(bytes(data))
    with pytest.raises(SessionError) as caught:
        read_session(path)
    assert str(caught.value).startswith(f"{path}: ")
    assert "\n" not in str(caught.value)


def test_an_mcap_log_is_not_a_session(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "log.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start()
        channel = writer.register_channel("/chatter", "json", 0)
        writer.add_message(channel, 1, b"{}", 1)
        writer.finish()
    with pytest.raises(SessionError, match="not a session file"):
        read_session(path)


def laser_map_arrays() -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """The arrays of a consistent 2D map of two keyframes, one constraint and three scans."""
    arrays = {"keyframe_poses": np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1]]),
              "edge_from": np.array([0], dtype=np.int64), "edge_to": np.array([1], dtype=np.int64),
              "measurements": np.array([[1.0, 0.0, 0.1]]), "information": np.eye(3)[None] * 100.0,
              "is_loop": np.array([False]), "scan_stamps_ns": np.array([1, 2, 3], dtype=np.int64),
              "scan_keyframes": np.array([0, 0, 1], dtype=np.int64), "scan_offsets": np.zeros((3, 3))}
    return arrays, [np.ones((4, 2)), np.ones((5, 2))]


@pytest.mark.parametrize(("damage", "message"), [
    ("drop scan_offsets", r"\(no scan_offsets\)"),
    ("edge to keyframe 2", r"constraints between keyframes that do not exist"),
    ("scan of keyframe 5", r"scans of keyframes that do not exist"),
    ("NaN measurement", r"measurements: values not finite"),
    ("one keyframe scan", r"1 keyframe scans for 2 keyframe poses"),
    ("poses of 4 numbers", r"keyframe_poses: float64 \(2, 4\)"),
])
def test_a_laser_map_whose_arrays_do_not_fit_is_refused_naming_file_and_array(tmp_path: Path, damage: str,
                                                                              message: str) -> None:
    from pipeline.session_file import saved_map_2d

    arrays, points = laser_map_arrays()
    path = tmp_path / "map.session"
    with path.open("wb") as stream:
        write_session(stream, {"sensor_kind": "scan"}, arrays, points)
    saved = saved_map_2d(path, read_session(path))  # the undamaged arrays make a map
    assert saved.graph().num_edges == 1 and saved.scans is not None and len(saved.scans.stamps_ns) == 3
    if damage == "drop scan_offsets":
        del arrays["scan_offsets"]
    elif damage == "edge to keyframe 2":
        arrays["edge_to"] = np.array([2], dtype=np.int64)
    elif damage == "scan of keyframe 5":
        arrays["scan_keyframes"] = np.array([0, 0, 5], dtype=np.int64)
    elif damage == "NaN measurement":
        arrays["measurements"] = np.array([[1.0, np.nan, 0.1]])
    elif damage == "one keyframe scan":
        points = points[:1]
    else:
        arrays["keyframe_poses"] = np.zeros((2, 4))
    with path.open("wb") as stream:
        write_session(stream, {"sensor_kind": "scan"}, arrays, points)
    with pytest.raises(SessionError, match=rf"^{path}: damaged session file .*{message}"):
        saved_map_2d(path, read_session(path))
