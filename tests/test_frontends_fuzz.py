"""Property-based fuzzing of the container readers: random byte mutations of small valid MCAP, ROS 1 and
ROS 2 files. Whatever the bytes, reading ends in a result or one of our exceptions (one line, naming the
file), and memory stays bounded."""

from __future__ import annotations

import os
import tracemalloc
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from frontends.errors import FrontendError, LogWarning
from frontends.logs import TransformTree, open_log
from frontends.slam2d.log_input import read_odometry, scans_in_base_frame
from tests._frontends_fixtures import write_mcap_ros, write_rosbag1, write_rosbag2

MEMORY_BOUND = 64 << 20
"""tracemalloc peak for reading a mutated file of a few kB (bytes)."""

FUZZ_SETTINGS = settings(
    # SGDSLAM_FUZZ_EXAMPLES=600 for a longer hunt than the suite's.
    max_examples=int(os.environ.get("SGDSLAM_FUZZ_EXAMPLES", "40")), deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


def read_everything(path: Path) -> None:
    with open_log(path) as log:
        log.info()
        list(log.messages({c.topic for c in log.channels}))
        if log.topics_of_kind("scan"):
            read_odometry(log)
            list(scans_in_base_frame(log, log.select_topic(("scan",)), TransformTree(), "base_link"))


_SOURCES: dict[str, tuple[Path, bytes]] = {}


def source(container: str, root: Path) -> tuple[Path, bytes]:
    """Where mutated copies of this container's file are written, and the valid bytes they come from
    (written once per session; not a fixture argument, so hypothesis does not print the bytes)."""
    if container not in _SOURCES:
        if container == "mcap":
            valid = write_mcap_ros(root / "valid.mcap")
        elif container == "rosbag1":
            valid = write_rosbag1(root / "valid.bag", compression="lz4")[0]
        else:
            valid = next(write_rosbag2(root / "ros2").glob("*.db3"))
        _SOURCES[container] = (root / f"mutated{valid.suffix}", valid.read_bytes())
    return _SOURCES[container]


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


# A mutation: overwrite bytes at a position given as a fraction of the file (so the same strategy reaches
# headers, chunks and indexes of files of any size), or cut the file there.
mutation = st.tuples(
    st.floats(min_value=0.0, max_value=1.0, exclude_max=True),
    st.binary(min_size=1, max_size=8),
)
mutations = st.lists(mutation, min_size=1, max_size=6)


def mutate(data: bytes, changes: list[tuple[float, bytes]], cut: float | None) -> bytes:
    out = bytearray(data)
    for where, new in changes:
        position = int(where * len(out))
        out[position : position + len(new)] = new
    if cut is not None:
        out = out[: int(cut * len(out))]
    return bytes(out)


def check_reading(path: Path) -> None:
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LogWarning)
            read_everything(path)
    except FrontendError as err:
        text = str(err)
        assert "\n" not in text and path.name in text, text
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < MEMORY_BOUND, f"peak {peak} bytes"


@pytest.mark.parametrize("container", ["mcap", "rosbag1", "rosbag2"])
@FUZZ_SETTINGS
@given(
    changes=mutations,
    cut=st.one_of(st.none(), st.floats(min_value=0.05, max_value=1.0)),
)
# Found by the suite: in the MCAP these bytes make a summary schema's string length huge, and a buffered
# reader allocated it (1.6 GB) before the read was cut to the file's size.
@example(changes=[(0.38638707174016723, b"\x00\x00")], cut=None)
def test_mutated_file_ends_in_result_or_our_error(
    container: str,
    changes: list[tuple[float, bytes]],
    cut: float | None,
    root: Path,
) -> None:
    path, valid = source(container, root)
    path.write_bytes(mutate(valid, changes, cut))
    check_reading(path)
