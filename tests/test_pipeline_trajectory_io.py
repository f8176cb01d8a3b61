"""TUM trajectory files: exact round trips (stamps as integer nanoseconds), the three pose layouts, and
one-line errors naming file:line for bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.errors import OutputError, PipelineError
from pipeline.trajectory_io import (
    TrajectoryFileError,
    format_stamp_ns,
    parse_stamp_ns,
    read_tum,
    write_tum,
)

INT64 = st.integers(min_value=-(2**63), max_value=2**63 - 1)
FINITE = st.floats(allow_nan=False, allow_infinity=False)


def bits(array: np.ndarray) -> np.ndarray:
    """The float64 bit patterns, so that equality also tells -0.0 from 0.0."""
    return np.ascontiguousarray(array, dtype=np.float64).view(np.int64)


# ------------------------------------------------------------------------------------------- round trips


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_tum_rows_round_trip_exactly(tmp_path: Path, data: st.DataObject) -> None:
    count = data.draw(st.integers(min_value=1, max_value=12))
    stamps = np.array(data.draw(st.lists(INT64, min_size=count, max_size=count)), dtype=np.int64)
    rows = data.draw(arrays(np.float64, (count, 7), elements=FINITE))
    rows[~np.any(rows[:, 3:] != 0.0, axis=1), 6] = 1.0  # a zero quaternion is rejected on reading
    path = tmp_path / "trajectory.tum"
    write_tum(path, stamps, rows)
    trajectory = read_tum(path)
    np.testing.assert_array_equal(trajectory.stamps_ns, stamps)
    assert trajectory.stamps_ns.dtype == np.int64
    np.testing.assert_array_equal(bits(trajectory.positions), bits(rows[:, :3]))
    np.testing.assert_array_equal(bits(trajectory.quaternions), bits(rows[:, 3:]))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    stamps=st.lists(st.integers(min_value=0, max_value=2**62), min_size=1, max_size=10),
    data=st.data(),
)
def test_planar_poses_round_trip(tmp_path: Path, stamps: list[int], data: st.DataObject) -> None:
    count = len(stamps)
    xy = data.draw(arrays(np.float64, (count, 2), elements=st.floats(-1e6, 1e6)))
    theta = data.draw(arrays(np.float64, (count,), elements=st.floats(-math.pi + 1e-9, math.pi - 1e-9)))
    poses = np.column_stack((xy, theta))
    path = tmp_path / "planar.tum"
    write_tum(path, np.array(stamps, dtype=np.int64), poses)
    trajectory = read_tum(path)
    assert trajectory.stamps_ns.tolist() == stamps
    np.testing.assert_array_equal(trajectory.positions, np.column_stack((xy, np.zeros(count))))
    expected_quaternions = [[0.0, 0.0, math.sin(t / 2), math.cos(t / 2)] for t in theta]
    np.testing.assert_allclose(trajectory.quaternions, expected_quaternions, rtol=0, atol=2e-16)
    planar = trajectory.planar()
    np.testing.assert_array_equal(planar[:, :2], xy)
    np.testing.assert_allclose(planar[:, 2], theta, rtol=0, atol=1e-12)


def test_stamps_a_float_cannot_hold_are_written_and_read_exactly(tmp_path: Path) -> None:
    stamps = np.array([1_700_000_000_123_456_789, 1_700_000_000_123_456_790, -1, 0, 2**63 - 1, -(2**63)])
    assert float(stamps[0]) == float(stamps[1])  # what a float64 would have made of them
    path = tmp_path / "stamps.tum"
    write_tum(path, stamps, np.zeros((len(stamps), 3)))
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#")
    assert [line.split()[0] for line in lines[1:]] == [
        "1700000000.123456789", "1700000000.123456790", "-0.000000001", "0.000000000",
        "9223372036.854775807", "-9223372036.854775808",
    ]
    assert read_tum(path).stamps_ns.tolist() == stamps.tolist()


def test_lines_are_what_evo_reads(tmp_path: Path) -> None:
    """evo splits on single spaces and skips lines starting with '#': 8 fields, no stray blanks."""
    path = tmp_path / "evo.tum"
    write_tum(path, np.array([10, 20]), np.array([[0.1, 2.0, 0.5], [3.0, -4.0, -1.0]]))
    text = path.read_text()
    assert text.endswith("\n") and not text.endswith("\n\n")
    data = [line for line in text.splitlines() if not line.startswith("#")]
    assert len(data) == 2
    for line in data:
        assert len(line.split(" ")) == 8
    assert data[0].split(" ")[1:3] == ["0.10000000000000001", "2"]  # %.17g: every bit of 0.1


def test_matrices_become_unit_quaternions_with_nonnegative_w(tmp_path: Path) -> None:
    half = math.radians(30.0) / 2
    about_z = np.eye(4)
    about_z[:2, :2] = [[math.cos(2 * half), -math.sin(2 * half)], [math.sin(2 * half), math.cos(2 * half)]]
    about_z[:3, 3] = [1.0, 2.0, 3.0]
    about_x_270 = np.eye(4)  # 270° about x: the quaternion with w < 0 is flipped to w > 0
    about_x_270[1:3, 1:3] = [[0.0, 1.0], [-1.0, 0.0]]
    path = tmp_path / "matrices.tum"
    write_tum(path, np.array([1, 2]), np.stack([about_z, about_x_270]))
    trajectory = read_tum(path)
    np.testing.assert_array_equal(trajectory.positions, [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(
        trajectory.quaternions,
        [[0.0, 0.0, math.sin(half), math.cos(half)], [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]],
        atol=1e-15,
    )
    assert trajectory.planar()[0, 2] == pytest.approx(math.radians(30.0), abs=1e-15)


def test_seven_column_poses_are_written_as_given(tmp_path: Path) -> None:
    row = [1.5, -2.5, 0.25, 0.0, 0.0, 2.0, 0.0]  # not a unit quaternion: written and read unchanged
    path = tmp_path / "seven.tum"
    write_tum(path, np.array([5]), np.array([row]))
    trajectory = read_tum(path)
    np.testing.assert_array_equal(trajectory.quaternions, [row[3:]])
    assert trajectory.planar()[0, 2] == pytest.approx(math.pi)  # yaw does not depend on the norm


def test_trajectory_arrays_are_read_only(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    write_tum(path, np.array([1]), np.zeros((1, 3)))
    trajectory = read_tum(path)
    with pytest.raises(ValueError):
        trajectory.positions[0, 0] = 1.0


# ------------------------------------------------------------------------------------------------ stamps


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("90.239599", 90_239_599_000),
        ("70", 70_000_000_000),
        ("5.", 5_000_000_000),
        (".5", 500_000_000),
        ("+1.000000001", 1_000_000_001),
        ("-0.5", -500_000_000),
        ("1.3e9", 1_300_000_000_000_000_000),
        ("1.305031102175304174e+09", 1_305_031_102_175_304_174),  # as numpy.savetxt (evo) writes
        ("7.028990000000000293e+01", 70_289_900_000),  # float noise below the nanosecond rounds away
        ("0.0000000005", 0),  # ties go to even
        ("0.0000000015", 2),
        ("0.00000000150001", 2),
        ("0.00000000149999", 1),
        ("-0.0000000015", -2),
        ("1e-300", 0),
        ("0e999", 0),
        ("9223372036.854775807", 2**63 - 1),
        ("-9223372036.854775808", -(2**63)),
        ("1700000000.123456789", 1_700_000_000_123_456_789),
    ],
)
def test_parse_stamp_ns(text: str, expected: int) -> None:
    assert parse_stamp_ns(text) == expected


@pytest.mark.parametrize(
    "text", ["", ".", "-", "abc", "1e", "e5", "nan", "inf", "1_000", "0x10", "1.2.3", "9223372036.854775808",
             "1e30", "--1"],
)
def test_parse_stamp_ns_rejects(text: str) -> None:
    with pytest.raises(ValueError):
        parse_stamp_ns(text)


@given(INT64)
def test_format_then_parse_is_identity(stamp: int) -> None:
    text = format_stamp_ns(stamp)
    assert len(text.split(".")[1]) == 9
    assert parse_stamp_ns(text) == stamp


# ------------------------------------------------------------------------------------------------ errors


def write(tmp_path: Path, text: str, name: str = "bad.tum") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD = "1.0 0 0 0 0 0 0 1"


@pytest.mark.parametrize(
    ("body", "line", "words"),
    [
        (f"{GOOD}\n1.0 0 0 0 0 0 1\n", 2, "expected 8 fields"),
        (f"# header\n{GOOD}\n\n1.0 0 0 0 0 0 0 1 7\n", 4, "found 9"),
        (f"{GOOD}\n2.0 0 x 0 0 0 0 1\n", 2, "ty is not a number"),
        (f"{GOOD}\n2.0 0 0 nan 0 0 0 1\n", 2, "tz is not finite"),
        (f"{GOOD}\nabc 0 0 0 0 0 0 1\n", 2, "not a decimal number of seconds"),
        (f"{GOOD}\n{GOOD}\n3.0 0 0 0 0 0 0 0\n", 3, "quaternion is zero"),
        (f"{GOOD}\n99999999999 0 0 0 0 0 0 1\n", 2, "out of range"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path: Path, body: str, line: int, words: str) -> None:
    path = write(tmp_path, body)
    with pytest.raises(TrajectoryFileError) as caught:
        read_tum(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:{line}: ")
    assert words in message
    assert "\n" not in message
    assert isinstance(caught.value, PipelineError)


@pytest.mark.parametrize("body", ["", "\n\n", "# timestamp tx ty tz qx qy qz qw\n# nothing else\n"])
def test_a_file_without_poses_is_an_error_naming_it(tmp_path: Path, body: str) -> None:
    path = write(tmp_path, body)
    with pytest.raises(TrajectoryFileError, match="no poses") as caught:
        read_tum(path)
    assert str(caught.value).startswith(f"{path}: ")


def test_unreadable_inputs_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryFileError, match="no such file"):
        read_tum(tmp_path / "missing.tum")
    with pytest.raises(TrajectoryFileError, match="folder"):
        read_tum(tmp_path)
    binary = tmp_path / "binary.tum"
    binary.write_bytes(f"{GOOD}\n".encode() + b"\xff\xfe\n")
    with pytest.raises(TrajectoryFileError, match=rf"^{binary}:2: not UTF-8"):
        read_tum(binary)


def test_comments_blank_lines_tabs_and_crlf_are_accepted(tmp_path: Path) -> None:
    text = "# header\r\n\r\n1.5\t1 2 3  0 0 0 1   # trailing comment\r\n  \r\n2.5 4 5 6 0 0 1 0\r\n"
    path = write(tmp_path, text)
    trajectory = read_tum(path)
    assert trajectory.stamps_ns.tolist() == [1_500_000_000, 2_500_000_000]
    np.testing.assert_array_equal(trajectory.positions, [[1, 2, 3], [4, 5, 6]])
    assert len(trajectory) == 2


def test_write_rejects_inconsistent_arrays(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    with pytest.raises(ValueError, match="2 stamps but 3 poses"):
        write_tum(path, np.array([1, 2]), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="integer"):
        write_tum(path, np.array([1.0, 2.0]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="shape"):
        write_tum(path, np.array([1, 2]), np.zeros((2, 5)))
    with pytest.raises(ValueError, match="finite"):
        write_tum(path, np.array([1]), np.array([[0.0, np.nan, 0.0]]))
    assert not path.exists()


def test_write_failure_is_an_output_error(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match="nowhere"):
        write_tum(tmp_path / "nowhere" / "t.tum", np.array([1]), np.zeros((1, 3)))
