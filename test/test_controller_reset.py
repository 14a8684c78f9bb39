"""A reset controller is a fresh one: the campaign reuses one controller per worker and configuration and
resets it between scenes (evaluation/campaign/running.py), so a scene's record must not depend on the scenes
run before it on the same controller.

Compared exactly (bit for bit) with a budget that never binds: the shipped budgets are wall-clock ones
(max_solve_time, the search's share of it, escape guesses left untried when the time left is short), and with
them a scene's outcome follows the machine's load, whatever ran before (campaign bicycle-0011, alone, converges
with max_solve_time 0.15 s and ends 4.2 from its target pose with 0.1 s, every sample 'ok' either way: fewer escape
guesses fit in the time left). With budgets that never bound, 30 bicycle and 20 van der Pol (live config) scenes
gave the same records run alone as after the scenes before them on one controller.
"""

from __future__ import annotations

import math

import numpy as np

from nmpc_avoid_ros.core.config.settings import default_config_path, load_params_file
from nmpc_avoid_ros.core.loop.closed_loop import ClosedLoopRun, run_closed_loop
from nmpc_avoid_ros.core.sample import preparation
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.evaluation.campaign.scenarios import families, make_specs, settings_from_params
from nmpc_avoid_ros.evaluation.campaign.scoring import STOPS

#: a budget no solve of these scenes comes near: the comparison must not depend on the machine's load
UNBOUND = 100.0
#: campaign vdp-0006 (van_der_pol_live.yaml, seed 0) stops after its sample 23, where an escape found nothing
#: better: the memory waits 10 samples before the next escape and has the passage mode due; vdp-0005's first
#: escapes come at samples 10-15 (a wait left over would put them off)
SCENE_A, STEPS_A = 6, 24
SCENE_B, STEPS_B = 5, 30


def run(controller: NmpcController, spec: dict, schedule, steps: int) -> ClosedLoopRun:
    """The scene as the campaign runs it (score_scenario): reset, then the closed loop."""
    controller.reset()
    return run_closed_loop(controller, spec["x0"], spec["target"], steps, spec["plant"], regions=schedule(spec),
                           stop_on=STOPS)


def test_reset_controller_matches_a_fresh_one_bit_for_bit(monkeypatch):
    # the preparation's own wall-clock rule (no law after a search that took most of the sample) unbound too: the one
    # clock left in these loops, the probable cause of a failure in a loaded parallel run (not reproduced alone)
    monkeypatch.setattr(preparation, "LAW_TIME_SHARE", math.inf)
    family = families({"vdp": default_config_path().parent / "van_der_pol_live.yaml"})["vdp"]
    settings = settings_from_params(load_params_file(family.config).section("controller"), max_solve_time=UNBOUND)
    specs = make_specs(family, max(SCENE_A, SCENE_B) + 1, 0, settings, "continuous")
    scene_a, scene_b = specs[SCENE_A], specs[SCENE_B]

    used = NmpcController(settings)
    first = run(used, scene_a, family.schedule, STEPS_A)
    # scene A leaves what a reset must forget: a plan prepared for the next sample (feedback), an escape's wait,
    # the passage mode due, its regions
    memory = used.memory
    assert memory.prepared is not None and memory.escape_wait > 0 and memory.passage_due and used.regions
    assert any(report.phase == "escape" for report in first.searches)
    after = run(used, scene_b, family.schedule, STEPS_B)
    fresh = run(NmpcController(settings), scene_b, family.schedule, STEPS_B)
    assert any(report.phase == "escape" for report in fresh.searches)

    for name in ("status", "feedback"):
        ours, theirs = getattr(after, name), getattr(fresh, name)
        k = next((k for k, (a, b) in enumerate(zip(ours, theirs)) if a != b), None)
        assert k is None, f"sample {k}: {name} {ours[k]!r} after scene A, {theirs[k]!r} fresh"
    differ = [k for k in range(len(fresh.u)) if not np.array_equal(after.u[k], fresh.u[k])]
    assert not differ, f"sample {differ[0]}: u {after.u[differ[0]]} after scene A, {fresh.u[differ[0]]} fresh"
    for name in ("x", "y_a", "costs", "iterations"):
        assert np.array_equal(getattr(after, name), getattr(fresh, name)), name
