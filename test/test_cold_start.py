"""The real-time path's start without a plan (Tiers.cold_start): FATROP on the ellipse tier from a
plan resting at the plant's output, then, only if that is unusable or penetrates, from the straight
line to the target; the IPOPT reference only when neither gives a usable plan, or when the regions
fit no tier.

The scenes come from the campaign (docs/campaign, seed 0).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from conftest import PAPER_TARGET, PAPER_X0, solver_calls

from nmpc_avoid_ros.bench.main import BICYCLE_ELLIPSES, VDP_ELLIPSES
from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.loop.closed_loop import make_plant, run_closed_loop
from nmpc_avoid_ros.core.nlp.search import Outcome, Start, plan_cost, solve_start
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon
from nmpc_avoid_ros.core.sample.candidates import Guess
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.guess_starts import guess_start
from nmpc_avoid_ros.core.sample.status import StepStatus
from nmpc_avoid_ros.core.sample.warm_start import initial_guess
from nmpc_avoid_ros.evaluation.campaign.scenarios import families, load_settings

#: campaign robot-0007: FATROP from the straight line used its 200 iterations in vain; the resting
#: plan converged to a lower cost (3866) than the IPOPT reference's start (4027)
ROBOT_0007 = {"x0": [4.166658085294912, 5.416388215345936, -0.4597393054455586, -0.2620438710245561],
              "target": [-4.652227218759113, -1.2363151806669066],
              "ellipses": [((-2.7621142084645403, 0.8406494381312491), (1.8600385052277928, 1.2785343973881242),
                            0.043101730749062754),
                           ((-7.909943408018712, 6.659081376521881), (1.4728686681371772, 1.3759231644437393),
                            1.9679499836273568),
                           ((1.4714907670348543, 3.4454530502999394), (0.46820869050014285, 1.2750675746013633),
                            0.1923260364021711)]}

#: campaign vdp-0336 (started from the straight line): the way to y* = 5.94 squeezes between an
#: ellipse and |x1 x2| <= 2; the plans of samples 3-5 balanced the two penalties at a keep-in depth of
#: 1.1e-3 (over the 1e-3 goal) while an input that stays clear existed
VDP_0336 = {"x0": [-0.2872201751467456, 0.8679714473761755], "target": [6.423580686312276],
            "ellipses": [((-3.9650493660771944, 1.6610760363401988), (0.7686199368423292, 0.5067914802599702),
                          2.070737325807088),
                         ((5.6070127987219225, 1.1657827733915942), (0.32317290776034385, 0.49476993356807397),
                          2.986316705941074),
                         ((2.0492698542836614, 0.41234760783442903), (1.2007945327049476, 0.41207297976398727),
                          1.3176781216781326),
                         ((-5.7055384875218635, 0.016996855797593913), (0.7495303065538432, 0.41306719171243633),
                          2.9738228750929756)]}


def shipped(family: str, **changes) -> ControllerSettings:
    """A family's shipped config (the real-time path) with a 2 s budget: a loaded test machine must
    not cut the solves whose outcome is asserted."""
    return load_settings(families()[family].config).replace(max_solve_time=2.0, **changes)


def ellipses(scene: dict, frame: str) -> list[Ellipse]:
    return [Ellipse(c, a, yaw, frame) for c, a, yaw in scene["ellipses"]]


def broken_guess(controller: NmpcController) -> Guess:
    """A guess of NaNs (what no guess builder makes; solve_start must refuse it before the solver)."""
    horizon, n, m = controller.nlp.layout.horizon, controller.model.n, controller.model.m
    return Guess("broken", np.array([math.nan]), np.full((horizon, n), math.nan), np.full((horizon, m), math.nan))


def reference_start_cost(controller: NmpcController, x: np.ndarray, y_t: np.ndarray) -> float:
    """The cost of the IPOPT reference's plan from the straight line (what the start was before)."""
    nlp = controller.cold_nlp
    par = controller.parameters(x, y_t, 0.0)
    w0, lam_x, lam_g = initial_guess(nlp, x, y_t, None, None, controller.settings, controller.model)
    result = solve_start(Start("reference", nlp, nlp.fill_slacks(w0, par), lam_x, lam_g, 200, True), par, 1e-6)
    assert result.solved
    return plan_cost(nlp, result.w, par)


def kept_cost(controller: NmpcController, x: np.ndarray, y_t: np.ndarray) -> float:
    """The cost of the plan the controller kept, evaluated on the regular NLP."""
    plan, nlp = controller.memory.plan, controller.nlp
    par = controller.parameters(x, y_t, 0.0)
    return plan_cost(nlp, nlp.fill_slacks(nlp.layout.join_w(plan.inputs, plan.states[1:], plan.y_a, None, x0=x),
                                          par), par)


def test_a_start_among_ellipses_is_solved_on_the_tier_from_the_resting_plan():
    controller = NmpcController(shipped("vdp"))
    controller.set_regions(VDP_ELLIPSES)
    x, y_t = np.array(PAPER_X0, float), np.array(PAPER_TARGET, float)
    result = controller.step(x, y_t, time=0.0)
    calls = solver_calls(controller, [result.search])
    # clear of the regions: the straight line is not tried
    assert calls == {"regular": 0, "reference": 0, "passage": 0, "tier0": 0, "tier2": 0, "tier4": 1}, calls
    report = result.search
    assert result.status == "ok" and (report.phase, report.kept) == ("cold", "rest"), report
    assert [t.label for t in report.tried] == ["rest"]
    reported = report.tried[0].cost
    assert kept_cost(controller, x, y_t) == pytest.approx(reported, rel=1e-5)
    assert kept_cost(controller, x, y_t) <= reference_start_cost(controller, x, y_t) * (1 + 1e-4)


def test_the_straight_line_is_tried_when_the_resting_plan_is_unusable():
    controller = NmpcController(shipped("vdp"), cold_guesses=lambda x, y_t: [
        broken_guess(controller), controller.escape.cold_guesses(x, y_t)[1]])
    controller.set_regions(VDP_ELLIPSES)
    straight = controller.escape.cold_guesses(np.array(PAPER_X0, float), np.array(PAPER_TARGET, float))[1]
    assert straight.label == "straight"
    result = controller.step(PAPER_X0, PAPER_TARGET, time=0.0)
    calls = solver_calls(controller, [result.search])
    assert calls["tier4"] == 1 and calls["reference"] == 0, calls  # the broken guess never reaches FATROP
    assert result.status == "ok", result.status
    report = result.search
    assert report.kept == "straight" and [(t.label, t.outcome) for t in report.tried] == [
        ("broken", "unusable"), ("straight", "kept")], report
    assert report.tried[0].solver_status == "non_finite_guess"


def test_the_resting_plan_carries_a_start_where_the_straight_line_fails():
    controller = NmpcController(shipped("robot"))
    controller.set_regions(ellipses(ROBOT_0007, "output"))
    x, y_t = np.array(ROBOT_0007["x0"]), np.array(ROBOT_0007["target"])
    result = controller.step(x, y_t, time=0.0)
    calls = solver_calls(controller, [result.search])
    assert calls["reference"] == 0 and calls["tier4"] == 1, calls
    assert result.status == "ok" and (result.search.phase, result.search.kept) == ("cold", "rest"), result.search
    assert kept_cost(controller, x, y_t) <= reference_start_cost(controller, x, y_t) * (1 + 1e-4)
    # the straight line alone: FATROP stops at its iteration budget deep inside a region (cost 4e7)
    par = controller.parameters(x, y_t, 0.0)
    start = guess_start(controller.tiered, x, par, controller.escape.cold_guesses(x, y_t)[1], budget=200, cold=True)
    line = solve_start(start, par, controller.settings.feasibility_tolerance)
    assert line.label == "straight" and (not line.usable or line.depth > 1e-3), line


def test_when_no_guess_is_usable_the_reference_solves_the_start():
    controller = NmpcController(shipped("vdp"), cold_guesses=lambda x, y_t: [broken_guess(controller)] * 2)
    controller.set_regions(VDP_ELLIPSES)
    result = controller.step(PAPER_X0, PAPER_TARGET, time=0.0)
    calls = solver_calls(controller, [result.search])
    assert calls["reference"] == 1 and calls["tier4"] == 0, calls  # a non-finite guess never reaches FATROP
    assert result.status == "ok" and [t.solver_status for t in result.search.tried][:2] == ["non_finite_guess"] * 2
    assert result.search.kept == "reference", result.search
    # the loop goes on from the reference's plan on the tier
    after = controller.step(result.states[1], PAPER_TARGET, time=0.5)
    calls = solver_calls(controller, [result.search, after.search])
    assert after.status == "ok" and calls["reference"] == 1 and calls["tier4"] == 1, calls


def test_regions_that_fit_no_tier_start_on_the_reference():
    square = Polygon(((1.0, 1.2), (1.6, 1.2), (1.6, 1.8), (1.0, 1.8)))
    controller = NmpcController(shipped("vdp"))
    controller.set_regions(list(VDP_ELLIPSES[:2]) + [square])
    result = controller.step(PAPER_X0, PAPER_TARGET, time=0.0)
    calls = solver_calls(controller, [result.search])
    assert calls["reference"] == 1 and sum(v for k, v in calls.items() if k.startswith("tier")) == 0, calls
    assert result.status == "ok" and [t.label for t in result.search.tried] == ["reference"], result.search


def test_a_squeeze_between_an_ellipse_and_the_keep_in_stays_within_the_goal():
    # the start the campaign run had: from the straight line (the resting plan takes another way)
    controller = NmpcController(shipped("vdp"), cold_guesses=lambda x, y_t: [
        g for g in controller.escape.cold_guesses(x, y_t) if g.label == "straight"])
    results = []
    run = run_closed_loop(controller, VDP_0336["x0"], VDP_0336["target"], 30,
                          regions=lambda k: ellipses(VDP_0336, "state") if k == 0 else None,
                          on_step=lambda k, r: results.append(r))
    keep_in = np.max(np.abs(run.x[1:, 0] * run.x[1:, 1])) - 2.0
    obstacles = max(e.depth(x) for e in ellipses(VDP_0336, "state") for x in run.x[1:])
    assert max(keep_in, obstacles) <= 1e-3, (keep_in, obstacles)
    # the controller tracks y_t's projection y* = 5.94 (core/nlp/projection.py): without the pull of 6.42 the
    # plan no longer squeezes (it predicted 1.1e-3 before and gave way to the recovery input then), and
    # the loop goes on to y*
    assert all(r.target == pytest.approx([5.94]) for r in results)
    assert run.x[-1, 0] > 5.0


def test_a_start_tries_no_further_guess_once_the_sample_budget_is_spent():
    """The budget rule (core/nlp/search.py): with the sample's search time spent, the first start still runs (a sample
    needs a plan), no further one. The time is spent here before the search, by a guess seam that sleeps it away:
    spent by a solve, it hung on how long an abandoned call and its fork took (the target projection's solve used
    to take most of a 10 ms budget; without it, all three starts ran in 3 ms)."""
    settings = shipped("vdp").replace(max_solve_time=0.02)  # a first start's budget: 0.2 s
    guesses = NmpcController(settings).escape.cold_guesses

    def slow_guesses(x: np.ndarray, y_t: np.ndarray) -> list[Guess]:
        time.sleep(controller.sample_budget())
        return guesses(x, y_t)

    controller = NmpcController(settings, cold_guesses=slow_guesses)
    controller.set_regions(VDP_ELLIPSES)
    x, y_t = np.array(PAPER_X0, float), np.array(PAPER_TARGET, float)
    result = controller.step(x, y_t, time=0.0)
    calls, tried = solver_calls(controller, [result.search]), result.search.tried
    # the resting plan is solved; neither the straight line nor the reference is started
    assert calls["tier4"] == 1 and calls["reference"] == 0, calls
    assert [t.label for t in tried] == ["rest", "straight", "reference"], tried
    assert all(t.outcome is Outcome.NOT_TRIED for t in tried[1:]), tried


#: campaign scene bicycle-0024 (the car at rest, no obstacle): its start x0 and goal pose
BICYCLE_0024 = {"x0": [-6.355656512209264, 2.870022962987896, 1.9523459771080096],
                "goal": [-1.7294034884835217, 4.221326421816794, -1.3779670930499923]}


def bicycle_controller(rollout: bool = True, **changes) -> tuple[ControllerSettings, NmpcController]:
    """config/bicycle.yaml's controller, interpreted, with `changes` to its settings; `rollout` False: its cold starts
    without the rollout guess (the resting plan first, as before core/sample/rollout.py)."""
    params = load_params_file("config/bicycle.yaml").section("controller")
    settings = ControllerSettings.from_params(params).replace(codegen=False, codegen_background=False, **changes)
    controller = NmpcController(settings)
    if not rollout:
        guesses = controller.escape.cold_guesses
        controller.cold_guesses = lambda x, y_t: [g for g in guesses(x, y_t) if g.label != "rollout"]
    return settings, controller


def test_a_fast_path_cold_start_gets_its_real_time_budget_and_the_reference_its_turn():
    """Campaign scene bicycle-0024: each fast-path cold start is cut at max_solve_time, so the reference would still
    answer the sample (FATROP 1.1.8 did not return from the resting plan there before core/nlp/stagewise.py's
    RANK_TOLERANCE: the first start took the whole cold budget, sample after sample, and the car never moved)."""
    settings, controller = bicycle_controller()
    x0, goal = np.array(BICYCLE_0024["x0"]), np.array(BICYCLE_0024["goal"])
    result = controller.step(x0, goal, (), time=0.0)
    assert result.status == StepStatus.OK
    fast = [t for t in result.search.tried if t.label != "reference" and t.solver_called]
    assert all(t.seconds <= settings.max_solve_time + 0.05 for t in fast)
    kept = [t.label for t in result.search.tried if t.outcome.value == "kept"]
    first = result.search.tried[0]
    assert len(kept) == 1 and (kept[0] != first.label) == (first.outcome.value != "kept")


def test_fatrop_solves_the_car_at_rest_from_its_resting_plan():
    """Campaign scene bicycle-0024 with the config's former integration_steps 4: FATROP converges from the plan resting
    where the car stands (kept, no other start). Before RANK_TOLERANCE (core/nlp/stagewise.py) it never returned: at
    v ~ 1e-4 the heading rows of the terminal equality passed FATROP's default rank test with a tiny pivot, and no
    primal regularisation made the reduced Hessian positive definite; the call was abandoned at max_solve_time."""
    settings, controller = bicycle_controller(rollout=False, integration_steps=4)
    result = controller.step(np.array(BICYCLE_0024["x0"]), np.array(BICYCLE_0024["goal"]), (), time=0.0)
    first = result.search.tried[0]
    assert (first.label, first.solver_status, first.outcome) == ("rest", "0", Outcome.KEPT), result.search.tried
    assert first.seconds < settings.max_solve_time


def test_the_car_starts_cold_from_its_own_model_driven_towards_the_goal():
    """The bench's car among its 4 ellipses (bench/main.py `shipped/bicycle_4_ellipses`): the cold start keeps the
    rollout guess (core/sample/rollout.py), which meets the dynamics and heads for the goal, in a fraction of the
    iterations the resting plan takes (measured: 15 against 116), and its plan costs no more."""
    regions = list(BICYCLE_ELLIPSES)
    x0, goal = np.array([-4.0, -3.0, 0.0]), np.array([3.0, 2.0, 0.0])
    runs = {}
    for rollout in (True, False):
        _, controller = bicycle_controller(rollout=rollout, max_solve_time=2.0)
        result = controller.step(x0, goal, regions, time=0.0)
        first = result.search.tried[0]
        assert first.outcome == Outcome.KEPT and result.status == StepStatus.OK, result.search.tried
        runs[rollout] = (first.label, result.iterations, first.cost)
    assert runs[True][0] == "rollout" and runs[False][0] == "rest"
    assert runs[True][1] <= runs[False][1] / 3
    assert runs[True][2] <= runs[False][2] * (1 + 1e-9)  # with the steering-rate limit both find the same plan


def test_the_car_parks_at_its_goal_without_a_fallback():
    """Campaign scene bicycle-0024 on the continuous plant: the car reaches its goal pose and every sample's FATROP
    solve returns. Before RANK_TOLERANCE the shifted plan near the goal (v ~ 0) hung FATROP every other sample: 58
    fallbacks in 200 samples, the IPOPT reference answering in between."""
    settings, controller = bicycle_controller()
    model = settings.build_model()
    plant = make_plant("continuous", model, settings)
    x, goal = np.array(BICYCLE_0024["x0"]), np.array(BICYCLE_0024["goal"])
    statuses = []
    for k in range(90):
        result = controller.step(x, goal, (), time=k * settings.sample_time)
        statuses.append(result.status)
        x = plant.advance(x, np.asarray(result.u), settings.sample_time)
    assert all(s == StepStatus.OK for s in statuses), statuses
    assert np.linalg.norm(model.output_error(x, goal)) < 0.05  # the output is the pose x


#: campaign scene bicycle-0011: the car at rest facing away from its goal pose, 4 ellipses (two of them across the way)
BICYCLE_0011 = {"x0": [-2.418849095835106, -2.8369122059315197, 2.759175607287441],
                "goal": [-8.085699866733849, -4.2106939889952315, 1.1740381740578654],
                "ellipses": [((-5.097365730158833, -4.020529178998495), (1.6595889830529682, 0.9462972632230005),
                              2.146019465901913),
                             ((-4.465313515782553, -3.5756299761652612), (0.9395079436199979, 1.9968618621029153),
                              2.593795718489984),
                             ((4.9686665807955634, 4.1105841727689025), (0.7437162776584737, 0.7517587796845995),
                              3.1200378920839436),
                             ((-3.156601181362248, 4.877003688691204), (0.43139807974659683, 1.4661562410158262),
                              2.934292637698942)]}


def test_a_cold_start_of_the_car_with_rate_limits_gets_the_iterations_it_needs():
    """Campaign scene bicycle-0011 with steering-rate and acceleration limits: from the resting plan FATROP needs about
    220 iterations on the 4-ellipse tier; a cold start capped at the regular 200 stopped short every sample (and
    IPOPT's reference too), so the car never moved. Cold FATROP starts of such a model get FAST_COLD_ITERATIONS
    (core/nlp/stagewise.py), still cut at max_solve_time (here long: interpreted solvers, the iterations under test)."""
    _, controller = bicycle_controller(rollout=False, input_rate_max=(1.0, 1.5), max_solve_time=2.0)
    regions = [Ellipse(center, axes, yaw, "output") for center, axes, yaw in BICYCLE_0011["ellipses"]]
    result = controller.step(np.array(BICYCLE_0011["x0"]), np.array(BICYCLE_0011["goal"]), regions, time=0.0)
    first = result.search.tried[0]
    assert (first.label, first.solver_status, first.outcome) == ("rest", "0", Outcome.KEPT), result.search.tried
    assert result.status == StepStatus.OK


def test_the_cars_cold_and_escape_guesses_are_its_own_model_within_its_rate_limits():
    """core/sample/rollout.py: the car's rollout guess and its escape guesses (through a detour waypoint, towards the
    point beyond the block) meet the model's own discrete dynamics exactly and change each input by at most one rate
    step from rest, where a polyline guess (the other models') meets neither."""
    settings, controller = bicycle_controller(input_rate_max=(1.0, 1.5))
    controller.set_regions(list(BICYCLE_ELLIPSES))
    x, goal = np.array([-4.0, -3.0, 0.0]), np.array([3.0, 2.0, 0.0])
    escapes = controller.escape.guesses(x, x.copy(), goal, controller.parameters(x, goal, 0.0), controller.regions)
    detours = [g for g in escapes if "_of_region" in g.label]
    assert detours and all(g.label.startswith("beyond") for g in escapes)  # the ellipses block: no manoeuvres
    step = controller.model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)
    rate = np.array(settings.input_rate_max) * settings.sample_time
    for guess in [controller.escape.cold_guesses(x, goal)[0], *escapes]:
        before = np.vstack([x, guess.states[:-1]])
        moved = np.array([np.asarray(step(a, u)).ravel() for a, u in zip(before, guess.inputs)])
        assert np.max(np.abs(moved - guess.states)) < 1e-9, guess.label
        assert np.all(np.abs(np.diff(np.vstack([np.zeros(2), guess.inputs]), axis=0)) <= rate + 1e-12), guess.label
    left, right = detours[0], detours[1]
    assert np.max(np.abs(left.states - right.states)) > 0.1  # either side of the region: two ways
