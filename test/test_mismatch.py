"""The plant-model mismatch margin (core/sample/mismatch.py): measured online from the one-step
prediction error, added to the obstacles, and what it buys on a plant that differs from the model.

The scene is campaign vdp-0274 (a thin ellipse the loop passes close to) with the live config's prediction
(RK4, 8 sub-steps, chord rows) and a plant whose actuator is weaker than the model says.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.loop.intersample import clearance_between_samples
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.mismatch import MARGIN_HEADROOM, MismatchMargin

ROOT = Path(__file__).resolve().parents[1]
MODEL = make_model("van_der_pol")
EULER = MODEL.discrete(0.5, "euler", 1)
BOUND = 1e-3


class StrongerActuator:
    """The van der Pol plant, integrated accurately, with the input acting `gain` times as strongly as modelled
    (gain < 1: weaker)."""

    def __init__(self, gain: float) -> None:
        self.gain = gain

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        def rhs(_t: float, s: np.ndarray) -> list[float]:
            return [s[1], 0.2 * (1 - s[0] ** 2) * s[1] - s[0] + self.gain * float(u[0])]

        return solve_ivp(rhs, (0.0, dt), np.asarray(x, float), method="DOP853", rtol=1e-10, atol=1e-12).y[:, -1]


def settings(**changes) -> ControllerSettings:
    return ControllerSettings(**changes)


def stay(x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """A flow under which nothing moves: the expectation's start state is what it predicts."""
    return np.array(x, float)


def test_the_error_is_measured_in_the_plane_against_the_plan_at_the_measurements_own_time() -> None:
    s = settings(mismatch_gain=1.0, mismatch_window=3, plane=(0, 1))
    mm = MismatchMargin()
    mm.expect(np.array([1.0, 2.0]), np.array([0.0]), 10.0, 0.5)
    mm.measure(np.array([1.3, 2.4]), 10.5, stay, MODEL, s, outputs_too=False)
    assert mm.last_error == pytest.approx(0.5) and list(mm.errors) == [pytest.approx(0.5)]
    # the plan's state for the measurement's own instant: 0.3 s after its start, whenever that is
    asked = []
    mm.expect(np.array([1.0, 2.0]), np.array([0.0]), 10.0, 0.5)
    mm.measure(np.array([1.3, 2.4]), 10.3, lambda x, u, dt: asked.append(dt) or x, MODEL, s, outputs_too=False)
    assert asked == [pytest.approx(0.3)]
    mm.errors.clear()
    mm.errors.append(0.5)
    assert mm.expected is None  # used once
    # a measurement that is not the next sample's (a missed sample: 1 s later) is not compared
    mm.expect(np.array([1.0, 2.0]), np.array([0.0]), 10.5, 0.5)
    mm.measure(np.array([9.0, 9.0]), 12.0, stay, MODEL, s, outputs_too=False)
    assert math.isnan(mm.last_error) and len(mm.errors) == 1
    # the window keeps the last mismatch_window errors
    for e in (0.1, 0.2, 0.3, 0.4):
        mm.expect(np.zeros(2), np.zeros(1), None, 0.5)
        mm.measure(np.array([e, 0.0]), None, stay, MODEL, s, outputs_too=False)
    assert list(mm.errors) == pytest.approx([0.2, 0.3, 0.4])


def test_the_margin_grows_at_once_shrinks_with_hysteresis_and_is_capped() -> None:
    s = settings(mismatch_gain=2.0, mismatch_window=2, max_mismatch_margin=0.5)
    mm = MismatchMargin()

    def error(e: float) -> bool:
        mm.expect(np.zeros(2), np.zeros(1), None, 0.5)
        mm.measure(np.array([e, 0.0]), None, stay, MODEL, s, outputs_too=False)
        return mm.update(s)

    assert error(0.0002) is False and mm.margin == 0.0  # 2 x 0.0002 is below the penetration tolerance
    assert error(0.1) and mm.margin == pytest.approx(MARGIN_HEADROOM * 0.2)
    assert error(0.11) is False  # 0.22 is within the headroom: no new problem
    assert error(0.09) is False  # the window's max (0.11) holds it
    assert error(0.09) is False  # target 0.18 is above half the margin: kept
    assert error(0.04) is False and error(0.04) and mm.margin == pytest.approx(MARGIN_HEADROOM * 0.08)
    assert error(10.0) and mm.margin == 0.5  # capped
    off = s.replace(mismatch_gain=0.0)
    assert mm.update(off) and mm.margin == 0.0


def test_the_controller_widens_the_obstacles_by_the_margin_and_the_certificate_restarts() -> None:
    s = settings(mismatch_gain=1.0, codegen=False, max_solve_time=2.0, mu=1e8)
    controller = NmpcController(s)
    ellipse = Ellipse((2.0, -0.5), (0.4, 0.2), 0.0, "state")
    controller.set_regions([ellipse])
    x = np.array([-5.0, 0.0])
    first = controller.step(x, [5.0], time=0.0)
    assert controller.mismatch_margin == 0.0
    predicted = np.asarray(EULER(x, first.u)).ravel()  # the default settings' prediction
    # the plant lands 0.1 away from the prediction: the obstacle is planned around 0.125 wider
    controller.step(predicted + np.array([0.06, 0.08]), [5.0], time=0.5)
    assert controller.memory.mismatch.last_error == pytest.approx(0.1)
    assert controller.mismatch_margin == pytest.approx(0.125)
    assert controller.regions == (ellipse,)  # what is recorded stays the real region
    planned = controller.planned_regions[0]
    assert planned.semi_axes == pytest.approx((0.525, 0.325))
    # the certificate sees the change of the planned problem
    from nmpc_avoid_ros.core.loop.certificate import StabilityCertificate

    controller.reset()
    certificate = StabilityCertificate(controller)
    r0 = controller.step(x, [5.0], time=0.0)
    certificate.observe(r0, np.array([5.0]), 0.0)
    predicted = np.asarray(EULER(x, r0.u)).ravel()
    r1 = controller.step(predicted + np.array([0.0, 0.2]), [5.0], time=0.5)
    sample = certificate.observe(r1, np.array([5.0]), 0.5)
    assert sample.reason == "parameters changed (obstacle settings): check restarted"


#: campaign vdp-0274 (seed 0): from (1.03, -1.61) to the target -4.66 past a 1.17 x 0.15 ellipse
THIN = [Ellipse((-1.151396057570926, -1.0583246575245728), (1.1686191696092787, 0.15245754836960676),
                0.8624660125850363, "state"),
        Ellipse((-2.0017692162609215, 1.1126558358904948), (0.4029768032437231, 0.3155308428301835),
                1.8190574338544054, "state")]


@pytest.mark.slow
@pytest.mark.parametrize("gain", [0.0, 1.0])
def test_a_weaker_actuator_enters_a_thin_ellipse_unless_the_margin_widens_it(gain) -> None:
    """The live config's prediction, a plant whose actuator gives 80 % of the modelled force. Without the
    margin the loop enters the thin ellipse (measured -0.73 between the samples) and |x1 x2| <= 2 (by 0.2);
    with mismatch_gain 1 (margin ~0.3) it stays clear of both and still gets past the ellipse to the target."""
    from nmpc_avoid_ros.core.config.settings import load_params_file

    params = load_params_file(ROOT / "config" / "van_der_pol_live.yaml").section("controller")
    # the live config also plans |x2| 5e-3 inside the box between the samples (its keep-in rows 3 and 4);
    # past this thin ellipse at 80 % force the loop then stops in front of it, clear of both (x1 -1.05, a
    # local minimum of the kind issue 31 is about), whenever |x2| is planned below 1.999: this test is about
    # the mismatch margin, so it keeps the |x1 x2| rows only (the live loop's box: test_latency, test_send_dds)
    params = {**params, "keep_in": params["keep_in"][:2], "keep_in_margin": 1e-3}
    # every sample searched: a 20 % weaker actuator misses the prediction by more than the feedback law's reach
    # in most samples, and the few it answers change this chaotic scene's path (clear without the margin: 0.12)
    settings = ControllerSettings.from_params(params).replace(codegen=False, max_solve_time=2.0, mismatch_gain=gain,
                                                              feedback=False)
    controller = NmpcController(settings)
    run = run_closed_loop(controller, [1.0346166655733864, -1.6059259800145278], [-4.655908510752598], 60,
                          StrongerActuator(0.8), regions=lambda k: THIN)
    between = clearance_between_samples(settings, MODEL, run.x[2:], run.u[2:], run.regions[2:])
    print(f"\nmismatch_gain {gain}: clearance between samples {between['min_clearance_obstacles']:.4f}, keep-in "
          f"excess {between['max_penetration_keep_in']:.4f}, margin {controller.mismatch_margin:.3f}, "
          f"final x {run.x[-1].round(3)}")
    assert run.x[-1][0] < -3.5  # past the ellipse, towards the target
    if gain == 0.0:
        assert between["min_clearance_obstacles"] < -0.1
    else:
        assert between["min_clearance_obstacles"] >= -BOUND and between["max_penetration_keep_in"] <= BOUND
        assert 0.05 < controller.mismatch_margin <= settings.max_mismatch_margin
