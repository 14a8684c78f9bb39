"""The `obstacles` node's sensed sources through real DDS: a probe publishes odometry and a LaserScan (best
effort, as a lidar driver does) or an OccupancyGrid (latched, as map_server does); the fitted regions arrive
as markers on `obstacles` (ns `scan` / `grid`, one id per tracked object, in odom); a scan that cannot be
placed is refused with a reason in /diagnostics and the regions published before stay."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.qos import qos_profile_sensor_data
from rosgraph import ROOT
from sensor_msgs.msg import LaserScan
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.core.perception.raycast import cast, room
from nmpc_avoid_ros.core.perception.scan import Pose2D
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS
from nmpc_avoid_ros.ros.robot import state_to_odometry

pytestmark = pytest.mark.dds

BEAMS = 360
INCREMENT = 2 * math.pi / BEAMS
ROBOT = Pose2D(-1.0, -0.5, 0.3)
CIRCLE = (1.5, 0.8, 0.3)


def scan_message(node, increment: float = INCREMENT) -> LaserScan:
    msg = LaserScan()
    msg.header.stamp = node.get_clock().now().to_msg()
    msg.header.frame_id = "base_scan"
    msg.angle_min, msg.angle_increment = -math.pi, increment
    msg.angle_max = -math.pi + INCREMENT * (BEAMS - 1)
    msg.range_min, msg.range_max = 0.1, 20.0
    ranges = cast(ROBOT, -math.pi + INCREMENT * np.arange(BEAMS), room(4.0, 3.0), [CIRCLE], 20.0)
    msg.ranges = np.where(np.isfinite(ranges), ranges, np.inf).astype(np.float32).tolist()
    return msg


def grid_message(node) -> OccupancyGrid:
    """A 10 m x 8 m grid at 5 cm in map, origin (-5, -4): one wall along y = 2 from x = -3 to 1, a 0.4 m pillar."""
    msg = OccupancyGrid()
    msg.header.stamp = node.get_clock().now().to_msg()
    msg.header.frame_id = "map"
    msg.info.resolution, msg.info.width, msg.info.height = 0.05, 200, 160
    msg.info.origin.position.x, msg.info.origin.position.y = -5.0, -4.0
    msg.info.origin.orientation.w = 1.0
    cells = np.zeros((160, 200), dtype=np.int8)
    cells[120:122, 40:120] = 100  # y in [2.0, 2.1), x in [-3, 1)
    cells[76:84, 126:134] = 100  # x in [1.3, 1.7), y in [-0.2, 0.2)
    cells[0:10, :] = -1  # unknown: not an obstacle
    msg.data = cells.ravel().tolist()
    return msg


@pytest.mark.slow  # 5-7 s: two nodes started, a diagnostics period or two waited for
def test_scan_and_grid_regions_arrive_as_markers_and_a_bad_scan_is_refused_with_a_reason(ros_graph):
    _, _, start, probe_factory = ros_graph
    scan_node = start("obstacles", "--ros-args", "-p", "source:=scan", "-p", "max_walls:=10")
    grid_node = start("obstacles", "--ros-args", "-r", "__node:=grid_obstacles", "-p", "source:=grid",
                      "-p", "half_window:=4.0", "-p", "lifetime:=0.0")
    probe = probe_factory()
    node = probe.node
    markers: dict[tuple[str, int], Marker] = {}
    statuses: list[dict[str, str]] = []

    arrays: list[MarkerArray] = []

    def on_markers(msg: MarkerArray) -> None:
        arrays.append(msg)
        for m in msg.markers:
            if m.action == Marker.DELETE:
                markers.pop((m.ns, m.id), None)
            else:
                markers[(m.ns, m.id)] = m

    node.create_subscription(MarkerArray, "obstacles", on_markers, LATCHED_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: statuses.extend(
        {"level": int.from_bytes(s.level, "little") if isinstance(s.level, bytes) else int(s.level),
         **{kv.key: kv.value for kv in s.values}} for s in m.status if s.name == "obstacles: scan"), STREAM_QOS)
    odom = node.create_publisher(Odometry, "odom", STREAM_QOS)
    scans = node.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
    grids = node.create_publisher(OccupancyGrid, "map", LATCHED_QOS)
    grids.publish(grid_message(node))
    assert probe.spin_until(lambda: scans.get_subscription_count() >= 1 and odom.get_subscription_count() >= 2,
                            60.0), scan_node.output()[-3000:] + grid_node.output()[-3000:]

    def feed(seconds: float, until=lambda: False, **scan_changes: float) -> None:
        end = node.get_clock().now().nanoseconds * 1e-9 + seconds
        while node.get_clock().now().nanoseconds * 1e-9 < end and not until():
            odom.publish(state_to_odometry([ROBOT.x, ROBOT.y, ROBOT.yaw], [0.0, 0.0], node.get_clock().now().to_msg(),
                                           "odom", "base_link"))
            scans.publish(scan_message(node, **scan_changes))
            probe.spin_for(0.1)

    def of(ns: str) -> list[Marker]:
        return [m for (n, _), m in markers.items() if n == ns]

    feed(20.0, until=lambda: len(of("scan")) >= 5 and len(of("grid")) == 2)
    circles = [m for m in of("scan") if m.type == Marker.CYLINDER]
    nearest = min(circles, key=lambda m: math.dist((m.pose.position.x, m.pose.position.y), CIRCLE[:2]))
    assert math.dist((nearest.pose.position.x, nearest.pose.position.y), CIRCLE[:2]) < 0.02
    assert nearest.scale.x == pytest.approx(0.6, abs=0.03) and nearest.header.frame_id == "odom"
    assert sum(m.type == Marker.LINE_STRIP for m in of("scan")) >= 4  # the four walls
    # the tracker's verdict travels: static regions say so, the controller estimates nothing of its own
    assert all(m.text == "velocity=0.0,0.0" for m in of("scan") + of("grid"))
    # the grid: a thin box along the wall y = 2 and a circle around the pillar at (1.5, 0)
    (wall,) = [m for m in of("grid") if m.type == Marker.LINE_STRIP]
    ys = [p.y for p in wall.points]
    assert min(ys) == pytest.approx(2.0, abs=0.05) and max(ys) < 2.25
    (pillar,) = [m for m in of("grid") if m.type == Marker.CYLINDER]
    assert math.dist((pillar.pose.position.x, pillar.pose.position.y), (1.5, 0.0)) < 0.05
    # a scan with a zero angle increment: refused with its reason, counted; the regions stay
    before = {k: (m.pose.position.x, m.pose.position.y) for k, m in markers.items() if k[0] == "scan"}
    feed(5.0, until=lambda: any(int(s.get("refused", 0)) > 0 for s in statuses), increment=0.0)
    # each refused scan sends the last good (static) regions again, unchanged: their lifetime does not run out
    arrays_before = len(arrays)
    feed(0.5, increment=0.0)
    resent = [m for a in arrays[arrays_before:] for m in a.markers if m.ns == "scan"]
    assert resent and all(m.action == Marker.ADD and (m.ns, m.id) in before for m in resent)
    refused = [s for s in statuses if int(s["refused"]) > 0]
    assert "angle_increment must be non-zero" in refused[-1]["last_refusal"]
    assert any(s["level"] == 1 for s in refused)  # WARN while refusing
    assert {k: (m.pose.position.x, m.pose.position.y) for k, m in markers.items() if k[0] == "scan"} == before
    assert "refused: scan: scan angle_increment must be non-zero" in scan_node.output()
    # scans without odometry for longer than max_odom_age (0.5 s): the robot's pose then is not known
    refusals = len(refused)
    end = time.monotonic() + 5.0
    while time.monotonic() < end and not any("max_odom_age" in s["last_refusal"] for s in statuses[refusals:]):
        scans.publish(scan_message(node))
        probe.spin_for(0.1)
    assert any("max_odom_age" in s["last_refusal"] for s in statuses[refusals:]), statuses[-1:]


def test_a_robot_controller_takes_the_scan_regions_in_odom_within_its_slots(ros_graph):
    """scan node (sized to the unicycle config's 4 ellipses and 2 polygons) -> a unicycle controller on the
    robot interface: every MarkerArray accepted (odom is its output plane), the regions in its slots."""
    _, _, start, probe_factory = ros_graph
    ctrl = start("controller", "--ros-args", "--params-file", str(ROOT / "config" / "unicycle.yaml"),
                 "-p", "target:=[3.0, 0.0]", "-p", "state_timeout:=30.0")
    scan_node = start("obstacles", "--ros-args", "-p", "source:=scan", "-p", "max_circles:=4", "-p", "max_walls:=2")
    probe = probe_factory()
    node = probe.node
    verdicts: list[dict[str, str]] = []
    node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: verdicts.extend(
        {kv.key: kv.value for kv in s.values} for s in m.status if "obstacles_verdict" in
        {kv.key for kv in s.values}), STREAM_QOS)
    odom = node.create_publisher(Odometry, "odom", STREAM_QOS)
    scans = node.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
    assert probe.spin_until(lambda: odom.get_subscription_count() >= 2 and scans.get_subscription_count() >= 1,
                            120.0), ctrl.output()[-3000:] + scan_node.output()[-3000:]

    def regions_in_use() -> bool:
        # the circle, a corner piece or two, and the two nearest walls: the slots hold them all
        return any(v.get("obstacles_verdict") == "accepted" and int(v.get("regions", 0)) >= 3 for v in verdicts)

    end = time.monotonic() + 60.0
    while time.monotonic() < end and not regions_in_use():
        odom.publish(state_to_odometry([ROBOT.x, ROBOT.y, ROBOT.yaw], [0.0, 0.0], node.get_clock().now().to_msg(),
                                       "odom", "base_link"))
        scans.publish(scan_message(node))
        probe.spin_for(0.1)
    assert regions_in_use(), ({k: v for k, v in verdicts[-1].items() if "obstacle" in k or k == "regions"},
                              ctrl.output()[-1500:])
    assert not any(v.get("obstacles_verdict") == "refused" for v in verdicts), [
        v.get("obstacles_reason") for v in verdicts if v.get("obstacles_verdict") == "refused"][:3]
