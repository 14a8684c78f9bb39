"""The controller's two interfaces to a plant (parameter `interface`).

- `array` (any model): Float64MultiArray on `state` (n values) in, on `command` (m values) out;
  what the controller draws lies in the abstract frames `state` and `output`.
- `robot` (a model whose file maps its state to a planar pose and its input to a velocity command,
  `planar`: e.g. `unicycle`, `bicycle`; ros/robot.py RobotModelMap): nav_msgs/Odometry
  on `odom` in (frame ids checked), geometry_msgs/TwistStamped (or Twist, `cmd_vel_stamped: false`)
  on `cmd_vel` out, geometry_msgs/PoseStamped goals on `goal_pose` in; everything is drawn in
  `odom_frame`. The array `target` topic stays available.

Each interface turns a received message into a validated vector (InputError with the reason
otherwise) and a command vector into its message; the node does the rest.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from ..core.config.settings import NodeSettings
from ..core.problem.models import Model
from ..ros.conversions import array_to_vector, vector_to_array
from ..ros.parameters import LATEST_QOS
from ..ros.robot import check_robot_model, goal_to_target, odometry_to_state, velocity_command
from ..ros.visualization import DisplayFrames

#: the command's writer keeps the latest command only (as nav2 publishes cmd_vel, and as the plant
#: reads it): a reliable writer whose history is full asks its readers for an acknowledgement with
#: every message, so the deactivate command of a node about to exit is confirmed in a few ms
#: (controller_threads.py `stop_samples`); with 100 kept, the readers answered at Fast DDS's periodic
#: heartbeat only, 2.8-3 s later (measured). A lost packet is repaired while it is still the latest.
COMMAND_QOS = LATEST_QOS


class ArrayInterface:
    """`state` / `command` as Float64MultiArray (the ros2_control forward-command convention)."""

    state_topic, state_type = "state", Float64MultiArray
    goal_type = None
    heading_index: int | None = None

    def __init__(self, node: Node, model: Model, options: NodeSettings) -> None:
        self.node, self.n = node, model.n
        self.frames = DisplayFrames("state", "output")
        self.marker_frame_aliases: dict[str, str] = {}
        self.publisher = node.create_publisher(Float64MultiArray, "command", COMMAND_QOS)

    def state_of(self, msg: Any, last: np.ndarray | None) -> np.ndarray:
        return array_to_vector(msg, self.n, "state")

    def publish_command(self, u: np.ndarray) -> None:
        self.publisher.publish(vector_to_array(u))

    def destroy(self) -> None:
        self.node.destroy_publisher(self.publisher)


class RobotInterface:
    """`odom` (Odometry) in, `cmd_vel` (TwistStamped or Twist) out, `goal_pose` (PoseStamped) in."""

    state_topic, state_type = "odom", Odometry
    goal_type = PoseStamped

    def __init__(self, node: Node, model: Model, options: NodeSettings) -> None:
        self.map = check_robot_model(model)
        self.heading_index = model.planar.yaw
        self.last_state: np.ndarray | None = None  # a command's twist may depend on the state (RobotModelMap)
        self.node = node
        self.with_heading = bool(model.angle_outputs)  # unicycle_pose: the goal's heading is part of y_t
        self.odom_frame, self.base_frame = options.odom_frame, options.base_frame
        self.stamped = options.cmd_vel_stamped
        self.frames = DisplayFrames(self.odom_frame, self.odom_frame)
        # obstacle markers from the robot stack, in the odometry frame, are positions (the output)
        self.marker_frame_aliases = {self.odom_frame: "output"}
        self.publisher = node.create_publisher(TwistStamped if self.stamped else Twist, "cmd_vel", COMMAND_QOS)

    def state_of(self, msg: Any, last: np.ndarray | None) -> np.ndarray:
        last_yaw = None if last is None else float(last[self.heading_index])
        self.last_state = self.map.state(odometry_to_state(msg, self.odom_frame, self.base_frame, last_yaw))
        return self.last_state

    def publish_command(self, u: np.ndarray) -> None:
        stamp = self.node.get_clock().now().to_msg()
        x = np.zeros(self.map.n) if self.last_state is None else self.last_state
        self.publisher.publish(velocity_command(self.map.twist(x, u), self.stamped, stamp, self.base_frame))

    def target_of(self, msg: Any) -> np.ndarray:
        return goal_to_target(msg, self.odom_frame, self.with_heading)

    def destroy(self) -> None:
        self.node.destroy_publisher(self.publisher)


INTERFACES = {"array": ArrayInterface, "robot": RobotInterface}
