"""Fixtures shared by the pipeline tests: a small loop graph, a simulated drive written as a ROS 2 MCAP,
the first scans of a real MCAP log, and a reader that turns a recording (.rrd) back into Python values."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer
from rerun.chunk import RrdReader
from typer.testing import Result

from optimizer import se2
from tests._frontends_fixtures import quaternion_from_yaw, ros2_mcap
from tests.laser_world import (
    World,
    drive,
    route_poses,
    simulate_scan,
    simulate_swept_scan,
    square_loop,
    wheel_odometry,
)

LOOP_POSES = 30


LOOP_INFORMATION = (50.0, 0.0, 0.0, 50.0, 0.0, 200.0)  # g2o upper triangle: xx xy xθ yy yθ θθ


def one_error_line(result: Result) -> str:
    """The one line a refused command printed (exit code 2, `replay: error: …`), for the caller to check."""
    assert result.exit_code == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("replay: error: ")
    return lines[0]


def loop_graph_text(poses: int = LOOP_POSES, seed: int = 3) -> str:
    """g2o text of a robot driving once around a circle: noisy odometry, two loop closures, and an initial
    estimate that drifts (a steady heading bias), so χ² starts high and the optimum is near zero."""
    rng = np.random.default_rng(seed)
    angles = 2.0 * np.pi * np.arange(poses) / poses
    truth = np.stack([5.0 * np.cos(angles), 5.0 * np.sin(angles), se2.wrap_angle(angles + np.pi / 2)], axis=1)
    odometry = [(i, i + 1) for i in range(poses - 1)]
    closures = [(poses - 1, 0), (poses // 3, 2 * poses // 3)]
    lines = []
    steps = se2.relative(truth[:-1], truth[1:]) + rng.normal(scale=[0.01, 0.01, 0.005], size=(poses - 1, 3))
    drifting = steps + np.array([0.0, 0.0, 0.03])
    initial = se2.compose_chain(drifting, start=truth[0])
    for index, (x, y, theta) in enumerate(initial):
        lines.append(f"VERTEX_SE2 {index} {x:.9f} {y:.9f} {theta:.9f}")
    information = " ".join(f"{value:g}" for value in LOOP_INFORMATION)
    for (a, b), z in zip(odometry, steps, strict=True):
        lines.append(f"EDGE_SE2 {a} {b} {z[0]:.9f} {z[1]:.9f} {z[2]:.9f} {information}")
    for a, b in closures:
        z = se2.relative(truth[a], truth[b])
        lines.append(f"EDGE_SE2 {a} {b} {z[0]:.9f} {z[1]:.9f} {z[2]:.9f} {information}")
    return "\n".join(lines) + "\n"


def write_loop_graph(path: Path) -> Path:
    path.write_text(loop_graph_text())
    return path


def read_ply(path: Path) -> np.ndarray:
    """The vertices of a binary little-endian PLY of float properties (what the 3D replay writes), as a
    structured array named as in its header; asserts the body holds exactly those vertices."""
    header, body = path.read_bytes().split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"], lines[:2]
    count = next(int(line.split()[2]) for line in lines if line.startswith("element vertex "))
    names = [line.split()[2] for line in lines if line.startswith("property float ")]
    assert len(names) == sum(line.startswith("property") for line in lines), "only float properties"
    assert len(body) == count * 4 * len(names), "the body is not the declared vertices"
    return np.frombuffer(body, dtype=[(name, "<f4") for name in names], count=count)


@dataclass
class EntityData:
    """What a recording holds for one entity: static rows, and per timeline the logged index values."""

    static_rows: int = 0
    timelines: set[str] = field(default_factory=set)
    steps: list[int] = field(default_factory=list)
    columns: dict[str, list[object]] = field(default_factory=lambda: defaultdict(list))
    static_columns: dict[str, list[object]] = field(default_factory=lambda: defaultdict(list))


def read_recording(path: Path, timeline: str = "iteration") -> dict[str, EntityData]:
    """Every entity of the (first) recording in an .rrd, with its data as Python values, rows sorted by
    `timeline`."""
    entities: dict[str, EntityData] = defaultdict(EntityData)
    for chunk in RrdReader(path).stream():
        entity = entities[chunk.entity_path]
        batch = chunk.to_record_batch()
        data_columns = [name for name in batch.schema.names if ":" in name]
        if chunk.is_static:
            entity.static_rows += chunk.num_rows
            for name in data_columns:
                entity.static_columns[name].extend(batch.column(name).to_pylist())
            continue
        entity.timelines.update(chunk.timeline_names)
        if timeline not in batch.schema.names:
            continue
        steps = batch.column(timeline).to_pylist()
        entity.steps.extend(steps)
        for name in data_columns:
            entity.columns[name].extend(batch.column(name).to_pylist())
    for entity in entities.values():  # chunks need not come in timeline order
        order = np.argsort(entity.steps, kind="stable")
        entity.steps = [entity.steps[i] for i in order]
        for name, values in entity.columns.items():
            entity.columns[name] = [values[i] for i in order]
    return dict(entities)


LASER_MOUNT = np.array([0.25, 0.0, 0.0])
"""The laser sits 25 cm ahead of the base: the replay must take that from /tf_static."""


BEAMS = 360


SCAN_PERIOD_NS = 400_000_000
DRIVE_STEP = 0.4
"""Metres between two scans of `write_drive`."""
DRIVE_SPEED = DRIVE_STEP / (SCAN_PERIOD_NS * 1e-9)


START_NS = 1_700_000_000_000_000_000


def write_log_start(log: Path, path: Path, scans: int, scan_topic: str = "/scan") -> Path:
    """The first `scans` messages on `scan_topic` of the MCAP `log`, with everything logged before the next
    one and every /tf_static message, written to `path` as they were (a real log, only shorter)."""
    with log.open("rb") as stream:
        rows = list(make_reader(stream).iter_messages(log_time_order=True))
    scan_times = [message.log_time for _, channel, message in rows if channel.topic == scan_topic]
    end = scan_times[scans] if scans < len(scan_times) else math.inf
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in rows:
            if message.log_time >= end and channel.topic != "/tf_static":
                continue
            assert schema is not None
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id])
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                               message.sequence)
        writer.finish()
    return path


def laser_ranges(points: np.ndarray) -> np.ndarray:
    """Sensor-frame points back to a 360-beam LaserScan's ranges (inf where a beam had no return)."""
    ranges = np.full(BEAMS, np.inf, dtype=np.float32)
    bearings = np.arctan2(points[:, 1], points[:, 0]) % (2 * math.pi)
    index = np.round(bearings / (2 * math.pi / BEAMS)).astype(int) % BEAMS
    ranges[index] = np.hypot(points[:, 0], points[:, 1])
    return ranges


def write_drive(path: Path, *, with_odometry: bool = True, scans: int | None = None,
                part: slice | None = None, later_ns: int = 0, seed: int = 7,
                sweep: float = 0.0, scan_period_ns: int = SCAN_PERIOD_NS,
                odometry_topic: bool = True, multi_echo: bool = False,
                world: World | None = None, upside_down: bool = False, scan_frame: str = "laser",
                mount_on_tf: bool = True, odometry_clock_ns: int = 0) -> np.ndarray:
    """Drive the simulated building's loop (or `world`'s route) at 1 m/s, writing /scan, /odom, /tf and
    /tf_static; returns the truth (base poses) per scan. `part`: only these scans of the drive, as a log
    recorded `later_ns` later whose wheel odometry starts at its own origin (a second recording of the same
    building). `sweep`: the laser takes its beams one after the other over this many seconds from the stamp
    (time_increment set), each from where the robot is then; 0: all at the stamp (time_increment 0).
    `scan_period_ns`: a faster laser, the robot as fast (`DRIVE_SPEED`; not with `sweep`). `odometry_topic`
    False: the odometry only in /tf. `multi_echo`: the scans as sensor_msgs/MultiEchoLaserScan, each return
    its beam's first echo. `world`: another building's route and walls (not with `sweep`). `upside_down`:
    the laser is mounted rolled by π (tf says so): it sees the world mirrored, its bearings turning
    clockwise in the base frame (not with `sweep`). `scan_frame`: the frame the scans name (tf names the
    laser "laser"). `mount_on_tf` False: no /tf_static, tf does not say where the laser sits.
    `odometry_clock_ns`: the odometry (/odom and its /tf) stamped on a clock this far from the laser's."""
    rng = np.random.default_rng(seed)
    world = world or square_loop()
    truth = drive(world, DRIVE_SPEED * scan_period_ns * 1e-9)[:scans]
    odometry = wheel_odometry(truth, rng)
    if part is not None:
        truth, odometry = truth[part], odometry[part]
        odometry = se2.relative(odometry[0], odometry)
    with ros2_mcap(path) as (messages, add):
        types = messages.types

        def transform(stamp: int, parent: str, child: str, pose: np.ndarray, rolled: bool = False) -> object:
            # Rolled by π about x after the yaw: q_yaw ⊗ (1, 0, 0, 0) in (x, y, z, w).
            q = quaternion_from_yaw(float(pose[2]))
            if rolled:
                q = (q[3], q[2], -q[1], -q[0])
            return types["geometry_msgs/msg/TransformStamped"](
                header=messages.header(stamp, parent),
                child_frame_id=child,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=float(pose[0]), y=float(pose[1]), z=0.0),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )

        if mount_on_tf:
            add(
                "/tf_static",
                "tf2_msgs/msg/TFMessage",
                START_NS,
                types["tf2_msgs/msg/TFMessage"](
                    transforms=[transform(START_NS, "base_link", "laser", LASER_MOUNT, rolled=upside_down)]
                ),
            )
        for k, pose in enumerate(truth):
            stamp = START_NS + later_ns + k * scan_period_ns
            if with_odometry:
                q = quaternion_from_yaw(float(odometry[k, 2]))
                covariance = np.zeros(36)
                odom = types["nav_msgs/msg/Odometry"](
                    header=messages.header(stamp + odometry_clock_ns, "odom"),
                    child_frame_id="base_link",
                    pose=types["geometry_msgs/msg/PoseWithCovariance"](
                        pose=types["geometry_msgs/msg/Pose"](
                            position=types["geometry_msgs/msg/Point"](
                                x=odometry[k, 0], y=odometry[k, 1], z=0.0
                            ),
                            orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                        ),
                        covariance=covariance,
                    ),
                    twist=types["geometry_msgs/msg/TwistWithCovariance"](
                        twist=types["geometry_msgs/msg/Twist"](
                            linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        ),
                        covariance=covariance,
                    ),
                )
                if odometry_topic:
                    add("/odom", "nav_msgs/msg/Odometry", stamp, odom)
                add(
                    "/tf",
                    "tf2_msgs/msg/TFMessage",
                    stamp,
                    types["tf2_msgs/msg/TFMessage"](
                        transforms=[transform(stamp + odometry_clock_ns, "odom", "base_link", odometry[k])]
                    ),
                )
            if sweep:
                points = _swept_points(k if part is None else k + (part.start or 0), sweep, rng)
            else:
                points = simulate_scan(world.segments, se2.compose(pose, LASER_MOUNT), beams=BEAMS,
                                       max_range=20.0, range_noise=0.01, rng=rng)
                if upside_down:  # its y axis points the other way
                    points = points * np.array([1.0, -1.0])
            ranges: object = laser_ranges(points)
            scan_type = "sensor_msgs/msg/LaserScan"
            if multi_echo:  # each return the first of its echoes, a weaker one 1.5 m behind it second
                scan_type = "sensor_msgs/msg/MultiEchoLaserScan"
                echo = types["sensor_msgs/msg/LaserEcho"]
                ranges = [echo(echoes=np.array([r, r + 1.5] if np.isfinite(r) else [], np.float32))
                          for r in laser_ranges(points)]
            scan = types[scan_type](
                header=messages.header(stamp, scan_frame),
                angle_min=0.0,
                angle_max=float(2 * math.pi * (BEAMS - 1) / BEAMS),
                angle_increment=float(2 * math.pi / BEAMS),
                time_increment=sweep / BEAMS,
                scan_time=0.1,
                range_min=0.05,
                range_max=20.0,
                ranges=ranges,
                intensities=[] if multi_echo else np.zeros(0, dtype=np.float32),
            )
            add("/scan", scan_type, stamp, scan)
    return truth


def _swept_points(scan: int, sweep: float, rng: np.random.Generator) -> np.ndarray:
    """The laser's points of `write_drive`'s scan `scan`, beam j (bearing j·2π/BEAMS) taken j·sweep/BEAMS
    seconds after the stamp from where the laser then is."""
    beam_times = np.arange(BEAMS) * (sweep / BEAMS)
    # `simulate_swept_scan` numbers its beams from bearing −π: its beam i is the LaserScan's beam i + π.
    in_scan_order = beam_times[(np.arange(BEAMS) + BEAMS // 2) % BEAMS]
    robot = route_poses(square_loop(), DRIVE_STEP * scan + DRIVE_SPEED * in_scan_order)
    lasers = se2.compose(robot, np.broadcast_to(LASER_MOUNT, robot.shape))
    points, _ = simulate_swept_scan(square_loop().segments, lasers, max_range=20.0, range_noise=0.01, rng=rng)
    return points


BROKEN_GRAPH = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0\n"  # the edge lacks values


def modules_a_fresh_replay_loads(log: Path, out: Path, prefixes: tuple[str, ...]) -> list[str]:
    """The loaded modules whose names start with one of `prefixes` after `replay LOG --out OUT` in a fresh
    process (a test session has imported everything already), its outputs checked written."""
    program = (
        "import json, sys\n"
        "from pipeline.cli import app\n"
        f"app([{str(log)!r}, '--out', {str(out)!r}, '--quiet'], standalone_mode=False)\n"
        f"print(json.dumps(sorted(name for name in sys.modules if name.startswith({prefixes!r}))))\n"
    )
    run = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=300,
                         stdin=subprocess.DEVNULL, cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stdout + run.stderr
    assert (out / f"{log.stem}.tum").exists()
    return json.loads(run.stdout.strip().splitlines()[-1])


def recording_streams_alive() -> int:
    """The rerun recording streams alive in this process: one `RecordingStream` thread each (Linux)."""
    tasks = Path("/proc/self/task").iterdir()
    return sum(1 for task in tasks if (task / "comm").read_text().strip() == "RecordingStream")
