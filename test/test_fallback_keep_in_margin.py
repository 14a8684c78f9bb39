"""The fallback's penetration check judges the keep-in sets, not the keep-in margin's band (core/sample/fallback.py).

config/mobile_robot_live.yaml planned its speed limit vx^2 + vy^2 <= 1.44 tightened by keep_in_margin 0.012 (now 0.024)
(1.195 m/s). In real time the plant cruised a hair inside that band (1.196-1.199 m/s, still under 1.2); every plan
from such a state keeps its first sub-steps at the state's depth (they share x(0)'s slack), and the check called
that "plan predicts penetration": fallback_safe, the robot braked (10 of 276 samples in one 50 s DDS run).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.nlp.search import depth_allowance
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController

LIVE = default_config_path().parent / "mobile_robot_live.yaml"
HEADING = math.atan2(-0.75, -0.92)  # the live run's way back, towards (-8, -6)


@pytest.fixture(scope="module")
def robot() -> NmpcController:
    """The live robot's problem on the interpreted IPOPT path (the check does not depend on the solver)."""
    params = load_params_file(LIVE).section("controller")
    # the margin the band below was measured with (the config now plans 1.19 m/s: 0.024)
    params.update(solver="ipopt", codegen=False, codegen_background=False, feedback=False, ellipse_tiers=[],
                  keep_in_margin=0.012)
    settings = ControllerSettings.from_params(params)
    assert settings.integration_steps == 4
    return NmpcController(settings)


def cruise(controller: NmpcController, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """A state at `speed` and the plan that holds it (v' = a - 0.5 v: a = 0.5 v)."""
    v = speed * np.array([math.cos(HEADING), math.sin(HEADING)])
    x = np.array([0.0, 0.0, *v])
    return x, np.tile(0.5 * v, (controller.settings.horizon, 1))


@pytest.mark.parametrize("speed", [1.1959, 1.1972, 1.1991, 1.1999])
def test_a_plan_inside_the_speed_limit_but_in_the_margins_band_is_not_penetration(robot, speed):
    x, holding = cruise(robot, speed)
    par = robot.parameters(x, np.array([-8.0, -6.0]))
    assert 0 < speed**2 - 1.44 + robot.settings.keep_in_margin  # inside the planned margin's band
    assert robot.fallback.predict(x, holding, par)[1] <= 1e-3  # the penetration tolerance
    assert robot.fallback.check_plan(x, par, holding) is None


def test_a_plan_over_the_speed_limit_is_still_replaced(robot):
    x, holding = cruise(robot, 1.2005)  # g = 1.2e-3 > 0 at every row
    par = robot.parameters(x, np.array([-8.0, -6.0]))
    assert robot.fallback.predict(x, holding, par)[1] == pytest.approx(1.2005**2 - 1.44 + 1e-3, abs=1e-9)
    choice = robot.fallback.check_plan(x, par, holding)
    assert choice is not None and choice.kind in ("safe", "recovery") and not choice.unavoidable, choice


@pytest.mark.parametrize("speed", [1.1962, 1.1994])
def test_a_state_in_the_margins_band_is_planned_from_without_the_escape_search(robot, speed):
    """Every plan from a state inside the band shares x(0)'s depth in its first slack: judged by the absolute
    depth it "penetrated", and the search tried every escape guess (0.13-0.21 s a sample at the live robot's
    speed limit, a fallback where the budget ran out). The search judges depth beyond x(0)'s own
    (`depth_allowance`): the regular plan is kept, clear."""
    x, _ = cruise(robot, speed)
    band = speed**2 - 1.44 + robot.settings.keep_in_margin
    result = robot.step(x, np.array([-8.0, -6.0]))
    assert result.status == "ok", result.search
    assert not any(line.phase == "escape" for line in result.search.tried), result.search
    kept = next(line for line in result.search.tried if line.outcome == "kept")
    assert kept.depth == pytest.approx(band, abs=1e-5)  # x(0)'s own depth, and no deeper
    assert depth_allowance(band) == pytest.approx(band + 1e-3) and depth_allowance(5e-4) == 1e-3


def test_an_obstacle_ahead_is_judged_with_its_margins_as_before(robot):
    """The region_margin (2 cm) still counts: a plan holding the robot 1 cm outside the real ellipse penetrates."""
    x, holding = cruise(robot, 1.0)
    robot.set_regions([Ellipse((-0.5, -0.5), (0.3, 0.3), 0.0, "output")])
    try:
        par = robot.parameters(x, np.array([-8.0, -6.0]))
        assert robot.fallback.predict(x, holding, par)[1] > 0.5
        choice = robot.fallback.check_plan(x, par, holding)
        assert choice is not None and choice.kind != "plan", choice
        # at rest 1 cm off the ellipse's edge (inside its 2 cm margin): penetration of the regions as planned
        rest = np.array([-0.5 + 0.31 * math.cos(HEADING + math.pi), -0.5 + 0.31 * math.sin(HEADING + math.pi), 0, 0])
        still = np.zeros((robot.settings.horizon, 2))
        par = robot.parameters(rest, np.array([-8.0, -6.0]))
        assert robot.fallback.predict(rest, still, par)[1] > 1e-3
    finally:
        robot.set_regions([])


def test_the_van_der_pol_live_check_is_unchanged_in_effect():
    """keep_in_margin 2e-3 >= the tolerance: a row counts as penetrating from |x1 x2| > 2 on (g + 1e-3 > 1e-3)."""
    params = load_params_file(default_config_path().parent / "van_der_pol_live.yaml").section("controller")
    params.update(solver="ipopt", codegen=False, codegen_background=False, feedback=False, ellipse_tiers=[])
    controller = NmpcController(ControllerSettings.from_params(params))
    par = controller.parameters(np.array([2.0, 0.5]), np.array([5.0]))
    # the keep-in g of the row is x1 x2 - 2 + 1e-3 (the judged share of the margin), above the tolerance only past 2
    depth = controller.fallback._judged_depth  # noqa: SLF001 - the function the check evaluates
    for x1x2, penetrates in ((1.9995, False), (2.0005, True)):
        x = np.array([x1x2 / 0.5, 0.5])
        g = float(np.max(np.asarray(depth(x, np.zeros(1), par, 0.0))))
        assert (g > 1e-3) is penetrates, (x1x2, g)
