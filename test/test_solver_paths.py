"""The fast solver paths: same closed loop as the IPOPT reference, compiled-code cache, budget.

Speed itself is measured by the benchmark (bench/, BENCHMARKS.md), not here.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import SOLVERS, ControllerSettings
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import SETTLING_TOLERANCE, max_abs_product, run_closed_loop, settling_step
from nmpc_avoid_ros.core.nlp.stagewise import StagewiseNlp
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import StepStatus

FAST = [s for s in SOLVERS if s != "ipopt"]
#: the paper problem exactly: its two keep-in regions, no obstacle slots
PAPER = ControllerSettings(max_ellipses=0, max_polygons=0)


@functools.cache
def paper_loop(solver: str, mu: float, plant: str, max_iterations: int = 200):
    controller = NmpcController(PAPER.replace(solver=solver, mu=mu, max_iterations=max_iterations))
    return run_closed_loop(controller, [-5.0, 0.0], [5.0], 50, plant), controller


@pytest.mark.parametrize("solver", FAST)
@pytest.mark.parametrize("mu,plant", [(1e8, "euler"), (1e8, "continuous"), (0.0, "euler")])
def test_fast_path_reproduces_the_ipopt_closed_loop(solver, mu, plant):
    ref, _ = paper_loop("ipopt", mu, plant)
    run, controller = paper_loop(solver, mu, plant)
    settle_ref = settling_step(ref.x[:, 0], 5.0, SETTLING_TOLERANCE)
    settle = settling_step(run.x[:, 0], 5.0, SETTLING_TOLERANCE)
    assert settle is not None and abs(settle - settle_ref) <= 2
    if mu > 0:
        assert max_abs_product(run.x) <= 2.005 if plant == "euler" else max_abs_product(run.x) <= 2.0
    else:
        assert max_abs_product(run.x) == pytest.approx(max_abs_product(ref.x), rel=1e-3)
    assert not any(StepStatus(s).is_fallback for s in run.status)
    # the fast solver, the cold-start reference, the fallback's recovery, the target projection
    assert controller.nlp_builds == 4


@pytest.mark.parametrize("solver", FAST)
def test_first_sample_matches_the_reference_optimum(solver):
    """Same optimum as the multiple-shooting NLP: u(0), y_a and the predicted states agree."""
    ref = NmpcController(PAPER).step([-5.0, 0.0], [5.0])
    res = NmpcController(PAPER.replace(solver=solver)).step([-5.0, 0.0], [5.0])
    assert res.status == "ok"
    np.testing.assert_allclose(res.u, ref.u, atol=1e-4)
    np.testing.assert_allclose(res.y_a, ref.y_a, atol=1e-4)
    np.testing.assert_allclose(res.states, ref.states, atol=1e-4)
    assert res.avoidance_cost == pytest.approx(ref.avoidance_cost, rel=1e-3, abs=1e-6)


def test_obstacle_changes_never_rebuild_the_fast_path():
    controller = NmpcController(ControllerSettings(solver="sqp", max_ellipses=2, max_polygons=0))
    solver, builds = controller.nlp.solver, controller.nlp_builds
    x = np.array([-5.0, 0.0])
    for k in range(6):
        regions = [Ellipse((-3.0 + 0.3 * k, 0.5), (0.4, 0.3), 0.1 * k)]
        res = controller.step(x, [5.0], regions)
        assert res.status in ("ok", "truncated", "unconverged")  # a solve's iterate applied (not a fallback)
        x = res.states[1]
    assert controller.nlp_builds == builds == 4 and controller.nlp.solver is solver


def test_nlp_builds_counts_every_solver_construction_and_run_time_changes_add_none(monkeypatch):
    """nlp_builds equals the nlpsol Functions really constructed (counted at casadi.nlpsol itself)."""
    import casadi
    from test_passage import VDP_0100, shipped

    real, constructed = casadi.nlpsol, []

    def counting_nlpsol(*args, **kwargs):
        constructed.append(args[1])  # the plugin
        return real(*args, **kwargs)

    # patched: casadi.nlpsol itself is the independent count nlp_builds is checked against
    monkeypatch.setattr(casadi, "nlpsol", counting_nlpsol)
    # every controller: its path's solver, the fallback's recovery solve and the target projection
    # (IPOPT); a fast path also
    # the cold-start reference (IPOPT); sqp with a real-time budget also its own cold-budget copy
    expected = {("ipopt", 200): ["ipopt"] * 3, ("fatrop", 200): ["fatrop"] + ["ipopt"] * 3,
                ("sqp", 5): ["sqpmethod", "sqpmethod"] + ["ipopt"] * 3}
    for (solver, budget), plugins in expected.items():
        constructed.clear()
        controller = NmpcController(PAPER.replace(solver=solver, max_iterations=budget, max_ellipses=1))
        assert sorted(constructed) == sorted(plugins) and controller.nlp_builds == len(plugins), solver
        x = np.array([-5.0, 0.0])
        for k, target in enumerate((5.0, -3.0, 2.0)):  # new targets, obstacles, weights: no construction
            controller.update_settings(mu=10.0 ** (4 + 2 * k), kappa=10.0 ** (3 + k), state_weights=(1.0, 2.0))
            x = controller.step(x, [target], [Ellipse((-3.0 + k, 1.0), (0.4, 0.3))]).states[1]
        assert len(constructed) == controller.nlp_builds == len(plugins), solver
    # the shipped van_der_pol.yaml (test_passage): FATROP: the regular NLP, the passage mode's long one and the
    # 3 ellipse tiers; IPOPT: the cold-start reference, the recovery and the target projection
    constructed.clear()
    controller = NmpcController(shipped())
    assert sorted(constructed) == ["fatrop"] * 5 + ["ipopt"] * 3 and controller.nlp_builds == 8
    x, y_t = np.array(VDP_0100["x0"]), np.array(VDP_0100["target"])
    controller.set_regions([Ellipse(*VDP_0100["ellipse"])])
    for _ in range(12):  # the stall escape's 3 guesses, one per sample, then the passage: none builds a solver
        result = controller.step(x, y_t)
        x = result.states[1]
        if result.search.entered_passage:
            break
    assert result.search.entered_passage and len(constructed) == controller.nlp_builds == 8


def test_compiled_solver_is_cached_by_structure(tmp_path):
    settings = PAPER.replace(solver="sqp", codegen=True, cache_dir=str(tmp_path))
    first = NmpcController(settings)
    assert first.nlp.solver_info["cache_hit"] is False
    libraries = sorted(tmp_path.glob("*.so"))
    assert len(libraries) == 2  # the SQP and its cold-start FATROP solver
    stamps = [lib.stat().st_mtime_ns for lib in libraries]
    # a second start with the same structure reuses the library; run-time parameters do not matter
    second = NmpcController(settings.replace(mu=0.0, kappa=10.0))
    assert second.nlp.solver_info["cache_hit"] is True
    assert sorted(tmp_path.glob("*.so")) == libraries
    assert [lib.stat().st_mtime_ns for lib in libraries] == stamps
    # the compiled and the interpreted solver give the same plan
    plain = NmpcController(PAPER.replace(solver="sqp"))
    a, b = first.step([-5.0, 0.0], [5.0]), plain.step([-5.0, 0.0], [5.0])
    np.testing.assert_allclose(a.states, b.states, atol=1e-9)
    # another structure gets its own library
    NmpcController(settings.replace(horizon=6))
    assert len(list(tmp_path.glob("*.so"))) == 4
    assert not list(tmp_path.glob("tmp*")), "no half-written build left behind"


def test_codegen_without_a_compiler_says_so(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-here")
    with pytest.raises(ConfigError, match="C compiler"):
        NmpcController(PAPER.replace(solver="sqp", codegen=True, cache_dir=str(tmp_path)))


@pytest.mark.parametrize("plant", ["euler", "continuous"])
def test_real_time_budget_cuts_and_continues(plant):
    """A fixed budget of 5 SQP iterations per sample: cut samples are flagged and continued from
    their iterate, every sample has a command, and the closed loop keeps the reference's quality."""
    ref, _ = paper_loop("ipopt", 1e8, plant)
    controller = NmpcController(PAPER.replace(solver="sqp", mu=1e8, max_iterations=5))
    cut = []
    run = run_closed_loop(controller, [-5.0, 0.0], [5.0], 50, plant,
                          on_step=lambda k, res: cut.append(res.budget_exhausted))
    assert any(cut), "a budget of 5 iterations must cut some samples"
    assert max(run.iterations[1:]) <= 5  # the cold start (sample 0) has its own budget
    assert len(run.u) == 50 and np.all(np.isfinite(run.u))
    settle = settling_step(run.x[:, 0], 5.0, SETTLING_TOLERANCE)
    assert settle is not None and abs(settle - settling_step(ref.x[:, 0], 5.0, SETTLING_TOLERANCE)) <= 2
    assert max_abs_product(run.x) <= 2.005


def test_budget_flag_reaches_the_step_result():
    controller = NmpcController(PAPER.replace(solver="sqp", max_iterations=1))
    first = controller.step([-5.0, 0.0], [5.0])  # cold start: its own, larger budget
    assert first.status == "ok" and not first.budget_exhausted
    res = controller.step(first.states[1], [-3.0])  # a new target cannot be reached in one iteration
    assert res.iterations == 1 and res.budget_exhausted
    assert res.status in ("truncated", "fallback_shift")


def test_stagewise_needs_the_closed_form_steady_state():
    with pytest.raises(ConfigError, match="closed-form"):
        NmpcController(PAPER.replace(solver="fatrop", use_closed_form_steady_state=False))


def test_stagewise_layout_round_trip_and_dual_shift():
    nlp = StagewiseNlp(PAPER.replace(solver="sqp", horizon=6))
    layout = nlp.layout
    rng = np.random.default_rng(0)
    U, X, y_a = rng.normal(size=(6, 1)), rng.normal(size=(6, 2)), rng.normal(size=1)
    w = layout.join_w(U, X, y_a, None, x0=np.array([1.0, 2.0]))
    U2, X2, y2, _ = layout.split_w(w)
    np.testing.assert_array_equal(U2, U)
    np.testing.assert_array_equal(X2, X)
    np.testing.assert_array_equal(y2, y_a)
    lam_x = np.arange(layout.n_w, dtype=float)
    lam_g = np.arange(nlp.lbg.size, dtype=float)
    sx, sg = nlp.shift_duals(lam_x, lam_g, 1)
    start = layout.stage_start
    block = [slice(start[k], start[k + 1]) for k in range(6)]  # stage k's variables
    np.testing.assert_array_equal(sx[block[1]], lam_x[block[2]])
    np.testing.assert_array_equal(sx[block[3]], lam_x[block[4]])
    np.testing.assert_array_equal(sx[block[5]], lam_x[block[5]])  # the last uniform stage stays
    np.testing.assert_array_equal(sx[block[0]], lam_x[block[0]])  # stage 0 keeps its own
    np.testing.assert_array_equal(sx[start[6]:], lam_x[start[6]:])  # and stage N
    # the constraint multipliers (lam_g = its index): stages 1..4 take the next stage's, one block of B
    # rows further, in one stretch between stage 0's rows and the last uniform stage's, which stay
    moved = np.flatnonzero(sg != lam_g)
    rows = sg[moved] - lam_g[moved]
    assert moved.size and moved[0] > 0 and np.all(np.diff(moved) == 1), moved
    assert np.all(rows == rows[0]) and moved.size == 4 * rows[0] and moved[-1] + rows[0] < lam_g.size, rows


def test_simulate_picks_a_solver_path_by_name(capsys, tmp_path):
    from nmpc_avoid_ros.tools.simulate import main

    assert main(["--solver", "list"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert listed == list(SOLVERS)
    out = tmp_path / "run.json"
    assert main(["--solver", "fatrop", "--steps", "12", "--json", str(out)]) == 0
    assert "solver=fatrop" in capsys.readouterr().out
    assert main(["--solver", "no_such_path"]) == 2
    assert "solver must be one of" in capsys.readouterr().err


def test_coast_applies_the_next_input_of_the_plan_and_shifts_the_warm_start():
    controller = NmpcController(PAPER)
    assert controller.coast() is None  # no plan yet
    first = controller.step([-5.0, 0.0], [5.0])
    coasted = controller.coast()
    assert coasted.status == "fallback_shift" and coasted.solver_status == "no_new_state"
    np.testing.assert_allclose(coasted.u, first.inputs[1])
    np.testing.assert_allclose(coasted.states[0], first.states[1])
    # two samples after the plan was made: the measured state is the plan's x(2)
    res = controller.step(first.states[2], [5.0])
    assert res.status == "ok"
    np.testing.assert_allclose(res.inputs[0], first.inputs[2], atol=1e-3)


def test_shipped_fast_config_reproduces_the_paper_loop(tmp_path, monkeypatch, capsys):
    from nmpc_avoid_ros.tools.simulate import main

    monkeypatch.setenv("NMPC_AVOID_ROS_CACHE", str(tmp_path))
    config = Path(__file__).resolve().parents[1] / "config" / "van_der_pol_fast.yaml"
    out = tmp_path / "run.json"
    assert main(["--config", str(config), "--json", str(out)]) == 0
    summary = json.loads(out.read_text())["summary"]
    assert summary["settling_step"] == 33 and summary["max_abs_x1x2"] <= 2.005
    assert summary["fallbacks"] == 0 and list(tmp_path.glob("*.so"))


def test_a_failed_warm_solve_is_reseeded_by_the_reference_on_the_next_sample():
    """A campaign case (vdp-0053, seed 0) where the Gauss-Newton SQP stalls on its own shifted
    guess: without a re-seed it fell back on every sample after the first (75 of 80 steady)."""
    settings = ControllerSettings(solver="sqp", max_iterations=100, max_ellipses=4, max_polygons=0)
    ellipses = [Ellipse((0.7457441621157708, 1.8267851342385972), (1.2231836060424943, 0.6113198492468527),
                        2.87267719273039),
                Ellipse((-5.611011741730347, -0.8486668081712256), (0.5039247496810355, 0.27197309640083045),
                        0.2990693975106868),
                Ellipse((-3.9237923926657623, -0.746251734882768), (0.6588111777657775, 0.7754012302276864),
                        0.44466204137123466),
                Ellipse((-4.60102777246489, -0.1389076786574137), (0.3271352666571766, 0.3291813331356161),
                        0.8655145876059412)]
    controller = NmpcController(settings)
    run = run_closed_loop(controller, [-0.2885125577159693, -1.8286417798494807], [-6.476806448979916], 12,
                          "euler", regions=lambda k: ellipses if k == 0 else None)
    assert StepStatus(run.status[1]).is_fallback  # the stall this test is about
    assert run.status[2] == "ok"  # re-seeded: the cold-start solvers, from the shifted plan
    assert sum(StepStatus(s).is_fallback for s in run.status) <= len(run.status) // 2
    assert run.x[-1, 0] < run.x[0, 0] - 2.0  # it moves towards y_t instead of holding
