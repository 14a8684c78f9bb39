"""Motion a robot user expects (issue 33 item 4), offline through the core NmpcController and the continuous plant:
forward only (a goal behind the unicycle is turned towards, not backed up to), the goal verdict of
core/loop/goal.py (reached, held by a hysteresis, resumed by a new goal; a goal inside an obstacle reported
unreachable with where the robot stops). The node's side, over DDS: test_goal_reached_dds.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_unicycle import OFFLINE_SOLVE_TIME, robot_settings

from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.loop.goal import SETTLED_SAMPLES, GoalWatch
from nmpc_avoid_ros.core.problem.models import make_model, unicycle_turn_guess
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController

TS = 0.2
#: the unicycle's shipped goal settings (config/unicycle.yaml)
GOAL = {"tolerance": 0.1, "hysteresis": 0.1, "rest_speed": 0.02}


def reverse_travel(x: np.ndarray) -> float:
    """m driven backwards along a unicycle trajectory x [K+1, 3] (displacement against the heading)."""
    step = np.diff(x[:, :2], axis=0)
    along = np.sum(step * np.column_stack([np.cos(x[:-1, 2]), np.sin(x[:-1, 2])]), axis=1)
    return float(-along[along < 0].sum())


def test_the_shipped_unicycle_turns_towards_a_goal_7_m_behind_it_instead_of_backing_up():
    """Before (input_min v = -0.3): 6 m backwards in these 20 s, still backing at 0.3 m/s. Forward only with the
    plain bound the solver stays at v = omega = 0 for ever (a local minimum at rest: turning does not move the
    output); started from the model's turn it turns on the spot, then drives."""
    controller = NmpcController(robot_settings(max_solve_time=OFFLINE_SOLVE_TIME))
    assert controller.settings.input_min[0] == 0.0  # config/unicycle.yaml: forward only
    run = run_closed_loop(controller, [3.0, 0.0, 0.0], [-4.0, 0.0], 100, "continuous")
    x = np.asarray(run.x)
    assert reverse_travel(x) <= 1.0 and np.all(run.u[:, 0] >= -1e-9)
    assert np.hypot(x[-1, 0] + 4.0, x[-1, 1]) < GOAL["tolerance"]
    # it turned first: half a turn within 3 s, on an arc of less than 1 m
    turned = np.argmax(np.abs(np.cos(x[:, 2]) + 1.0) < 0.1)
    assert 0 < turned * TS <= 3.0 and np.hypot(*(x[turned, :2] - x[0, :2])) < 1.0


@pytest.mark.slow
def test_a_parked_robot_turns_to_a_new_goal_behind_it_and_reversing_is_a_setting():
    controller = NmpcController(robot_settings(max_solve_time=OFFLINE_SOLVE_TIME))
    run = run_closed_loop(controller, [-1.0, 0.0, 0.0], lambda k: [1.5, 0.0] if k < 40 else [-2.5, 0.3], 100,
                          "continuous")
    x = np.asarray(run.x)
    assert np.hypot(x[40, 0] - 1.5, x[40, 1]) < GOAL["tolerance"]  # parked at the first goal, facing +x
    assert reverse_travel(x) <= 1.0
    assert np.hypot(x[-1, 0] + 2.5, x[-1, 1] - 0.3) < GOAL["tolerance"]
    # input_min v < 0 lets it reverse: the same goal behind is backed up to
    backing = NmpcController(robot_settings(max_solve_time=OFFLINE_SOLVE_TIME, input_min=[-0.3, -1.5]))
    assert reverse_travel(np.asarray(run_closed_loop(backing, [3.0, 0.0, 0.0], [-4.0, 0.0], 20, "continuous").x)) > 1.0


def test_the_turn_guess_is_for_a_forward_only_unicycle_with_its_target_behind():
    lo, hi = np.array([0.0, -1.5]), np.array([0.8, 1.5])
    x = np.array([1.0, 2.0, 0.0])
    assert unicycle_turn_guess(x, [3.0, 2.5], 15, TS, lo, hi) is None  # ahead: driving approaches it
    assert unicycle_turn_guess(x, [0.98, 2.0], 15, TS, lo, hi) is None  # 2 cm behind: stays parked
    assert unicycle_turn_guess(x, [-2.0, 2.0], 15, TS, np.array([-0.3, -1.5]), hi) is None  # may reverse
    states, inputs = unicycle_turn_guess(x, [-2.0, 2.0], 15, TS, lo, hi)  # straight behind: to the left
    assert states.shape == (15, 3) and inputs.shape == (15, 2)
    assert np.all(inputs[:, 0] >= 0) and np.all(np.abs(inputs[:, 1]) <= 1.5) and inputs[0, 1] > 0
    turning = inputs[:, 0] == 0
    np.testing.assert_allclose(states[turning][:, :2], [[1.0, 2.0]] * int(turning.sum()))  # on the spot
    assert states[-1, 2] == pytest.approx(math.pi) and states[-1, 0] < 1.0  # then along the new heading
    _, right = unicycle_turn_guess(x, [-2.0, 1.0], 15, TS, lo, hi)
    assert right[0, 1] < 0  # a goal behind to the right: turned to the right
    assert make_model("unicycle").turn_guess is unicycle_turn_guess
    assert make_model("double_integrator_2d").turn_guess is None


def watch_along(watch: GoalWatch, positions, goal, result=None, **changes):
    settings = {**GOAL, **changes}
    return [watch.observe([px, py, 0.0], goal, result, [], (0, 1), (0, 1), **settings) for px, py in positions]


def test_a_goal_is_reached_within_its_tolerance_held_by_the_hysteresis_and_resumed_by_a_new_goal():
    watch = GoalWatch(make_model("unicycle"))
    first = watch_along(watch, [(0.0, 0.0), (0.85, 0.0), (0.95, 0.0), (0.85, 0.0), (0.79, 0.0)], [1.0, 0.0])
    assert [v.reached for v in first] == [False, False, True, True, False]  # in at 0.1, out past 0.2
    assert [v.changed for v in first] == [False, False, True, False, True]
    assert [v.holds for v in first] == [v.reached for v in first] and first[2].distance == pytest.approx(0.05)
    assert first[2].values()["goal_reached"] == "true" and "goal reached" in first[2].note()
    again = watch_along(watch, [(0.95, 0.0), (0.95, 0.0)], [1.0, 0.0])
    assert [v.reached for v in again] == [True, True]
    moved = watch_along(watch, [(0.95, 0.0)], [3.0, 0.0])  # a new goal: control resumes at once
    assert not moved[0].reached and moved[0].changed
    assert not any(v.reached for v in watch_along(watch, [(3.0, 0.0)], [3.0, 0.0], tolerance=0.0))  # 0: off
    # a double integrator's goal is reached at rest only: zero acceleration would let it drift on
    rolling = GoalWatch(make_model("double_integrator_2d"))
    verdicts = [rolling.observe([0.99, 0.0, vx, 0.0], [1.0, 0.0], None, [], (0, 1), (0, 1), **GOAL)
                for vx in (0.3, 0.01)]
    assert [v.reached for v in verdicts] == [False, True]


@pytest.mark.slow
def test_a_goal_inside_an_obstacle_is_reported_unreachable_with_where_the_robot_stops():
    """Before: status ok sample after sample while the command crept at 1e-4 m/s in front of the obstacle, and
    nothing said the goal could not be reached."""
    controller = NmpcController(robot_settings(max_solve_time=OFFLINE_SOLVE_TIME))
    ellipse = Ellipse((2.0, 0.0), (0.6, 0.6), 0.0, "output")
    controller.set_regions([ellipse])
    watch, verdicts, goal = GoalWatch(controller.model), [], [2.0, 0.0]

    def observe(k, result):
        s = controller.settings
        regions = [r.inflated(s.region_margin + controller.mismatch_margin) for r in controller.regions]
        verdicts.append(watch.observe(result.measured_state, goal, result, regions, s.plane, s.output_plane,
                                      time=k * TS, **GOAL))

    run = run_closed_loop(controller, [0.0, 0.1, 0.0], goal, 50, "continuous", on_step=observe)
    x = np.asarray(run.x)
    assert all(v.unreachable == "inside an obstacle region" and not v.reached for v in verdicts)
    last = verdicts[-1]
    assert last.values()["goal_unreachable"] == "true" and "stopping at" in last.note()
    assert ellipse.depth(last.stop) < 1e-3 and np.hypot(*(last.stop - ellipse.center)) < 0.8  # just in front of it
    assert np.hypot(*(x[-1, :2] - last.stop)) < GOAL["tolerance"]  # and that is where the robot is
    held = [k for k, v in enumerate(verdicts) if v.holds]
    assert held and held == list(range(held[0], len(verdicts)))  # settled there: zero command from then on
    assert held[0] >= SETTLED_SAMPLES
    # a goal out of the obstacle's way is not unreachable
    free = GoalWatch(controller.model).observe(x[-1], [0.0, 2.0], controller.step(x[-1], [0.0, 2.0]), [ellipse],
                                               (0, 1), (0, 1), **GOAL)
    assert free.unreachable == ""


@pytest.mark.parametrize("x0, goal", [([0.0, 0.0, 0.0], [2.0, 1.0, math.pi / 2]),  # ahead, arrive turned left
                                      ([3.0, 0.0, 0.0], [-4.0, 0.0, math.pi]),  # behind, arrive facing it
                                      ([0.0, 0.0, 3.0], [2.0, -1.0, -math.pi / 2])])  # -pi/2 is 4.71 from 3.0
def test_a_goal_pose_is_reached_with_its_heading_by_unicycle_pose(x0, goal):
    """model unicycle_pose (y = [x, y, theta]) with output_weights [1, 1, 0.3]: the shipped unicycle's settings
    otherwise (forward only, acceleration limits). The heading arrives within 0.01 rad the short way round
    (the target's yaw is taken within pi of the robot's heading), the position within the goal tolerance."""
    settings = robot_settings(model="unicycle_pose", output_weights=[1.0, 1.0, 0.3], max_solve_time=OFFLINE_SOLVE_TIME)
    run = run_closed_loop(NmpcController(settings), x0, goal, 120, "continuous")
    x = np.asarray(run.x)
    assert np.hypot(*(x[-1, :2] - goal[:2])) <= GOAL["tolerance"]
    assert abs(math.remainder(x[-1, 2] - goal[2], 2 * math.pi)) <= 0.01
    assert np.all(run.u[:, 0] >= -1e-9) and {str(s) for s in run.status} == {"ok"}
    assert abs(x[-1, 2] - x0[2]) < 2 * math.pi  # no extra turn


def test_angle_outputs_take_the_target_the_short_way_and_weights_must_fit_the_outputs():
    model = make_model("unicycle_pose")
    assert model.p == 3 and model.angle_outputs == ((2, 2),)
    np.testing.assert_allclose(model.nearest_target(np.array([1.0, 2.0, -math.pi / 2]), np.array([0.0, 0.0, 3.0])),
                               [1.0, 2.0, 1.5 * math.pi])
    np.testing.assert_allclose(model.output_error(np.array([0.0, 0.0, 7.0]), np.array([0.0, 0.0, 0.5])),
                               [0.0, 0.0, math.remainder(6.5, 2 * math.pi)])
    plain = make_model("unicycle")
    assert plain.nearest_target(np.array([1.0, 2.0]), np.array([0.0, 0.0, 9.0])).tolist() == [1.0, 2.0]
    from nmpc_avoid_ros.core.errors import ConfigError
    with pytest.raises(ConfigError, match="output_weights needs 3 values"):
        NmpcController(robot_settings(model="unicycle_pose", output_weights=[1.0, 0.3]))
