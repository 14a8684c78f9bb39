"""The unicycle model and its robot-message conversions, without a ROS graph."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, Quaternion, Twist
from rosgraph import ROOT

from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.errors import ConfigError, InputError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.ros.robot import (
    goal_to_target,
    odometry_to_state,
    state_to_odometry,
    twist_to_command,
    unwrap,
    velocity_command,
    yaw_of,
    yaw_quaternion,
)

CONFIG = ROOT / "config" / "unicycle.yaml"


#: solver budget of the offline loops here: the shipped 0.15 s cuts a third of the IPOPT solves on a
#: quiet machine already (the cut iterate is continued next sample), more on a loaded one, so the loop
#: would depend on the machine; these tests are about where the robot goes, not how fast it decides
OFFLINE_SOLVE_TIME = 2.0


def robot_settings(**changes):
    return ControllerSettings.from_params(load_params_file(CONFIG).section("controller")).replace(**changes)


def test_any_heading_at_rest_is_an_equilibrium_and_motion_follows_the_heading():
    model = make_model("unicycle")
    for theta in (-3.0, 0.0, 1.2, 7.0):
        x = np.array([1.0, -2.0, theta])
        np.testing.assert_allclose(np.asarray(model.dynamics(x, [0.0, 0.0])).ravel(), 0.0)
        np.testing.assert_allclose(np.asarray(model.dynamics(x, [0.5, 0.2])).ravel(),
                                   [0.5 * math.cos(theta), 0.5 * math.sin(theta), 0.2])
    assert model.steady_state is None  # no closed form: theta_a is a decision variable


def test_the_robot_parks_with_a_free_heading_and_the_fast_paths_refuse_the_model():
    controller = NmpcController(robot_settings(keep_in=[], max_solve_time=OFFLINE_SOLVE_TIME))
    run = run_closed_loop(controller, [0.0, 0.0, 0.0], [0.0, 2.0], 40, "euler")  # a goal to the left
    x = np.asarray(run.x)
    assert np.hypot(x[-1, 0], x[-1, 1] - 2.0) < 0.01
    # it arrives heading left and parks so: with theta_a fixed at 0 it would have to turn back
    assert abs(x[-1, 2]) > 1.0
    result = controller.step(x[-1], [0.0, 2.0])
    np.testing.assert_allclose(np.asarray(controller.model.dynamics(result.x_a, result.u_a)).ravel(), 0.0,
                               atol=1e-6)  # x_a is at rest
    assert abs(result.x_a[2] - x[-1, 2]) < 0.1
    for solver in ("fatrop", "sqp"):
        with pytest.raises(ConfigError, match="closed-form steady state"):
            NmpcController(robot_settings(solver=solver))


@pytest.mark.slow
def test_offline_loop_reaches_the_goal_around_two_ellipses():
    controller = NmpcController(robot_settings(max_solve_time=OFFLINE_SOLVE_TIME))
    ellipses = [Ellipse((-1.2, -1.0), (0.7, 0.5), 0.5, "output"), Ellipse((1.2, 0.7), (0.5, 0.8), 0.0, "output")]
    controller.set_regions(ellipses)
    run = run_closed_loop(controller, [-4.0, -3.0, 0.0], [3.0, 2.0], 80, "euler")
    x = np.asarray(run.x)
    assert np.hypot(x[-1, 0] - 3.0, x[-1, 1] - 2.0) < 0.1
    assert max(e.depth(p[:2]) for e in ellipses for p in x) <= 1e-3


def test_yaw_conversions_refuse_what_is_no_rotation_and_unwrap_through_pi():
    for yaw in (-3.1, -1.0, 0.0, 2.5):
        assert yaw_of(yaw_quaternion(yaw)) == pytest.approx(yaw)
    assert yaw_of(Quaternion(x=0.0, y=0.0, z=2.0, w=0.0)) == pytest.approx(math.pi)  # non-unit: normalised
    with pytest.raises(InputError, match="zero norm"):
        yaw_of(Quaternion(x=0.0, y=0.0, z=0.0, w=0.0))
    with pytest.raises(InputError, match="NaN"):
        yaw_of(Quaternion(x=0.0, y=0.0, z=math.nan, w=1.0))
    assert unwrap(-3.1, 3.1) == pytest.approx(-3.1 + 2 * math.pi)  # crossing +pi continues past pi
    assert unwrap(0.2, 4 * math.pi) == pytest.approx(0.2 + 4 * math.pi)
    assert unwrap(0.2, None) == 0.2


def test_odometry_goal_and_twist_round_trips_and_frame_checks():
    odom = state_to_odometry([1.0, 2.0, 3.0], [0.4, -0.1], PoseStamped().header.stamp, "odom", "base_link")
    np.testing.assert_allclose(odometry_to_state(odom, "odom", "base_link", 3.0), [1.0, 2.0, 3.0])
    assert (odom.twist.twist.linear.x, odom.twist.twist.angular.z) == (0.4, -0.1)
    with pytest.raises(InputError, match="header.frame_id is 'odom', expected 'map'"):
        odometry_to_state(odom, "map", "base_link")
    with pytest.raises(InputError, match="child_frame_id"):
        odometry_to_state(odom, "odom", "base_footprint")
    goal = PoseStamped()
    goal.header.frame_id = "map"
    goal.pose.position.x, goal.pose.position.y = 3.0, 2.0
    with pytest.raises(InputError, match="goal_pose header.frame_id is 'map'"):
        goal_to_target(goal, "odom")
    goal.header.frame_id = "odom"
    np.testing.assert_allclose(goal_to_target(goal, "odom"), [3.0, 2.0])
    # for unicycle_pose the goal's heading too (a quaternion of yaw 2.5 rad, not normalised)
    goal.pose.orientation.z, goal.pose.orientation.w = 2 * math.sin(1.25), 2 * math.cos(1.25)
    np.testing.assert_allclose(goal_to_target(goal, "odom", with_heading=True), [3.0, 2.0, 2.5])
    goal.pose.orientation.z = goal.pose.orientation.w = 0.0
    with pytest.raises(InputError, match="zero norm"):
        goal_to_target(goal, "odom", with_heading=True)
    stamped = velocity_command([0.3, 0.2], True, goal.header.stamp, "base_link")
    assert stamped.header.frame_id == "base_link"
    np.testing.assert_allclose(twist_to_command(stamped), [0.3, 0.2])
    plain = velocity_command([0.3, 0.2], False, goal.header.stamp, "base_link")
    assert isinstance(plain, Twist)
    plain.angular.z = math.inf
    with pytest.raises(InputError, match="cmd_vel"):
        twist_to_command(plain)
