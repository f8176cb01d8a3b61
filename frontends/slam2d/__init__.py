"""2D laser SLAM: scan-matching odometry, keyframes and verified loop closures into a pose graph."""

from frontends.slam2d.config import RETIRED_SETTINGS, Slam2DConfig
from frontends.slam2d.frontend import LaserFrontend, ScanInBase
from frontends.slam2d.local_map import one_per_cell, one_per_cell_each, place
from frontends.slam2d.log_input import OdometryTrack, read_odometry, scans_in_base_frame
from frontends.slam2d.occupancy import OccupancyGrid, occupancy_grid
from frontends.slam2d.slam import LaserSlam2D, ScanEstimate, Slam2DGraph

__all__ = ["RETIRED_SETTINGS", "LaserFrontend", "LaserSlam2D", "OccupancyGrid", "OdometryTrack",
           "ScanEstimate", "ScanInBase", "Slam2DConfig", "Slam2DGraph", "occupancy_grid", "one_per_cell",
           "one_per_cell_each", "place", "read_odometry", "scans_in_base_frame"]
