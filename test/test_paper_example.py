"""The paper's van der Pol example (section V) reproduced offline, and run-time changes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import InputError, RegionError
from nmpc_avoid_ros.core.loop.closed_loop import max_abs_product, run_closed_loop, settling_step
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import StepStatus

TOL = 0.05  # settling band on x1


def settled(run):
    return settling_step(run.x[:, 0], 5.0, TOL)


@pytest.mark.parametrize("mu,plant", [(0.0, "euler"), (1e8, "euler"), (0.0, "continuous"), (1e8, "continuous")])
def test_no_solve_failure_in_the_four_paper_runs(paper, mu, plant):
    run = paper(mu, plant)
    assert run.status == ["ok"] * 50
    # the NLP's solver, the fallback's recovery solve and the target projection, never rebuilt
    assert run.info["nlp_builds"] == 3


def test_without_avoidance_settles_fast_and_violates_the_energy_limit(paper):
    run = paper(0.0, "euler")
    assert settled(run) is not None and settled(run) <= 25
    assert max_abs_product(run.x) > 9.0


def test_with_avoidance_stays_out_of_the_region_and_settles_later(paper):
    run, free = paper(1e8, "euler"), paper(0.0, "euler")
    assert max_abs_product(run.x) <= 2.001
    assert settled(run) is not None and settled(run) <= 45
    assert settled(run) > settled(free)


def test_continuous_plant_with_avoidance(paper):
    run = paper(1e8, "continuous")
    assert max_abs_product(run.x) <= 2.05
    assert settled(run) is not None and settled(run) <= 50


def test_constraints_hold_along_the_paper_runs(paper):
    for mu in (0.0, 1e8):
        run = paper(mu, "euler")
        assert np.all(np.abs(run.x[:, 0]) <= 6 + 1e-6)
        assert np.all(np.abs(run.x[:, 1]) <= 2 + 1e-6)
        assert np.all(np.abs(run.u) <= 6 + 1e-6)


def test_unreachable_target_converges_to_the_best_reachable_steady_output():
    settings = ControllerSettings()
    controller = NmpcController(settings)
    run = run_closed_loop(controller, [-5.0, 0.0], [8.0], 80, "euler")
    # Y_r = lambda * [-6, 6] for x1 (and u_a = y_a within lambda * [-6, 6]): V_o is minimised at 6 lambda
    best = 6.0 * settings.steady_state_scale
    assert run.y_a[-1, 0] == pytest.approx(best, abs=1e-4)
    assert run.x[-1, 0] == pytest.approx(best, abs=1e-3)
    assert np.all(np.abs(run.x[:, 0]) <= 6 + 1e-6) and np.all(np.abs(run.x[:, 1]) <= 2 + 1e-6)
    assert np.all(np.abs(run.u) <= 6 + 1e-6)
    assert max_abs_product(run.x) <= 2.001


def test_constraint_form_of_the_steady_state_matches_the_closed_form(paper):
    """Eq. 8e-8f (x_a, u_a as variables tied by the equilibrium) gives the same loop as g_x, g_u."""
    controller = NmpcController(ControllerSettings(mu=1e8, use_closed_form_steady_state=False))
    run = run_closed_loop(controller, [-5.0, 0.0], [5.0], 50, "euler")
    reference = paper(1e8, "euler")
    assert run.status == ["ok"] * 50
    np.testing.assert_allclose(run.x, reference.x, atol=1e-4)


def test_target_change_takes_effect_at_the_next_step_without_rebuild():
    controller = NmpcController(ControllerSettings())
    builds = controller.nlp_builds
    x = np.array([0.5, 0.0])
    first = controller.step(x, [1.0])
    second = controller.step(x, [-3.0])
    assert controller.nlp_builds == builds
    assert first.y_a[0] > 0.5 and second.y_a[0] < -1.0
    assert second.u[0] < first.u[0]


def test_obstacle_change_takes_effect_at_the_next_step_without_rebuild():
    controller = NmpcController(ControllerSettings(keep_in=()))
    builds = controller.nlp_builds
    x = np.array([-5.0, 0.0])
    free = controller.step(x, [5.0])
    # a disc across the free path's first predicted points
    x1_pred = free.states[1]
    blocker = Ellipse(center=(x1_pred[0], x1_pred[1]), semi_axes=(0.6, 0.6))
    controller.reset()
    avoided = controller.step(x, [5.0], [blocker])
    assert controller.nlp_builds == builds
    depths = [blocker.depth(p) for p in avoided.states[1:]]
    assert max(depths) < 1e-3 < blocker.depth(x1_pred[:2])
    controller.reset()
    again = controller.step(x, [5.0], [])
    np.testing.assert_allclose(again.u, free.u, atol=1e-6)


def test_invalid_inputs_are_refused_and_change_nothing():
    controller = NmpcController(ControllerSettings())
    with pytest.raises(InputError, match="expected 2 values"):
        controller.step([1.0], [5.0])
    with pytest.raises(InputError, match="NaN"):
        controller.step([np.nan, 0.0], [5.0])
    with pytest.raises(InputError, match="target"):
        controller.step([0.0, 0.0], [np.inf])
    too_many = [Ellipse((float(i), 0.0), (0.1, 0.1)) for i in range(9)]
    with pytest.raises(RegionError, match="capacity"):
        controller.step([0.0, 0.0], [1.0], too_many)
    assert controller.regions == ()
    assert controller.step([0.0, 0.0], [1.0]).status == "ok"


def test_failed_solve_falls_back_to_the_shifted_plan_then_the_steady_input():
    controller = NmpcController(ControllerSettings())
    x = np.array([-5.0, 0.0])
    plan = controller.step(x, [5.0])
    controller.worker.interrupt()  # the last good plan, then every solver call fails (abandoned, core/nlp/worker.py)
    statuses, inputs = [], []
    for k in range(7):
        # the plant follows the plan (its states, then x_a): each candidate is judged from there
        res = controller.step(plan.states[min(k + 1, 5)], [5.0])
        statuses.append(res.status)
        inputs.append(res.u[0])
    assert statuses[:4] == ["fallback_shift"] * 4
    assert statuses[4:] == ["fallback_steady"] * 3
    # one enum, whose members are the strings that JSON files and diagnostics carry
    assert all(isinstance(s, StepStatus) and s.is_fallback for s in statuses)
    assert json.loads(json.dumps(statuses)) == statuses and str(statuses[0]) == "fallback_shift"
    np.testing.assert_allclose(inputs[:4], plan.inputs[1:, 0])
    np.testing.assert_allclose(inputs[4:], [plan.u_a[0]] * 3)


def test_no_plan_and_a_failed_solve_gives_the_safe_input_unless_it_predicts_a_violation():
    controller = NmpcController(ControllerSettings(max_iterations=1))
    res = controller.step([0.0, 0.0], [5.0])  # u = 0 keeps van der Pol at rest here
    assert res.status == "fallback_safe"
    assert res.u.tolist() == [0.0]
    # from (-5, 0), u = 0 swings x2 beyond its bound of 2 within the horizon: the recovery solve
    res = controller.step([-5.0, 0.0], [5.0])
    assert res.status == "fallback_recovery" and res.predicted_violation <= 1e-3, res.fallback_reason
    assert controller.fallback.predict(np.array([-5.0, 0.0]), np.zeros((5, 1)), controller.parameters(
        np.array([-5.0, 0.0]), np.array([5.0])))[1] > 0.1


def test_runtime_weight_change_needs_no_rebuild_and_structural_change_is_refused():
    controller = NmpcController(ControllerSettings())
    builds = controller.nlp_builds
    controller.update_settings(mu=0.0, kappa=10.0)
    assert controller.settings.mu == 0.0 and controller.nlp_builds == builds
    with pytest.raises(ValueError, match="horizon"):
        controller.update_settings(horizon=10)
    with pytest.raises(ValueError, match="mu"):
        controller.update_settings(mu=-1.0)


def test_general_hard_inequalities_are_part_of_Z_and_lambda_scales_the_steady_state():
    """`constraints: ['x1 <= 3']`: the loop never exceeds it; (x_a, u_a) in lambda Z gives x_a1 <= 3 lambda."""
    settings = ControllerSettings(constraints=("x1 <= 3",))
    controller = NmpcController(settings)
    run = run_closed_loop(controller, [-5.0, 0.0], [5.0], 60, "euler")
    assert run.status == ["ok"] * 60
    assert np.max(run.x[:, 0]) <= 3 + 1e-6
    assert run.y_a[-1, 0] == pytest.approx(3 * settings.steady_state_scale, abs=1e-4)
    assert run.x[-1, 0] == pytest.approx(3 * settings.steady_state_scale, abs=1e-3)
