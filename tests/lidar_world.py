"""A synthetic 3D LiDAR world for the slam3d tests: a town block of boxes, a spinning LiDAR, a loop drive.

Nothing here uses the frontend's code: poses, rays and returns are computed from first principles (the
slab test for ray/box intersection, rotations written out), so the tests compare against an independent
truth.

- A world is an (M, 6) array of boxes (x0, y0, z0, x1, y1, z1) above a ground plane z = 0.
- `town_loop()` is a block of buildings with a street all around it and more buildings, poles and parked
  cars outside; the vehicle drives once around the block (a rounded rectangle) and a bit further.
- `simulate_sweep` spins a multi-ring LiDAR for one sweep while the vehicle moves: each column of beams is
  cast from the sensor pose at its own time, and the points are returned in the sensor frame of that
  time with their time since the sweep started — the motion distortion a real sensor has.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit
from numpy.typing import NDArray

from frontends.slam3d.config import OdometryConfig
from frontends.slam3d.odometry import KissOdometry, OdometryStep

FloatArray = NDArray[np.float64]

SWEEP_PERIOD = 0.1
"""Seconds per revolution (10 Hz)."""


def rotation_z(theta: float | FloatArray) -> FloatArray:
    c, s = np.cos(theta), np.sin(theta)
    out = np.zeros((*np.shape(theta), 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def rotation_y(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def homogeneous(rotation: FloatArray, translation: FloatArray) -> FloatArray:
    out = np.zeros((*rotation.shape[:-2], 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def planar_to_matrix(poses: FloatArray) -> FloatArray:
    """(..., 3) planar poses (x, y, yaw) on the ground as (..., 4, 4) matrices (z = 0)."""
    poses = np.asarray(poses, dtype=np.float64)
    translation = np.concatenate([poses[..., :2], np.zeros((*poses.shape[:-1], 1))], axis=-1)
    return homogeneous(rotation_z(poses[..., 2]), translation)


# ------------------------------------------------------------------------------------------- the world


@dataclass(frozen=True)
class Route:
    """A closed loop of four straights and four left turns, driven counter-clockwise from (`start_x`, 0)
    heading +x: the bottom straight starts at (`x0`, 0). Each turn eases in and out of its radius over
    `ease` metres (curvature ramping linearly, as a driver turns the wheel): a real vehicle's yaw rate
    does not jump, and a constant-velocity motion model should not be asked to follow one that does."""

    x0: float
    long_side: float
    short_side: float
    radius: float
    ease: float
    start_x: float

    @property
    def perimeter(self) -> float:
        return float(_route_table(self)[0][-1])

    def pose(self, distance: FloatArray) -> FloatArray:
        """(N, 3) planar poses after driving `distance` (N,) metres (wrapping around the loop)."""
        along, x, y, heading = _route_table(self)
        s = (np.atleast_1d(np.asarray(distance, dtype=np.float64)) + (self.start_x - self.x0)) % along[-1]
        out = np.stack(
            [np.interp(s, along, x), np.interp(s, along, y), np.interp(s, along, heading)], axis=-1
        )
        out[:, 2] = (out[:, 2] + math.pi) % (2 * math.pi) - math.pi
        return out


ROUTE_RESOLUTION = 0.01


@functools.cache
def _route_table(route: Route) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Arc length, x, y and (unwrapped) heading about every `ROUTE_RESOLUTION` metres, integrated from
    the curvature profile (midpoint rule)."""
    full = 1.0 / route.radius
    arc = 0.5 * math.pi * route.radius - route.ease  # with both easings each turn is exactly 90°
    pieces: list[tuple[float, float, float]] = []  # (length, curvature at its start, at its end)
    for side in (route.long_side, route.short_side) * 2:
        pieces += [(side, 0.0, 0.0), (route.ease, 0.0, full), (arc, full, full), (route.ease, full, 0.0)]
    step_lengths, curvatures = [], []
    for length, start, end in pieces:
        count = max(1, round(length / ROUTE_RESOLUTION))
        step_lengths.append(np.full(count, length / count))
        curvatures.append(start + (end - start) * (np.arange(count) + 0.5) / count)
    step = np.concatenate(step_lengths)
    turn = np.concatenate(curvatures) * step
    heading = np.concatenate([[0.0], np.cumsum(turn)])
    middle = heading[:-1] + 0.5 * turn
    x = route.x0 + np.concatenate([[0.0], np.cumsum(step * np.cos(middle))])
    y = np.concatenate([[0.0], np.cumsum(step * np.sin(middle))])
    return np.concatenate([[0.0], np.cumsum(step)]), x, y, heading


@dataclass(frozen=True)
class World:
    boxes: FloatArray
    route: Route


def town_loop(seed: int = 3) -> World:
    """A 40 m × 24 m block (street on its centre line all around, 12 m wide) with irregular buildings
    inside and outside, poles and parked cars: every corner of the loop looks different."""
    rng = np.random.default_rng(seed)
    route = Route(x0=9.0, long_side=22.0, short_side=6.0, radius=7.0, ease=4.0, start_x=12.0)
    boxes = [
        # inside the block: buildings of different sizes and heights
        [7, 7, 0, 14, 12, 12],
        [15.5, 7, 0, 22, 10, 8],
        [24, 7, 0, 33, 11.5, 15],
        [7, 13.5, 0, 12, 17, 6],
        [14, 12, 0, 25, 17, 10],
        [27, 13, 0, 33, 17, 20],
        [23, 10.5, 0, 23.6, 11.2, 3],
    ]
    # outside: a row of buildings with gaps along each side, seeded
    for side in range(4):
        position = -10.0
        end = 50.0 if side % 2 == 0 else 34.0
        while position < end:
            width = rng.uniform(5.0, 12.0)
            depth = rng.uniform(6.0, 12.0)
            top = rng.uniform(5.0, 22.0)
            setback = rng.uniform(6.0, 8.0)
            a, b = position, position + width
            if side == 0:
                boxes.append([a, -setback - depth, 0, b, -setback, top])
            elif side == 1:
                boxes.append([a, 24 + setback, 0, b, 24 + setback + depth, top])
            elif side == 2:
                boxes.append([-setback - depth, a, 0, -setback, b, top])
            else:
                boxes.append([40 + setback, a, 0, 40 + setback + depth, b, top])
            position = b + rng.uniform(2.0, 6.0)
    # poles and parked cars along the kerbs, 3.5 – 5 m from the centre line, irregularly spaced
    for _ in range(24):
        side = rng.integers(4)
        along = rng.uniform(6.0, 34.0) if side < 2 else rng.uniform(6.0, 18.0)
        offset = rng.uniform(3.5, 5.0) * (1 if side in (0, 2) else -1)
        size = (0.3, 0.3, rng.uniform(3.0, 6.0)) if rng.random() < 0.6 else (4.5, 1.8, 1.5)
        if side >= 2:
            size = (size[1], size[0], size[2])
        x, y = {0: (along, -offset), 1: (along, 24 + offset), 2: (-offset, along), 3: (40 + offset, along)}[
            side
        ]
        boxes.append([x - size[0] / 2, y - size[1] / 2, 0, x + size[0] / 2, y + size[1] / 2, size[2]])
    return World(np.array(boxes, dtype=np.float64), route)


def straight_street(length: float = 400.0, half_width: float = 6.0, height: float = 8.0) -> FloatArray:
    """Two long featureless walls along x, nothing else: every stretch looks the same (boxes)."""
    return np.array(
        [
            [-length / 2, -half_width - 1.0, 0.0, length / 2, -half_width, height],
            [-length / 2, half_width, 0.0, length / 2, half_width + 1.0, height],
        ]
    )


# ------------------------------------------------------------------------------------------- the sensor


@dataclass(frozen=True)
class Lidar:
    rings: int = 32
    columns: int = 1024
    lowest: float = math.radians(-25.0)
    highest: float = math.radians(15.0)
    max_range: float = 60.0
    range_noise: float = 0.01

    def directions(self, phase: float = 0.0, tilt: float = 0.0) -> FloatArray:
        """(rings, columns, 3) unit beam directions in the sensor frame; column j at azimuth
        2π (j + phase)/columns (the sensor sweeps counter-clockwise starting along +x), every ring's
        elevation raised by `tilt` ring spacings."""
        spacing = (self.highest - self.lowest) / max(self.rings - 1, 1)
        elevation = np.linspace(self.lowest, self.highest, self.rings)[:, None] + tilt * spacing
        azimuth = 2.0 * math.pi * (np.arange(self.columns)[None, :] + phase) / self.columns
        return np.stack(
            np.broadcast_arrays(
                np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
            ),
            axis=-1,
        )


@njit(cache=True)
def _cast(boxes: FloatArray, origins: FloatArray, directions: FloatArray) -> FloatArray:  # pragma: no cover
    count = origins.shape[0]
    out = np.full(count, np.inf)
    for i in range(count):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        best = -oz / dz if dz < -1e-9 else np.inf  # the ground z = 0
        for b in range(boxes.shape[0]):
            near, far = -np.inf, np.inf
            for o, d, low, high in (
                (ox, dx, boxes[b, 0], boxes[b, 3]),
                (oy, dy, boxes[b, 1], boxes[b, 4]),
                (oz, dz, boxes[b, 2], boxes[b, 5]),
            ):
                if abs(d) < 1e-12:
                    if o < low or o > high:
                        near, far = np.inf, -np.inf
                        break
                    continue
                t0, t1 = (low - o) / d, (high - o) / d
                if t0 > t1:
                    t0, t1 = t1, t0
                near, far = max(near, t0), min(far, t1)
            if far >= near and 1e-6 < near < best:
                best = near
        out[i] = best
    return out


def cast(boxes: FloatArray, origins: FloatArray, directions: FloatArray) -> FloatArray:
    """Distance along each ray (N,) to the nearest box (slab test) or the ground z = 0, inf when none."""
    return _cast(
        np.ascontiguousarray(boxes, dtype=np.float64),
        np.ascontiguousarray(origins, dtype=np.float64),
        np.ascontiguousarray(directions, dtype=np.float64),
    )


def simulate_sweep(
    boxes: FloatArray,
    sensor_poses: FloatArray,
    lidar: Lidar,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """One sweep: `sensor_poses` (columns, 4, 4) is the sensor's pose in the world when each column fires.
    Returns the points (N, 3) in the sensor frame *at each point's own time* and those times (N,) in
    seconds since the sweep started (float32, as a driver writes them)."""
    # Identical sampling in every sweep would bias point-to-point registration (towards standing still,
    # and in pitch: rings trace the same lines on flat walls): a real sensor's firing azimuths differ from
    # one revolution to the next, and the vehicle's bounce shifts its rings over real, uneven surfaces.
    local = lidar.directions(phase=float(rng.uniform()), tilt=float(rng.uniform(-0.5, 0.5)))  # (R, C, 3)
    world_directions = np.einsum("cij,rcj->rci", sensor_poses[:, :3, :3], local)
    origins = np.broadcast_to(sensor_poses[None, :, :3, 3], world_directions.shape)
    distance = cast(boxes, origins.reshape(-1, 3), world_directions.reshape(-1, 3)).reshape(local.shape[:2])
    distance = distance + lidar.range_noise * rng.standard_normal(distance.shape)
    valid = np.isfinite(distance) & (distance > 0.5) & (distance <= lidar.max_range)
    points = local[valid] * distance[valid][:, None]
    times = np.broadcast_to(SWEEP_PERIOD * np.arange(lidar.columns)[None, :] / lidar.columns, distance.shape)[
        valid
    ]
    return points.astype(np.float32), times.astype(np.float32)


def mount_matrix(translation: tuple[float, float, float], pitch: float) -> FloatArray:
    """The sensor's pose in the base frame: translated, pitched about y."""
    return homogeneous(rotation_y(pitch), np.asarray(translation, dtype=np.float64))


@dataclass(frozen=True, eq=False)
class Drive:
    """Ground truth of a drive: base poses (planar, at each sweep's start) and the sweeps."""

    base_poses: FloatArray
    """(S, 3) planar base pose at each sweep's start."""
    clouds: tuple[NDArray[np.float32], ...]
    """Points in the sensor frame (distorted by the motion, as recorded)."""
    times: tuple[NDArray[np.float32], ...]
    mount: FloatArray
    distances: FloatArray
    """(S,) distance along the route at each sweep's start (m)."""
    speeds: FloatArray
    """(S,) metres driven during each sweep."""


def drive(
    world: World,
    *,
    sweeps: int,
    step: float,
    start: float = 0.0,
    ramp: int = 10,
    lidar: Lidar | None = None,
    mount: FloatArray | None = None,
    seed: int = 0,
) -> Drive:
    """Drive `sweeps` sweeps along the world's route: standing still for the first sweep, then speeding
    up over `ramp` sweeps to `step` metres per sweep (`step` / 0.1 s m/s), as a recording starts."""
    lidar = lidar or Lidar()
    mount = mount_matrix((0.4, 0.0, 1.8), math.radians(2.0)) if mount is None else mount
    rng = np.random.default_rng(seed)
    speeds = step * np.clip(np.arange(sweeps) / max(ramp, 1), 0.0, 1.0)  # metres during each sweep
    starts = start + np.concatenate([[0.0], np.cumsum(speeds)[:-1]])
    base_poses = world.route.pose(starts)
    clouds, times = [], []
    fraction = np.arange(lidar.columns) / lidar.columns
    for s, speed in zip(starts, speeds, strict=True):
        column_poses = planar_to_matrix(world.route.pose(s + speed * fraction))
        points, stamps = simulate_sweep(world.boxes, column_poses @ mount, lidar, rng)
        clouds.append(points)
        times.append(stamps)
    return Drive(base_poses, tuple(clouds), tuple(times), mount, starts, speeds)


# ------------------------------------------------------------------------------------------- the log

START_NS = 1_700_000_000_000_000_000
SENSOR_FRAME = "lidar"
BASE_FRAME = "base_link"


def write_cloud_log(
    path: Path, drive: Drive, *, with_times: bool = True, with_mount: bool = True, later_ns: int = 0
) -> NDArray[np.int64]:
    """The drive as a ROS 2 MCAP: `/points` sensor_msgs/PointCloud2 (x, y, z, intensity float32, and a
    float32 `time` field in seconds since the stamp when `with_times`), stamped at each sweep's start
    (from `START_NS` + `later_ns`: a recording made later), and `/tf_static` base_link → lidar (the
    mount) when `with_mount`. Returns the stamps."""
    from scipy.spatial.transform import Rotation

    from tests._frontends_fixtures import ros2_mcap

    stamps = START_NS + later_ns + np.arange(len(drive.clouds), dtype=np.int64) * int(SWEEP_PERIOD * 1e9)
    names = ["x", "y", "z", "intensity", *(["time"] if with_times else [])]
    point_dtype = np.dtype([(name, "<f4") for name in names])
    with ros2_mcap(path) as (messages, add):
        types = messages.types
        fields = [
            types["sensor_msgs/msg/PointField"](name=name, offset=4 * i, datatype=7, count=1)
            for i, name in enumerate(names)
        ]
        if with_mount:
            q = Rotation.from_matrix(drive.mount[:3, :3]).as_quat()
            t = drive.mount[:3, 3]
            transform = types["geometry_msgs/msg/TransformStamped"](
                header=messages.header(int(stamps[0]), BASE_FRAME),
                child_frame_id=SENSOR_FRAME,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
            add("/tf_static", "tf2_msgs/msg/TFMessage", int(stamps[0]),
                types["tf2_msgs/msg/TFMessage"](transforms=[transform]))  # fmt: skip
        for stamp, points, times in zip(stamps.tolist(), drive.clouds, drive.times, strict=True):
            data = np.zeros(len(points), dtype=point_dtype)
            data["x"], data["y"], data["z"] = points.T
            data["intensity"] = 100.0
            if with_times:
                data["time"] = times
            cloud = types["sensor_msgs/msg/PointCloud2"](
                header=messages.header(stamp, SENSOR_FRAME),
                height=1,
                width=len(points),
                fields=fields,
                is_bigendian=False,
                point_step=point_dtype.itemsize,
                row_step=point_dtype.itemsize * len(points),
                data=np.frombuffer(data.tobytes(), dtype=np.uint8),
                is_dense=True,
            )
            add("/points", "sensor_msgs/msg/PointCloud2", stamp, cloud)
    return stamps


LOOP_SWEEPS = 163
LOOP_STEP = 0.8


@functools.cache
def loop_drive() -> Drive:
    """Once around `town_loop` and about 12 m further (the start is seen again), 8 m/s after a 1 s
    start-up, a 32 × 720 LiDAR mounted 1.8 m up and pitched 2°. Cached: several test modules use it."""
    return drive(town_loop(), sweeps=LOOP_SWEEPS, step=LOOP_STEP, lidar=Lidar(columns=720))


class DistortedOdometry:
    """KISS-ICP whose every pose is then moved by `distortion(distance driven)` (a 4×4 transform applied
    in the odometry frame): a drift that grows with the distance, as real LiDAR odometry drifts, which the
    loop closures (and, for height, only the SE(3) polish) must take out."""

    def __init__(self, distortion: Callable[[float], FloatArray],
                 config: OdometryConfig | None = None) -> None:
        self._inner = KissOdometry(config)
        self._distortion = distortion
        self._travel = 0.0
        self._previous: FloatArray | None = None

    def register(
        self,
        points: FloatArray,
        point_times: FloatArray | None = None,
        motion_guess: FloatArray | None = None,
    ) -> OdometryStep | None:
        step = self._inner.register(points, point_times, motion_guess)
        if step is None:
            return None
        if self._previous is not None:
            self._travel += float(np.linalg.norm(step.pose[:3, 3] - self._previous[:3, 3]))
        self._previous = step.pose
        drift = self._distortion(self._travel)
        return OdometryStep(drift @ step.pose, step.points, drift @ step.points_pose, step.deskewed)
