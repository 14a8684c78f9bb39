"""The honest status (core/loop/alarm.py): a state inside a region, or a plan entering one, is reported."""

from __future__ import annotations

import math

import numpy as np

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.loop.alarm import ALARM_DEPTH, AvoidanceCheck
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController

TARGET = np.array([5.0])


def controller(**changes) -> NmpcController:
    return NmpcController(ControllerSettings(max_solve_time=2.0, **changes))


def test_a_free_sample_raises_no_alarm() -> None:
    c = controller()
    alarm = AvoidanceCheck(c).check(c.step([-5.0, 0.0], TARGET))
    assert alarm.message == "" and alarm.state_depth < 0 and alarm.plan_depth <= ALARM_DEPTH


def test_a_state_inside_an_obstacle_is_reported_with_its_depth() -> None:
    c = controller()
    c.set_regions([Ellipse((1.0, 0.5), (0.5, 0.5))])
    alarm = AvoidanceCheck(c).check(c.step([1.0, 0.5], TARGET))
    assert math.isclose(alarm.state_depth, 1.0)  # at the centre: 1 - 0
    assert alarm.message.startswith("state inside a region by 1")


def test_a_plan_that_trades_penetration_for_offset_is_reported() -> None:
    """mu = 0: no avoidance at all, so the plan runs through the obstacle on its way to y_t."""
    c = controller(mu=0.0)
    c.set_regions([Ellipse((0.0, 1.0), (1.0, 1.0))])
    results = [c.step([-5.0, 0.0], TARGET)]
    check = AvoidanceCheck(c)
    alarms = [check.check(results[0])]
    for _ in range(6):
        results.append(c.step(results[-1].states[1], TARGET))
        alarms.append(check.check(results[-1]))
    assert any("plan enters a region" in a.message for a in alarms)
    assert all(a.plan_depth > ALARM_DEPTH for a in alarms if "plan enters" in a.message)
