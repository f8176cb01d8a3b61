"""3D LiDAR SLAM: KISS-ICP odometry, keyframes and verified loop closures into a pose graph."""

from frontends.slam3d import planar
from frontends.slam3d.config import Slam3DConfig
from frontends.slam3d.frontend import LidarFrontend
from frontends.slam3d.odometry import downsample
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph

__all__ = ["CloudEstimate", "LidarFrontend", "LidarSlam3D", "Slam3DConfig", "Slam3DGraph", "downsample",
           "planar"]
