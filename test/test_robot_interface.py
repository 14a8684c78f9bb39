"""The unicycle behind standard robot messages, through real DDS: Odometry in, TwistStamped out,
a goal from `goal_pose`, obstacles as markers in the odom frame; bad robot messages refused."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSPresetProfiles
from rosgraph import ROOT
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.core.errors import InputError
from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.ros.markers import regions_to_markers
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS
from nmpc_avoid_ros.ros.robot import state_to_odometry, yaw_of

pytestmark = [pytest.mark.dds, pytest.mark.slow]

CONFIG = ROOT / "config" / "unicycle.yaml"
PARAMS = ["--ros-args", "--params-file", str(CONFIG)]
GOAL = (3.0, 2.0)
#: two ellipses across the straight line from (-4, -3) to the goal, in the odom frame
ELLIPSES = [Ellipse((-1.2, -1.0), (0.7, 0.5), 0.5, "output"), Ellipse((1.2, 0.7), (0.5, 0.8), 0.0, "output")]


class RobotProbe:
    """The probe's view of a robot graph: odometry, commands, diagnostics; publishes goals and obstacles."""

    def __init__(self, probe) -> None:
        self.probe = probe
        node = probe.node
        self.odom: list[tuple[float, float, float, float]] = []  # (receipt time, x, y, yaw)
        self.frames: set[tuple[str, str]] = set()
        self.commands: list[TwistStamped] = []
        self.diags: list[dict] = []
        node.create_subscription(Odometry, "odom", self._on_odom, STREAM_QOS)
        node.create_subscription(TwistStamped, "cmd_vel", self.commands.append, STREAM_QOS)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, STREAM_QOS)
        self.obstacles = node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
        # RViz's "2D Goal Pose" tool publishes with the default (volatile) QoS
        self.goal = node.create_publisher(PoseStamped, "goal_pose", QoSPresetProfiles.DEFAULT.value)
        self.odom_pub = node.create_publisher(Odometry, "odom", STREAM_QOS)

    def _on_odom(self, msg: Odometry) -> None:
        p = msg.pose.pose.position
        try:
            yaw = yaw_of(msg.pose.pose.orientation)
        except InputError:  # the bad messages this probe itself sends
            yaw = math.nan
        self.odom.append((time.monotonic(), p.x, p.y, yaw))
        self.frames.add((msg.header.frame_id, msg.child_frame_id))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.startswith("/controller"):
                values = {kv.key: kv.value for kv in status.values}
                values["level"] = int.from_bytes(status.level, "little") if isinstance(status.level, bytes) \
                    else int(status.level)
                values["message"] = status.message
                self.diags.append(values)

    def send_goal(self, x: float, y: float, frame: str = "odom") -> None:
        msg = PoseStamped()
        msg.header.frame_id = frame
        msg.header.stamp = self.probe.node.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y = x, y
        msg.pose.orientation.w = 1.0
        assert self.probe.spin_until(lambda: self.goal.get_subscription_count() >= 1, 20)
        self.goal.publish(msg)


def test_unicycle_reaches_a_goal_pose_among_two_ellipses_through_dds(ros_graph):
    """Lockstep (the plant integrates the continuous unicycle over each sample and answers each
    command; the controller solves each odometry message), so the result does not depend on the
    machine's load; penetration is checked between the samples too, by integrating each command."""
    _, _, start, probe = ros_graph
    p = probe()
    robot = RobotProbe(p)
    obstacles = regions_to_markers(ELLIPSES)
    for marker in obstacles.markers:
        marker.header.frame_id = marker.header.frame_id and "odom"  # the robot stack's frame (DELETEALL stays '')
    robot.obstacles.publish(obstacles)
    lockstep = ["-p", "lockstep:=true"]
    ctrl = start("controller", *PARAMS, *lockstep)
    plant = start("plant", *PARAMS, *lockstep, "-p", "wait_for_subscribers:=2")
    assert p.spin_until(lambda: len(robot.odom) >= 1 and "2 region(s) stored" in ctrl.output(), 60), \
        (ctrl.output(), plant.output())
    assert robot.commands == []  # no goal yet: the controller idles and the plant holds
    robot.send_goal(*GOAL)
    steps = 100  # 20 s at Ts = 0.2 s
    assert p.spin_until(lambda: len(robot.odom) > steps, 180), (ctrl.output()[-3000:], robot.diags[-1:])
    states = np.array([odom[1:] for odom in robot.odom[: steps + 1]])
    distance = np.hypot(states[:, 0] - GOAL[0], states[:, 1] - GOAL[1])
    assert distance[-1] < 0.1
    settling_step = int(np.flatnonzero(distance >= 0.1)[-1] + 1)
    # between samples: integrate each applied command over its sample from the state it met
    plant_model = ContinuousPlant(make_model("unicycle"))
    fine = []
    for x, command in zip(states[:steps], robot.commands[:steps]):
        u = np.array([command.twist.linear.x, command.twist.angular.z])
        for _ in range(10):
            x = plant_model.advance(x, u, 0.02)
            fine.append(x[:2])
    penetration = max(max(0.0, e.depth(q)) for e in ELLIPSES for q in states[:, :2])
    # the NLP penalises the sampled states only: the arc between two samples may cut a region's
    # edge by a little (a chord of v Ts = 0.16 m)
    between = max(max(0.0, e.depth(q)) for e in ELLIPSES for q in fine)
    solved = [d for d in robot.diags if "solve_time_ms" in d]
    median_ms = float(np.median([float(d["solve_time_ms"]) for d in solved]))
    statuses = sorted({d["status"] for d in solved})
    print(f"unicycle through DDS (lockstep, continuous plant): within 0.1 m from step {settling_step} "
          f"({settling_step * 0.2:.1f} s), max penetration at the samples {penetration:.2e}, between them "
          f"{between:.2e}, solve median {median_ms:.1f} ms over {len(solved)} samples, statuses {statuses}")
    assert penetration <= 1e-3 and between <= 1e-2
    # the straight line crosses both ellipses: avoiding them is what kept the path out
    line = np.linspace((-4.0, -3.0), GOAL, 200)
    assert all(max(e.depth(q) for q in line) > 0.1 for e in ELLIPSES)
    # REP 103/105: commands stamped in the base frame, odometry in odom -> base_link
    assert all(c.header.frame_id == "base_link" and (c.header.stamp.sec or c.header.stamp.nanosec)
               for c in robot.commands)
    assert robot.frames == {("odom", "base_link")}
    assert plant.stop() == 0 and ctrl.stop() == 0


def test_bad_robot_messages_are_refused_with_a_reason_and_the_loop_goes_on(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    robot = RobotProbe(p)
    ctrl = start("controller", *PARAMS, "-p", "state_timeout:=5.0")
    stamp = p.node.get_clock().now().to_msg()
    good = state_to_odometry([0.0, 0.0, 0.0], [0.0, 0.0], stamp, "odom", "base_link")
    wrong_frame = state_to_odometry([5.0, 5.0, 0.0], [0.0, 0.0], stamp, "map", "base_link")
    wrong_child = state_to_odometry([5.0, 5.0, 0.0], [0.0, 0.0], stamp, "odom", "base_footprint")
    with_nan = state_to_odometry([math.nan, 0.0, 0.0], [0.0, 0.0], stamp, "odom", "base_link")
    zero_quaternion = state_to_odometry([5.0, 5.0, 0.0], [0.0, 0.0], stamp, "odom", "base_link")
    zero_quaternion.pose.pose.orientation.w = 0.0

    def feed(msg: Odometry, seconds: float = 0.3) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            robot.odom_pub.publish(msg)
            p.spin_for(0.05)

    robot.send_goal(1.0, 0.5)
    assert p.spin_until(lambda: feed(good, 0.2) or any(d.get("status") == "ok" for d in robot.diags), 30), \
        ctrl.output()
    cases = [(wrong_frame, "odometry header.frame_id is 'map', expected 'odom'"),
             (wrong_child, "child_frame_id is 'base_footprint'"),
             (with_nan, "NaN"), (zero_quaternion, "zero norm")]
    for bad, reason in cases:
        n = len(robot.diags)
        feed(bad, 0.3)
        feed(good, 0.6)
        after = robot.diags[n:]
        assert any(reason in d.get("last_rejected", "") for d in after), (reason, after[-1:])
        solved = [d for d in after if d.get("status") in ("ok", "truncated", "unconverged")]
        assert solved and json.loads(solved[-1]["state"]) == [0.0, 0.0, 0.0]  # only the good state was used
    n = len(robot.diags)
    robot.send_goal(9.0, 9.0, frame="map")  # a goal in another frame: refused, the old target stays
    feed(good, 0.6)
    assert any("goal_pose header.frame_id is 'map'" in d.get("last_rejected", "") for d in robot.diags[n:])
    assert "target y_t = [9.0, 9.0]" not in ctrl.output()
    last = robot.diags[-1]
    assert last["status"] in ("ok", "truncated", "unconverged") and int(last["rejected_inputs"]) >= 5
    assert ctrl.alive() and ctrl.stop() == 0


def test_the_car_like_robot_reaches_a_goal_pose_with_its_turning_radius_through_dds(ros_graph):
    """config/bicycle.yaml (a model file's `planar` map: cmd_vel is v and the yaw rate v tan(delta) / L, the plant
    turns it back into the steering angle), lockstep, interpreted FATROP (no compile in a test): the goal pose
    reached past the two ellipses, every command within the car's turning radius."""
    _, _, start, probe = ros_graph
    p = probe()
    robot = RobotProbe(p)
    obstacles = regions_to_markers(ELLIPSES)
    for marker in obstacles.markers:
        marker.header.frame_id = marker.header.frame_id and "odom"
    robot.obstacles.publish(obstacles)
    config = ["--ros-args", "--params-file", str(ROOT / "config" / "bicycle.yaml")]
    fast = ["-p", "lockstep:=true", "-p", "codegen:=false", "-p", "codegen_background:=false"]
    ctrl = start("controller", *config, *fast)
    plant = start("plant", *config, "-p", "lockstep:=true", "-p", "wait_for_subscribers:=2")
    assert p.spin_until(lambda: len(robot.odom) >= 1 and "2 region(s) stored" in ctrl.output(), 60), \
        (ctrl.output(), plant.output())
    robot.send_goal(*GOAL)  # heading 0
    steps = 100
    assert p.spin_until(lambda: len(robot.odom) > steps, 240), (ctrl.output()[-3000:], robot.diags[-1:])
    states = np.array([odom[1:] for odom in robot.odom[: steps + 1]])
    assert np.hypot(states[-1, 0] - GOAL[0], states[-1, 1] - GOAL[1]) < 0.1 and abs(states[-1, 2]) < 0.1
    assert max(max(0.0, e.depth(q)) for e in ELLIPSES for q in states[:, :2]) <= 1e-3
    model = make_model("bicycle")
    wheelbase, steer_max = model.parameters["wheelbase"], model.bounds["input_max"][1]
    for command in robot.commands[:steps]:
        v, omega = command.twist.linear.x, command.twist.angular.z
        assert abs(omega) <= abs(v) * math.tan(steer_max) / wheelbase + 1e-9
    assert "Assumption 5" in ctrl.output()  # a car at rest cannot move sideways: the start says so
    assert plant.stop() == 0 and ctrl.stop() == 0
