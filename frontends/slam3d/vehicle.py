"""Where the LiDAR sits on the vehicle (tf) and what the vehicle's own odometry says about its motion.

- `lidar_mount` finds the base frame the poses are of and the sensor's pose in it. By default the base is
  the frame that moves (`frontends.protocol.default_base_frame`, the laser logs' rule too).
- `OdometryPrior` holds the log's wheel / INS odometry (`frontends.logs.OdometryPose` stream) and
  interpolates the base's pose at a cloud's stamp; `LidarSlam3D.add_cloud(cloud, odometry_pose=...)` turns
  two of them into KISS-ICP's motion guess.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.errors import FrontendError
from frontends.logs import OdometryPose, TransformTree, rotations
from frontends.protocol import default_base_frame
from frontends.slam3d import se3

FloatArray = NDArray[np.float64]

DEFAULT_MAX_ODOMETRY_GAP_NS = 500_000_000
"""The prior is not interpolated across a gap in the odometry longer than this (0.5 s)."""


@dataclass(frozen=True, eq=False)
class LidarMount:
    """The frame the SLAM's poses are of, and the sensor's pose in it."""

    base_frame: str
    sensor_frame: str
    sensor_to_base: FloatArray
    """4×4: maps points from the sensor frame into the base frame (identity when they are one frame)."""
    from_tf: bool
    """False when tf does not know the sensor frame: the base is the sensor."""


def lidar_mount(
    tree: TransformTree, sensor_frame: str, stamp_ns: int, base_frame: str | None = None
) -> LidarMount | None:
    """The sensor's mount on the base at `stamp_ns` (the first cloud's), the base being `base_frame` or
    else `default_base_frame`. None when `base_frame` is given and tf does not link it to the sensor
    frame (the default base is always linked: it is found along the sensor's tf chain)."""
    chosen = base_frame if base_frame is not None else default_base_frame(tree, sensor_frame)
    if chosen == sensor_frame:
        return LidarMount(chosen, sensor_frame, np.eye(4), sensor_frame in tree.frames)
    mount = tree.sensor_mount(chosen, sensor_frame, stamp_ns)
    return None if mount is None else LidarMount(chosen, sensor_frame, mount.matrix(), True)


class OdometryPrior:
    """The base's odometry poses (in the odometry's fixed frame) over time, interpolated at any stamp."""

    def __init__(
        self,
        stamps_ns: ArrayLike,
        translations: ArrayLike,
        quaternions: ArrayLike,
        *,
        max_gap_ns: int = DEFAULT_MAX_ODOMETRY_GAP_NS,
        child_frame: str = "",
    ) -> None:
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        self.stamps_ns = stamps[order]
        self.translations = np.asarray(translations, dtype=np.float64).reshape(-1, 3)[order]
        quaternions = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
        self.quaternions = rotations.normalize(quaternions[order])
        if not (len(self.stamps_ns) == len(self.translations) == len(self.quaternions)):
            raise FrontendError("odometry stamps, translations and rotations differ in number")
        self.max_gap_ns = max_gap_ns
        self.child_frame = child_frame
        """The frame whose poses these are (the odometry's child frame)."""
        self.base_in_child = np.eye(4)
        """4×4 pose of the SLAM's base frame in `child_frame` (`rebase`): `at` returns the base's pose."""

    def rebase(self, base_in_child: ArrayLike) -> OdometryPrior:
        """The same odometry as poses of another frame rigidly attached to the child frame, e.g. the
        LiDAR mount's base frame when the odometry is of `base_footprint`: `base_in_child` is that
        frame's pose in the child frame (tf's child → base lookup)."""
        rebased = OdometryPrior(
            self.stamps_ns,
            self.translations,
            self.quaternions,
            max_gap_ns=self.max_gap_ns,
            child_frame=self.child_frame,
        )
        rebased.base_in_child = np.asarray(base_in_child, dtype=np.float64)
        return rebased

    @classmethod
    def from_poses(
        cls, poses: Iterable[OdometryPose], *, max_gap_ns: int = DEFAULT_MAX_ODOMETRY_GAP_NS
    ) -> OdometryPrior | None:
        """From a log's odometry stream (`LogReader.odometry(topic)`); None when it is empty. Non-finite
        poses are left out."""
        items = [p for p in poses if np.all(np.isfinite(p.translation)) and np.all(np.isfinite(p.rotation))]
        if not items:
            return None
        return cls(
            [p.stamp_ns for p in items],
            [p.translation for p in items],
            [p.rotation for p in items],
            max_gap_ns=max_gap_ns,
            child_frame=items[0].child_frame_id,
        )

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def at(self, stamp_ns: int) -> FloatArray | None:
        """4×4 pose of the base at `stamp_ns`, interpolated between the two odometry poses around it
        (linear in translation, slerp in rotation); None outside the odometry's time span or inside a
        gap longer than `max_gap_ns`."""
        stamps = self.stamps_ns
        high = int(np.searchsorted(stamps, stamp_ns, side="left"))
        if high < len(stamps) and stamps[high] == stamp_ns:
            pose = se3.from_rotation_translation(
                rotations.to_matrix(self.quaternions[high]), self.translations[high]
            )
            return pose @ self.base_in_child
        if high == 0 or high == len(stamps):
            return None
        low = high - 1
        span = int(stamps[high] - stamps[low])
        if span > self.max_gap_ns:
            return None
        fraction = (stamp_ns - int(stamps[low])) / span
        translation = (1.0 - fraction) * self.translations[low] + fraction * self.translations[high]
        rotation = rotations.slerp(self.quaternions[low], self.quaternions[high], fraction)
        pose = se3.from_rotation_translation(rotations.to_matrix(rotation), translation)
        return pose @ self.base_in_child
