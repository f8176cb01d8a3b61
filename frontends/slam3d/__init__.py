"""3D LiDAR SLAM: KISS-ICP odometry, keyframes and verified loop closures into a pose graph.

The names are imported on first use (`lazy_loader`, SPEC 1): `pipeline.config` reads `Slam3DConfig` in
every `replay`, and a laser replay should not pay for the frontend behind it (KISS-ICP, scipy's rotations:
0.2–0.3 s of start-up)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import lazy_loader

if TYPE_CHECKING:
    from frontends.slam3d import planar as planar
    from frontends.slam3d.config import Se3PolishConfig as Se3PolishConfig
    from frontends.slam3d.config import Slam3DConfig as Slam3DConfig
    from frontends.slam3d.frontend import LidarFrontend as LidarFrontend
    from frontends.slam3d.localization import CloudLocalizationConfig as CloudLocalizationConfig
    from frontends.slam3d.localization import CloudLocalizer as CloudLocalizer
    from frontends.slam3d.localization import LocalizedCloud as LocalizedCloud
    from frontends.slam3d.odometry import downsample as downsample
    from frontends.slam3d.pose_graph3d import PolishResult as PolishResult
    from frontends.slam3d.resume import ResumedLidarSlam3D as ResumedLidarSlam3D
    from frontends.slam3d.resume import SavedGraph3D as SavedGraph3D
    from frontends.slam3d.slam import CloudEstimate as CloudEstimate
    from frontends.slam3d.slam import LidarSlam3D as LidarSlam3D
    from frontends.slam3d.slam import Slam3DGraph as Slam3DGraph
    from frontends.slam3d.vehicle import LidarMount as LidarMount
    from frontends.slam3d.vehicle import OdometryPrior as OdometryPrior
    from frontends.slam3d.vehicle import lidar_mount as lidar_mount

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submodules=["planar"], submod_attrs={
    "config": ["Se3PolishConfig", "Slam3DConfig"],
    "frontend": ["LidarFrontend"],
    "localization": ["CloudLocalizationConfig", "CloudLocalizer", "LocalizedCloud"],
    "odometry": ["downsample"],
    "pose_graph3d": ["PolishResult"],
    "resume": ["ResumedLidarSlam3D", "SavedGraph3D"],
    "slam": ["CloudEstimate", "LidarSlam3D", "Slam3DGraph"],
    "vehicle": ["LidarMount", "OdometryPrior", "lidar_mount"],
})
