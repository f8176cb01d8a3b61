"""What the frontends hand to the rest of the pipeline: frozen dataclasses over numpy arrays.

Times are integer nanoseconds since the epoch: `stamp_ns` is the sensor stamp (ROS `header.stamp`,
Foxglove `timestamp`), the time of record; `log_time_ns` is when the recorder wrote the message.
Rotations are unit quaternions in (x, y, z, w) order. Arrays are read-only. Frame ids are named as tf2
names them (`tf_frame`): without tf1's leading slash.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends.logs import rotations


def tf_frame(frame_id: str) -> str:
    """`frame_id` as tf2 names it: without a leading slash. tf1 named frames "/base_link"; tf2 drops the
    slash on every lookup, so a log whose driver stamps "laser" while its tf says "/laser" (or the other way
    round: old bags, tf1-era drivers) is one tree in ROS, and must be here."""
    return frame_id[1:] if frame_id.startswith("/") else frame_id


def _tf_named(item: Any, *fields: str) -> None:
    """Rename the frame-id `fields` of a frozen dataclass `item` as tf2 names them (`tf_frame`)."""
    for name in fields:
        frame_id = getattr(item, name)
        if frame_id.startswith("/"):
            object.__setattr__(item, name, tf_frame(frame_id))


def _frozen(array: NDArray[Any]) -> NDArray[Any]:
    array.setflags(write=False)  # half the cost of `flags.writeable = False`: it is paid per message
    return array


@dataclass(frozen=True, eq=False, slots=True)
class Scan2D:
    """One planar laser scan, valid beams only.

    `points` (N, 2) float64 are in `frame_id` (the sensor frame as recorded). float64 because 2D scans are
    small (hundreds of beams) and everything downstream (scan matching, SE(2) poses) works in float64.
    `ranges` and `bearings` (N,) are the sensor's polar measurements of the same beams (bearing 0 along the
    sensor's x axis). Beams that were non-finite or outside [range_min, range_max] are dropped;
    `beam_count` is how many beams the message had before that. `point_times` (N,) are each beam's time in
    seconds after `stamp_ns` when the message said when its beams were taken (a LaserScan's
    `time_increment`), else None: a laser sweeps its beams one after the other while the robot moves.
    """

    stamp_ns: int
    log_time_ns: int
    frame_id: str
    points: NDArray[np.float64]
    ranges: NDArray[np.float64]
    bearings: NDArray[np.float64]
    beam_count: int
    point_times: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        n = self.ranges.shape[0]
        times_shape = (n,) if self.point_times is None else self.point_times.shape
        if self.points.shape != (n, 2) or self.bearings.shape != (n,) or times_shape != (n,):
            raise ValueError(
                f"Scan2D arrays disagree: points {self.points.shape}, ranges {self.ranges.shape}, "
                f"bearings {self.bearings.shape}, point_times {times_shape}"
            )
        _tf_named(self, "frame_id")
        _frozen(self.points)
        _frozen(self.ranges)
        _frozen(self.bearings)
        if self.point_times is not None:
            _frozen(self.point_times)

    @property
    def stamp(self) -> float:
        """Sensor stamp in seconds since the epoch (for display; keep `stamp_ns` for arithmetic)."""
        return self.stamp_ns * 1e-9

    def transformed(self, transform: Transform) -> Scan2D:
        """The same scan with `points` in `transform.parent_frame` (`transform` maps the scan's frame there).

        The 3D transform is applied to (x, y, 0) and z dropped, so only a planar mounting keeps the scan
        exact. `ranges` and `bearings` stay the sensor's own measurements.
        """
        if transform.child_frame != self.frame_id:
            raise ValueError(
                f"transform is for frame {transform.child_frame!r}, scan is in {self.frame_id!r}"
            )
        xyz = np.zeros((self.points.shape[0], 3))
        xyz[:, :2] = self.points
        points = np.ascontiguousarray(transform.apply(xyz)[:, :2])
        return Scan2D(
            self.stamp_ns,
            self.log_time_ns,
            transform.parent_frame,
            points,
            self.ranges,
            self.bearings,
            self.beam_count,
            self.point_times,
        )


@dataclass(frozen=True, eq=False, slots=True)
class Cloud3D:
    """One 3D point cloud, finite points only.

    `points` (N, 3) float32 in `frame_id` (float32 like the sensors deliver them; a cloud is large).
    `point_times` (N,) float64 are seconds relative to `stamp_ns` when the cloud had a per-point time
    field, else None.
    """

    stamp_ns: int
    log_time_ns: int
    frame_id: str
    points: NDArray[np.float32]
    point_times: NDArray[np.float64] | None

    def __post_init__(self) -> None:
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"Cloud3D points must be (N, 3), got {self.points.shape}")
        if self.point_times is not None:
            if self.point_times.shape != (self.points.shape[0],):
                raise ValueError(
                    f"Cloud3D point_times {self.point_times.shape} do not match points {self.points.shape}"
                )
            _frozen(self.point_times)
        _tf_named(self, "frame_id")
        _frozen(self.points)

    @property
    def stamp(self) -> float:
        """Sensor stamp in seconds since the epoch."""
        return self.stamp_ns * 1e-9


@dataclass(frozen=True, eq=False, slots=True)
class OdometryPose:
    """The pose of `child_frame_id` (the robot base) in `frame_id` (odometry's fixed frame) at `stamp_ns`.

    From nav_msgs/Odometry, foxglove.PoseInFrame(s) (whose child_frame_id is ""), or a dynamic tf edge.
    """

    stamp_ns: int
    log_time_ns: int
    frame_id: str
    child_frame_id: str
    translation: NDArray[np.float64]
    rotation: NDArray[np.float64]

    def __post_init__(self) -> None:
        if self.translation.shape != (3,) or self.rotation.shape != (4,):
            raise ValueError("OdometryPose needs translation (3,) and rotation (4,)")
        _tf_named(self, "frame_id", "child_frame_id")
        _frozen(self.translation)
        _frozen(self.rotation)

    @property
    def yaw(self) -> float:
        """Heading about z, in (-π, π]."""
        return float(rotations.yaw(self.rotation))

    @property
    def se2(self) -> NDArray[np.float64]:
        """(x, y, yaw): the planar pose, in the optimizer's SE(2) convention."""
        return np.array([self.translation[0], self.translation[1], self.yaw])

    def matrix(self) -> NDArray[np.float64]:
        """The 4×4 homogeneous matrix mapping child coordinates into `frame_id`."""
        return _homogeneous(self.translation, self.rotation)


@dataclass(frozen=True, eq=False, slots=True)
class Transform:
    """A rigid transform mapping coordinates in `child_frame` into `parent_frame` at `stamp_ns`.

    Static transforms (from /tf_static or a static Foxglove topic) hold at every time.
    """

    parent_frame: str
    child_frame: str
    stamp_ns: int
    log_time_ns: int
    translation: NDArray[np.float64]
    rotation: NDArray[np.float64]
    is_static: bool

    def __post_init__(self) -> None:
        if self.translation.shape != (3,) or self.rotation.shape != (4,):
            raise ValueError("Transform needs translation (3,) and rotation (4,)")
        _tf_named(self, "parent_frame", "child_frame")
        _frozen(self.translation)
        _frozen(self.rotation)

    @property
    def yaw(self) -> float:
        """Heading about z, in (-π, π]."""
        return float(rotations.yaw(self.rotation))

    def matrix(self) -> NDArray[np.float64]:
        """The 4×4 homogeneous matrix mapping child coordinates into parent coordinates."""
        return _homogeneous(self.translation, self.rotation)

    def apply(self, points: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
        """Map (N, 3) points from `child_frame` into `parent_frame`."""
        return np.asarray(points, dtype=np.float64) @ rotations.to_matrix(self.rotation).T + self.translation


def _homogeneous(translation: NDArray[np.float64], rotation: NDArray[np.float64]) -> NDArray[np.float64]:
    matrix = np.eye(4)
    matrix[:3, :3] = rotations.to_matrix(rotation)
    matrix[:3, 3] = translation
    return matrix


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """One topic of a log: its name, message type (ROS 2 form such as `sensor_msgs/msg/LaserScan`, or the
    Foxglove schema name such as `foxglove.LaserScan`), message count and wire encoding."""

    name: str
    type: str
    count: int
    encoding: str


@dataclass(frozen=True, slots=True)
class LogInfo:
    """What a log holds, read from its summary or index (not from its messages).

    `container` is one of "mcap", "rosbag1", "rosbag2-sqlite3", "rosbag2-mcap". `start_ns` / `end_ns` are
    the log times of the first and last message (both inclusive; 0 and 0 for an empty log). `files` are
    the files read (several for split bags).
    """

    path: Path
    container: str
    start_ns: int
    end_ns: int
    topics: tuple[TopicInfo, ...]
    files: tuple[Path, ...]

    @property
    def duration_s(self) -> float:
        """Time span from the first to the last message, in seconds."""
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def message_count(self) -> int:
        """Messages on all topics."""
        return sum(topic.count for topic in self.topics)

    def to_json_dict(self) -> dict[str, Any]:
        """The shape `replay info --json` prints."""
        return {
            "path": str(self.path),
            "container": self.container,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "topics": [{"name": t.name, "type": t.type, "count": t.count} for t in self.topics],
        }
