"""The `obstacles` node's sensed sources (`source: scan` or `grid`): regions fitted to what the robot sees.

    ros2 run nmpc_avoid_ros obstacles --ros-args -p source:=scan -p "laser_offset:=[0.2, 0.0, 0.0]"
    ros2 run nmpc_avoid_ros obstacles --ros-args -p source:=grid -p half_window:=4.0

`scan` (sensor_msgs/LaserScan, sensor-data QoS: best effort) with `odom` (nav_msgs/Odometry): every scan
is turned into regions at once (core/perception). `grid` (nav_msgs/OccupancyGrid on `map`, latched and
volatile publishers alike) with `odom`: the occupied cells within `half_window` of the robot, refitted
when a new grid arrives or the robot moved by more than `cluster_gap`, at most `grid_rate` times a
second (between refits the regions are sent again, so that they do not expire). A costmap's inflated cells
count as obstacles where they reach `occupied_threshold`: give the grid without its inflation layer (or
the threshold of its lethal cost), as the controller grows every region by the robot's body itself. Regions go out on
`obstacles` as one marker per tracked object (ns = `ns_prefix`, default the source's name; id = track
id; a moving one carries its velocity), a DELETE for each object no longer seen, each with `lifetime`,
so the regions of a stopped node expire.

Bad input (a scan that cannot be placed, a grid whose fields do not fit, an unknown frame, a bad
odometry) is refused with a rate-limited warning naming the reason and counted in /diagnostics; the
regions last published stay in force: a refused scan sends the static ones again unchanged, so their
lifetime does not end while the sensor sends what cannot be used (it does once the node stops; a moving
one's pose goes stale and it expires). NaN and infinite ranges are dropped and counted (REP 117: no
return).
"""

from __future__ import annotations

import math
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import LaserScan
from visualization_msgs.msg import Marker, MarkerArray

from ..core.errors import ConfigError, InputError
from ..core.perception.fitting import FitSettings
from ..core.perception.grid import Grid
from ..core.perception.scan import Pose2D
from ..core.perception.sensing import Perceived, Perception, PerceptionSettings
from ..core.perception.tracks import TrackSettings
from ..ros.conversions import stamp_to_seconds
from ..ros.parameters import LATCHED_QOS, STREAM_QOS, ParamSpec, declare, finite_vector
from ..ros.perception import (
    check_scan_frame,
    occupancy_grid,
    odometry_pose,
    perception_status,
    scan_geometry,
    scan_ranges,
    tracked_markers,
)
from ..ros.qos import LatchedSubscription

D, I, S = ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_INTEGER, ParameterType.PARAMETER_STRING
SENSED_SPECS = [
    ParamSpec("odom_frame", "odom", "the odometry's frame: the regions' frame (REP 105)", S, read_only=True),
    ParamSpec("base_frame", "base_link", "the odometry's child frame", S, read_only=True),
    ParamSpec("laser_frame", "", "scan header.frame_id required (empty: any, placed by laser_offset)", S,
              read_only=True),
    ParamSpec("laser_offset", [0.0, 0.0, 0.0], "the laser frame in base_frame: x, y (m), yaw (rad)",
              ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=True),
    ParamSpec("map_frame", "map", "a grid in this frame is taken as given in odom_frame (no localisation "
              "correction without tf2); empty: odom_frame only", S, read_only=True),
    ParamSpec("max_circles", 6, "circles published, nearest first: the controller's max_ellipses", I,
              read_only=True, int_range=(0, 1000)),
    ParamSpec("max_walls", 3, "wall segments (boxes) published, nearest first: the controller's max_polygons", I,
              read_only=True, int_range=(0, 1000)),
    ParamSpec("cluster_gap", 0.25, "returns closer than this are one object, m", D, read_only=True,
              float_range=(0.01, 10.0)),
    ParamSpec("breakpoint_angle", 10.0, "scan: neighbouring returns also link up to r sin(d) / sin(b - d) apart "
              "(b this, deg; d their angle apart; 0: cluster_gap only): a wall seen at a grazing angle stays one",
              D, read_only=True, float_range=(0.0, 80.0)),
    ParamSpec("wall_thickness", 0.12, "a cluster within this of a line is a wall segment, m", D, read_only=True,
              float_range=(0.001, 10.0)),
    ParamSpec("max_circle_diameter", 1.0, "a cluster at most this long is a circle, m", D, read_only=True,
              float_range=(0.01, 100.0)),
    ParamSpec("max_speed", 3.0, "fastest obstacle tracked, m/s (the controller's max_obstacle_speed)", D,
              read_only=True, float_range=(0.01, 100.0)),
    ParamSpec("half_window", 5.0, "grid: cells within this of the robot are looked at, m", D, read_only=True,
              float_range=(0.1, 1000.0)),
    ParamSpec("occupied_threshold", 65, "grid: a cell at least this occupied (percent) is an obstacle", I,
              read_only=True, int_range=(1, 100)),
    ParamSpec("grid_rate", 2.0, "grid: refits per second at most, Hz", D, read_only=True, float_range=(0.01, 100.0)),
    ParamSpec("max_odom_age", 0.5, "a scan further than this (s) from the last odometry is refused; within it the "
              "pose is moved to the scan's stamp with the odometry's twist", D, read_only=True,
              float_range=(0.0, 60.0)),
    ParamSpec("lifetime", 1.0, "marker lifetime, s (0: forever): a stopped node's regions expire", D,
              read_only=True, float_range=(0.0, 3600.0)),
]

#: seconds between two warnings about refused input
WARN_PERIOD = 5.0


class SensedObstacles:
    """Scan or grid + odometry -> core perception -> markers, on the `obstacles` node it is given."""

    def __init__(self, node: Node, source: str, ns: str) -> None:
        self.node, self.source, self.ns = node, source, ns
        v: dict[str, Any] = declare(node, SENSED_SPECS)
        offset = finite_vector(v["laser_offset"], 3, "laser_offset")
        try:
            settings = PerceptionSettings(
                fit=FitSettings(cluster_gap=v["cluster_gap"], wall_thickness=v["wall_thickness"],
                                max_circle_diameter=v["max_circle_diameter"],
                                breakpoint_angle=math.radians(v["breakpoint_angle"])),
                tracks=TrackSettings(max_speed=v["max_speed"]), max_circles=v["max_circles"],
                max_walls=v["max_walls"], laser_offset=Pose2D(*offset), half_window=v["half_window"],
                occupied_threshold=v["occupied_threshold"])
        except InputError as exc:
            raise ConfigError(str(exc)) from None
        self.perception = Perception(settings)
        self.odom_frame, self.base_frame, self.laser_frame = v["odom_frame"], v["base_frame"], v["laser_frame"]
        self.grid_frames = (v["odom_frame"], v["map_frame"])
        self.lifetime = float(v["lifetime"])
        self.max_odom_age = float(v["max_odom_age"])
        self.pose: Pose2D | None = None
        self.odometry: tuple[float, float, float] = (0.0, 0.0, 0.0)  # stamp (s), speed (m/s), yaw rate (rad/s)
        self.grid: Grid | None = None
        self.fitted_at: tuple[Grid, Pose2D] | None = None  # the grid and pose of the last grid fit
        self.published_ids: set[int] = set()
        self.last_good: MarkerArray | None = None
        self.counts = {"received": 0, "refused": 0, "published": 0, "not_finite_beams": 0, "out_of_range_beams": 0,
                       "regions": 0, "waiting_for_odom": 0}
        self.last_refusal = ""
        self.refused_reported = 0
        self.pub = node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
        self.diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        node.create_subscription(Odometry, "odom", self.on_odom, qos_profile_sensor_data)
        if source == "scan":
            node.create_subscription(LaserScan, "scan", self.on_scan, qos_profile_sensor_data)
        else:
            self.grid_subscription = LatchedSubscription(node, OccupancyGrid, "map", self.on_grid)
            # ticks often enough to send the regions again before their lifetime ends
            period = 1.0 / float(v["grid_rate"])
            node.create_timer(min(period, self.lifetime / 2) if self.lifetime > 0 else period, self.refit_grid)
        node.create_timer(1.0, self.publish_diagnostics)

    def on_odom(self, msg: Odometry) -> None:
        try:
            self.pose, stamp, speed, yaw_rate = odometry_pose(msg, self.odom_frame, self.base_frame)
            # an unstamped odometry (stamp 0) holds when it arrives
            self.odometry = (stamp if stamp > 0 else self.node.get_clock().now().nanoseconds * 1e-9, speed, yaw_rate)
        except InputError as exc:
            self.refuse(f"odometry: {exc}")

    def on_scan(self, msg: LaserScan) -> None:
        self.counts["received"] += 1
        if self.pose is None:
            self.counts["waiting_for_odom"] += 1
            return
        try:
            check_scan_frame(msg, self.laser_frame)
            stamp = self.stamp_of(msg)
            seen = self.perception.from_scan(scan_ranges(msg), scan_geometry(msg), self.pose_at(stamp), stamp)
        except InputError as exc:
            self.refuse(f"scan: {exc}")
            self.resend_last_good()
            return
        self.publish(seen, msg.header.stamp)

    def on_grid(self, msg: OccupancyGrid) -> None:
        self.counts["received"] += 1
        try:
            self.grid = occupancy_grid(msg, self.grid_frames)
        except InputError as exc:
            self.refuse(f"grid: {exc}")

    def refit_grid(self) -> None:
        grid, pose = self.grid, self.pose
        if grid is None or pose is None:
            return
        if self.fitted_at is not None:
            fitted_grid, fitted_pose = self.fitted_at
            moved = math.dist((pose.x, pose.y), (fitted_pose.x, fitted_pose.y))
            if fitted_grid is grid and moved <= self.perception.settings.fit.cluster_gap:
                # the same grid seen from (nearly) the same place: the regions hold; sent again before they expire
                if self.lifetime > 0 and self.perception.last is not None:
                    self.publish(self.perception.last, self.node.get_clock().now().to_msg(), count_beams=False)
                return
        now = self.node.get_clock().now()
        self.publish(self.perception.from_grid(grid, pose, now.nanoseconds * 1e-9), now.to_msg())
        self.fitted_at = (grid, pose)

    def pose_at(self, stamp: float) -> Pose2D:
        """The robot's pose at `stamp` (s): the last odometry's moved by its twist; InputError if too far apart."""
        odom_stamp, speed, yaw_rate = self.odometry
        dt = stamp - odom_stamp
        if abs(dt) > self.max_odom_age:
            raise InputError(f"the scan is {dt:+.3f} s from the last odometry, more than max_odom_age "
                             f"{self.max_odom_age:g} s: the robot's pose then is not known")
        return self.pose.moved(speed, yaw_rate, dt)

    def stamp_of(self, msg: LaserScan) -> float:
        """The scan's stamp (s); a zero stamp (a driver that sets none): the node clock's now."""
        stamp = stamp_to_seconds(msg.header.stamp)
        return stamp if stamp > 0 else self.node.get_clock().now().nanoseconds * 1e-9

    def publish(self, seen: Perceived, stamp: object, count_beams: bool = True) -> None:
        ids = {track_id for track_id, _ in seen.regions}
        markers = tracked_markers(seen.regions, sorted(self.published_ids - ids), self.ns, stamp, self.odom_frame,
                                  self.lifetime)
        self.pub.publish(markers)
        # what a refused scan sends again: the static regions (a moving one's pose goes stale; it expires)
        static = {track_id for track_id, region in seen.regions if not region.moving}
        self.last_good = MarkerArray(markers=[m for m in markers.markers if m.action != Marker.DELETE
                                              and m.id in static])
        self.published_ids = ids
        self.counts["published"] += 1
        self.counts["regions"] = len(ids)
        if count_beams:
            self.counts["not_finite_beams"] += seen.not_finite
            self.counts["out_of_range_beams"] += seen.out_of_range

    def resend_last_good(self) -> None:
        """The static regions last published, sent again unchanged (their stamps too): their lifetime restarts
        while the sensor sends what cannot be used, and still ends once this node stops. Moving ones are not
        (their pose goes stale; the controller would refuse them past max_obstacle_stamp_skew): they expire."""
        if self.last_good is not None and self.last_good.markers:
            self.pub.publish(self.last_good)

    def refuse(self, reason: str) -> None:
        self.counts["refused"] += 1
        self.last_refusal = reason
        self.node.get_logger().warning(f"refused: {reason}; the last good regions stay",
                                       throttle_duration_sec=WARN_PERIOD)

    def publish_diagnostics(self) -> None:
        new = self.counts["refused"] - self.refused_reported
        self.refused_reported = self.counts["refused"]
        self.diagnostics.publish(perception_status(self.node.get_fully_qualified_name(), self.source, self.counts,
                                                   self.last_refusal, self.node.get_clock().now().to_msg(), new))
