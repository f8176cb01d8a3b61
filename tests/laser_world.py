"""A synthetic 2D laser world for the slam2d tests: walls as line segments, a ray caster, a robot's drive.

Nothing here uses the frontend's code: the ground truth, the scans and the odometry are computed from
first principles (ray/segment intersection, SE(2) composition written out), so the tests compare the
frontend against an independent truth.

- A world is an (M, 4) array of wall segments (x0, y0, x1, y1) plus a route (waypoints the robot drives
  through, corners rounded into arcs).
- `simulate_scan` casts every beam against every segment at once (beams × segments arrays).
- `drive` samples the rounded route every `step` metres: ground-truth poses.
- `wheel_odometry` integrates the true increments with seeded noise, a scale error and a heading bias:
  odometry that drifts the way real wheel odometry does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------------------------- SE(2)


def wrap(theta: FloatArray | float) -> FloatArray:
    return (np.asarray(theta) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """a·b for (..., 3) poses."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap(a[..., 2] + b[..., 2])], axis=-1)


def between(a: FloatArray, b: FloatArray) -> FloatArray:
    """a⁻¹·b for (..., 3) poses: b seen from a."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[..., 2] - a[..., 2])], axis=-1)


def transform_points(points: FloatArray, pose: FloatArray) -> FloatArray:
    """Points (N, 2) given in the frame of `pose`, expressed in the frame `pose` is given in."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([pose[0] + c * points[:, 0] - s * points[:, 1],
                            pose[1] + s * points[:, 0] + c * points[:, 1]])


def align_to_first(poses: FloatArray, truth: FloatArray) -> FloatArray:
    """`poses` moved rigidly so their first pose coincides with the first true pose."""
    return compose(truth[0], between(poses[0], poses))


def drive_errors(poses: FloatArray, truth: FloatArray, distance: float = 10.0) -> dict[str, float]:
    """A drive's estimated poses scored against the truth: the absolute trajectory error (RMSE of the
    positions, the first pose aligned), and the mean relative error between poses `distance` metres apart
    along the drive (translation m, rotation deg)."""
    aligned = align_to_first(poses, truth)
    steps = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    span = max(1, int(round(distance / max(float(np.mean(steps)), 1e-9))))
    estimated, true = between(poses[:-span], poses[span:]), between(truth[:-span], truth[span:])
    return {
        "ate": float(np.sqrt(np.mean(np.sum((aligned[:, :2] - truth[:, :2]) ** 2, axis=1)))),
        "relative_m": float(np.mean(np.hypot(*(estimated[:, :2] - true[:, :2]).T))),
        "relative_deg": float(np.degrees(np.mean(np.abs(wrap(estimated[:, 2] - true[:, 2]))))),
    }


# -------------------------------------------------------------------------------------------- walls


def wall(start: Sequence[float], end: Sequence[float],
         doors: Sequence[tuple[float, float]] = ()) -> FloatArray:
    """A straight wall from `start` to `end` with door gaps (distance of the door's centre from `start`,
    width): the segments between the gaps, (K, 4)."""
    a, b = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    length = float(np.hypot(*(b - a)))
    direction = (b - a) / length
    cuts = [0.0]
    for centre, width in sorted(doors):
        cuts += [centre - 0.5 * width, centre + 0.5 * width]
    cuts.append(length)
    pieces = [(s, e) for s, e in zip(cuts[::2], cuts[1::2], strict=True) if e - s > 1e-9]
    return np.array([[*(a + s * direction), *(a + e * direction)] for s, e in pieces]).reshape(-1, 4)


def box(x0: float, y0: float, x1: float, y1: float) -> FloatArray:
    """The four sides of an axis-aligned rectangle, (4, 4)."""
    return np.array([[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]],
                    dtype=np.float64)


def room(x0: float, y0: float, x1: float, y1: float, open_side: str) -> FloatArray:
    """A rectangle's walls without the `open_side` ("south", "east", "north", "west"): that side is the
    corridor wall the room's door is cut in."""
    sides = dict(zip(("south", "east", "north", "west"), box(x0, y0, x1, y1), strict=True))
    return np.array([side for name, side in sides.items() if name != open_side])


@dataclass(frozen=True)
class World:
    segments: FloatArray
    """(M, 4) walls (x0, y0, x1, y1)."""
    route: FloatArray
    """(W, 2) waypoints the robot drives through in order; corners are rounded by `turn_radius`."""
    turn_radius: float


def square_loop() -> World:
    """A building floor: a square loop of 2 m corridors (outer walls on [0, 20]², inner on [2, 18]²),
    doors into rooms on both sides, two halls inside, clutter boxes along the corridor walls.

    The route drives the loop anticlockwise from the middle of the south corridor and goes on past the
    start, so the end of the drive revisits its beginning.
    """
    parts = [
        # Outer corridor walls with doors into the rooms outside.
        wall((0, 0), (20, 0), doors=[(5.0, 1.0), (13.5, 1.0)]),
        wall((20, 0), (20, 20), doors=[(7.0, 1.0), (15.0, 0.9)]),
        wall((20, 20), (0, 20), doors=[(11.0, 1.2)]),
        wall((0, 20), (0, 0), doors=[(5.5, 1.0), (15.0, 1.0)]),
        room(3.5, -4.0, 8.0, 0.0, "north"),
        room(11.0, -3.5, 16.0, 0.0, "north"),
        room(20.0, 4.0, 25.0, 10.0, "west"),
        room(20.0, 13.0, 23.0, 18.0, "west"),
        room(6.0, 20.0, 13.0, 24.0, "south"),
        room(-4.0, 11.0, 0.0, 17.0, "east"),
        room(-3.0, 3.0, 0.0, 8.0, "east"),
        # Inner corridor walls with doors into the two halls, and the partition between the halls.
        wall((2, 2), (18, 2), doors=[(7.5, 1.2)]),
        wall((18, 2), (18, 18), doors=[(10.0, 1.0)]),
        wall((18, 18), (2, 18), doors=[(14.0, 1.0)]),
        wall((2, 18), (2, 2), doors=[(10.0, 1.0)]),
        wall((10, 2), (10, 18), doors=[(8.0, 1.0)]),
        # Furniture in the halls and in the rooms.
        box(5.0, 5.0, 6.0, 6.5), box(13.0, 6.0, 14.5, 7.0), box(7.0, 13.0, 8.0, 14.0),
        box(14.0, 14.0, 15.5, 14.5), box(12.0, 10.0, 12.4, 10.4), box(4.0, -3.0, 5.0, -2.5),
        box(22.5, 6.0, 23.5, 8.5), box(9.0, 22.0, 10.5, 23.0), box(-2.0, 13.0, -1.2, 14.5),
        # Clutter against the corridor walls (at most 0.4 m deep: the robot drives 1 m from the walls).
        box(7.0, 0.0, 7.5, 0.3), box(15.5, 1.7, 16.2, 2.0), box(19.6, 3.0, 20.0, 3.8),
        box(18.0, 9.0, 18.4, 9.5), box(13.0, 19.7, 14.0, 20.0), box(6.0, 18.0, 6.5, 18.3),
        box(0.0, 9.5, 0.4, 10.3), box(1.6, 16.0, 2.0, 16.6), box(11.0, 0.0, 11.3, 0.25),
        box(19.7, 12.0, 20.0, 12.3), box(3.0, 19.75, 3.6, 20.0), box(0.0, 2.5, 0.3, 3.0),
    ]
    route = np.array([[6, 1], [19, 1], [19, 19], [1, 19], [1, 1], [12, 1]], dtype=np.float64)
    return World(np.concatenate(parts), route, turn_radius=1.0)


def long_corridor(length: float = 200.0, width: float = 2.0) -> World:
    """Two parallel walls y = ±width/2 along x ∈ [−length/2, length/2], nothing else: seen from the middle
    within a laser's range, every stretch looks the same."""
    half = 0.5 * length
    segments = np.array([[-half, -0.5 * width, half, -0.5 * width], [-half, 0.5 * width, half, 0.5 * width]])
    return World(segments, np.array([[-10.0, 0.0], [10.0, 0.0]]), turn_radius=0.5)


def ring_corridors(length: float = 140.0) -> World:
    """Two parallel 3 m corridors `length` m long, joined at both ends (a thin ring around a wall), nothing
    along them but their walls; clutter at the west end, where the drive starts and, after a lap, ends.

    Along the corridors no scan pins the robot's position along them: the wheel odometry decides it. A
    lap later the clutter at the start is the only place where the map can be seen to be off."""
    parts = [
        wall((0, 0), (length, 0)), wall((length, 0), (length, 6)), wall((length, 6), (0, 6)),
        wall((0, 6), (0, 0)), wall((8, 3), (length - 8, 3)),
        box(1.0, 0.0, 1.6, 0.4), box(3.0, 5.5, 4.2, 6.0), box(6.0, 0.0, 6.3, 0.6), box(0.0, 2.0, 0.5, 2.8),
        box(10.0, 0.0, 10.8, 0.3), box(9.0, 5.7, 9.4, 6.0), box(12.0, 2.7, 12.6, 3.0),
        box(2.0, 3.0, 2.6, 3.4),
        box(length - 4.0, 0.0, length - 3.5, 0.4), box(length - 2.0, 5.6, length - 1.0, 6.0),
    ]
    route = np.array([[4, 1.5], [length - 4, 1.5], [length - 4, 4.5], [4, 4.5], [4, 1.5], [30, 1.5]],
                     dtype=np.float64)
    return World(np.concatenate(parts), route, turn_radius=1.0)


def corridor_of_doors(doors_open: bool, length: float = 30.0) -> World:
    """A 2 m corridor along x ∈ [0, `length`] closed at both ends. With `doors_open`, nine doors on each
    side (3 m apart) open into small rooms; without, its walls are plain: a map made with the doors shut
    cannot tell where along the corridor a scan was taken (a laser of 8 m reaches an end only near it),
    while the open doors tell each scan from the next. The route drives its length."""
    south = [(3.0 + 3.0 * k, 0.9) for k in range(9)]
    north = [(centre + 1.2, width) for centre, width in south]
    parts = [wall((0, 0), (length, 0), doors=south if doors_open else []),
             wall((0, 2), (length, 2), doors=north if doors_open else []),
             wall((0, 0), (0, 2)), wall((length, 0), (length, 2))]
    if doors_open:
        parts += [room(centre - 0.8, -1.5, centre + 0.8, 0.0, "north") for centre, _ in south]
        parts += [room(centre - 0.8, 2.0, centre + 0.8, 3.5, "south") for centre, _ in north]
    return World(np.concatenate(parts), np.array([[1.5, 1.0], [length - 1.5, 1.0]]), turn_radius=0.5)


TWIN_ROOM_SHIFT = 3.5
"""Room B is room A moved this far east (m): closer than a loop-closure search radius."""


def twin_rooms() -> World:
    """A corridor (y ∈ [0, 2]) with two identical rooms side by side on its north wall (A on x ∈ [2, 5.5],
    B the same shifted by `TWIN_ROOM_SHIFT`), same door, same furniture: seen from inside, a room does not
    say which one it is. The route visits A, then B, then A again (the true loop closure).
    """
    interior = [box(2.2, 5.2, 2.8, 5.7), box(5.0, 2.2, 5.3, 2.7), box(2.2, 2.2, 2.5, 2.9),
                box(4.6, 5.6, 5.3, 5.8)]
    room_a = [room(2.0, 2.0, 2.0 + TWIN_ROOM_SHIFT, 6.0, "south"), *interior]
    room_b = [part + np.array([TWIN_ROOM_SHIFT, 0.0, TWIN_ROOM_SHIFT, 0.0]) for part in room_a]
    door_a = 3.5  # x of the centre of room A's door (the wall starts at x = −1)
    parts = [
        wall((-1, 0), (14, 0)),
        wall((-1, 2), (14, 2), doors=[(door_a + 1.0, 1.0), (door_a + 1.0 + TWIN_ROOM_SHIFT, 1.0)]),
        wall((-1, 0), (-1, 2)),
        wall((14, 0), (14, 2)),
        *room_a,
        *room_b,
        # The corridor, unlike the rooms, is not periodic.
        box(0.5, 0.0, 1.0, 0.3), box(9.5, 0.0, 10.5, 0.4), box(12.0, 1.7, 12.6, 2.0),
    ]
    # Enter through the door (x + 0.2), drive a small loop in the room, leave through the door (x − 0.2).
    def visit(door: float) -> list[list[float]]:
        return [[door + 0.2, 1.0], [door + 0.2, 5.0], [door + 1.4, 5.0], [door + 1.4, 3.2], [door - 0.2, 3.2],
                [door - 0.2, 1.0]]

    door_b = door_a + TWIN_ROOM_SHIFT
    route = [[0.0, 1.0], *visit(door_a), *visit(door_b), *visit(door_a), [0.5, 1.0]]
    return World(np.concatenate(parts), np.array(route, dtype=np.float64), turn_radius=0.5)


# ------------------------------------------------------------------------------------------ the laser


def simulate_scan(segments: FloatArray, pose: FloatArray, *, beams: int = 360, fov: float = 2.0 * math.pi,
                  max_range: float = 20.0, range_noise: float = 0.0,
                  rng: np.random.Generator | None = None) -> FloatArray:
    """The returns of a laser at `pose` (x, y, θ) among `segments`: bearing-ordered points (N, 2) in the
    sensor frame, one per beam whose nearest wall lies within `max_range` (after the range noise).

    Beams are spread over `fov` centred on the heading (a full circle: `beams` bearings from −π, the
    last one short of +π).
    """
    points, _ = simulate_swept_scan(segments, np.broadcast_to(np.asarray(pose, dtype=np.float64), (beams, 3)),
                                    fov=fov, max_range=max_range, range_noise=range_noise, rng=rng)
    return points


def beam_bearings(beams: int, fov: float) -> FloatArray:
    """The bearings of `simulate_scan`'s beams, in the order the laser takes them."""
    if fov >= 2.0 * math.pi - 1e-12:
        return -0.5 * fov + fov * np.arange(beams) / beams
    return np.linspace(-0.5 * fov, 0.5 * fov, beams)


def simulate_swept_scan(segments: FloatArray, beam_poses: FloatArray, *, fov: float = 2.0 * math.pi,
                        max_range: float = 20.0, range_noise: float = 0.0,
                        rng: np.random.Generator | None = None) -> tuple[FloatArray, NDArray[np.bool_]]:
    """A laser that takes beam i from `beam_poses[i]` (B, 3), as a real one does while the robot moves:
    (the points (N, 2), each in the sensor frame of its own beam, as the laser reports them; which of the
    B beams returned)."""
    if rng is None:
        rng = np.random.default_rng(0)
    beams = beam_poses.shape[0]
    bearings = beam_bearings(beams, fov)
    angles = beam_poses[:, 2] + bearings
    direction = np.column_stack([np.cos(angles), np.sin(angles)])  # (B, 2)
    start = segments[None, :, :2] - beam_poses[:, None, :2]  # (B, M, 2) from the sensor
    edge = segments[:, 2:] - segments[:, :2]  # (M, 2)

    # Solve origin + r·d = start + u·edge for every beam × segment: r along the beam, u along the wall.
    def cross(a: FloatArray, b: FloatArray) -> FloatArray:
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

    denominator = cross(direction[:, None, :], edge[None, :, :])  # (B, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = cross(start, edge[None, :, :]) / denominator
        along = cross(start, direction[:, None, :]) / denominator
    hits = (np.abs(denominator) > 1e-12) & (distance > 1e-9) & (along >= 0.0) & (along <= 1.0)
    ranges = np.where(hits, distance, np.inf).min(axis=1)
    ranges = ranges + range_noise * rng.standard_normal(beams)
    valid = np.isfinite(ranges) & (ranges > 0.0) & (ranges <= max_range)
    kept, kept_bearings = ranges[valid], bearings[valid]
    return np.column_stack([kept * np.cos(kept_bearings), kept * np.sin(kept_bearings)]), valid


def wall_distances(points_in_world: FloatArray, segments: FloatArray) -> FloatArray:
    """Each point's distance to the nearest wall."""
    start, end = segments[None, :, :2], segments[None, :, 2:]
    edge = end - start
    along = np.clip(np.sum((points_in_world[:, None, :] - start) * edge, axis=2)
                    / np.maximum(np.sum(edge * edge, axis=2), 1e-12), 0.0, 1.0)
    nearest = start + along[..., None] * edge
    return np.min(np.linalg.norm(points_in_world[:, None, :] - nearest, axis=2), axis=1)


# ------------------------------------------------------------------------------------------- driving


def _rounded_route(route: FloatArray, radius: float) -> list[tuple[str, FloatArray, float, float, float]]:
    """The route as primitives (kind, start point, start heading, length, turn direction ±1)."""
    primitives: list[tuple[str, FloatArray, float, float, float]] = []
    points = [np.asarray(p, dtype=np.float64) for p in route]
    position = points[0]
    for k in range(1, len(points)):
        direction = points[k] - points[k - 1]
        heading = math.atan2(direction[1], direction[0])
        end = points[k]
        tangent = 0.0
        turn = 0.0
        if k + 1 < len(points):
            following = points[k + 1] - points[k]
            turn = float(wrap(math.atan2(following[1], following[0]) - heading))
            tangent = radius * math.tan(0.5 * abs(turn))
        line_end = end - tangent * direction / np.hypot(*direction)
        length = float(np.hypot(*(line_end - position)))
        if length > 1e-9:
            primitives.append(("line", position, heading, length, 0.0))
        position = line_end
        if abs(turn) > 1e-9:
            primitives.append(("arc", position, heading, radius * abs(turn), math.copysign(1.0, turn)))
            side = math.copysign(radius, turn)
            centre = position + side * np.array([-math.sin(heading), math.cos(heading)])
            final = heading + turn
            position = centre + side * np.array([math.sin(final), -math.cos(final)])
    return primitives


def drive(world: World, step: float) -> FloatArray:
    """Ground-truth poses (K, 3) every `step` metres of arc length along the world's rounded route."""
    return route_poses(world, np.arange(0.0, route_length(world) + 1e-9, step))


def route_length(world: World) -> float:
    return float(sum(p[3] for p in _rounded_route(world.route, world.turn_radius)))


def route_poses(world: World, arc_length: FloatArray) -> FloatArray:
    """Poses (K, 3) at the given arc lengths (m, within [0, `route_length`]) along the rounded route."""
    primitives = _rounded_route(world.route, world.turn_radius)
    lengths = np.array([p[3] for p in primitives])
    starts = np.concatenate([[0.0], np.cumsum(lengths)])
    which = np.clip(np.searchsorted(starts, arc_length, side="right") - 1, 0, len(primitives) - 1)
    poses = np.empty((len(arc_length), 3))
    radius = world.turn_radius
    for index, (kind, origin, heading, _, turn) in enumerate(primitives):
        mine = which == index
        s = arc_length[mine] - starts[index]
        if kind == "line":
            poses[mine, 0] = origin[0] + s * math.cos(heading)
            poses[mine, 1] = origin[1] + s * math.sin(heading)
            poses[mine, 2] = heading
        else:
            centre = origin + turn * radius * np.array([-math.sin(heading), math.cos(heading)])
            theta = heading + turn * s / radius
            poses[mine, 0] = centre[0] + turn * radius * np.sin(theta)
            poses[mine, 1] = centre[1] - turn * radius * np.cos(theta)
            poses[mine, 2] = theta
    poses[:, 2] = wrap(poses[:, 2])
    return poses


def wheel_odometry(truth: FloatArray, rng: np.random.Generator, *, linear_noise: float = 0.02,
                   angular_noise: float = 0.005, scale_error: float = 0.01,
                   heading_bias_per_metre: float = 0.004) -> FloatArray:
    """Odometry poses (K, 3) starting at the first true pose: each true increment is scaled by
    (1 + `scale_error`), its heading biased by `heading_bias_per_metre` × distance, and perturbed by
    Gaussian noise (σ = `linear_noise` × distance in x and y, `angular_noise` rad per step in θ)."""
    steps = between(truth[:-1], truth[1:])
    distance = np.hypot(steps[:, 0], steps[:, 1])
    noisy = steps.copy()
    noisy[:, :2] *= 1.0 + scale_error
    noisy[:, :2] += linear_noise * distance[:, None] * rng.standard_normal((len(steps), 2))
    noisy[:, 2] += heading_bias_per_metre * distance + angular_noise * rng.standard_normal(len(steps))
    odometry = np.empty_like(truth)
    odometry[0] = truth[0]
    for k, increment in enumerate(noisy):
        odometry[k + 1] = compose(odometry[k], increment)
    return odometry


@dataclass(frozen=True, eq=False)
class Run:
    """A simulated recording: one scan per pose."""

    stamps_ns: NDArray[np.int64]
    truth: FloatArray
    """(K, 3) ground-truth poses of the robot (the laser sits at the robot's origin)."""
    odometry: FloatArray
    """(K, 3) wheel-odometry poses (drifting)."""
    scans: tuple[FloatArray, ...]
    """Each scan's points (N, 2) in the robot frame."""
    point_times: tuple[FloatArray, ...] | None = None
    """Each scan's points' times (N,) in seconds after its stamp (`simulate_swept_run`); None: every point
    taken at the stamp."""


def simulate_run(world: World, *, step: float = 0.2, speed: float = 0.5, seed: int = 0,
                 beams: int = 360, fov: float = 2.0 * math.pi, max_range: float = 20.0,
                 range_noise: float = 0.01, **odometry_noise: float) -> Run:
    """Drive the world's route at `speed` (m/s), scanning every `step` metres."""
    rng = np.random.default_rng(seed)
    truth = drive(world, step)
    odometry = wheel_odometry(truth, rng, **odometry_noise)
    scans = tuple(simulate_scan(world.segments, pose, beams=beams, fov=fov, max_range=max_range,
                                range_noise=range_noise, rng=rng) for pose in truth)
    stamps = 1_700_000_000_000_000_000 + np.arange(len(truth), dtype=np.int64) * round(step / speed * 1e9)
    return Run(stamps, truth, odometry, scans)


def simulate_swept_run(world: World, *, speed: float = 1.0, scan_rate: float = 10.0, sweep: float = 0.1,
                       seed: int = 0, beams: int = 360, fov: float = 2.0 * math.pi, max_range: float = 20.0,
                       range_noise: float = 0.01, **odometry_noise: float) -> Run:
    """Drive the route at `speed` (m/s) with a laser that scans `scan_rate` times a second and takes its
    beams one after the other over `sweep` seconds, each from where the robot is then. `truth` is the pose
    at each scan's stamp, its first beam's time (as in a LaserScan), and `point_times` the beams' times."""
    rng = np.random.default_rng(seed)
    duration = route_length(world) / speed - sweep
    scan_times = np.arange(0.0, duration, 1.0 / scan_rate)
    beam_offsets = np.arange(beams) * (sweep / beams)
    truth = route_poses(world, speed * scan_times)
    scans, times = [], []
    for start in scan_times:
        beam_poses = route_poses(world, speed * (start + beam_offsets))
        points, valid = simulate_swept_scan(world.segments, beam_poses, fov=fov, max_range=max_range,
                                            range_noise=range_noise, rng=rng)
        scans.append(points)
        times.append(beam_offsets[valid])
    odometry = wheel_odometry(truth, rng, **odometry_noise)
    stamps = 1_700_000_000_000_000_000 + np.round(scan_times * 1e9).astype(np.int64)
    return Run(stamps, truth, odometry, tuple(scans), tuple(times))
