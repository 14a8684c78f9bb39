"""The passage's trajectory search (core/sample/trajectory_guess.py): a guess that is a trajectory of the model.

Scene vdp-0005 of the live campaign (seed 0, config/van_der_pol_live.yaml, continuous plant): a thin ellipse
lies across van der Pol's steady states between x1 = 1.31 and the target 2.0. The escape's polylines and the
passage NLP from them ended in plans through the ellipse, and the loop rested at x1 = 1.309 (`local_minimum`:
the campaign's own trajectory search found the way round). Held here:

- the search finds a swing round the ellipse: its first stages are the model's own trajectory under the inputs
  it holds, every stage clear as the passage NLP judges it (sub-steps and chords), ending at rest past the
  ellipse;
- the search stops at its end: past it, no stage function is evaluated;
- in the closed loop the passage mode enters from it and the loop reaches the target, clear of the ellipse
  and inside |x1 x2| <= 2.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.loop.closed_loop import make_plant, run_closed_loop
from nmpc_avoid_ros.core.nlp.search import VIOLATION_TOLERANCE
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.guess_starts import guess_w
from nmpc_avoid_ros.core.sample.trajectory_guess import TrajectorySearch

ROOT = Path(__file__).resolve().parents[1]
LIVE = ControllerSettings.from_params(
    load_params_file(ROOT / "config" / "van_der_pol_live.yaml").section("controller")).replace(codegen=False)
VDP_0005 = {"x0": [-0.01924262801082577, -0.4877127799297547], "target": [2.0025403963436457],
            "ellipse": Ellipse((1.0819683494169132, 0.7256852953918453), (1.3263373522058703, 0.29089738860129516),
                               2.2423124325816306)}
STALL = np.array([1.309367845, 0.0])  # where the loop rested before


def stalled_controller() -> tuple[NmpcController, np.ndarray]:
    """A controller with the scene's ellipse, one sample answered at the stall state, and its parameters there."""
    controller = NmpcController(LIVE)
    controller.step(STALL, np.array(VDP_0005["target"]), [VDP_0005["ellipse"]])
    return controller, controller.parameters(STALL, np.array(VDP_0005["target"]))


def test_the_search_finds_a_clear_swing_of_the_model_round_the_ellipse() -> None:
    controller, par = stalled_controller()
    passage = controller.passage
    y_a = STALL[:1]
    beyond = passage.guesses.beyond_blocks(y_a, passage.guesses.aim(np.array(VDP_0005["target"])), par)
    assert beyond and beyond[0][0] > 1.31
    guess = passage.search.find(STALL, y_a, beyond[0], par, time.perf_counter() + 30.0)
    assert guess is not None and guess.states.shape == (passage.horizon, 2)
    # its first stages are the model's trajectory (the NLP's own discretisation), up to where it rests
    step = controller.model.discrete_path(LIVE.sample_time, LIVE.discretization, LIVE.integration_steps)
    x, moved = STALL, 0
    for u, state in zip(guess.inputs, guess.states):
        following = np.asarray(step(x, u)[:, -1]).ravel()
        if not np.allclose(following, state, atol=1e-9):
            break
        x, moved = state, moved + 1
    assert moved >= 3, guess.states  # a swing: down, then up and over, not a line
    assert np.min(guess.states[:moved, 1]) < -0.5 and np.max(guess.states[:moved, 1]) > 0.5, guess.states
    assert x[0] > beyond[0][0] and abs(x[1]) < 0.2  # at rest past the ellipse where the search ended
    # clear as the passage NLP judges it, at and between the samples
    assert passage.nlp.max_depth(guess_w(passage.nlp, STALL, par, guess), par) <= VIOLATION_TOLERANCE
    np.testing.assert_allclose(guess.states[-1], [beyond[0][0], 0.0])  # resting at y_beyond's steady state


def test_the_search_stops_at_its_end() -> None:
    controller, par = stalled_controller()
    search: TrajectorySearch = controller.passage.search
    calls = []
    search._maps = {size: (lambda *args, f=f: calls.append(1) or f(*args)) for size, f in search._maps.items()}
    assert search.find(STALL, STALL[:1], np.array([2.6]), par, time.perf_counter() - 1.0) is None
    assert not calls


@pytest.mark.slow
def test_the_stalled_scene_passes_the_ellipse_and_reaches_the_target() -> None:
    # a generous budget: the search and the long NLP's solve each have the sample they need on a loaded machine
    controller = NmpcController(LIVE.replace(max_solve_time=2.0))
    ellipse = VDP_0005["ellipse"]
    run = run_closed_loop(controller, VDP_0005["x0"], VDP_0005["target"], 80, "continuous",
                          regions=lambda k: [ellipse] if k == 0 else None)
    # the mode is entered between the samples (the preparation's search); the samples after it solve the long NLP
    assert any(r.phase == "passage" for r in run.searches), [r.phase for r in run.searches]
    # and the long plan, prepared between the samples, answers some of them by its feedback law: no solve before the
    # command (they searched, 25-50 ms each, before the passage NLP had a law)
    in_passage = [k for k, r in enumerate(run.searches) if r.phase == "passage"]
    assert any(run.feedback[k] == "answered" for k in in_passage), [run.feedback[k] for k in in_passage]
    assert run.x[-1, 0] == pytest.approx(VDP_0005["target"][0], abs=0.05)
    assert max(ellipse.depth(x) for x in run.x) <= 1e-3
    assert np.max(np.abs(run.x[:, 0] * run.x[:, 1])) <= 2.0 + 1e-3


def test_the_campaign_counts_a_passage_entered_between_the_samples() -> None:
    """A preparation enters the passage mode after the command; the next step's report is the mode's own search.
    The campaign counted entries by the step's `entered_passage` and read 0 where 290 samples ran the long NLP."""
    from nmpc_avoid_ros.core.nlp.search import SearchReport
    from nmpc_avoid_ros.evaluation.campaign.scoring import passage_entries

    phases = ["warm", "escape", "passage_try", "passage", "passage", "passage_ended", "warm", "passage", "warm"]
    reports = [SearchReport(phase=phase) for phase in phases]
    assert passage_entries(reports) == (2, 3)
    reports[2].entered_passage = True  # entered by the step's own search: the same entry
    assert passage_entries(reports) == (2, 4)


def test_every_prepared_plan_of_the_passage_gets_its_feedback_law() -> None:
    """The long plans ride the ellipse's edge with slacks of ~3e-8. A law rebuilt the slacks as max(0, depth), which
    misses the solver's by its tolerance; with mu = 1e8 the cost's gradient moved by 1-2.4 and 6 of the 10
    preparations in the mode had no law ("stationarity residual"): their samples searched before the command. The
    plan now carries its solver's slacks (Plan.slacks)."""
    controller = NmpcController(LIVE.replace(max_solve_time=2.0))
    plant = make_plant("continuous", controller.model, controller.settings)
    x, target, regions = np.array(VDP_0005["x0"]), np.array(VDP_0005["target"]), [VDP_0005["ellipse"]]
    laws = []  # (has a law, why not) of each preparation in the mode
    for _ in range(40):
        result = controller.step(x, target, regions)
        regions = None
        x = plant.advance(x, result.u, LIVE.sample_time)
        prepared = controller.prepare()
        if controller.memory.passage and prepared is not None:
            laws.append((prepared.law is not None, prepared.why))
    assert len(laws) >= 5, "the scene entered the passage mode for a few samples"
    assert all(has_law for has_law, _ in laws), laws
