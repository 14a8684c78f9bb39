"""escape_guesses_per_sample: the local-minimum escape and the passage mode spread their guesses
over samples, so one sample's work stays bounded (core/sample/guess_starts.py guess_batch).

Scenes: the bench's `vdp_4_ellipses` (the paper's run among 4 ellipses, one across the steady
states on the way; all guesses at once made its worst warm sample 3 FATROP solves) and campaign
vdp-0100, where only the passage mode gets past (test_passage.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PAPER_TARGET, PAPER_X0
from test_passage import BEST, VDP_0100, run_vdp_0100, shipped

from nmpc_avoid_ros.bench.main import VDP_ELLIPSES
from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.nlp.search import Outcome
from nmpc_avoid_ros.core.sample.candidates import Guess
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.guess_starts import guess_batch


def _guesses(count: int) -> list[Guess]:
    return [Guess(f"g{i}", np.zeros(1), np.zeros((5, 2)), np.zeros((5, 1))) for i in range(count)]


def test_guess_batch_takes_the_next_guesses_and_starts_over_when_the_list_shrank():
    five = _guesses(5)
    batch, rest = guess_batch(five, 0, 0)
    assert [g.label for g in batch] == ["g0", "g1", "g2", "g3", "g4"] and rest == 0  # 0: all at once
    batch, rest = guess_batch(five, 0, 2)
    assert [g.label for g in batch] == ["g0", "g1"] and rest == 3
    batch, rest = guess_batch(five, 4, 2)
    assert [g.label for g in batch] == ["g4"] and rest == 0
    batch, rest = guess_batch(_guesses(3), 4, 2)  # the scene changed and fewer guesses are left
    assert [g.label for g in batch] == ["g0", "g1"] and rest == 1
    assert guess_batch([], 0, 1) == ([], 0)


def test_a_bad_guesses_per_sample_is_refused():
    with pytest.raises(ConfigError, match="escape_guesses_per_sample"):
        ControllerSettings(escape_guesses_per_sample=-1)


@pytest.fixture
def count_guess_solves():
    """A list that gets, per controller step, how many escape or passage guesses were solved (read from
    the step's search report)."""
    per_step: list[int] = []

    def on_step(k, result):
        per_step.append(sum(t.phase in ("escape", "passage_try") and t.outcome is not Outcome.NOT_TRIED
                            for t in result.search.tried))

    return per_step, on_step


def run_four_ellipses(per_sample: int, on_step=None):
    settings = ControllerSettings(max_solve_time=2.0, escape_guesses_per_sample=per_sample)
    results = []

    def record(k, result):
        results.append(result)
        if on_step:
            on_step(k, result)

    run = run_closed_loop(NmpcController(settings), PAPER_X0, PAPER_TARGET, 50,
                          regions=lambda k: list(VDP_ELLIPSES) if k == 0 else None, on_step=record)
    penetration = max(max(e.depth(x) for e in VDP_ELLIPSES for x in run.x),
                      float(np.max(np.abs(run.x[:, 0] * run.x[:, 1])) - 2.0))
    return run, results, penetration


def test_one_guess_per_sample_spreads_the_escape_and_still_reaches_the_target(count_guess_solves):
    per_step, on_step = count_guess_solves
    run, results, penetration = run_four_ellipses(1, on_step)
    assert max(per_step) == 1, per_step
    spread = [r.search for r in results if r.search.more_next_sample]
    assert spread, "the escape never needed a second sample: the scene no longer tests the batches"
    assert run.x[-1, 0] == pytest.approx(PAPER_TARGET[0], abs=0.05)
    assert penetration <= 1e-3
    assert set(run.status) == {"ok"}

    per_step.clear()
    all_at_once, _, penetration = run_four_ellipses(0, on_step)
    assert max(per_step) >= 3  # the same scene solves 3 guesses in one sample without the cap
    assert all_at_once.x[-1, 0] == pytest.approx(PAPER_TARGET[0], abs=0.05) and penetration <= 1e-3


def test_the_passage_mode_tries_its_guesses_one_per_sample_and_still_passes(count_guess_solves):
    per_step, on_step = count_guess_solves
    controller, run, results, penetration = run_vdp_0100(shipped().replace(escape_guesses_per_sample=1),
                                                         on_step=on_step)
    assert max(per_step) == 1, per_step
    assert run.x[-1, 0] == pytest.approx(BEST, abs=0.02), run.x[-1]
    assert penetration <= 1e-3
    labels = [r.escape for r in results]  # for the failure message only
    assert any(r.search.entered_passage for r in results), labels
    assert any(r.search.phase == "escape" and r.search.more_next_sample for r in results), \
        "the stall escape before the passage was not spread"
    assert VDP_0100["target"][0] < BEST  # the best admissible point, not the target, is what is reached
