"""`obstacles`: publishes a scene's obstacles as stamped markers on `obstacles`, at a fixed rate; or, with
`source: scan` or `grid`, the regions fitted to a laser scan or an occupancy grid (nodes/obstacles_sensed.py).

    ros2 run nmpc_avoid_ros obstacles --ros-args -p scene:=config/scenes/crossing_walker.yaml -p rate:=10.0
    ros2 run nmpc_avoid_ros obstacles --ros-args -p source:=scan

Scene time 0 is the arrival of the first `state` message (`start_on: state`, so the obstacles
start with the plant) or the node's start (`start_on: start`). Every tick publishes the obstacles
alive at scene time s, where they are at s, as one MarkerArray that replaces the whole set
(DELETEALL, then one marker per obstacle, ns `<prefix>/<obstacle id>`), stamped with the node
clock. With `explicit_velocity` each marker carries its velocity in `text` (`velocity=vx,vy`);
without, the controller estimates it from the successive stamped poses, as from any tracker.
The set at scene time 0 also goes out at once on start (latched), so a controller has it before
the first state. On simulated time (`use_sim_time`, a lockstep plant's /clock: `demo --scene
--lockstep`) the scene runs on that clock: the timer fires when the clock passes a period (once
per lockstep sample for rates above 1/sample_time), and stamps and poses are those of the tick.
"""

from __future__ import annotations

from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray

from ..core.errors import ConfigError
from ..core.loop.scene import load_scene
from ..ros.markers import delete_all_marker, region_marker
from ..ros.parameters import LATCHED_QOS, STREAM_QOS, ParamSpec, declare
from .obstacles_sensed import SensedObstacles
from .runner import run_node

START_MODES = ("state", "start")
SOURCES = ("scene", "scan", "grid")

OBSTACLE_SPECS = [
    ParamSpec("source", "scene", "what the obstacles come from: a scene file, a LaserScan on `scan` or an "
              "OccupancyGrid on `map` (both with `odom`)", ParameterType.PARAMETER_STRING, read_only=True,
              choices=SOURCES),
    ParamSpec("scene", "", "scene YAML whose obstacles are published", ParameterType.PARAMETER_STRING,
              read_only=True),
    ParamSpec("rate", 10.0, "markers published per second, Hz", ParameterType.PARAMETER_DOUBLE, read_only=True,
              float_range=(0.1, 1000.0)),
    ParamSpec("explicit_velocity", True, "write each obstacle's velocity into the marker text (velocity=vx,vy); "
              "false: the controller estimates it from the stamps", ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("start_on", "state", "scene time 0: the first state message, or the node's start",
              ParameterType.PARAMETER_STRING, read_only=True, choices=START_MODES),
    ParamSpec("ns_prefix", "", "marker namespace prefix (empty: the source's name)", ParameterType.PARAMETER_STRING,
              read_only=True),
]


class ObstaclesNode(Node):
    """Thin node: scene time -> core regions -> markers (or a sensed source's, SensedObstacles)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("obstacles", **kwargs)
        values = declare(self, OBSTACLE_SPECS)
        if values["source"] not in SOURCES:
            raise ConfigError(f"source must be one of {SOURCES}, got {values['source']!r}")
        self.prefix = str(values["ns_prefix"]) or values["source"]
        if values["source"] != "scene":
            self.sensed = SensedObstacles(self, values["source"], self.prefix)
            self.get_logger().info(f"obstacles ready: regions fitted to the {values['source']} and odom, "
                                   f"published as ns {self.prefix!r}")
            return
        if not values["scene"]:
            raise ConfigError("parameter scene is required: the scene YAML whose obstacles to publish")
        if values["start_on"] not in START_MODES:
            raise ConfigError(f"start_on must be one of {START_MODES}, got {values['start_on']!r}")
        self.scene = load_scene(values["scene"])
        self.explicit = bool(values["explicit_velocity"])
        self.started: float | None = None if values["start_on"] == "state" else self.now()
        self.published = 0
        self.pub = self.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
        if self.started is None:
            self.create_subscription(Float64MultiArray, "state", self.on_state, STREAM_QOS)
        self.timer = self.create_timer(1.0 / float(values["rate"]), self.publish)
        self.publish()  # on sim time the timer waits for the first /clock tick: the set is out before x0
        self.get_logger().info(f"obstacles ready: {len(self.scene.obstacles)} obstacle(s) of {self.scene.path} at "
                               f"{values['rate']:g} Hz, scene time starts on {values['start_on']}, "
                               f"velocity {'explicit' if self.explicit else 'left to estimation'}")

    def now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def on_state(self, _msg: Float64MultiArray) -> None:
        if self.started is None:
            self.started = self.now()
            self.get_logger().info("first state: scene time starts")

    def scene_markers(self, now: float) -> MarkerArray:
        """The set at node-clock time `now` (s): poses at scene time now - start (0 before the start)."""
        scene_time = 0.0 if self.started is None else now - self.started
        markers = [delete_all_marker()]
        for name, region in self.scene.named_regions_at(scene_time):
            # the same pose, its stamp moved from scene time to the node clock
            stamped = region.with_motion(region.velocity, now) if region.moving else region
            marker = region_marker(stamped, 0, f"{self.prefix}/{name}", now)
            if not self.explicit:
                marker.text = ""
            markers.append(marker)
        return MarkerArray(markers=markers)

    def publish(self) -> None:
        self.pub.publish(self.scene_markers(self.now()))
        self.published += 1


def main(argv: list[str] | None = None) -> int:
    return run_node(ObstaclesNode, argv, "obstacles", __doc__)
