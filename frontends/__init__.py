"""Frontends: read laser and LiDAR logs (MCAP, ROS 1 bags, ROS 2 bags) into typed, time-ordered streams.

`open_log(path)` picks the container from the path and its contents and returns a `LogReader`; its
`info()` reads the summary / index, and its iterators (`scans`, `clouds`, `odometry`, `transforms`,
`messages`) stream `Scan2D`, `Cloud3D`, `OdometryPose` and `Transform` in sensor-time order.
"""

from frontends.errors import (
    FrontendError,
    LogFileError,
    LogWarning,
    TopicSelectionError,
    TransformLookupError,
)
from frontends.log import LogReader, open_log
from frontends.transforms import TransformTree
from frontends.types import Cloud3D, LogInfo, OdometryPose, Scan2D, TopicInfo, Transform

__all__ = [
    "Cloud3D",
    "FrontendError",
    "LogFileError",
    "LogInfo",
    "LogReader",
    "LogWarning",
    "OdometryPose",
    "Scan2D",
    "TopicInfo",
    "TopicSelectionError",
    "Transform",
    "TransformLookupError",
    "TransformTree",
    "open_log",
]
