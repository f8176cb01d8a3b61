"""A CARMEN laser log (Radish: FLASER or ROBOTLASER1 scans, ODOM lines) as a ROS 2 MCAP, converted as
../shared's ACES and CSAIL were, to measure the 2D path on logs outside ../shared.

    python benchmarks/carmen_log.py IN.clf OUT.mcap [--odometry odom|scans|none] [--drop F] [--jitter S]
    python benchmarks/carmen_log.py IN.rawlog OUT.mcap ...  # the same log as MRPT converted it

The Radish logs are in MOLAorg/mola_test_datasets (`datasets/radish/*.clf.bz2`, CC-BY-3.0): fr079.clf
(the Freiburg building-079 log issue 12 names), intel.clf (the Intel Research Lab), fr-clinic_robotlaser.clf.
The UAL log (`datasets/ual/ual_dataset_2014_05_23_2dlaser_odo.rawlog`, CC-BY-3.0, J. L. Blanco-Claraco:
a vehicle driving 570 m around a block of the University of Almería in 3 minutes, a SICK at 18 Hz, 30–50 m
ranges outdoors, 2 m ahead of the base; odometry at 80 Hz) is an observation-only rawlog: its range
scans (version 6: the aperture, the sensor pose, a valid flag per range) and odometry observations
(version 1) are read as MRPT's `serializeFrom` lays them out; a range not valid is written as NaN.
MIT Killian Court (the paper's real log, section IV.C) is there only as MRPT's `carmen2rawlog` wrote it,
`datasets/radish/mit-killian.rawlog`: read by `read_rawlog`, the same FLASER scans (180 beams, read as
−90° every 1° like the CLF's: the rawlog's 90° aperture is the converter's, it says the same of ACES, whose
round trip gives the CLF's ranges and odometry), each with the odometry logged before it, stamps as MRPT
wrote them (its own clock: 4.4 h for Killian).

- Scans: `/scan` LaserScans in frame `laser`, stamped with the line's ipc timestamp. FLASER: N beams from
  −90° every 180° / (N − N mod 2) (ACES's 180 beams every 1°, CSAIL's 361 every 0.5°); ROBOTLASER1: the
  line's own start angle and resolution (fr-clinic interlaces four layouts 0.25° apart). range_max just
  below the log's largest range (its no-return value).
- Odometry: `/tf` odom → base_link. `odom` (default): from the ODOM lines at their own stamps, a line
  repeating its predecessor dropped; `scans`: each scan's own odometry fields, at its stamp (ROBOTLASER1
  logs have no ODOM lines); `none`: no odometry.
- `/tf_static` base_link → laser: identity for FLASER, ROBOTLASER1's laser pose in the robot's frame.
- Messages are written in stamp order. The Intel log's stamps go up to 0.6 s back and come in bursts
  1 ms apart; they are kept as they are, as a bag converted from it has them.
- `--drop F` leaves out a random share F of the scans (seed 1); `--jitter S` moves each scan's stamp by
  up to ±S seconds (seed 0): perturbed copies of a real log.
"""

from __future__ import annotations

import argparse
import gzip
import math
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests._frontends_fixtures import ros2_mcap  # noqa: E402


@dataclass(frozen=True)
class Scan:
    stamp_ns: int
    ranges: np.ndarray
    first_angle: float
    increment: float
    odometry: tuple[float, float, float]


@dataclass(frozen=True)
class RawlogScan:
    ranges: np.ndarray
    first_angle: float
    increment: float
    mount: tuple[float, float, float] | None
    """The laser's pose (x, y, yaw) in the robot's frame, None where the rawlog's is not the laser's."""


@dataclass(frozen=True)
class CarmenLog:
    scans: list[Scan]
    odometry: list[tuple[int, tuple[float, float, float]]]
    """(stamp ns, (x, y, yaw)) of every ODOM line."""
    mount: tuple[float, float, float]
    """The laser's pose (x, y, yaw) in the robot's frame."""


def _stamp(value: str) -> int:
    return round(float(value) * 1e9)


def read_carmen(path: Path) -> CarmenLog:
    scans: list[Scan] = []
    odometry: list[tuple[int, tuple[float, float, float]]] = []
    mount = (0.0, 0.0, 0.0)
    for line in path.read_text().splitlines():
        fields = line.split()
        if not fields:
            continue
        if fields[0] == "FLASER":  # FLASER n r1..rn x y θ odom_x odom_y odom_θ ipc_stamp host logger_stamp
            count = int(fields[1])
            rest = fields[2 + count:]
            ranges = np.array(fields[2:2 + count], dtype=np.float32)
            pose = (float(rest[3]), float(rest[4]), float(rest[5]))
            scans.append(Scan(_stamp(rest[6]), ranges, -math.pi / 2, math.pi / (count - count % 2), pose))
        elif fields[0] == "ROBOTLASER1":
            # type start fov resolution max accuracy remission_mode n r1..rn m e1..em laser_x laser_y laser_θ
            # robot_x robot_y robot_θ tv rv forward_safety side_safety turn_axis ipc_stamp host logger_stamp
            count = int(fields[8])
            rest = fields[9 + count:]
            rest = rest[1 + int(rest[0]):]
            laser = [float(value) for value in rest[0:3]]
            robot = (float(rest[3]), float(rest[4]), float(rest[5]))
            c, s = math.cos(robot[2]), math.sin(robot[2])
            dx, dy = laser[0] - robot[0], laser[1] - robot[1]
            mount = (c * dx + s * dy, -s * dx + c * dy, laser[2] - robot[2])
            ranges = np.array(fields[9:9 + count], dtype=np.float32)
            scans.append(Scan(_stamp(rest[11]), ranges, float(fields[2]), float(fields[4]), robot))
        elif fields[0] == "ODOM":  # ODOM x y θ tv rv accel ipc_stamp host logger_stamp
            pose = (float(fields[1]), float(fields[2]), float(fields[3]))
            if not odometry or odometry[-1][1] != pose:
                odometry.append((_stamp(fields[7]), pose))
    return CarmenLog(scans, odometry, mount)


_FILETIME_TO_UNIX_100NS = 116_444_736_000_000_000
"""MRPT stamps count 100 ns from 1601-01-01 (Windows FILETIME)."""


class _MrptArchive:
    """MRPT's serialization (`CArchive::WriteObject`): a byte 0x80 | name length, the class name, a version
    byte, the fields, the end flag 0x88."""

    def __init__(self, data: bytes) -> None:
        self.data, self.at = data, 0

    def take(self, size: int) -> bytes:
        if self.at + size > len(self.data):
            raise ValueError(f"rawlog cut short at byte {self.at}")
        self.at += size
        return self.data[self.at - size:self.at]

    def unpack(self, layout: str) -> tuple:
        return struct.unpack("<" + layout, self.take(struct.calcsize("<" + layout)))

    def string(self) -> str:
        return self.take(self.unpack("I")[0]).decode()

    def _range_scan(self, version: int) -> tuple[int, RawlogScan]:
        """A CObservation2DRangeScan's fields after its version: (stamp, scan)."""
        aperture, right_to_left, _ = self.unpack("fBf")  # aperture, right to left, max range
        _, mount = self.read_object()
        count = self.unpack("I")[0]
        ranges = np.frombuffer(self.take(4 * count), "<f4").astype(np.float32)
        valid = np.frombuffer(self.take(count), np.uint8).astype(bool)
        stamp = self.unpack("fQf")[1]  # σ, stamp, beam aperture
        self.string()  # sensor label
        if version == 7:  # carmen2rawlog's (the Radish rawlogs; see the module's docstring)
            # Δpitch, the intensity flag (unset): it wrote more zeros than these. Its aperture is not the
            # FLASER's 180°, its sensor pose (identity) not a laser mount, and every range is valid.
            while self.data[self.at] == 0:
                self.at += 1
            return stamp, RawlogScan(ranges, -math.pi / 2, math.pi / (count - count % 2), None)
        self.unpack("d")  # Δpitch (a double here)
        ranges = np.where(valid, ranges, np.float32(np.nan))  # no return (REP 117)
        if not right_to_left:
            ranges = ranges[::-1].copy()
        return stamp, RawlogScan(ranges, -aperture / 2, aperture / (count - 1), mount)

    def read_object(self) -> tuple[str, object]:
        head = self.take(1)[0]
        if not head & 0x80:
            raise ValueError(f"no object at byte {self.at - 1}")
        name, version = self.take(head & 0x7F).decode(), self.take(1)[0]
        if name.endswith("CPose2D") and version == 1:
            value: object = self.unpack("3d")
        elif name == "mrpt::poses::CPose3D" and version == 3:
            value = self.unpack("12d")  # x, y, z, the rotation matrix
        elif name.endswith("CPose3D") and version == 2:
            x, y, _, qw, qx, qy, qz = self.unpack("7d")  # x, y, z, the rotation as a quaternion
            value = (x, y, math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))
        elif name.endswith("CObservationOdometry") and version in (1, 2):
            _, pose = self.read_object()
            self.string()  # sensor label
            stamp = self.unpack("Q")[0]
            if version == 1:  # an observation-only rawlog's: ticks and velocities, whatever the flags say
                self.unpack("?ii?ff")
            else:
                for size in (8, 8):  # encoder ticks, velocities: each behind a presence flag
                    self.take(size if self.take(1)[0] else 0)
            value = (stamp, pose)
        elif name.endswith("CObservation2DRangeScan") and version in (6, 7):
            value = self._range_scan(version)
        else:
            raise ValueError(f"unsupported object {name} version {version} at byte {self.at}")
        if self.take(1) != b"\x88":
            raise ValueError(f"{name} does not end where expected (byte {self.at - 1})")
        return name, value


def read_rawlog(path: Path) -> CarmenLog:
    """An MRPT rawlog of FLASER scans and odometry (`carmen2rawlog`'s, gzip), as `read_carmen` reads a CLF."""
    archive = _MrptArchive(gzip.decompress(path.read_bytes()))
    scans: list[Scan] = []
    odometry: list[tuple[int, tuple[float, float, float]]] = []
    latest = (0.0, 0.0, 0.0)
    mount: tuple[float, float, float] | None = None
    while archive.at < len(archive.data):
        name, value = archive.read_object()
        stamp_100ns, payload = value  # type: ignore[misc]
        stamp = (stamp_100ns - _FILETIME_TO_UNIX_100NS) * 100
        if name.endswith("CObservationOdometry"):
            if payload != latest or not odometry:
                odometry.append((stamp, payload))
            latest = payload
        elif name.endswith("CObservation2DRangeScan"):
            assert isinstance(payload, RawlogScan)
            if mount is not None and payload.mount is not None and payload.mount != mount:
                raise ValueError(f"the laser's mount changes at byte {archive.at}: one mount is written")
            mount = mount or payload.mount
            scans.append(Scan(stamp, payload.ranges, payload.first_angle, payload.increment, latest))
    return CarmenLog(scans, odometry, mount or (0.0, 0.0, 0.0))


def stamp_offsets(count: int, jitter: float) -> np.ndarray:
    """The (count,) int64 offsets (ns) `write_mcap` adds to the scans' stamps for `jitter` (seed 0)."""
    return np.round(np.random.default_rng(0).uniform(-jitter, jitter, count) * 1e9).astype(np.int64)


def write_mcap(log: CarmenLog, out: Path, odometry: str, drop: float, jitter: float) -> None:
    scans = log.scans
    offsets = stamp_offsets(len(scans), jitter)
    kept = np.random.default_rng(1).uniform(size=len(scans)) >= drop
    events: list[tuple[int, int, str, object]] = [
        (scan.stamp_ns + int(offset), 1, "scan", scan)
        for scan, offset, keep in zip(scans, offsets, kept, strict=True) if keep]
    if odometry == "odom":
        events += [(stamp, 0, "odometry", pose) for stamp, pose in log.odometry]
    elif odometry == "scans":
        events += [(stamp, 0, "odometry", scan.odometry) for stamp, _, _, scan in events]
    events.sort(key=lambda event: (event[0], event[1]))
    top = float(max(np.nanmax(scan.ranges) for scan in scans))
    with ros2_mcap(out) as (messages, add):
        types = messages.types

        def transforms(stamp: int, parent: str, child: str, pose: tuple[float, float, float]) -> object:
            """A TFMessage of the one planar edge parent → child."""
            return messages.tf_message([messages.transform_stamped(stamp, parent, child, (*pose[:2], 0.0),
                                                                   pose[2])])

        first = events[0][0]
        add("/tf_static", "tf2_msgs/msg/TFMessage", first, transforms(first, "base_link", "laser", log.mount))
        for stamp, _, kind, item in events:
            if kind == "odometry":
                add("/tf", "tf2_msgs/msg/TFMessage", stamp, transforms(stamp, "odom", "base_link", item))
                continue
            assert isinstance(item, Scan)
            count = len(item.ranges)
            add("/scan", "sensor_msgs/msg/LaserScan", stamp, types["sensor_msgs/msg/LaserScan"](
                header=messages.header(stamp, "laser"), angle_min=item.first_angle,
                angle_max=item.first_angle + item.increment * (count - 1), angle_increment=item.increment,
                time_increment=0.0, scan_time=0.0, range_min=0.0,
                range_max=float(np.nextafter(np.float32(top), np.float32(0.0))),
                ranges=item.ranges, intensities=np.zeros(0, dtype=np.float32)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--odometry", choices=("odom", "scans", "none"), default="odom")
    parser.add_argument("--drop", type=float, default=0.0, help="share of the scans left out")
    parser.add_argument("--jitter", type=float, default=0.0, help="± seconds added to each scan's stamp")
    args = parser.parse_args()
    log = read_rawlog(args.log) if args.log.suffix == ".rawlog" else read_carmen(args.log)
    odometry = "scans" if args.odometry == "odom" and not log.odometry else args.odometry
    write_mcap(log, args.out, odometry, args.drop, args.jitter)
    print(f"{args.out}: {len(log.scans)} scans, odometry from {odometry}")


if __name__ == "__main__":
    main()
