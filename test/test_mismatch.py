"""The plant-model mismatch margin (core/sample/mismatch.py): measured online from the one-step
prediction error, added to the obstacles, and what it buys on a plant that differs from the model.

The scene is the README's obstacle (config/scenes/readme_obstacle.yaml: from rest at x = (5, 0) to the
target -3 past the ellipse centred (2, -0.5), semi-axes 0.4 x 0.2) with the live config's prediction
(RK4, 8 sub-steps) and a plant whose actuator is stronger than the model says.
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
from nmpc_avoid_ros.core.loop.scene import load_scene
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.mismatch import MARGIN_HEADROOM, MismatchMargin
from nmpc_avoid_ros.tools.simulate import scene_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "config" / "scenes" / "readme_obstacle.yaml"
MODEL = make_model("van_der_pol")
EULER = MODEL.discrete(0.5, "euler", 1)
BOUND = 1e-3


class StrongerActuator:
    """The van der Pol plant, integrated accurately, with the input acting `gain` times as strongly as modelled."""

    def __init__(self, gain: float) -> None:
        self.gain = gain

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        def rhs(_t: float, s: np.ndarray) -> list[float]:
            return [s[1], 0.2 * (1 - s[0] ** 2) * s[1] - s[0] + self.gain * float(u[0])]

        return solve_ivp(rhs, (0.0, dt), np.asarray(x, float), method="DOP853", rtol=1e-10, atol=1e-12).y[:, -1]


def settings(**changes) -> ControllerSettings:
    return ControllerSettings(**changes)


def test_the_error_is_measured_in_the_plane_one_sample_after_its_prediction() -> None:
    s = settings(mismatch_gain=1.0, mismatch_window=3, plane=(0, 1))
    mm = MismatchMargin()
    mm.expect(np.array([1.0, 2.0]), np.array([0.0]), 10.0, 0.5)
    mm.measure(np.array([1.3, 2.4]), 10.5, MODEL, s, outputs_too=False)
    assert mm.last_error == pytest.approx(0.5) and list(mm.errors) == [pytest.approx(0.5)]
    assert mm.expected is None  # used once
    # a measurement that is not the next sample's (a missed sample: 1 s later) is not compared
    mm.expect(np.array([1.0, 2.0]), np.array([0.0]), 10.5, 0.5)
    mm.measure(np.array([9.0, 9.0]), 12.0, MODEL, s, outputs_too=False)
    assert math.isnan(mm.last_error) and len(mm.errors) == 1
    # the window keeps the last mismatch_window errors
    for e in (0.1, 0.2, 0.3, 0.4):
        mm.expect(np.zeros(2), np.zeros(1), None, 0.5)
        mm.measure(np.array([e, 0.0]), None, MODEL, s, outputs_too=False)
    assert list(mm.errors) == pytest.approx([0.2, 0.3, 0.4])


def test_the_margin_grows_at_once_shrinks_with_hysteresis_and_is_capped() -> None:
    s = settings(mismatch_gain=2.0, mismatch_window=2, max_mismatch_margin=0.5)
    mm = MismatchMargin()

    def error(e: float) -> bool:
        mm.expect(np.zeros(2), np.zeros(1), None, 0.5)
        mm.measure(np.array([e, 0.0]), None, MODEL, s, outputs_too=False)
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
    planned = controller._regions[0]
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


@pytest.mark.slow
@pytest.mark.parametrize("gain", [0.0, 1.0])
def test_a_stronger_actuator_enters_the_readme_ellipse_unless_the_margin_widens_it(gain) -> None:
    """Actuator 10 % stronger than modelled. Without the margin the loop passes through the ellipse
    (measured -0.19 between the samples); with mismatch_gain 1 (margin ~0.12) it passes it clear, at the
    samples and between them, and still gets past it to the target side. Measured, not asserted: 25 %
    stronger, the widened ellipse and |x1 x2| <= 2 close the way and the loop stops in front of it
    (x1 = 2.65) where without the margin it went through it by 0.73."""
    scene = load_scene(SCENE)
    scenario = scene_scenario(scene, codegen=False, max_solve_time=2.0)
    controller = NmpcController(scenario.settings.replace(mismatch_gain=gain))
    run = run_closed_loop(controller, scenario.x0, scenario.target, 40, StrongerActuator(1.1),
                          regions=lambda k: scene.regions_at(k * scenario.settings.sample_time))
    between = clearance_between_samples(scenario.settings, MODEL, run.x, run.u, run.regions)
    at_samples = max(r.depth(x[:2]) for x, rs in zip(run.x, run.regions) for r in rs)
    print(f"\nmismatch_gain {gain}: clearance between samples {between['min_clearance_obstacles']:.4f}, "
          f"deepest g at the samples {at_samples:.4f}, margin {controller.mismatch_margin:.3f}, "
          f"final x {run.x[-1].round(3)}")
    assert run.x[-1][0] < 0.0  # past the ellipse, near the target -3
    if gain == 0.0:
        assert between["min_clearance_obstacles"] < -0.1
    else:
        assert between["min_clearance_obstacles"] >= -BOUND and at_samples <= BOUND
        assert 0.05 < controller.mismatch_margin <= scenario.settings.max_mismatch_margin
