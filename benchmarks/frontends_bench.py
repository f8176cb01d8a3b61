"""Frontends throughput: LaserScan messages/s per container, PointCloud2 MB/s, `info` on a 1 GB MCAP.

    python benchmarks/frontends_bench.py [--workdir /tmp] [--keep]

Writes its logs (about 1.3 GB in all) to a temporary directory, deletes them afterwards, and prints a
markdown table. Each figure is the best of three runs (the machine may be shared).
"""

from __future__ import annotations

import argparse
import resource
import shutil
import struct
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable from a checkout without installing the package
    sys.path.insert(0, str(REPO))

from frontends.logs import open_log  # noqa: E402
from frontends.logs.converters import ros_point_cloud2  # noqa: E402
from frontends.logs.decoding.ros_wire import point_cloud2  # noqa: E402

LASER_TYPE = "sensor_msgs/msg/LaserScan"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
T0 = 1_700_000_000_000_000_000
STORE_ROS2 = get_typestore(Stores.ROS2_HUMBLE)
STORE_ROS1 = get_typestore(Stores.ROS1_NOETIC)


def laser_scan(store: object, beams: int, rng: np.random.Generator) -> object:
    types = store.types  # type: ignore[attr-defined]
    stamp = types["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    fields = types["std_msgs/msg/Header"].__dataclass_fields__
    header = types["std_msgs/msg/Header"](
        **({"seq": 0} if "seq" in fields else {}), stamp=stamp, frame_id="laser"
    )
    ranges = rng.uniform(0.1, 30.0, beams).astype(np.float32)
    ranges[rng.random(beams) < 0.05] = np.inf
    return types[LASER_TYPE](
        header=header,
        angle_min=-np.pi / 2,
        angle_max=np.pi / 2,
        angle_increment=np.pi / (beams - 1),
        time_increment=0.0,
        scan_time=0.025,
        range_min=0.1,
        range_max=25.0,
        ranges=ranges,
        intensities=np.zeros(0, np.float32),
    )


def stamped(template: bytes, cdr: bool, stamp_ns: int) -> bytes:
    """The template payload with its header stamp replaced (CDR: after the 4-byte encapsulation; ROS 1:
    after seq)."""
    payload = bytearray(template)
    struct.pack_into("<iI" if cdr else "<II", payload, 4, stamp_ns // 10**9, stamp_ns % 10**9)
    return bytes(payload)


def scan_payloads(cdr: bool, beams: int, count: int) -> Iterator[tuple[int, bytes]]:
    rng = np.random.default_rng(1)
    store = STORE_ROS2 if cdr else STORE_ROS1
    message = laser_scan(store, beams, rng)
    template = bytes(
        store.serialize_cdr(message, LASER_TYPE) if cdr else store.serialize_ros1(message, LASER_TYPE)
    )
    for i in range(count):
        stamp = T0 + i * 25_000_000
        yield stamp, stamped(template, cdr, stamp)


def write_mcap_scans(path: Path, beams: int, count: int, compression: CompressionType) -> Path:
    definition, _ = STORE_ROS2.generate_msgdef(LASER_TYPE, ros_version=2)
    with path.open("wb") as stream:
        writer = McapWriter(stream, chunk_size=4 << 20, compression=compression)
        writer.start("ros2", "frontends benchmark")
        schema = writer.register_schema(LASER_TYPE, "ros2msg", definition.encode())
        channel = writer.register_channel("/scan", "cdr", schema)
        for stamp, payload in scan_payloads(True, beams, count):
            writer.add_message(channel, stamp + 1_000_000, payload, stamp + 1_000_000)
        writer.finish()
    return path


def write_rosbag1_scans(path: Path, beams: int, count: int) -> Path:
    writer = Rosbag1Writer(path)
    writer.open()
    connection = writer.add_connection("/scan", LASER_TYPE, typestore=STORE_ROS1)
    for stamp, payload in scan_payloads(False, beams, count):
        writer.write(connection, stamp + 1_000_000, payload)
    writer.close()
    return path


def write_rosbag2_scans(path: Path, beams: int, count: int) -> Path:
    writer = Rosbag2Writer(path, version=8)
    writer.open()
    connection = writer.add_connection("/scan", LASER_TYPE, typestore=STORE_ROS2)
    for stamp, payload in scan_payloads(True, beams, count):
        writer.write(connection, stamp + 1_000_000, payload)
    writer.close()
    return path


def cloud_payload(points: int, rng: np.random.Generator) -> bytes:
    """A Velodyne-like cloud: x, y, z, intensity float32, ring uint16, time float32 (22 → 24-byte step)."""
    types = STORE_ROS2.types
    field = types["sensor_msgs/msg/PointField"]
    layout = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4), ("time", 20, 7)]
    data = np.zeros(
        points,
        dtype=[("xyz", "<f4", 3), ("intensity", "<f4"), ("ring", "<u2"), ("pad", "u1", 2), ("time", "<f4")],
    )
    data["xyz"] = rng.normal(0.0, 20.0, (points, 3))
    data["xyz"][rng.random(points) < 0.02] = np.nan
    data["time"] = np.linspace(0.0, 0.1, points)
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="velodyne"
    )
    message = types[CLOUD_TYPE](
        header=header,
        height=1,
        width=points,
        fields=[field(name=n, offset=o, datatype=d, count=1) for n, o, d in layout],
        is_bigendian=False,
        point_step=24,
        row_step=24 * points,
        data=data.view(np.uint8),
        is_dense=False,
    )
    return bytes(STORE_ROS2.serialize_cdr(message, CLOUD_TYPE))


def write_mcap_clouds(path: Path, count: int, points: int) -> tuple[Path, int]:
    definition, _ = STORE_ROS2.generate_msgdef(CLOUD_TYPE, ros_version=2)
    template = cloud_payload(points, np.random.default_rng(2))
    with path.open("wb") as stream:
        writer = McapWriter(stream, chunk_size=8 << 20, compression=CompressionType.NONE)
        writer.start("ros2", "frontends benchmark")
        schema = writer.register_schema(CLOUD_TYPE, "ros2msg", definition.encode())
        channel = writer.register_channel("/points", "cdr", schema)
        for i in range(count):
            stamp = T0 + i * 100_000_000
            writer.add_message(channel, stamp, stamped(template, True, stamp), stamp)
        writer.finish()
    return path, count * points * 24


def best_of(runs: int, work: Callable[[], int]) -> tuple[float, int]:
    """(shortest wall time, what `work` returned)."""
    best = float("inf")
    result = 0
    for _ in range(runs):
        start = time.perf_counter()
        result = work()
        best = min(best, time.perf_counter() - start)
    return best, result


def count_scans(path: Path) -> int:
    return sum(1 for _ in open_log(path).scans())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()))
    parser.add_argument("--keep", action="store_true", help="keep the generated logs")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="frontends-bench-", dir=args.workdir))
    rows: list[tuple[str, str, str, bool]] = []
    try:
        # Load (or compile) the numba kernels before timing anything.
        count_scans(write_mcap_scans(workdir / "warmup.mcap", 361, 10, CompressionType.ZSTD))
        # The 1 GB log first, while the process's peak memory is still that of an empty run.

        big_beams = 760  # ≈ 3.1 kB per message
        big_count = 340_000
        big = write_mcap_scans(workdir / "big.mcap", big_beams, big_count, CompressionType.NONE)
        size_gb = big.stat().st_size / 1e9
        seconds, _ = best_of(3, lambda: len(open_log(big).info().topics))
        rows.append(
            (
                f"`info` on a {size_gb:.2f} GB MCAP ({big_count:,} messages)",
                f"{seconds * 1000:,.1f} ms",
                "≤ 1 s",
                seconds <= 1.0,
            )
        )
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        start = time.perf_counter()
        streamed = count_scans(big)
        elapsed = time.perf_counter() - start
        grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
        rows.append(
            (
                f"stream all {streamed:,} scans of the {size_gb:.2f} GB MCAP",
                f"{elapsed:.1f} s, peak RSS +{grown:.0f} MB",
                "memory independent of length",
                grown < 200,
            )
        )

        for beams in (361, 1081):
            scans = 40_000
            mcap = write_mcap_scans(workdir / f"scans{beams}.mcap", beams, scans, CompressionType.ZSTD)
            seconds, n = best_of(3, lambda path=mcap: count_scans(path))
            rate = n / seconds
            rows.append(
                (
                    f"LaserScan from MCAP (ROS 2, zstd chunks, {beams} beams)",
                    f"{rate:,.0f} msg/s",
                    "≥ 50,000 msg/s",
                    rate >= 50_000,
                )
            )
        beams, scans = 361, 40_000
        bag = write_rosbag1_scans(workdir / "scans.bag", beams, scans)
        seconds, n = best_of(3, lambda: count_scans(bag))
        rows.append(
            (
                f"LaserScan from ROS 1 bag ({beams} beams)",
                f"{n / seconds:,.0f} msg/s",
                "≥ 20,000 msg/s",
                n / seconds >= 20_000,
            )
        )
        db3 = write_rosbag2_scans(workdir / "scans_ros2", beams, scans)
        seconds, n = best_of(3, lambda: count_scans(db3))
        rows.append(
            (
                f"LaserScan from ROS 2 sqlite3 bag ({beams} beams)",
                f"{n / seconds:,.0f} msg/s",
                "≥ 20,000 msg/s",
                n / seconds >= 20_000,
            )
        )

        clouds, points = 60, 120_000
        cloud_path, point_bytes = write_mcap_clouds(workdir / "clouds.mcap", clouds, points)
        seconds, n = best_of(3, lambda: sum(1 for _ in open_log(cloud_path).clouds()))
        rate = point_bytes / seconds / 1e6
        rows.append(
            (
                f"PointCloud2 from MCAP ({points:,} points × 24 B, uncompressed)",
                f"{rate:,.0f} MB/s",
                "≥ 200 MB/s",
                rate >= 200,
            )
        )
        payload = cloud_payload(points, np.random.default_rng(3))
        seconds, n = best_of(
            3,
            lambda: sum(
                ros_point_cloud2(point_cloud2(payload, True), 0).points.shape[0] > 0 for _ in range(20)
            ),
        )
        rate = 20 * points * 24 / seconds / 1e6
        rows.append(
            ("PointCloud2 payload → Cloud3D (decode only)", f"{rate:,.0f} MB/s", "≥ 200 MB/s", rate >= 200)
        )
        kitti = REPO.parent / "shared" / "data" / "logs" / "kitti" / "kitti_city.mcap"
        if kitti.exists():
            seconds, n = best_of(3, lambda: sum(c.points.shape[0] for c in open_log(kitti).clouds()))
            rate = n * 16 / seconds / 1e6
            rows.append(
                (
                    "PointCloud2 KITTI (../shared, zstd-19 chunks, 16 B points)",
                    f"{rate:,.0f} MB/s",
                    "≥ 200 MB/s",
                    rate >= 200,
                )
            )

    finally:
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)

    print("| measurement | result | target | met |")
    print("|---|---|---|---|")
    for label, result, target, met in rows:
        print(f"| {label} | {result} | {target} | {'yes' if met else 'NO'} |")


if __name__ == "__main__":
    main()
