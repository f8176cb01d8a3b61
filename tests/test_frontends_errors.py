"""Bad input: one-line errors naming the file (and message index), damaged logs read up to what is intact
with a warning of what was lost. No tracebacks from the libraries underneath, no hangs."""

from __future__ import annotations

import re
import shutil
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag2 import Writer as Rosbag2Writer

from frontends.errors import FrontendError, LogFileError, LogWarning, TopicSelectionError
from frontends.logs import open_log
from tests._frontends_fixtures import RosMessages, ScanTruth, write_mcap_ros, write_rosbag1, write_rosbag2


def truncated_copy(source: Path, target: Path, fraction: float) -> Path:
    data = source.read_bytes()
    target.write_bytes(data[: int(len(data) * fraction)])
    return target


def mcap_data_end(data: bytes) -> int:
    """Where an MCAP's summary section starts (the footer's summary_start), i.e. the end of its data."""
    footer = len(data) - 8 - 29
    return int(struct.unpack_from("<Q", data, footer + 9)[0])


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(LogFileError, match=r"nothing\.mcap: no such file or directory$"):
        open_log(tmp_path / "nothing.mcap")


def test_empty_file(tmp_path: Path) -> None:
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(LogFileError) as raised:
        open_log(tmp_path / "empty.mcap")
    assert str(raised.value) == f"{tmp_path / 'empty.mcap'}: empty file"


def test_not_a_log(tmp_path: Path) -> None:
    (tmp_path / "notes.bag").write_text("shopping list\n")
    with pytest.raises(
        LogFileError, match=r"notes\.bag: not a log \(expected an MCAP file, a ROS 1 bag or a ROS 2 bag\)"
    ):
        open_log(tmp_path / "notes.bag")


def test_old_ros1_bag_format(tmp_path: Path) -> None:
    (tmp_path / "old.bag").write_bytes(b"#ROSBAG V1.2\n" + bytes(100))
    with pytest.raises(LogFileError, match=r"ROS 1 bag format 1\.2 is not supported"):
        open_log(tmp_path / "old.bag")


def test_directory_without_a_log(tmp_path: Path) -> None:
    (tmp_path / "readme.txt").write_text("hi")
    with pytest.raises(LogFileError, match=r"no log in this directory"):
        open_log(tmp_path)


def test_a_directory_with_logs_of_two_kinds_is_refused_not_guessed(tmp_path: Path) -> None:
    """A bag and an MCAP side by side (a recording and its conversion, or two runs): which one was meant
    is the user's to say, as with two MCAP files (before: the bag, silently)."""
    write_rosbag1(tmp_path / "building.bag")
    write_mcap_ros(tmp_path / "corridor.mcap")
    with pytest.raises(LogFileError, match=r"more than one kind .*: building\.bag, corridor\.mcap; name one"):
        open_log(tmp_path)


def test_ros2_bag_missing_its_storage_file(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag")
    (bag / "bag.db3").unlink()
    with pytest.raises(LogFileError) as raised:
        open_log(bag)
    assert str(raised.value) == f"{bag}: ROS 2 bag is missing its storage file bag.db3"


def test_ros2_bag_with_broken_metadata(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    with pytest.raises(LogFileError, match=r"metadata\.yaml: not valid YAML"):
        open_log(bag)
    (bag / "metadata.yaml").write_text("something_else: 1\n")
    with pytest.raises(LogFileError, match=r"metadata\.yaml: not ROS 2 bag metadata"):
        open_log(bag)


def test_ros2_db3_opened_directly(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag")
    (bag / "metadata.yaml").unlink()
    log = open_log(bag / "bag.db3")
    assert log.info().container == "rosbag2-sqlite3"
    assert {t.name: t.count for t in log.info().topics}["/scan"] == 5
    assert len(list(log.scans())) == 5


def test_bad_payload_names_topic_and_message_index(tmp_path: Path) -> None:
    messages = RosMessages(ros1=False)
    path = tmp_path / "bad.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream, compression=CompressionType.NONE)
        writer.start("ros2", "test")
        schema = writer.register_schema("sensor_msgs/msg/LaserScan", "ros2msg", b"")
        channel = writer.register_channel("/scan", "cdr", schema)
        for i, (_, msgtype, log_time, message) in enumerate(
            m for m in messages.recording() if m[0] == "/scan"
        ):
            data = messages.serialize(message, msgtype)
            writer.add_message(channel, log_time, data[:30] if i == 2 else data, log_time)
        writer.finish()
    log = open_log(path)
    with pytest.raises(LogFileError) as raised:
        list(log.scans())
    text = str(raised.value)
    assert text.startswith(f"{path}: cannot decode sensor_msgs/msg/LaserScan on /scan: ")
    assert text.endswith(" #2")
    assert raised.value.message_index == 2
    assert "\n" not in text


def test_unusable_protobuf_schema(tmp_path: Path) -> None:
    path = tmp_path / "fox.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start("", "test")
        schema = writer.register_schema("foxglove.LaserScan", "protobuf", b"not a descriptor set")
        channel = writer.register_channel("/scan", "protobuf", schema)
        writer.add_message(channel, 1, b"", 1)
        writer.finish()
    with pytest.raises(
        LogFileError, match=r"fox\.mcap: cannot read foxglove\.LaserScan on /scan: unusable protobuf schema"
    ):
        list(open_log(path).scans())


def test_unknown_encoding_is_not_a_candidate(tmp_path: Path) -> None:
    path = tmp_path / "flat.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start("", "test")
        schema = writer.register_schema("foxglove.LaserScan", "flatbuffer", b"")
        channel = writer.register_channel("/scan", "flatbuffer", schema)
        writer.add_message(channel, 1, b"", 1)
        writer.finish()
    with pytest.raises(
        TopicSelectionError, match=r"no LaserScan topic; the log has: /scan \(foxglove\.LaserScan\)"
    ):
        open_log(path).scans()


def _scan_stamps(path: Path) -> list[int]:
    return [scan.stamp_ns for scan in open_log(path).scans()]


def test_truncated_mcap_reads_what_is_intact(tmp_path: Path) -> None:
    whole = write_mcap_ros(tmp_path / "whole.mcap", chunk_size=512)
    expected = _scan_stamps(whole)
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(mcap_data_end(data) * 0.55)])
    with pytest.warns(LogWarning, match=r"cut\.mcap: file is truncated"):
        info = open_log(cut).info()
    intact = {t.name: t.count for t in info.topics}["/scan"]
    assert 0 < intact < 5
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stamps = _scan_stamps(cut)
    texts = [str(w.message) for w in caught if issubclass(w.category, LogWarning)]
    assert len(texts) == 1 and texts[0].startswith(f"{cut}: file is truncated")
    assert stamps == expected[: len(stamps)] and len(stamps) == intact
    # One log read several times (its summary, then its scans, as a replay does): one warning, the same
    # words each time (before: one a pass, each ending with that pass's count, so never merged).
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = open_log(cut)
        log.info()
        list(log.scans())
        list(log.scans())
    assert len([w for w in caught if issubclass(w.category, LogWarning)]) == 1


def test_truncated_mcap_inside_a_chunk_estimates_the_loss(tmp_path: Path) -> None:
    # One uncompressed chunk holds everything (a zstd block cut in half decodes to nothing).
    whole = write_mcap_ros(tmp_path / "whole.mcap", chunk_size=1 << 20, compression=CompressionType.NONE)
    expected = _scan_stamps(whole)
    data = whole.read_bytes()
    position = 8  # walk the records (opcode u8, length u64) to the chunk (opcode 6) and cut its middle
    while data[position] != 0x06:
        position += 9 + struct.unpack_from("<Q", data, position + 1)[0]
    chunk_length = struct.unpack_from("<Q", data, position + 1)[0]
    (tmp_path / "cut.mcap").write_bytes(data[: position + 9 + chunk_length // 2])
    with pytest.warns(
        LogWarning, match=r"ends inside a chunk record .*; about (\d+) messages of that record are lost"
    ) as record:
        items = list(open_log(tmp_path / "cut.mcap").messages(["/scan", "/odom", "/tf", "/points"]))
    read = len(items)
    estimate = int(re.search(r"about (\d+) messages", str(record[0].message)).group(1))
    assert 0 < read < 17
    assert estimate > 0  # (missing bytes / mean message size: rough here, where schemas fill the chunk)
    with pytest.warns(LogWarning):
        stamps = _scan_stamps(tmp_path / "cut.mcap")
    assert stamps == expected[: len(stamps)]


def test_truncated_bag_reads_what_is_intact(tmp_path: Path) -> None:
    whole = write_rosbag1(tmp_path / "whole.bag", compression="lz4")[0]
    expected = _scan_stamps(whole)
    cut = truncated_copy(whole, tmp_path / "cut.bag", 0.5)
    with pytest.warns(LogWarning, match=r"cut\.bag: bag is truncated: it ends inside a record at byte \d+"):
        stamps = _scan_stamps(cut)
    assert 0 < len(stamps) < 5
    assert stamps == expected[: len(stamps)]


def test_bag_without_index_is_read_front_to_back(tmp_path: Path) -> None:
    whole = write_rosbag1(tmp_path / "whole.bag")[0]
    data = whole.read_bytes()
    index_position = struct.unpack_from("<Q", data, data.index(b"index_pos=") + len(b"index_pos="))[0]
    (tmp_path / "unindexed.bag").write_bytes(data[:index_position])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing was lost: no warning
        assert _scan_stamps(tmp_path / "unindexed.bag") == _scan_stamps(whole)
        assert {t.name: t.count for t in open_log(tmp_path / "unindexed.bag").info().topics}["/scan"] == 5


def test_truncated_ros2_sqlite_counts_lost_messages(tmp_path: Path) -> None:
    messages = RosMessages(ros1=False)
    bag = tmp_path / "long"
    writer = Rosbag2Writer(bag, version=8)
    writer.open()
    connection = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=messages.store)
    for i in range(300):
        truth = ScanTruth(10**18 + i * 10**8, 10**18 + i * 10**8, tuple(np.linspace(1.0, 5.0, 360)))
        data = messages.serialize(messages.laser_scan(truth), "sensor_msgs/msg/LaserScan")
        writer.write(connection, truth.log_time_ns, data)
    writer.close()
    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(bag / "metadata.yaml", cut / "metadata.yaml")
    truncated_copy(bag / "long.db3", cut / "long.db3", 0.7)
    with pytest.warns(
        LogWarning, match=r"storage file long\.db3 is truncated or damaged: (\d+) of 300 messages lost"
    ) as record:
        stamps = _scan_stamps(cut)
    assert 0 < len(stamps) < 300
    assert f"{300 - len(stamps)} of 300 messages lost" in str(record[0].message)
    assert stamps == [10**18 + i * 10**8 for i in range(len(stamps))]
    assert (bag / "long.db3").stat().st_size > (cut / "long.db3").stat().st_size  # the original is untouched


def test_errors_are_frontend_errors() -> None:
    assert issubclass(LogFileError, FrontendError)
    assert issubclass(TopicSelectionError, FrontendError)
