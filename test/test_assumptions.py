"""The paper's assumptions checked at start (core/problem/assumptions.py) and the bicycle declared as a model file."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.shapes import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import StepStatus


def test_the_paper_example_meets_assumption_5_and_a_robot_at_rest_does_not():
    assert NmpcController(ControllerSettings()).assumption_warnings == []
    robot = ControllerSettings.from_params(load_params_file("config/unicycle.yaml").section("controller"))
    warnings = NmpcController(robot).assumption_warnings
    assert len(warnings) == 1 and "Assumption 5" in warnings[0] and "unicycle" in warnings[0]


def test_a_horizon_shorter_than_the_state_is_refused_for_the_terminal_equality():
    with pytest.raises(ConfigError, match="horizon 1 is below the 2 states"):
        NmpcController(ControllerSettings(horizon=1))
    NmpcController(ControllerSettings(horizon=2))  # N = n is allowed


def test_the_bicycle_commands_the_yaw_rate_its_steering_gives_and_reads_it_back():
    planar = make_model("bicycle").planar
    wheelbase = make_model("bicycle").parameters["wheelbase"]
    twist = np.asarray(planar.command([0.0, 0.0, 0.0], [0.8, 0.3])).ravel()
    np.testing.assert_allclose(twist, [0.8, 0.8 * math.tan(0.3) / wheelbase])
    np.testing.assert_allclose(np.asarray(planar.from_command([0.0, 0.0, 0.0], twist)).ravel(), [0.8, 0.3])
    np.testing.assert_allclose(np.asarray(planar.from_command([0.0, 0.0, 0.0], [0.0, 1.0])).ravel(), [0.0, 0.0])


def test_the_shipped_bicycle_config_drives_to_a_goal_pose_among_four_ellipses_with_its_turning_radius():
    params = load_params_file("config/bicycle.yaml").section("controller")
    settings = ControllerSettings.from_params(params).replace(codegen=False, codegen_background=False)
    regions = (Ellipse((-1.5, -1.0), (0.5, 0.5), frame="output"), Ellipse((1.0, 0.5), (0.4, 0.6), frame="output"),
               Ellipse((-2.5, 1.0), (0.5, 0.3), frame="output"), Ellipse((1.5, -1.5), (0.3, 0.3), frame="output"))
    run = run_closed_loop(NmpcController(settings), [-4.0, -3.0, 0.0], [3.0, 2.0, 0.0], 100, "continuous",
                          regions=lambda k: regions if k == 0 else None)
    assert np.hypot(*(run.x[-1, :2] - [3.0, 2.0])) < 0.1  # the config's goal_tolerance
    assert all(status == StepStatus.OK for status in run.status)
    for e in regions:  # clear of every ellipse at the samples
        scaled = (run.x[:, :2] - e.center) / e.semi_axes
        assert np.min(np.sum(scaled**2, axis=1)) > 1.0
    assert np.all(np.abs(run.u[:, 1]) <= 0.5 + 1e-6)  # the steering bound: a turning radius >= 0.92 m

