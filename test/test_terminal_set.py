"""The general scheme's terminal ingredients (core/problem/terminal.py) and `terminal: set` (core/nlp/terminal.py)."""

from __future__ import annotations

import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import max_abs_product, run_closed_loop, settling_step
from nmpc_avoid_ros.core.nlp import terminal as nlp_terminal
from nmpc_avoid_ros.core.nlp.gauss_newton import upper_cholesky
from nmpc_avoid_ros.core.nlp.stagewise import make_nlp
from nmpc_avoid_ros.core.nlp.terminal import ShiftedTail, terminal_ingredients, terminal_problem
from nmpc_avoid_ros.core.problem.annulus import shell_decreases
from nmpc_avoid_ros.core.problem.intervals import interval_evaluate
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.terminal import TerminalIngredients, local_controller
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import StepStatus
from nmpc_avoid_ros.core.sample.step_result import StepResult

SETTINGS = ControllerSettings(terminal="set")
MODEL = make_model("van_der_pol")


@pytest.fixture(scope="module")
def paper_set(tmp_path_factory):
    """The paper's ingredients, computed once (~20 s) into a cache of this module's own, as a controller does into
    the user's (the tests below read them from the process's copy, as a controller does)."""
    settings = SETTINGS.replace(cache_dir=str(tmp_path_factory.mktemp("terminal_cache")))
    return settings, terminal_ingredients(settings, MODEL), terminal_problem(settings, MODEL)


@pytest.mark.slow
def test_computed_within_a_minute_and_cached_on_disk(paper_set):
    settings, ingredients, _ = paper_set
    assert ingredients.seconds < 60 and ingredients.cache == "computed"
    files = list((Path(settings.cache_dir) / "terminal").glob("*.json"))
    assert len(files) == 1
    again = TerminalIngredients.from_dict(json.loads(files[0].read_text()))
    for y in (-5.9, -1.0, 0.0, 4.2):
        np.testing.assert_array_equal(again.cost_matrix(y), ingredients.cost_matrix(y))
        assert again.alpha(y) == ingredients.alpha(y)


def test_fitted_alpha_is_below_the_certified_one_on_the_grid(paper_set):
    _, ingredients, _ = paper_set
    fitted = np.array([ingredients.alpha(y) for y in ingredients.grid_y])
    assert np.all(fitted <= ingredients.grid_alpha) and np.all(fitted > 0)
    assert ingredients.midpoint_ratio >= 1


def test_symbolic_ingredients_equal_the_numeric_ones(paper_set):
    _, ingredients, _ = paper_set
    y = ca.SX.sym("y", 1)
    function = ca.Function("f", [y], [ingredients.symbolic(y), *ingredients.levels(y, None)])
    for value in (-5.94, -2.5, 0.3, 5.0):
        p, alpha = function(value)
        np.testing.assert_allclose(np.asarray(p), ingredients.cost_matrix(value), rtol=1e-12)
        assert float(alpha) == pytest.approx(ingredients.alpha(value), rel=1e-12)


def test_shell_certificate_refuses_a_level_where_a_sampled_state_breaks_the_decrease(paper_set):
    """At y_a = 5 the decrease fails on V_f = 1300 for some sampled state (measured: from about 1220 on): the
    branch and bound must not certify that shell, and does certify the level in use."""
    _, ingredients, problem = paper_set
    p = ingredients.cost_matrix(5.0)
    k = problem.gain(5.0, p, ingredients.margin)
    x_s, u_s = problem.steady_state(5.0)
    w, v = np.linalg.eigh(p)
    angles = np.linspace(0, 2 * np.pi, 720)
    e = v @ (np.vstack([np.cos(angles), np.sin(angles)]) / np.sqrt(w)[:, None]) * np.sqrt(1300.0)
    u = u_s[:, None] + k @ e
    after = np.asarray(problem.step.map(angles.size)(x_s[:, None] + e, u)) - x_s[:, None]
    change = np.einsum("ik,ij,jk->k", after, p, after) - 1300.0 + (e * e).sum(0) + ((u - u_s[:, None]) ** 2).sum(0)
    assert change.max() > 0
    inner = ingredients.alpha(5.0) / 2
    assert not shell_decreases(problem.step, problem.q, problem.r, p, k, x_s, u_s, inner, 1300.0)
    assert shell_decreases(problem.step, problem.q, problem.r, p, k, x_s, u_s, inner, ingredients.alpha(5.0))


def test_interval_bounds_contain_sampled_values():
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [ca.vertcat(x[0] * x[1] ** 3 - ca.sin(x[0]) / (2 + x[1]), ca.cos(x[1]) * ca.exp(x[0]))])
    lo, hi = np.array([-1.0, 0.5]), np.array([0.7, 1.5])
    bounds = interval_evaluate(f, [lo], [hi])[0]
    rng = np.random.default_rng(0)
    values = np.array([np.asarray(f(rng.uniform(lo, hi))).ravel() for _ in range(500)])
    assert np.all(bounds[:, 0] <= values.min(axis=0)) and np.all(values.max(axis=0) <= bounds[:, 1])


@settings(max_examples=300, deadline=None, derandomize=True)
@given(y_a=st.floats(-5.94, 5.94), direction=st.floats(0, 2 * np.pi), level=st.floats(0, 1))
def test_local_controller_keeps_the_set_and_decreases_v_f_by_the_stage_cost(paper_set, y_a, direction, level):
    """Assumption 3.3-3.4 on the nonlinear Euler map: from a state in {V_f <= alpha(y_a)}, kappa stays in Z, the
    next state in the set, and V_f(x+) - V_f(x) <= -l(x - x_a, kappa - u_a)."""
    settings_, ingredients, problem = paper_set
    p, alpha = ingredients.cost_matrix(y_a), ingredients.alpha(y_a)
    w, v = np.linalg.eigh(p)
    unit = np.array([np.cos(direction), np.sin(direction)])
    e = v @ (unit / np.sqrt(w)) * np.sqrt(level * alpha)  # V_f(e) = level alpha
    x_a, u_a = problem.steady_state(y_a)
    x = x_a + e
    u = local_controller(problem, ingredients, x, y_a)
    assert np.all(np.abs(x) <= [6, 2]) and abs(u[0]) <= 6
    x_next = np.asarray(MODEL.discrete(0.5)(x, u)).ravel()
    v_f = e @ p @ e
    v_f_next = (x_next - x_a) @ p @ (x_next - x_a)
    stage = e @ e + float((u - u_a) @ (u - u_a))
    assert v_f_next <= alpha * (1 + 1e-9)
    assert v_f_next - v_f <= -stage + 1e-9 * max(1.0, v_f)


def test_paper_run_with_the_terminal_set(paper_set):
    settings_, _, _ = paper_set
    run = run_closed_loop(NmpcController(settings_), [-5.0, 0.0], [5.0], 50, "euler")
    assert run.status == ["ok"] * 50
    assert max_abs_product(run.x) <= 2.0005
    # no later than the equality's 33 (docs/terminal_set.md)
    assert settling_step(run.x[:, 0], 5.0, 0.05) <= 33
    # the decrease with the set's shifted candidate (u(1..N-1), kappa(x(N))) holds at every sample
    assert sum(c["checked"] for c in run.certificate) == 49
    assert run.certificate[-1]["certificate_violations"] == 0
    # each sample carries V_f of its plan and alpha(y_a): x(N) inside the set (StepResult.terminal_cost, _level)
    v_f, alpha = run.terminal.T
    assert np.all(alpha > 0) and np.all(v_f >= 0) and np.all(v_f <= alpha * (1 + 1e-6))
    assert run.to_json()["terminal"]["level"] == alpha.tolist()


def test_shifted_tail_is_the_local_controller_and_keeps_the_candidate_in_the_set(paper_set):
    settings_, ingredients, problem = paper_set
    tail = ShiftedTail(settings_, MODEL)
    x_a, u_a = problem.steady_state(2.0)
    x_n = x_a + np.array([0.05, -0.03])
    u, x_next = tail(x_n, np.array([2.0]), x_a, u_a)
    np.testing.assert_allclose(u, local_controller(problem, ingredients, x_n, 2.0))
    p = ingredients.cost_matrix(2.0)
    assert (x_next - x_a) @ p @ (x_next - x_a) < (x_n - x_a) @ p @ (x_n - x_a) <= ingredients.alpha(2.0)
    equality = ShiftedTail(ControllerSettings(), MODEL)
    u, x_next = equality(x_n, np.array([2.0]), x_a, u_a)
    np.testing.assert_array_equal(u, u_a)
    np.testing.assert_array_equal(x_next, x_a)


def test_terminal_set_admits_a_wider_steady_output_range_than_the_equality(paper_set):
    """From the paper's x0 at N = 5 the set lets y_a move further than x(N) = x_a does (docs/terminal_set.md)."""
    from nmpc_avoid_ros.tools.terminal_sets import Feasibility

    settings_, _, _ = paper_set
    equality = Feasibility(5, "equality", settings_).y_a_range(np.array([-5.0, 0.0]))
    with_set = Feasibility(5, "set", settings_).y_a_range(np.array([-5.0, 0.0]))
    assert with_set[0] < equality[0] - 0.03 and with_set[1] > equality[1] + 0.2


def test_upper_cholesky_factor_of_a_symbolic_matrix():
    p = ca.SX.sym("p", 3, 3)
    factor = ca.Function("r", [p], [upper_cholesky(p)])
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 3))
    spd = a @ a.T + 3 * np.eye(3)
    r = np.asarray(factor(spd))
    np.testing.assert_allclose(r.T @ r, spd, rtol=1e-12)
    assert np.allclose(np.tril(r, -1), 0) and np.all(np.diag(r) > 0)


@pytest.mark.parametrize("solver", ["sqp", "sqp_hpipm"])
def test_sqp_hessian_with_the_terminal_set_is_positive_semidefinite(paper_set, solver):
    """The SQP paths' Hessian (core/nlp/gauss_newton.py): V_f and the set row as least squares, so it is positive
    semi-definite at any point and multipliers; the exact Hessian of V_f = e'P(y_a)e is not."""
    settings_, _, _ = paper_set
    nlp = make_nlp(settings_.replace(solver=solver))
    hessian = nlp.solver.get_function("nlp_hess_l")
    rng = np.random.default_rng(0)
    for _ in range(5):
        w = rng.uniform(-3, 3, nlp.layout.n_w)
        w[nlp.layout.y_index] = rng.uniform(-5, 5)
        lam_g = rng.uniform(-1e3, 1e3, nlp.lbg.size)
        h = np.asarray(hessian(w, np.zeros(nlp.parameter_count), 1.0, lam_g))
        assert np.linalg.eigvalsh((h + h.T) / 2).min() >= -1e-6 * np.abs(h).max()
    exact = ca.Function("h", [nlp.problem["x"], nlp.problem["p"]], [ca.hessian(nlp.problem["f"], nlp.problem["x"])[0]])
    h = np.asarray(exact(w, np.zeros(nlp.parameter_count)))
    assert np.linalg.eigvalsh((h + h.T) / 2).min() < -1e-6 * np.abs(h).max()


@pytest.mark.parametrize("solver", ["sqp", "sqp_hpipm"])
@pytest.mark.parametrize("mu", [1e8, 0.0])
def test_sqp_paths_with_the_terminal_set_run_the_ipopt_loop(paper_set, solver, mu):
    """With the least-squares V_f the SQP paths settle on the paper's run with IPOPT's set loop and no fallback
    (before: 4 and 1 of 50 samples solved); a sample may end `unconverged` as on these paths with the equality."""
    settings_, _, _ = paper_set
    runs = [run_closed_loop(NmpcController(settings_.replace(solver=path, mu=mu)), [-5.0, 0.0], [5.0], 50, "euler")
            for path in (solver, "ipopt")]
    assert set(runs[0].status) <= {"ok", "unconverged"} and runs[0].status.count("ok") >= 38
    assert settling_step(runs[0].x[:, 0], 5.0, 0.05) == settling_step(runs[1].x[:, 0], 5.0, 0.05)
    np.testing.assert_allclose(runs[0].x[-10:], runs[1].x[-10:], atol=1e-3)  # on the way an unconverged iterate
    if mu:
        assert max_abs_product(runs[0].x) <= 2.0005
    assert runs[0].certificate[-1]["certificate_violations"] == 0


def test_fatrop_path_with_the_terminal_set_runs_the_ipopt_loop(paper_set):
    """The stage-wise formulation (V_f, the set row and x(N)'s slack at stage N-1) gives IPOPT's loop."""
    settings_, _, _ = paper_set
    runs = [run_closed_loop(NmpcController(settings_.replace(solver=solver)), [-5.0, 0.0], [5.0], 50, "euler")
            for solver in ("fatrop", "ipopt")]
    assert runs[0].status == ["ok"] * 50
    np.testing.assert_allclose(runs[0].x, runs[1].x, atol=1e-4)
    assert runs[0].certificate[-1]["certificate_violations"] == 0


def test_models_without_the_ingredients_are_refused_with_the_reason():
    with pytest.raises(ConfigError, match="closed-form steady state"):
        terminal_problem(SETTINGS.replace(model="unicycle"), make_model("unicycle"))
    with pytest.raises(ConfigError, match="hard constraints"):
        terminal_problem(SETTINGS.replace(constraints=("x1 + x2 <= 3",)), MODEL)
    with pytest.raises(ConfigError, match="input_rate_max"):
        terminal_problem(SETTINGS.replace(input_rate_max=(4.0,)), MODEL)


ROBOT = make_model("double_integrator_2d")
ROBOT_SETTINGS = ControllerSettings(model="double_integrator_2d", terminal="set", keep_in=(), sample_time=0.2,
                                    state_weights=(1.0,) * 4, input_weights=(1.0,) * 2)


@pytest.fixture(scope="module")
def robot_set(tmp_path_factory):
    settings = ROBOT_SETTINGS.replace(cache_dir=str(tmp_path_factory.mktemp("cache")))
    return settings, terminal_ingredients(settings, ROBOT), terminal_problem(settings, ROBOT)


def test_cache_round_trip_of_a_linear_model(robot_set, monkeypatch):
    settings_, ingredients, _ = robot_set
    monkeypatch.setattr(nlp_terminal, "_IN_PROCESS", {})  # as a new process: read from the disk cache
    again = terminal_ingredients(settings_, ROBOT)
    assert again.cache == "hit"
    np.testing.assert_array_equal(again.cost_matrix([1.0, 2.0]), ingredients.cost_matrix([1.0, 2.0]))
    np.testing.assert_array_equal(again.box_rows, ingredients.box_rows)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(y_a=st.tuples(st.floats(-9.9, 9.9), st.floats(-9.9, 9.9)),
       direction=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda d: np.linalg.norm(d) > 1e-3),
       level=st.floats(0, 1))
def test_linear_model_keeps_its_set_in_z_and_decreases_v_f(robot_set, y_a, direction, level):
    """The double integrator (linear, two outputs): one P for every y_a, the ellipsoid inside Z by its box rows."""
    settings_, ingredients, problem = robot_set
    x_a, u_a = problem.steady_state(np.array(y_a))
    p, alpha = ingredients.cost_matrix(y_a), ingredients.alpha(y_a, np.concatenate([x_a, u_a]))
    e = np.array(direction) / np.sqrt(np.array(direction) @ p @ np.array(direction)) * np.sqrt(level * alpha)
    x = x_a + e
    u = local_controller(problem, ingredients, x, np.array(y_a))
    lo = np.array(settings_.state_min + settings_.input_min)
    hi = np.array(settings_.state_max + settings_.input_max)
    z = np.concatenate([x, u])
    assert np.all(lo - 1e-9 <= z) and np.all(z <= hi + 1e-9)
    x_next = np.asarray(ROBOT.discrete(0.2)(x, u)).ravel()
    v_f, v_f_next = e @ p @ e, (x_next - x_a) @ p @ (x_next - x_a)
    assert v_f_next - v_f <= -(e @ e + (u - u_a) @ (u - u_a)) + 1e-9 * max(1.0, v_f)


def test_linear_model_with_the_set_settles_sooner_at_a_shorter_horizon(robot_set):
    """Measured (docs/terminal_set.md): from rest at the origin to y_t = (5, 3), |y - y_t| < 0.05 from sample 25
    with the set at N = 4 and 34 at N = 2 (below n = 4: refused with the equality), 37 with the equality at N = 4."""
    settings_, _, _ = robot_set

    def settle(run):
        error = np.linalg.norm(run.x[:, :2] - [5.0, 3.0], axis=1)
        return next(k for k in range(len(error)) if np.all(error[k:] < 0.05))

    runs = {(t, n): run_closed_loop(NmpcController(settings_.replace(terminal=t, horizon=n)), [0.0] * 4, [5.0, 3.0],
                                    60, "euler") for t, n in (("set", 2), ("equality", 4))}
    assert all(run.status == ["ok"] * 60 for run in runs.values())
    assert settle(runs["set", 2]) < settle(runs["equality", 4])
    assert runs["set", 2].certificate[-1]["certificate_violations"] == 0


def _first_plan(settings_):
    controller = NmpcController(settings_)
    result = controller.step([-5.0, 0.0], [5.0])
    return controller, result, controller.memory.plan


def test_plan_continues_with_the_local_controller_and_the_result_carries_v_f(paper_set):
    """With the set a kept plan runs on after x(N) with kappa(x, y_a) (Plan.tail: the warm start's shift and the
    fallback's `shift` candidate), and the result carries V_f and alpha; the equality's plan rests at (u_a, x_a)."""
    settings_, ingredients, problem = paper_set
    controller, result, plan = _first_plan(settings_)
    x_n, y_a = plan.states[-1], plan.y_a
    inputs, states = plan.shifted(2)
    u = local_controller(problem, ingredients, x_n, y_a)
    np.testing.assert_allclose(inputs[-2], u, rtol=1e-12)
    np.testing.assert_allclose(states[-2], np.asarray(problem.step(x_n, u)).ravel(), rtol=1e-12)
    np.testing.assert_allclose(inputs[-1], local_controller(problem, ingredients, states[-2], y_a), rtol=1e-12)
    e = x_n - plan.x_a
    assert result.terminal_cost == pytest.approx(e @ ingredients.cost_matrix(y_a) @ e, rel=1e-12)
    assert result.terminal_level == pytest.approx(ingredients.alpha(y_a), rel=1e-12)
    assert result.terminal_inside is True
    _, result, plan = _first_plan(settings_.replace(terminal="equality"))
    assert plan.tail is None and np.isnan(result.terminal_cost) and result.terminal_inside is None
    inputs, states = plan.shifted(2)
    np.testing.assert_array_equal(inputs[-2:], [plan.u_a, plan.u_a])
    np.testing.assert_array_equal(states[-2:], [plan.x_a, plan.x_a])


def test_budget_cut_iterate_and_fallback_candidates_continue_with_kappa(paper_set):
    """A budget-cut iterate's shift ends with kappa(x(N)) (core/sample/warm_start.py), and the fallback's `steady`
    candidate under the set is the local controller from the current state (core/sample/fallback.py)."""
    from nmpc_avoid_ros.core.sample.warm_start import initial_guess

    settings_, ingredients, problem = paper_set
    controller, _, plan = _first_plan(settings_)
    nlp, x = controller.nlp, plan.states[1]
    w = nlp.layout.join_w(plan.inputs, plan.states[1:], plan.y_a, None, x0=plan.states[0])
    pending = (w, np.zeros(nlp.layout.n_w), np.zeros(nlp.lbg.size))
    guess = initial_guess(nlp, x, np.array([5.0]), None, pending, settings_, MODEL, tail=controller._tail)[0]
    U, X, _, _ = nlp.layout.split_w(guess)
    u = local_controller(problem, ingredients, plan.states[-1], plan.y_a)
    np.testing.assert_allclose(U[-1], u, rtol=1e-12)
    np.testing.assert_allclose(X[-1], np.asarray(problem.step(plan.states[-1], u)).ravel(), rtol=1e-12)
    local = controller._tail.rollout(x, plan.y_a, plan.x_a, plan.u_a, settings_.horizon, [-6.0], [6.0])
    np.testing.assert_allclose(local[0][0], local_controller(problem, ingredients, x, plan.y_a), rtol=1e-12)
    par = controller.parameters(x, np.array([5.0]))
    choice = controller.fallback.choose(x, par, None, local[0], False, recover=False)
    assert choice.kind == "steady" and np.array_equal(choice.inputs, local[0])
    np.testing.assert_allclose(choice.states[1:], local[1], rtol=1e-9)


def test_diagnostics_carry_the_terminal_cost_and_level():
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticStatus

    from nmpc_avoid_ros.nodes.controller_views import diagnostic_array

    def values(result):
        msg = diagnostic_array("/c", Time(), DiagnosticStatus.OK, "ok", {}, result, 0.0, 0.0, None)
        return {v.key: v.value for v in msg.status[0].values}

    result = StepResult(np.zeros(1), np.zeros((6, 2)), np.zeros((5, 1)), np.zeros(1), np.zeros(2), np.zeros(1),
                        0.0, 0.0, 0.0, StepStatus.OK, "0", 3, 1e-3)
    equality = values(result)
    assert (equality["terminal_cost"], equality["terminal_level"], equality["terminal_inside"]) == ("nan", "nan", "")
    result.terminal_cost, result.terminal_level = 12.5, 40.0
    keys = ("terminal_cost", "terminal_level", "terminal_inside")
    assert tuple(values(result)[key] for key in keys) == ("12.5", "40", "True")
