"""Ellipse tiers (core/nlp/tiers.py): smaller copies of the regular NLP for samples with few regions.

A tier solves the same problem without the empty slots, so its closed loop equals the regular
NLP's to the solver's tolerance; samples whose regions do not fit (a polygon, more ellipses than
the largest tier) use the regular NLP; nothing is built at run time.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PAPER_TARGET, PAPER_X0, solver_calls

from nmpc_avoid_ros.bench.main import VDP_ELLIPSES
from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon
from nmpc_avoid_ros.core.sample.controller import NmpcController

#: the paper's settings with a 2 s budget (a loaded test machine must not cut solves short)
BASE = ControllerSettings(max_solve_time=2.0)


def four_ellipse_run(settings: ControllerSettings, regions=VDP_ELLIPSES):
    controller = NmpcController(settings)
    run = run_closed_loop(controller, PAPER_X0, PAPER_TARGET, 45, regions=lambda k: list(regions) if k == 0 else None)
    return controller, run, solver_calls(controller, run.searches)


def test_a_tier_solves_the_samples_its_ellipses_fit_and_the_loop_is_the_regular_one():
    tiered, run, calls = four_ellipse_run(BASE.replace(ellipse_tiers=(2, 4)))
    regular, reference, _ = four_ellipse_run(BASE)
    # the 4 ellipses fit the tier of 4 (not the one of 2): every warm regular solve is the tier's;
    # the regular NLP solves only the escape guesses (cold start: IPOPT's own, the regular one here)
    assert calls["tier4"] >= 40 and calls["tier2"] == 0, calls
    assert calls["regular"] < calls["tier4"], calls
    assert np.allclose(run.x, reference.x, atol=1e-5), np.max(np.abs(run.x - reference.x))
    assert np.allclose(run.u, reference.u, atol=1e-4)
    assert run.x[-1, 0] == pytest.approx(PAPER_TARGET[0], abs=0.05)
    assert set(run.status) == {"ok"}
    # built once: the regular NLP, its recovery solve and the two tiers; nothing during the run
    assert run.info["nlp_builds"] == tiered.nlp_builds == regular.nlp_builds + 2


def test_regions_that_do_not_fit_a_tier_use_the_regular_nlp():
    square = Polygon(((1.0, 1.2), (1.6, 1.2), (1.6, 1.8), (1.0, 1.8)))
    _, run, calls = four_ellipse_run(BASE.replace(ellipse_tiers=(4,)), regions=list(VDP_ELLIPSES[:2]) + [square])
    assert calls["tier4"] == 0 and calls["regular"] >= 45, calls  # a polygon: the tiers have no polygon slot
    five = list(VDP_ELLIPSES) + [Ellipse((-4.5, -1.5), (0.3, 0.2))]
    _, run, calls = four_ellipse_run(BASE.replace(ellipse_tiers=(2, 4)), regions=five)
    assert calls["tier4"] == calls["tier2"] == 0, calls  # 5 ellipses: more than the largest tier
    assert set(run.status) == {"ok"}


def test_a_moving_ellipse_is_predicted_in_the_tier_as_in_the_regular_nlp():
    walker = Ellipse((0.5, 0.9), (0.4, 0.25), 0.0, "state", velocity=(0.05, 0.0))

    def run(settings):
        controller = NmpcController(settings)
        run = run_closed_loop(controller, PAPER_X0, PAPER_TARGET, 30, regions=lambda k: [walker] if k == 0 else None)
        return run, solver_calls(controller, run.searches)

    tiered, calls = run(BASE.replace(ellipse_tiers=(1,)))
    reference, _ = run(BASE)
    assert calls["tier1"] >= 25, calls
    assert np.allclose(tiered.x, reference.x, atol=1e-5), np.max(np.abs(tiered.x - reference.x))


@pytest.mark.parametrize("tiers", [(8,), (2, 9)])
def test_a_tier_not_below_max_ellipses_is_refused(tiers):
    with pytest.raises(ConfigError, match="ellipse_tiers must each be below max_ellipses"):
        ControllerSettings(ellipse_tiers=tiers)
