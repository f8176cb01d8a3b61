"""3D LiDAR SLAM: KISS-ICP odometry, keyframes and verified loop closures into a pose graph.

The names are imported on first use (PEP 562): `pipeline.config` reads `Slam3DConfig` in every `replay`,
and a laser replay should not pay for the frontend behind it (KISS-ICP, scipy's rotations: 0.2–0.3 s of
start-up)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from frontends.slam3d import planar
    from frontends.slam3d.config import Se3PolishConfig, Slam3DConfig
    from frontends.slam3d.frontend import LidarFrontend
    from frontends.slam3d.localization import CloudLocalizationConfig, CloudLocalizer, LocalizedCloud
    from frontends.slam3d.odometry import downsample
    from frontends.slam3d.pose_graph3d import PolishResult
    from frontends.slam3d.resume import ResumedLidarSlam3D, SavedGraph3D
    from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph
    from frontends.slam3d.vehicle import LidarMount, OdometryPrior, default_base_frame, lidar_mount

_MODULE_OF = {
    "CloudEstimate": "slam",
    "CloudLocalizationConfig": "localization",
    "CloudLocalizer": "localization",
    "LidarFrontend": "frontend",
    "LidarMount": "vehicle",
    "LidarSlam3D": "slam",
    "LocalizedCloud": "localization",
    "OdometryPrior": "vehicle",
    "PolishResult": "pose_graph3d",
    "ResumedLidarSlam3D": "resume",
    "SavedGraph3D": "resume",
    "Se3PolishConfig": "config",
    "Slam3DConfig": "config",
    "Slam3DGraph": "slam",
    "default_base_frame": "vehicle",
    "downsample": "odometry",
    "lidar_mount": "vehicle",
}
"""Each exported name → the submodule defining it (`planar` is a submodule itself)."""

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


def __getattr__(name: str) -> Any:
    if name == "planar":
        return importlib.import_module(f"{__name__}.planar")
    if name not in _MODULE_OF:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_MODULE_OF[name]}"), name)
    globals()[name] = value
    return value
