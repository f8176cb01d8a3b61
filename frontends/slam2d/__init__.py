"""2D laser SLAM: scan-matching odometry, keyframes and verified loop closures into a pose graph.

The names are imported on first use (`lazy_loader`, SPEC 1): `pipeline.config` reads `Slam2DConfig` in
every `replay`, and a replay of point clouds should not pay for the laser frontend behind it (its compiled
kernels, 0.3 s of start-up)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import lazy_loader

if TYPE_CHECKING:
    from frontends.slam2d.config import RETIRED_SETTINGS as RETIRED_SETTINGS
    from frontends.slam2d.config import Slam2DConfig as Slam2DConfig
    from frontends.slam2d.frontend import LaserFrontend as LaserFrontend
    from frontends.slam2d.frontend import ScanInBase as ScanInBase
    from frontends.slam2d.local_map import one_per_cell as one_per_cell
    from frontends.slam2d.local_map import one_per_cell_each as one_per_cell_each
    from frontends.slam2d.local_map import place as place
    from frontends.slam2d.log_input import OdometryTrack as OdometryTrack
    from frontends.slam2d.log_input import read_odometry as read_odometry
    from frontends.slam2d.log_input import scans_in_base_frame as scans_in_base_frame
    from frontends.slam2d.occupancy import OccupancyGrid as OccupancyGrid
    from frontends.slam2d.occupancy import occupancy_grid as occupancy_grid
    from frontends.slam2d.slam import LaserSlam2D as LaserSlam2D
    from frontends.slam2d.slam import ScanEstimate as ScanEstimate
    from frontends.slam2d.slam import Slam2DGraph as Slam2DGraph

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "config": ["RETIRED_SETTINGS", "Slam2DConfig"],
    "frontend": ["LaserFrontend", "ScanInBase"],
    "local_map": ["one_per_cell", "one_per_cell_each", "place"],
    "log_input": ["OdometryTrack", "read_odometry", "scans_in_base_frame"],
    "occupancy": ["OccupancyGrid", "occupancy_grid"],
    "slam": ["LaserSlam2D", "ScanEstimate", "Slam2DGraph"],
})
