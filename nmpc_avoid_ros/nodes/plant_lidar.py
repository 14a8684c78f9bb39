"""The plant's world (`world`: a map_server YAML) and its simulated 2D lidar, for a planar robot.

    ros2 run nmpc_avoid_ros plant --ros-args --params-file config/unicycle.yaml \
        -p world:=config/worlds/room.yaml -p walkers:=config/worlds/room_walkers.yaml

The map goes out once on `map` (nav_msgs/OccupancyGrid, latched, in `odom_frame`: a simulated robot's
odometry does not drift, so map and odom coincide); the lidar, at the robot's base (`base_frame`), casts
`lidar_beams` beams over `lidar_fov` at `lidar_rate` Hz against the map and the walkers (a scene file's
obstacles, core/loop/scene.py, moving on the scene's clock from the plant's first command: an ellipse seen
as the circle of its longer semi-axis, a polygon as its edges) and publishes `scan`
(sensor_msgs/LaserScan, sensor-data QoS). The casting is core/loop/world.py's.
"""

from __future__ import annotations

import math
import time

import numpy as np
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import ParameterType
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import LaserScan

from ..core.errors import ConfigError
from ..core.loop.scene import load_scene
from ..core.loop.world import find_world, load_world
from ..core.perception.scan import Pose2D
from ..core.problem.shapes import Ellipse
from ..ros.parameters import LATCHED_QOS, ParamSpec
from ..ros.world_messages import laser_scan_message, occupancy_grid_message

LIDAR_SPECS = [
    ParamSpec("world", "", "a map_server YAML (docs/usage.md, 'A world to drive in'): published on `map`, and the "
              "lidar's walls; '' for none", ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("walkers", "", "a scene YAML whose obstacles the lidar sees moving (scene time 0: the first command); "
              "'' for none", ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("lidar_rate", 10.0, "scans per second, Hz (0: no lidar)", ParameterType.PARAMETER_DOUBLE,
              read_only=True, float_range=(0.0, 100.0)),
    ParamSpec("lidar_beams", 360, "beams per scan", ParameterType.PARAMETER_INTEGER, read_only=True,
              int_range=(1, 10000)),
    ParamSpec("lidar_fov", 2 * math.pi, "field of view, rad, centred ahead", ParameterType.PARAMETER_DOUBLE,
              read_only=True, float_range=(0.01, 2 * math.pi)),
    ParamSpec("lidar_range_max", 8.0, "longest range, m (beyond: +inf, no return)", ParameterType.PARAMETER_DOUBLE,
              read_only=True, float_range=(0.1, 100.0)),
    ParamSpec("lidar_range_min", 0.05, "shortest range, m (above 0: a scan's range_min <= 0 is refused by the "
              "obstacles node, as by REP 117 readers)", ParameterType.PARAMETER_DOUBLE, read_only=True,
              float_range=(0.001, 10.0)),
]


class SimulatedLidar:
    """The world and lidar of a plant node (`node`: its pose_and_velocity, holding, odom/base frames, stamp)."""

    def __init__(self, node, values: dict) -> None:
        self.node = node
        if node.planar is None:
            raise ConfigError(f"world: the model {node.model.name!r} is not a planar robot (no x, y, yaw to place "
                              "a lidar)")
        self.world = load_world(values["world"])
        self.walkers = load_scene(find_world(values["walkers"])) if values["walkers"] else None
        beams, fov = int(values["lidar_beams"]), float(values["lidar_fov"])
        self.angle_min = -fov / 2
        self.angle_increment = fov / beams if fov >= 2 * math.pi - 1e-9 else fov / max(beams - 1, 1)
        self.angles = self.angle_min + self.angle_increment * np.arange(beams)
        self.range_min, self.range_max = float(values["lidar_range_min"]), float(values["lidar_range_max"])
        if self.range_min >= self.range_max:
            raise ConfigError(f"lidar_range_min {self.range_min:g} must be below lidar_range_max {self.range_max:g}")
        self.scan_time = 1.0 / float(values["lidar_rate"]) if values["lidar_rate"] > 0 else 0.0
        self.started: float | None = None  # monotonic s of the first command: the walkers' scene time 0
        self.scans = 0
        self.pub_map = node.create_publisher(OccupancyGrid, "map", LATCHED_QOS)
        self.pub_map.publish(occupancy_grid_message(self.world.grid, node.stamp(), node.odom_frame))
        self.pub_scan = None
        if self.scan_time > 0:
            self.pub_scan = node.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
            node.create_timer(self.scan_time, self.publish_scan)

    def circles_and_segments(self) -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float, float]]]:
        """The walkers where they are now: circles (cx, cy, r) and polygon edges (x0, y0, x1, y1), m."""
        if self.walkers is None:
            return [], []
        if self.started is None and not self.node.holding:
            self.started = time.monotonic()
        scene_time = 0.0 if self.started is None else time.monotonic() - self.started
        circles, segments = [], []
        for region in self.walkers.regions_at(scene_time):
            if isinstance(region, Ellipse):
                circles.append((*region.center, max(region.semi_axes)))
            else:
                corners = list(region.vertices)
                segments += [(*a, *b) for a, b in zip(corners, corners[1:] + corners[:1])]
        return circles, segments

    def scan(self) -> np.ndarray:
        """Ranges [B] (m) from the robot's pose now."""
        pose, _ = self.node.pose_and_velocity()
        circles, segments = self.circles_and_segments()
        sensor = Pose2D(*pose)
        return self.world.scan(sensor, self.angles, self.range_max, self.range_min, circles, segments)

    def publish_scan(self) -> None:
        msg = laser_scan_message(self.scan(), self.angle_min, self.angle_increment, self.range_min, self.range_max,
                                 self.scan_time, self.node.stamp(), self.node.base_frame)
        self.pub_scan.publish(msg)
        self.scans += 1
