"""Passage mode (core/sample/passage.py): the long-horizon escape past a region the N = 5 plan cannot pass.

The regression scene is campaign vdp-0100 (seed 0, shipped van_der_pol.yaml): one ellipse across
the steady states between x0 and the target; with N = 5 the loop rests at x1 = 3.757 in front of
it (classified 'local_minimum'), and no initial guess helps: the terminal equality x(N) = x_a
needs a plan from rest in front of the ellipse to rest beyond it within 2.5 s, which the keep-in
|x1 x2| <= 2 forbids.
"""

from __future__ import annotations

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.nlp.worker import ABANDONED
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController

VDP_0100 = {"x0": [4.131043263542839, 0.32547682974441017], "target": [-7.568570929658973],
            "ellipse": ((3.0189786313202767, 0.21428810184309643), (0.7578689514354666, 0.7994778332882292),
                        2.305788859587471)}
#: the best admissible point y~ = y*: lambda * x1_min (the target -7.57 is beyond the box)
BEST = -6.0 * 0.99
STEPS = 80


def shipped() -> ControllerSettings:
    """The shipped van_der_pol.yaml, with a 2 s budget: a loaded test machine must not cut the guesses short."""
    params = load_params_file(default_config_path()).section("controller")
    return ControllerSettings.from_params(params).replace(max_solve_time=2.0)


def parameter_count(nlp) -> int:
    return int(nlp.solver.size1_in(nlp.solver.index_in("p")))


def run_vdp_0100(settings: ControllerSettings, on_step=None):
    region = Ellipse(*VDP_0100["ellipse"])
    controller = NmpcController(settings)
    results = []

    def record(k, result):
        results.append(result)
        if on_step:
            on_step(k, result)

    run = run_closed_loop(controller, VDP_0100["x0"], VDP_0100["target"], STEPS,
                          regions=lambda k: [region] if k == 0 else None, on_step=record)
    depth = max(region.depth(x) for x in run.x)
    keep_in = float(np.max(np.abs(run.x[:, 0] * run.x[:, 1])) - 2.0)
    return controller, run, results, max(depth, keep_in)


@pytest.fixture(scope="module")
def with_passage():
    settings = shipped()
    assert settings.escape_horizon > settings.horizon  # the shipped config turns the mode on
    return run_vdp_0100(settings)


def test_campaign_scene_is_passed_with_the_mode_and_rested_in_front_of_without(with_passage):
    controller, run, results, penetration = with_passage
    assert run.x[-1, 0] == pytest.approx(BEST, abs=0.02), run.x[-1]
    assert penetration <= 1e-3
    assert set(run.status) == {"ok"}
    labels = [r.escape for r in results]  # for the failure message only
    entered = [k for k, r in enumerate(results) if r.search.entered_passage]
    ended = [k for k, r in enumerate(results) if r.search.phase == "passage_ended"]
    assert len(entered) == 1 and len(ended) == 1 and entered[0] < ended[0], labels
    long_ = controller.settings.escape_horizon
    # the long NLP from entry to the hand-back, the regular one before and after
    assert all(r.horizon == long_ and r.inputs.shape == (long_, 1) for r in results[entered[0]:ended[0]])
    assert all(r.horizon == 5 for r in results[:entered[0]] + results[ended[0]:])
    # built once: the long NLP adds one build to the regular controller's; nothing during the run
    without_mode = NmpcController(shipped().replace(escape_horizon=0))
    assert run.info["nlp_builds"] == controller.nlp_builds == without_mode.nlp_builds + 1

    _, alone, _, penetration = run_vdp_0100(shipped().replace(escape_horizon=0))
    assert alone.x[-1, 0] > 3.5, "without the passage mode the loop rests in front of the ellipse"
    assert abs(alone.x[-1, 0] - BEST) > 9.0 and penetration <= 1e-3


def test_certificate_skips_the_horizon_switches_and_checks_the_passage(with_passage):
    _, run, results, _ = with_passage
    certificate = run.certificate
    switches = [k for k in range(1, len(results)) if results[k].horizon != results[k - 1].horizon]
    assert len(switches) == 2
    for k in switches:
        assert not certificate[k]["checked"] and "horizon switched" in certificate[k]["reason"]
    long_checked = [c for c, r in zip(certificate, results) if c["checked"] and r.horizon > 5]
    assert len(long_checked) > 10  # the passage mode's own samples are checked, with the long NLP
    assert not any(c["violated"] for c in certificate)


def test_a_failed_passage_solve_falls_back_to_the_shifted_long_plan():
    controller = NmpcController(shipped())
    region = Ellipse(*VDP_0100["ellipse"])
    x, y_t = np.array(VDP_0100["x0"]), np.array(VDP_0100["target"])
    controller.set_regions([region])
    for _ in range(10):
        result = controller.step(x, y_t)
        x = result.states[1]
        if result.search.phase == "passage":
            break
    assert result.search.phase == "passage", "the passage mode was not entered"
    previous = result.inputs.copy()
    controller.worker.interrupt()  # the sample's solver call fails: abandoned (core/nlp/worker.py)
    failed = controller.step(x, y_t)
    assert [(t.label, t.solver_status) for t in failed.search.tried] == [("passage", ABANDONED)], failed.search
    assert failed.status == "fallback_shift" and failed.horizon == controller.passage.horizon
    np.testing.assert_array_equal(failed.u, previous[1])  # the long plan's next input
    assert failed.search.phase == "passage" and controller.memory.passage
    controller.worker.resume()
    assert controller.step(failed.states[1], y_t).status == "ok"  # and on with the long plan


def test_the_two_nlps_share_the_parameter_vector():
    controller = NmpcController(shipped())
    short, long_ = controller.nlp, controller.passage.nlp
    assert long_.layout.horizon == controller.settings.escape_horizon > short.layout.horizon
    assert parameter_count(long_) == parameter_count(short) and long_.slot_layout == short.slot_layout
    # a moving ellipse: stage k of either NLP sees it at k Ts from the same slot parameters
    controller.set_regions([Ellipse((0.0, 0.5), (0.4, 0.3), 0.0, "state", (0.2, 0.0))])
    par = controller.parameters(np.array([-5.0, 0.0]), np.array([5.0]), time=0.0)
    x, u = np.array([1.5, 0.5]), np.zeros(1)
    for t in (0.0, 2.5, 7.5):
        np.testing.assert_array_equal(long_.region_depth(x, u, par, t), short.region_depth(x, u, par, t))


@pytest.mark.parametrize("changes, message", [
    ({"escape_horizon": -1}, "escape_horizon must be an integer in"),
    ({"escape_horizon": 5}, "escape_horizon must be 0 \\(off\\) or greater than horizon = 5"),
    ({"escape_horizon": 3}, "escape_horizon must be 0 \\(off\\) or greater than horizon = 5"),
    ({"horizon": 12, "escape_horizon": 10}, "greater than horizon = 12"),
    ({"escape_horizon": 2.5}, "escape_horizon must be an integer"),
])
def test_a_bad_escape_horizon_is_refused(changes, message):
    with pytest.raises(ConfigError, match=message):
        ControllerSettings(**changes)
    with pytest.raises(ConfigError, match=message):
        ControllerSettings.from_params({k: v for k, v in changes.items()})
    assert ControllerSettings(escape_horizon=0).escape_horizon == 0


def test_a_model_without_escape_guesses_refuses_the_mode():
    settings = ControllerSettings(model="unicycle", state_min=(-10.0, -10.0, -1e9), state_max=(10.0, 10.0, 1e9),
                                  input_min=(-1.0, -1.0), input_max=(1.0, 1.0), keep_in=(),
                                  state_weights=(1.0, 1.0, 0.1), input_weights=(0.1, 0.1), escape_horizon=10)
    with pytest.raises(ConfigError, match="escape_horizon needs the escape guesses"):
        NmpcController(settings)
