"""3D LiDAR SLAM: KISS-ICP odometry, keyframes and verified loop closures into a pose graph."""

from frontends.slam3d import planar
from frontends.slam3d.config import Se3PolishConfig, Slam3DConfig
from frontends.slam3d.frontend import LidarFrontend
from frontends.slam3d.localization import CloudLocalizationConfig, CloudLocalizer, LocalizedCloud
from frontends.slam3d.odometry import downsample
from frontends.slam3d.pose_graph3d import PolishResult
from frontends.slam3d.resume import ResumedLidarSlam3D, SavedGraph3D
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph
from frontends.slam3d.vehicle import LidarMount, OdometryPrior, default_base_frame, lidar_mount

__all__ = [
    "CloudEstimate",
    "CloudLocalizationConfig",
    "CloudLocalizer",
    "LidarFrontend",
    "LidarMount",
    "LidarSlam3D",
    "LocalizedCloud",
    "OdometryPrior",
    "PolishResult",
    "ResumedLidarSlam3D",
    "SavedGraph3D",
    "Se3PolishConfig",
    "Slam3DConfig",
    "Slam3DGraph",
    "default_base_frame",
    "downsample",
    "lidar_mount",
    "planar",
]
