"""Goal reached through real DDS (issue 33 item 4): the shipped unicycle's controller and plant nodes in real time
(timer, continuous plant at 40 Hz). Within goal_tolerance the controller publishes exactly zero cmd_vel (no creep)
within 2 s of the robot's odometry entering it, latches `~/goal_reached` true and says `goal_reached` in its
diagnostics; a new goal behind the robot resumes control, is turned towards (never a negative speed) and reached."""

from __future__ import annotations

import time

import numpy as np
import pytest
from geometry_msgs.msg import TwistStamped
from rosgraph import ROOT
from std_msgs.msg import Bool
from test_robot_interface import RobotProbe

from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS

pytestmark = [pytest.mark.dds, pytest.mark.slow]

PARAMS = ["--ros-args", "--params-file", str(ROOT / "config" / "unicycle.yaml")]
START = (-4.0, -3.0)  # the plant's initial_state, heading +x
TOLERANCE = 0.1  # config/unicycle.yaml goal_tolerance
#: the time from the odometry entering the tolerance to the first zero command (the brief's bound)
ZERO_WITHIN = 2.0


def command_times(robot: RobotProbe) -> tuple[np.ndarray, np.ndarray]:
    """(receipt times [K] (time.monotonic), commands [K, 2] (v, omega)) of the cmd_vel heard so far."""
    return np.array([t for t, _ in robot.timed]), np.array([[c.twist.linear.x, c.twist.angular.z]
                                                            for _, c in robot.timed]).reshape(-1, 2)


def entered(robot: RobotProbe, goal: tuple[float, float], after: float) -> float | None:
    """The receipt time of the first odometry after `after` within TOLERANCE of `goal`, or None."""
    for t, x, y, _ in robot.odom:
        if t > after and np.hypot(x - goal[0], y - goal[1]) <= TOLERANCE:
            return t
    return None


def test_a_reached_goal_stops_the_commands_and_says_so_and_a_new_goal_behind_resumes(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    robot = RobotProbe(p)
    robot.timed = []  # (receipt time, TwistStamped)
    p.node.create_subscription(TwistStamped, "cmd_vel", lambda m: robot.timed.append((time.monotonic(), m)),
                               STREAM_QOS)
    reached: list[tuple[float, bool]] = []
    p.node.create_subscription(Bool, "/controller/goal_reached", lambda m: reached.append((time.monotonic(), m.data)),
                               LATCHED_QOS)
    ctrl = start("controller", *PARAMS)
    plant = start("plant", *PARAMS)
    assert p.spin_until(lambda: len(robot.odom) >= 1 and reached, 60), (ctrl.output()[-3000:], plant.output())
    assert reached[-1][1] is False  # latched at configure: not reached
    first = (START[0] + 1.5, START[1])  # 1.5 m ahead
    sent = time.monotonic()
    robot.send_goal(*first)
    assert p.spin_until(lambda: reached[-1][1] is True, 60), (ctrl.output()[-3000:], robot.diags[-1:])
    p.spin_for(2.5)  # the commands after it
    inside = entered(robot, first, sent)
    times, commands = command_times(robot)
    zero = times[(times > inside) & np.all(commands == 0.0, axis=1)]
    assert zero.size, commands[-5:]
    delay = float(zero[0] - inside)
    later = commands[times >= zero[0]]
    motion = np.ptp(np.array([o[1:3] for o in robot.odom if o[0] > zero[0] + 0.1]), axis=0)
    diag = [d for d in robot.diags if "goal_reached" in d][-1]
    print(f"goal reached: odometry within {TOLERANCE} m, first zero cmd_vel {delay * 1e3:.0f} ms later; "
          f"{len(later)} commands since, max |u| {np.max(np.abs(later)):.1e}; moved {motion.max():.1e} m since")
    assert delay <= ZERO_WITHIN
    assert np.all(later == 0.0) and len(later) >= 10  # stopped for good: no creep
    assert motion.max() < 1e-3
    assert diag["goal_reached"] == "true" and float(diag["goal_distance"]) <= TOLERANCE and \
        "goal reached" in diag["message"]
    # a late joiner hears it: transient local
    late: list[bool] = []
    p.node.create_subscription(Bool, "/controller/goal_reached", lambda m: late.append(m.data), LATCHED_QOS)
    assert p.spin_until(lambda: late, 10) and late == [True]
    # a new goal behind the robot: control resumes, turns towards it (v >= 0) and reaches it
    resumed = time.monotonic()
    robot.send_goal(*START)
    assert p.spin_until(lambda: reached[-1][1] is True and reached[-1][0] > resumed, 90), \
        (ctrl.output()[-3000:], robot.diags[-1:])
    assert [flag for t, flag in reached if t > resumed] == [False, True]
    times, commands = command_times(robot)
    since = commands[times > resumed]
    assert np.all(since[:, 0] >= 0.0) and np.max(since[:, 0]) > 0.1  # forward only, and it drove
    assert entered(robot, START, resumed) is not None
    assert plant.stop() == 0 and ctrl.stop() == 0
