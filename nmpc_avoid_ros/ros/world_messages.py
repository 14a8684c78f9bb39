"""The simulated world's messages: a map as nav_msgs/OccupancyGrid and a lidar's ranges as sensor_msgs/LaserScan
(core/loop/world.py computes them)."""

from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose
from nav_msgs.msg import MapMetaData, OccupancyGrid
from sensor_msgs.msg import LaserScan

from ..core.perception.grid import Grid


def occupancy_grid_message(grid: Grid, stamp: Time, frame: str) -> OccupancyGrid:
    """The grid (cells [rows, cols], row 0 at the bottom) as an OccupancyGrid in `frame`."""
    height, width = grid.cells.shape
    origin = Pose()
    origin.position.x, origin.position.y = float(grid.origin.x), float(grid.origin.y)
    origin.orientation.z, origin.orientation.w = math.sin(grid.origin.yaw / 2), math.cos(grid.origin.yaw / 2)
    msg = OccupancyGrid()
    msg.header.stamp, msg.header.frame_id = stamp, frame
    msg.info = MapMetaData(map_load_time=stamp, resolution=float(grid.resolution), width=width, height=height,
                           origin=origin)
    msg.data = grid.cells.astype(np.int8).ravel().tolist()
    return msg


def laser_scan_message(ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float,
                       range_max: float, scan_time: float, stamp: Time, frame: str) -> LaserScan:
    """Ranges [B] (m, +inf: no return) of beams from angle_min by angle_increment (rad) as a LaserScan."""
    msg = LaserScan()
    msg.header.stamp, msg.header.frame_id = stamp, frame
    msg.angle_min = float(angle_min)
    msg.angle_increment = float(angle_increment)
    msg.angle_max = float(angle_min + angle_increment * (len(ranges) - 1))
    msg.time_increment, msg.scan_time = 0.0, float(scan_time)
    msg.range_min, msg.range_max = float(range_min), float(range_max)
    msg.ranges = np.asarray(ranges, np.float32).tolist()
    return msg
