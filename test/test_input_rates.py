"""Input-rate limits (setting input_rate_max): a robot's acceleration limits in the plan, so that no command
differs from the one in force by more than the limit times the sample time (issue: cmd_vel stepped from 0 to
0.8 m/s and +-1.5 rad/s in one message)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import FeedbackOutcome

ROOT = Path(__file__).resolve().parents[1]
UNICYCLE = ControllerSettings.from_params(load_params_file(ROOT / "config" / "unicycle.yaml").section("controller"))


def steps(run, settings) -> np.ndarray:
    """|u(k) - u(k-1)| per sample, from rest (the first command against zero)."""
    return np.abs(np.diff(np.vstack([np.zeros(len(settings.input_weights)), run.u]), axis=0))


@pytest.mark.parametrize("feedback", [False, True])
def test_the_shipped_unicycle_never_steps_its_command_beyond_its_acceleration_limits(feedback):
    settings = UNICYCLE.replace(feedback=feedback)
    assert settings.input_rate_max == (1.0, 3.0)
    controller = NmpcController(settings)
    run = run_closed_loop(controller, [-4.0, -3.0, 0.0], [3.0, 2.0], 80, "continuous")
    limit = np.array(settings.input_rate_max) * settings.sample_time
    assert np.all(steps(run, settings) <= limit + 1e-6)  # from rest on, fallbacks included
    assert np.linalg.norm(run.x[-1][:2] - [3.0, 2.0]) < 0.05  # and still gets there
    if feedback:  # the law follows the command in force (a parameter that changes every sample)
        assert sum(f == FeedbackOutcome.ANSWERED for f in run.feedback) >= 20


def test_without_limits_the_first_command_jumps_to_the_input_bound():
    settings = UNICYCLE.replace(input_rate_max=())
    run = run_closed_loop(NmpcController(settings), [-4.0, -3.0, 0.0], [3.0, 2.0], 5, "continuous")
    assert np.max(steps(run, settings)[:, 0]) > 0.5  # 0 -> 0.8 m/s, the step


def test_limits_need_one_value_per_input():
    with pytest.raises(ConfigError, match="input_rate_max needs 2 values"):
        NmpcController(UNICYCLE.replace(input_rate_max=(1.0,)))


ROBOT = ControllerSettings.from_params(load_params_file(ROOT / "config" / "mobile_robot.yaml").section("controller"))


@pytest.mark.parametrize("solver", ["fatrop", "sqp", "sqp_hpipm"])
def test_every_stage_wise_path_keeps_the_limits_and_follows_the_multiple_shooting_loop(solver):
    """The stage-wise formulation carries the input before each stage's own as a state (core/nlp/stagewise.py), so
    the limit couples no two stages: the structure-exploiting paths plan it as IPOPT does."""
    limited = dict(input_rate_max=(1.0, float("inf")), codegen=False, ellipse_tiers=())
    x0, goal = [-8.0, -6.0, 0.0, 0.0], [8.0, 6.0]
    controllers = {name: NmpcController(ROBOT.replace(solver=name, **limited)) for name in ("ipopt", solver)}
    layout = controllers[solver].nlp.layout  # only the limited input is carried: one state per stage, not m
    assert layout.prev_index.shape == (ROBOT.horizon + 1, 1)
    runs = {name: run_closed_loop(c, x0, goal, 25, "continuous") for name, c in controllers.items()}
    settings = ROBOT.replace(**limited)
    for run in runs.values():
        assert np.all(steps(run, settings)[1:, 0] <= settings.sample_time + 1e-6)  # 1 m/s^2 on the first input
        assert np.max(steps(run, settings)[1:, 1]) > settings.sample_time  # the second is not limited
    assert np.max(np.abs(runs[solver].x - runs["ipopt"].x)) < 1e-3  # the same plans


BICYCLE = ControllerSettings.from_params(load_params_file(ROOT / "config" / "bicycle.yaml").section("controller"))


def test_the_shipped_car_turns_its_steering_wheel_at_most_its_rate_and_parks():
    """config/bicycle.yaml limits the steering rate (1.5 rad/s: 0.3 rad a sample), not the speed's change: the car
    from rest facing its goal's side still reaches its goal pose, and no command steers further than that from the
    one before, the first against the wheels straight."""
    settings = BICYCLE.replace(codegen=False)
    assert settings.input_rate_max == (float("inf"), 1.5)
    run = run_closed_loop(NmpcController(settings), [-4.0, -3.0, 0.0], [3.0, 2.0, 0.0], 70, "continuous")
    change = steps(run, settings)
    assert np.all(change[:, 1] <= 1.5 * settings.sample_time + 1e-6)
    assert np.max(change[:, 1]) > 0.29  # the limit is reached: it binds
    assert np.max(change[:, 0]) > 0.3  # the speed is not limited
    assert np.linalg.norm(run.x[-1][:2] - [3.0, 2.0]) < 0.1 and abs(run.x[-1][2]) < 0.1


def test_a_fallback_slows_the_robot_within_its_limits_and_predicts_the_way_it_takes():
    """The fallback's candidates go through the rate limits from the command in force (FallbackSelector.followed):
    the safe input (stop) brakes at the limit and its prediction covers the braking distance. Before, the robot
    was commanded to stop at once, a step the plan's next rate row then forbade its warm start to match."""
    settings = UNICYCLE.replace(codegen=False)
    controller = NmpcController(settings)
    x, goal = np.array([0.0, 0.0, 0.0]), np.array([3.0, 0.0])
    cruising = np.array([0.8, 0.0])
    controller.memory.command = cruising
    choice = controller.fallback.choose(x, controller.parameters(x, goal), None, None, False, recover=False)
    assert choice.kind == "safe"
    step = settings.input_rate_max[0] * settings.sample_time
    braking = np.maximum(cruising[0] - step * np.arange(1, 6), 0.0)
    assert np.allclose(choice.inputs[:5, 0], braking)  # 0.8 -> 0 at the limit, not at once
    assert choice.states[-1][0] > 0.8 * settings.sample_time  # it rolls on while it brakes
    unlimited = NmpcController(settings.replace(input_rate_max=()))
    unlimited.memory.command = cruising
    at_once = unlimited.fallback.choose(x, unlimited.parameters(x, goal), None, None, False, recover=False)
    assert np.all(at_once.inputs == 0.0)


def test_a_steady_fallback_applies_the_input_it_was_judged_by_not_the_plans_next_one():
    """When the shifted plan would drive into a region and holding u_a (a stop) would not, the `steady` fallback's
    command is the stop as the actuators follow it, and its prediction is that stop's. Before, the result took the
    plan's next input (the `shift` candidate's): campaign bicycle_world-0027 drove on at full speed, judged 0.87
    deep, with `fallback_steady` in its diagnostics."""
    settings = UNICYCLE.replace(codegen=False)
    controller = NmpcController(settings)
    x, goal = np.array([0.0, 0.0, 0.0]), np.array([4.0, 0.0])
    for _ in range(6):  # under way towards the goal
        result = controller.step(x, goal)
        x = result.states[1]
    plan = controller.memory.plan
    assert result.u[0] > 0.3 and plan.u_a[0] == pytest.approx(0.0, abs=1e-6)
    # a wall across the plan's way, 1.2 m ahead: braking stops short of it, driving on the plan does not
    wall = Ellipse((x[0] + 1.2, 0.0), (0.3, 2.0))
    controller.worker.interrupt()  # every solver call fails: the fallback answers
    fallback = controller.step(x + 0.0, goal, [wall])
    assert fallback.status == "fallback_steady", fallback.fallback_reason
    assert fallback.fallback_predicted["shift"] > 0.0 and fallback.fallback_predicted["steady"] == 0.0
    step = np.asarray(settings.input_rate_max) * settings.sample_time
    assert fallback.u[0] == pytest.approx(max(result.u[0] - step[0], 0.0))  # braking at the limit
    predicted = controller.fallback.predict(x, fallback.inputs, controller.parameters(x, goal))[0]
    np.testing.assert_allclose(fallback.states, predicted, atol=1e-9)
    # the next sample starts from the stop applied, not from the plan that drove into the wall
    follow = controller.memory.plan
    assert follow.age == 0 and np.array_equal(follow.inputs, fallback.inputs)
    assert np.array_equal(follow.states, fallback.states) and follow.u_a[0] == 0.0
    np.testing.assert_allclose(follow.x_a[:2], fallback.states[-1][:2])


def test_a_fallback_commands_inside_the_input_box_when_the_plan_meets_its_bound_to_a_tolerance_only():
    """A solver meets an input bound to its tolerance only; the `shift` and `steady` fallbacks judge and apply the
    plan's inputs clipped into the box. Before, a shift fallback applied the raw plan: the flood test's van der
    Pol (|u| <= 6) commanded beyond 6 (CI of stop 41)."""
    settings = UNICYCLE.replace(codegen=False)
    controller = NmpcController(settings)
    x, goal = np.array([0.0, 0.0, 0.0]), np.array([4.0, 0.0])
    for _ in range(3):
        x = controller.step(x, goal).states[1]
    plan = controller.memory.plan
    hi, lo = np.asarray(settings.input_max), np.asarray(settings.input_min)
    plan.inputs[:, 0] = hi[0] + 1e-7  # the plan rides the upper speed bound, a little beyond it
    plan.inputs[:, 1] = lo[1] - 1e-7  # and the lower turn-rate bound
    plan.u_a[:] = hi + 1e-7
    controller.worker.interrupt()  # every solver call fails: the fallback answers
    fallback = controller.step(x + 0.0, goal)
    assert fallback.status in ("fallback_shift", "fallback_steady"), fallback.fallback_reason
    assert np.all(fallback.inputs <= hi) and np.all(fallback.inputs >= lo), fallback.inputs
    assert np.all(fallback.u <= hi) and np.all(fallback.u >= lo)
    assert fallback.u[0] == hi[0] or fallback.status == "fallback_steady"
