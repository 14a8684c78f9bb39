"""Preparation and feedback (core/sample/feedback.py, core/nlp/sensitivity.py): a sample prepared ahead for the
predicted state answers the state that arrives from its plan and law, no solver call, with the command a
searched sample would give; where the law does not hold the sample searches as before."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.loop.closed_loop import ClosedLoopRun, ContinuousPlant, Plant, drive, make_plant
from nmpc_avoid_ros.core.nlp.sensitivity import KktSensitivity
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.feedback import FeedbackLaws
from nmpc_avoid_ros.core.sample.status import FeedbackOutcome, StepStatus

ROOT = Path(__file__).resolve().parents[1]


def config(name: str) -> ControllerSettings:
    return ControllerSettings.from_params(load_params_file(ROOT / "config" / f"{name}.yaml").section("controller"))


#: the paper's config (IPOPT, multiple shooting, Euler prediction: quick) and the live one (FATROP, stage-wise,
#: RK4 in 8 sub-steps with the between-sample rows and ellipse tiers: the path users run, slow uncompiled)
#: both with a generous clock budget: these tests compare loops, and a solve cut by the clock on a loaded machine (two
#: test workers) parted the paper's searched and prepared loops at mu = 0 by 2.46 once
CONFIGS = {"paper": config("van_der_pol").replace(max_solve_time=2.0),
           "live": config("van_der_pol_live").replace(codegen=False, max_solve_time=2.0)}
#: the plant of each config's loop: the paper's is its own Euler map (its prediction misses the continuous plant by
#: up to ~0.06 a sample, beyond the law's reach in most samples: they search), the live config's the continuous one
PLANT = {"paper": "euler", "live": "continuous"}
BOTH = [pytest.param("paper"), pytest.param("live", marks=pytest.mark.slow)]
LIVE = CONFIGS["live"]


#: a miss of the prediction that keeps the prepared active set, and how much of the command's error the law
#: removes: the live (stage-wise) problem's to second order (measured 1e-7 left of 3e-3 at 1e-3); the paper's
#: rides the region with its slacks' bound s >= 0 and rows s >= g nearly both active, which flip at misses of
#: 3e-4 (those samples search) and leave the first-order correction cruder (measured 8e-6 left of 5e-5)
MISS = {"paper": 1e-4, "live": 1e-3}
CORRECTED = {"paper": 0.5, "live": 1e-2}
#: how far the prepared loop may part from the searched one: the paper's is its own plant (no miss: the law adds
#: nothing); the live config's searched plans are themselves only as exact as FATROP's acceptable stop (KKT error
#: 1e-4; measured: 1.5e-5 apart at mu = 0, where the slacks' rows are weakly active)
SAME_LOOP = {"paper": 1e-6, "live": 1e-4}


def controller_of(name: str, feedback: bool, **changes) -> NmpcController:
    return NmpcController(CONFIGS[name].replace(feedback=feedback, **changes))


def live(feedback: bool, **changes) -> NmpcController:
    return controller_of("live", feedback, **changes)


def prepared_controller(name: str = "paper", steps: int = 8, beside: NmpcController | None = None, **changes
                        ) -> tuple[NmpcController, Plant, np.ndarray]:
    """A controller `steps` samples into the paper's run on its config's plant, prepared for the next (`beside`,
    another controller, steps on the same states)."""
    controller = controller_of(name, True, **changes)
    plant = make_plant(PLANT[name], controller.model, controller.settings)
    x = np.array([-5.0, 0.0])
    for _ in range(steps):
        result = controller.step(x, [5.0])
        if beside is not None:
            beside.step(x, [5.0])
        x = plant.advance(x, result.u, LIVE.sample_time)
        controller.prepare()
    return controller, plant, x


@pytest.mark.parametrize("mu", [1e8, 0.0])
@pytest.mark.parametrize("name", BOTH)
def test_the_prepared_loop_is_the_searched_loop_without_a_solver_call_in_most_samples(name, mu):
    runs = {}
    for feedback in (False, True):
        controller = controller_of(name, feedback, mu=mu)
        plant = make_plant(PLANT[name], controller.model, controller.settings)
        runs[feedback] = drive(controller, plant, [-5.0, 0.0], [5.0], 40, LIVE.sample_time)
    searched, prepared = runs[False], runs[True]
    assert np.max(np.abs(prepared.x - searched.x)) < SAME_LOOP[name]  # the same closed loop
    answered = [r for r in prepared.outcomes if r.feedback is FeedbackOutcome.ANSWERED]
    assert len(answered) >= 0.8 * len(prepared.outcomes)
    for result in answered:  # no solver ran in the sample; its preparation did, between the samples
        assert result.solver_status == "feedback" and result.search.tried  # the preparation's search, ahead
        assert 0 < result.feedback_time < result.solve_time and result.preparation_time > 0
        assert result.iterations == 0 and str(result.status) == "ok"
    assert all(r.feedback is None and not r.preparation_time for r in searched.outcomes)
    # the state-to-command time the campaign reports: an answered sample's feedback time, a searched one's solve
    command = ClosedLoopRun.from_trajectory(prepared).command_time
    feedback_times = np.array([r.feedback_time for r in prepared.outcomes])
    assert np.allclose(command[feedback_times > 0], feedback_times[feedback_times > 0], atol=1e-12)
    assert np.array_equal(ClosedLoopRun.from_trajectory(searched).command_time, searched.solve_time)


@pytest.mark.parametrize("name", BOTH)
def test_the_law_corrects_a_state_off_the_prediction_to_second_order(name):
    reference = controller_of(name, False)  # searches every sample, on the same states
    controller, _, x = prepared_controller(name, beside=reference)
    prepared = controller.prepared
    assert prepared is not None and prepared.law is not None
    off = x + MISS[name] * np.array([1.0, -0.5])  # the plant missed the prediction
    searched = reference.step(off, [5.0])
    answered = controller.step(off, [5.0])
    assert answered.feedback is FeedbackOutcome.ANSWERED
    miss = np.max(np.abs(prepared.plan.inputs[0] - searched.u))
    assert miss > 1e-5  # the prepared command alone is off, to first order
    assert np.max(np.abs(answered.u - searched.u)) < CORRECTED[name] * miss


@pytest.mark.slow
def test_a_state_the_law_refuses_is_answered_by_one_qp_as_the_search_would():
    """A miss of 1e-2 (ten times the law's reach here): the law's move is refused (its active set changes or it is
    infeasible to second order), and one QP on the linearisation at it (core/sample/feedback_qp.py) answers, no
    solver call, with the command of a converged search at that state."""
    reference = controller_of("live", False)
    controller, _, x = prepared_controller("live", steps=4, beside=reference, feedback_qp=True)
    off = x + 1e-2 * np.array([1.0, -0.5]) / np.hypot(1.0, 0.5)
    prepared = controller.prepared
    searched = reference.step(off, [5.0])
    answered = controller.step(off, [5.0])
    assert answered.feedback is FeedbackOutcome.ANSWERED_QP and answered.answered
    assert answered.solver_status == "feedback" and answered.iterations == 0 and answered.status is StepStatus.OK
    assert np.max(np.abs(prepared.plan.inputs[0] - searched.u)) > 1e-3  # the prepared command alone is off
    assert np.max(np.abs(answered.u - searched.u)) < 1e-6  # measured 5.6e-9
    without, _, x_without = prepared_controller("live", steps=4, feedback_qp=False)
    assert np.array_equal(x_without, x)
    refused = without.step(off, [5.0])  # the setting off: the sample searches
    assert refused.feedback in (FeedbackOutcome.INFEASIBLE, FeedbackOutcome.ACTIVE_SET_CHANGED)
    assert refused.search.tried and np.max(np.abs(refused.u - searched.u)) < 1e-6


def test_a_new_target_or_a_far_state_is_searched():
    controller, plant, x = prepared_controller()
    changed = controller.step(x, [4.0])
    assert changed.feedback is FeedbackOutcome.INPUTS_CHANGED and changed.search.tried
    x = plant.advance(x, changed.u, LIVE.sample_time)
    assert controller.prepare() is not None
    far = controller.step(x + np.array([0.5, -0.3]), [4.0])
    assert far.feedback in (FeedbackOutcome.INFEASIBLE, FeedbackOutcome.ACTIVE_SET_CHANGED) and far.search.tried
    assert str(far.status) in ("ok", "unconverged")


def test_a_search_cut_at_the_command_budget_goes_on_in_the_preparation_and_the_next_sample_is_answered():
    """`command_budget`: a sample its law does not answer searches at most that long before its command (here too
    short for any solve: the fallback); the preparation after the command searches with the whole budget from
    where the fallback leads, and the sample after it is answered by that plan's law, as a searched one would be."""
    reference = controller_of("paper", False)
    controller, plant, x = prepared_controller(steps=4, beside=reference, command_budget=1e-4)
    assert controller.sample_budget() == 1e-4
    assert controller.sample_budget(before_command=False) == controller.settings.max_solve_time
    cut = controller.step(x, [4.0])  # a new target: the law does not hold, the sample searches
    reference.step(x, [4.0])
    assert cut.feedback is FeedbackOutcome.INPUTS_CHANGED and cut.status is StepStatus.FALLBACK_SHIFT, cut.status
    x = plant.advance(x, cut.u, LIVE.sample_time)
    prepared = controller.prepare()
    assert prepared is not None and prepared.law is not None, prepared
    answered, searched = controller.step(x, [4.0]), reference.step(x, [4.0])
    assert answered.feedback is FeedbackOutcome.ANSWERED
    assert np.max(np.abs(answered.u - searched.u)) < 1e-5


@pytest.mark.slow
def test_a_moving_region_is_followed_by_the_law():
    walker = Ellipse((1.0, 1.8), (0.4, 0.3), 0.0, velocity=(0.05, 0.0), stamp=0.0)
    controller = live(True, predict_obstacles=True)
    reference = live(False, predict_obstacles=True)
    plant = ContinuousPlant(controller.model)
    x, answered = np.array([-5.0, 0.0]), 0
    for k in range(12):
        t = k * LIVE.sample_time
        regions = [walker] if k == 0 else None
        result = controller.step(x, [5.0], regions, time=t)
        check = reference.step(x, [5.0], regions, time=t)
        answered += result.feedback is FeedbackOutcome.ANSWERED
        assert np.max(np.abs(result.u - check.u)) < 1e-4  # what a searched sample applies
        x = plant.advance(x, result.u, LIVE.sample_time)
        controller.prepare()
    assert answered >= 8


def test_coasting_drops_the_plan_prepared_for_the_sample_it_replaces_and_off_prepares_nothing():
    controller, _, x = prepared_controller(steps=4)
    assert controller.prepared is not None
    controller.coast()
    assert controller.prepared is None
    assert controller.prepare() is None  # nothing to predict from: the last step's state is a sample old
    result = controller.step(x, [5.0])  # one sample later than the lost preparation: searched
    assert result.feedback is None and result.search.tried
    off = controller_of("paper", False)
    off.step([-5.0, 0.0], [5.0])
    assert off.prepare() is None


def test_the_laws_derivatives_are_saved_once_and_read_back_unchanged(tmp_path):
    """A later start reads the KKT derivatives from the cache (core/nlp/sensitivity.py) and gets the same law; a
    damaged file is built again and replaced."""
    controller, _, _ = prepared_controller("paper", steps=3)
    prepared = controller.prepared
    assert prepared is not None and prepared.law is not None
    nlp, par = prepared.nlp, prepared.law.par
    columns = prepared.law.columns
    bounds = (nlp.lbx, nlp.ubx, nlp.lbg, nlp.ubg)
    built = KktSensitivity(nlp.problem, columns, tmp_path)
    saved = sorted(tmp_path.glob("kkt_*.casadi"))
    assert [p.name.rsplit("_", 1)[1] for p in saved] == ["first.casadi", "second.casadi"]
    assert not list(tmp_path.glob("*.part"))  # written whole
    stamps = [p.stat().st_mtime_ns for p in saved]
    read = KktSensitivity(nlp.problem, columns, tmp_path)
    assert [p.stat().st_mtime_ns for p in saved] == stamps  # read, not written again
    laws = [s.law(prepared.law.w, par, bounds) for s in (built, read)]
    assert np.array_equal(laws[0].dw, laws[1].dw) and np.array_equal(laws[0].dw, prepared.law.dw)
    saved[0].write_bytes(b"not a CasADi function")
    again = KktSensitivity(nlp.problem, columns, tmp_path)
    assert np.array_equal(again.law(prepared.law.w, par, bounds).dw, laws[0].dw)
    assert saved[0].stat().st_size > 100  # replaced by a whole file


def test_a_later_nlps_law_is_built_by_a_thread_and_served_once_there(tmp_path, monkeypatch):
    """With `background`, the passage NLP's law is built by a thread: until it is there its plans have no law (they
    search), then they get one; the constructor does not wait for it."""
    from nmpc_avoid_ros.core.sample import feedback

    controller, _, _ = prepared_controller("paper", steps=3)
    prepared = controller.prepared
    assert prepared is not None and prepared.law is not None
    nlp = prepared.nlp
    go = threading.Event()

    def held_build(*args):  # the derivatives wait until the test has looked
        assert go.wait(60.0)
        return KktSensitivity(*args)

    monkeypatch.setattr(feedback, "KktSensitivity", held_build)
    laws = FeedbackLaws([], None, True, later=[nlp], derivatives_in=tmp_path)
    assert not laws.built(nlp) and isinstance(laws.prepare(nlp, prepared.plan, prepared.law.par), str)
    go.set()
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and isinstance(laws.prepare(nlp, prepared.plan, prepared.law.par), str):
        time.sleep(0.05)
    law = laws.prepare(nlp, prepared.plan, prepared.law.par)
    assert laws.built(nlp) and not isinstance(law, str), law
    assert np.allclose(law.dw, prepared.law.dw, atol=1e-9)


def test_a_later_law_that_fails_to_build_is_said_and_its_plans_search(monkeypatch, caplog):
    from nmpc_avoid_ros.core.sample import feedback

    controller, _, _ = prepared_controller("paper", steps=3)
    prepared = controller.prepared
    assert prepared is not None and prepared.law is not None

    def broken(*args):
        raise OSError("No space left on device")

    monkeypatch.setattr(feedback, "KktSensitivity", broken)
    with caplog.at_level("WARNING", logger=feedback.__name__):
        laws = FeedbackLaws([], None, True, later=[prepared.nlp])
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not caplog.records:
            time.sleep(0.02)
    assert "no feedback law for the NLP of horizon" in caplog.text and "No space left" in caplog.text
    assert not laws.built(prepared.nlp) and isinstance(laws.prepare(prepared.nlp, prepared.plan, prepared.law.par), str)


def test_a_save_cut_short_by_the_process_end_leaves_no_half_written_file(tmp_path):
    """A save or a compile on a thread can be running when the process ends: its partial file or temporary folder goes
    at exit (core/nlp/native_threads.py `scratch`), and its own replace then fails quietly."""
    from nmpc_avoid_ros.core.nlp import native_threads, sensitivity

    partial = tmp_path / "tmpabc.part"
    partial.write_bytes(b"half a function")
    build = tmp_path / "tmpbuild"
    build.mkdir()
    (build / "feedback_answer.c").write_text("int half;")
    with native_threads.scratch(partial), native_threads.scratch(build):
        native_threads._remove_scratch()
    assert not partial.exists() and not build.exists()
    function = ca.Function("f", [ca.SX.sym("x")], [ca.SX.sym("x") * 0])
    sensitivity._save_atomically(function, tmp_path / "missing_folder" / "f.casadi")  # creates its folder
    assert ca.Function.load(str(tmp_path / "missing_folder" / "f.casadi")).name() == "f"
    assert oct((tmp_path / "missing_folder" / "f.casadi").stat().st_mode & 0o777) == "0o644"
