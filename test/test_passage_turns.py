"""The escape and the passage take turns in the one search (core/sample/search_phases.py), offline, no solver.

After a vain stall escape the passage NLP's guesses are due, one batch a sample. They must all get their
turn before the escape's wait runs out: before the fix the wait (ESCAPE_RETRY_SAMPLES searches, fewer
samples with feedback's two searches a sample) counted down during the passage's samples, a new escape
cycle took over, and its vain end restarted the passage at its first guess, so the later passage guesses
(more than ten of them: a van der Pol scene with several ellipses) were never solved (issue 31 item 1).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from nmpc_avoid_ros.core.nlp.search import SearchReport
from nmpc_avoid_ros.core.sample import search_phases
from nmpc_avoid_ros.core.sample.guess_starts import guess_batch
from nmpc_avoid_ros.core.sample.memory import SampleMemory
from nmpc_avoid_ros.core.sample.search_phases import ESCAPE_RETRY_SAMPLES, SearchPhases

ESCAPE_GUESSES, PASSAGE_GUESSES = 3, ESCAPE_RETRY_SAMPLES + 5


class _Layout:
    horizon = 5

    @staticmethod
    def y_a(w: np.ndarray) -> np.ndarray:
        return w[:1]


class _Phases(SearchPhases):
    """A controller stalled in front of a region whose every escape and passage guess is in vain."""

    def __init__(self) -> None:
        layout = _Layout()
        self.nlp = SimpleNamespace(layout=layout)
        self.tiered = self.cold_nlp = self.nlp
        self.settings = SimpleNamespace(mu=1e8, feasibility_tolerance=1e-6, escape_guesses_per_sample=1,
                                        solver="fatrop", max_iterations=200)
        self.memory = SampleMemory()
        self.memory.plan = SimpleNamespace(y_a=np.array([1.0]))
        self._regions = ()
        self.base = SimpleNamespace(label="shifted", nlp=self.nlp, w=np.array([1.0]), depth=0.0, clear=True)
        guesses = [SimpleNamespace(label=f"e{i}") for i in range(ESCAPE_GUESSES)]
        self.escape = SimpleNamespace(available=True, should_try=lambda *a: True,
                                      guesses=lambda *a: guesses, penetration_guesses=lambda *a: guesses)
        passage_guesses = [SimpleNamespace(label=f"passage:p{i}") for i in range(PASSAGE_GUESSES)]

        def starts(x, y_t, par, base, regions, next_guess, per_sample, end, found):
            batch, rest = guess_batch(passage_guesses, next_guess, per_sample)
            return batch, len(passage_guesses) - rest, rest, found

        self.passage = SimpleNamespace(available=True, can_hand_back=lambda *a: False, starts=starts,
                                       admit=lambda *a: (lambda c: "offset not lower"))

    def _regular_starts(self, sample):
        return [SimpleNamespace(label="shifted")], "warm"


def _search(starts, par, time_left, report, phase, tolerance, base=None, admit=None, stop_at_clear=False,
            allowance=1e-3):
    """Every guess in vain: the regular start gives the stalled plan, the escape keeps its base, no passage."""
    labels = [s.label for s in starts]
    report.tried.extend(SimpleNamespace(label=label, phase=phase) for label in labels)
    if phase == "warm":
        return _search.base, _search.base, 0.0
    return base, None, 0.0


def test_every_passage_guess_is_tried_before_the_escape_comes_back(monkeypatch) -> None:
    phases = _Phases()
    _search.base = phases.base
    monkeypatch.setattr(search_phases, "search", _search)
    monkeypatch.setattr(search_phases, "guess_start", lambda nlp, x, par, guess, *a, **k: guess)
    sample = SimpleNamespace(in_domain=True, par=np.zeros(1), x=np.zeros(2), y_t=np.array([2.0]), seconds=0.0,
                             regular=None, time_left=lambda: 1.0, allowance=1e-3, stall_deferred=False)
    solved: list[tuple[str, str]] = []
    for _ in range(ESCAPE_GUESSES + PASSAGE_GUESSES + 2):
        report = SearchReport()
        sample.carry = phases.memory.carry()  # each sample begins from the memory and advances it at its end
        phases._search(sample, report)
        phases.memory.advance(sample.carry)
        solved.extend((t.phase, t.label) for t in report.tried if t.phase != "warm")
    phases_seen = [phase for phase, _ in solved]
    assert phases_seen[:ESCAPE_GUESSES] == ["escape"] * ESCAPE_GUESSES
    passage = [label for phase, label in solved if phase == "passage_try"]
    # every passage guess once, in order, before any new escape
    assert passage[:PASSAGE_GUESSES] == [f"passage:p{i}" for i in range(PASSAGE_GUESSES)]
    assert "escape" not in phases_seen[ESCAPE_GUESSES:ESCAPE_GUESSES + PASSAGE_GUESSES]


def test_a_step_before_its_command_leaves_a_stalls_guesses_to_the_preparation(monkeypatch) -> None:
    """With `feedback` a step that searches (no law held) does so before its command: it solves the regular start
    only, and a stall's escape and passage guesses wait for the preparation after the command (a passage try there
    held the command up to 0.3 s in the live campaign); the turns' bookkeeping is the preparation's alone."""
    phases = _Phases()
    _search.base = phases.base
    monkeypatch.setattr(search_phases, "search", _search)
    monkeypatch.setattr(search_phases, "guess_start", lambda nlp, x, par, guess, *a, **k: guess)

    def sample(deferred: bool) -> SimpleNamespace:
        return SimpleNamespace(in_domain=True, par=np.zeros(1), x=np.zeros(2), y_t=np.array([2.0]), seconds=0.0,
                               regular=None, time_left=lambda: 1.0, allowance=1e-3, stall_deferred=deferred,
                               carry=phases.memory.carry())

    for deferred, phases_expected in ((True, ["warm"]), (False, ["warm", "escape"])):
        before = (phases.memory.escape_next, phases.memory.escape_wait, phases.memory.passage_due)
        report, step = SearchReport(), sample(deferred)
        phases._search(step, report)
        phases.memory.advance(step.carry)
        assert [t.phase for t in report.tried] == phases_expected
        if deferred:
            assert (phases.memory.escape_next, phases.memory.escape_wait, phases.memory.passage_due) == before
