"""Reading robot logs: MCAP, ROS 1 bags and ROS 2 bags into typed, time-ordered streams.

`open_log(path)` picks the container from the path and its contents and returns a `LogReader`; its
`info()` reads the summary / index, and its iterators (`scans`, `clouds`, `odometry`, `transforms`,
`messages`) stream `Scan2D`, `Cloud3D`, `OdometryPose` and `Transform` in sensor-time order.
`TransformTree` answers tf lookups over the log's transforms.

Layers, bottom up: `containers/` find and unpack messages, `decoding/` turns payload bytes into fields,
`converters` turns fields into our types, `dispatch` picks the converter for a schema, `ordering` merges
streams by sensor time, `guard` bounds what one message may claim.
"""

from frontends.logs.log import ODOMETRY_FRAME, LogReader, open_log
from frontends.logs.transforms import TransformTree
from frontends.logs.types import Cloud3D, LogInfo, OdometryPose, Scan2D, TopicInfo, Transform, tf_frame

__all__ = ["ODOMETRY_FRAME", "Cloud3D", "LogInfo", "LogReader", "OdometryPose", "Scan2D", "TopicInfo",
           "Transform", "TransformTree", "open_log", "tf_frame"]
