"""sensor_msgs/LaserScan, nav_msgs/OccupancyGrid and nav_msgs/Odometry -> core perception inputs, and tracked
regions -> the markers on `obstacles` (core/perception).

Frames (REP 105, no tf2): the odometry gives base_link in odom; the scan's frame is the laser, placed at
the node's `laser_offset` from base_link (its header.frame_id is checked only when `laser_frame` is set);
a grid must be in odom or in the map frame the node is told coincides with it. Markers go out in odom
(the controller's robot interface maps odom to its `output` plane).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import OccupancyGrid, Odometry
from sensor_msgs.msg import LaserScan
from visualization_msgs.msg import MarkerArray

from ..core.errors import InputError
from ..core.perception.grid import Grid
from ..core.perception.scan import Pose2D, ScanGeometry
from ..core.problem.shapes import Ellipse, Polygon
from .conversions import stamp_to_seconds
from .markers import delete_marker, region_marker, velocity_text
from .robot import odometry_to_state, yaw_of

#: markers of fitted regions: the same fill as the scene's, a wall segment's outline a little thicker
WALL_LINE_WIDTH = 0.04


def scan_geometry(msg: LaserScan) -> ScanGeometry:
    """The fields of a scan that place its beams (checked against its ranges by core: ScanGeometry.check)."""
    return ScanGeometry(float(msg.angle_min), float(msg.angle_max), float(msg.angle_increment),
                        float(msg.range_min), float(msg.range_max))


def scan_ranges(msg: LaserScan) -> np.ndarray:
    """The ranges (m) as float64 [B], without a per-beam Python loop (rclpy holds them as array('f'))."""
    ranges = msg.ranges
    try:
        return np.frombuffer(ranges, dtype=np.float32).astype(float)
    except (TypeError, ValueError):
        return np.asarray(ranges, dtype=float).ravel()


def check_scan_frame(msg: LaserScan, laser_frame: str) -> None:
    """InputError unless the scan is in `laser_frame` (empty: any frame, placed by the laser offset)."""
    if laser_frame and msg.header.frame_id != laser_frame:
        raise InputError(f"scan header.frame_id is {msg.header.frame_id!r}, expected {laser_frame!r} (no tf lookup "
                         f"here: the laser is placed by laser_offset from the base frame)")


def odometry_pose(msg: Odometry, odom_frame: str, base_frame: str) -> tuple[Pose2D, float, float, float]:
    """(base_link in odom, stamp (s), forward speed (m/s), yaw rate (rad/s)) of an Odometry; InputError with the
    reason (wrong frames, NaN, a zero quaternion)."""
    x, y, yaw = odometry_to_state(msg, odom_frame, base_frame)
    twist = msg.twist.twist
    speed, yaw_rate = float(twist.linear.x), float(twist.angular.z)
    if not (math.isfinite(speed) and math.isfinite(yaw_rate)):
        raise InputError(f"odometry twist must be finite, got linear.x {speed}, angular.z {yaw_rate}")
    return Pose2D(float(x), float(y), float(yaw)), stamp_to_seconds(msg.header.stamp), speed, yaw_rate


def occupancy_grid(msg: OccupancyGrid, frames: Iterable[str]) -> Grid:
    """The checked grid of an OccupancyGrid in one of `frames`; InputError with the reason."""
    allowed = tuple(f for f in frames if f)
    if msg.header.frame_id not in allowed:
        raise InputError(f"grid header.frame_id is {msg.header.frame_id!r}, expected one of {allowed} (no tf "
                         f"lookup here)")
    info = msg.info
    origin = info.origin
    position = (float(origin.position.x), float(origin.position.y))
    if not all(np.isfinite(position)):
        raise InputError(f"grid origin must be finite, got {position}")
    pose = Pose2D(*position, yaw_of(origin.orientation))
    data = msg.data
    try:
        cells = np.frombuffer(data, dtype=np.int8)
    except (TypeError, ValueError):
        cells = np.asarray(data, dtype=np.int8)
    return Grid.from_fields(cells, int(info.width), int(info.height), float(info.resolution), pose)


def tracked_markers(regions: Sequence[tuple[int, Ellipse | Polygon]], gone: Iterable[int], ns: str, stamp: Time,
                    frame_id: str, lifetime: float) -> MarkerArray:
    """Tracked regions -> a DELETE for each track id in `gone`, then one ADD marker each (ns, id = track id);
    header.frame_id `frame_id` (the regions' plane: odom). The DELETEs first: the controller applies the markers
    in order, and a new track's ADD before the DELETE of the one it replaces found its slots full ("capacity of
    4 ellipses reached": 5-6 refusals a run in the room world). Every marker carries its velocity in `text`, a
    static one `velocity=0.0,0.0`: the tracker has decided, and the controller must not estimate a motion of its
    own from the poses (the seen part of a wall slides along it as the robot moves)."""
    markers = [delete_marker(ns, track_id) for track_id in gone]
    for track_id, region in regions:
        marker = region_marker(region, track_id, ns, stamp, lifetime)
        marker.header.frame_id = frame_id
        marker.text = velocity_text(region.velocity)
        if isinstance(region, Polygon):
            marker.scale.x = WALL_LINE_WIDTH
        markers.append(marker)
    return MarkerArray(markers=markers)


def perception_status(hardware_id: str, source: str, counts: dict[str, int], last_refusal: str, stamp: Time,
                      new_refusals: int) -> DiagnosticArray:
    """The obstacles node's counts as one DiagnosticStatus (name `obstacles: <source>`): WARN while input was
    refused since the last report, with the last reason in `last_refusal`."""
    level = DiagnosticStatus.WARN if new_refusals else DiagnosticStatus.OK
    message = f"{new_refusals} input(s) refused: {last_refusal}" if new_refusals else "ok"
    values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
    values.append(KeyValue(key="last_refusal", value=last_refusal))
    status = DiagnosticStatus(level=level, name=f"obstacles: {source}", message=message, hardware_id=hardware_id,
                              values=values)
    array = DiagnosticArray(status=[status])
    array.header.stamp = stamp
    return array
