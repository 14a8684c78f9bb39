"""The sample's search phases (a mixin of NmpcController, core/sample/controller.py): the regular starts, then
the local-minimum escape guesses or the passage NLP's guesses from the plan found, all through the one
`search` (core/nlp/search.py) within the sample's deadline."""

from __future__ import annotations

import math

import numpy as np

from ..nlp.search import Candidate, SearchReport, Start, search
from ..nlp.stagewise import COLD_START_ITERATIONS
from ..nlp.tiers import TieredNlp
from ..nlp.tracking import NlpBase
from .candidates import escape_admission, guess_batch, guess_start
from .memory import Sample
from .warm_start import initial_guess

#: samples without a new escape attempt after one that found no better plan (the scene is static)
ESCAPE_RETRY_SAMPLES = 10


class SearchPhases:
    """The search of NmpcController's sample (every method reads the controller's NLPs, settings and memory)."""

    def _search_within(self, sample: Sample, report: SearchReport) -> tuple[Candidate | None, Candidate | None]:
        """`_search` with the solver calls' deadline of the sample set for its duration."""
        self.worker.deadline = sample.deadline
        try:
            return self._search(sample, report)
        finally:
            self.worker.deadline = math.inf  # a solve outside a sample (tools, tests) has no deadline

    def _search(self, sample: Sample, report: SearchReport) -> tuple[Candidate | None, Candidate | None]:
        """The sample's search: the regular starts, then the escape or the passage guesses from the plan
        found. Returns (the best plan or None, the regular search's last candidate)."""
        mem, s = self.memory, self.settings
        if not sample.in_domain:
            report.phase = "no_solve"
            return None, None
        previous_y_a = None if mem.plan is None else mem.plan.y_a.copy()
        if mem.passage and self.passage.can_hand_back(mem.plan, self.nlp.layout.horizon):
            # the long plan reaches its x_a within N samples: its first N stages are a regular plan
            mem.plan, mem.pending, mem.passage = self.passage.hand_back(mem.plan, self.nlp), None, False
            report.phase = "passage_ended"
        starts, phase = self._regular_starts(sample)
        report.phase = "passage_ended" if report.phase == "passage_ended" else phase
        best, last, spent = search(starts, sample.par, sample.time_left(), report, phase, s.feasibility_tolerance,
                                   stop_at_clear=True, allowance=sample.allowance)
        sample.seconds += spent
        sample.regular = best or last
        if best is None or mem.passage:
            return best, last
        penetrating = s.mu > 0 and self.escape.available and not best.clear
        # the passage's guesses, once due, run to their end before the escape's wait counts down again: else a
        # new escape cycle began after ESCAPE_RETRY_SAMPLES searches (fewer with feedback's two searches a
        # sample) and its vain end restarted the passage at its first guess, so later ones were never tried
        if penetrating:
            best = self._escape(sample, best, True, report)
        elif mem.passage_due:
            best = self._try_passage(sample, best, previous_y_a, report)
        elif self._escape_due(best, previous_y_a, sample):
            best = self._escape(sample, best, False, report)
        return best, last

    def _regular_starts(self, sample: Sample) -> tuple[list[Start], str]:
        """The sample's first starts and their phase: the passage mode's shifted long plan; a budget-cut
        iterate continued; a cold start's guesses (on an ellipse tier: the resting plan, then the straight
        line; then the SQP path itself; then the reference, core/nlp/tiers.py and docs/design.md); or the
        shifted plan (on the tier that holds the regions)."""
        mem, s, x, y_t = self.memory, self.settings, sample.x, sample.y_t
        if mem.passage:
            return [self._start("passage", self.active_nlp, sample, s.max_iterations)], "passage"
        if mem.pending is not None:
            return [self._start("continued", self.nlp, sample, s.max_iterations)], "continue"
        if not self._cold():
            label = "straight" if mem.plan is None else "shifted"
            return [self._start(label, self.tiered, sample, s.max_iterations)], "warm"
        budget = max(s.max_iterations, COLD_START_ITERATIONS)
        starts = []
        if self.tiered.tier is not None and mem.plan is None and self.escape.available:
            starts = [guess_start(self.tiered, x, sample.par, guess, budget=budget, cold=True)
                      for guess in self.cold_guesses(x, y_t)]
        # SQP paths try a cold start themselves (cheap, and it works on small problems); FATROP fails
        # slowly there (hundreds of ms): the reference solves it
        if s.solver.startswith("sqp"):
            starts.append(self._start("straight" if mem.plan is None else "shifted", self.nlp, sample, budget, True))
        # a fast path's cold start gets its real-time budget, not the cold one, so that the reference always has
        # its turn: FATROP did not return from some starts of a car-like robot at rest (campaign bicycle-0024:
        # every sample's 1.2 s went to it, the car never moved; IPOPT solved the same sample in 14 iterations)
        for start in starts:
            start.time_limit = s.max_solve_time
        starts.append(self._start("reference", self.cold_nlp, sample, budget, True))
        return starts, "cold"

    def _start(self, label: str, nlp: NlpBase, sample: Sample, budget: int, cold: bool = False) -> Start:
        """A start of `nlp` from the warm-start rules (core/sample/warm_start.py) at this sample."""
        regular = nlp.regular if isinstance(nlp, TieredNlp) else nlp
        w0, lam_x0, lam_g0 = initial_guess(regular, sample.x, sample.y_t, self.memory.plan, self.memory.pending,
                                           self.settings, self.model, keep_duals=regular is self.active_nlp)
        return Start(label, nlp, regular.fill_slacks(w0, sample.par), lam_x0, lam_g0, budget, cold)

    def _escape_due(self, base: Candidate, previous_y_a: np.ndarray | None, sample: Sample) -> bool:
        """Try escape guesses now? Stalled in front of a blocking region, and not tried in vain just before."""
        if self.memory.escape_wait > 0:
            self.memory.escape_wait -= 1
            return False
        y_a = base.nlp.layout.y_a(base.w)
        return self.escape.should_try(y_a, previous_y_a, sample.y_t, sample.par)

    def _escape(self, sample: Sample, base: Candidate, penetrating: bool, report: SearchReport) -> Candidate:
        """The lowest-cost plan among the base and the escape guesses (for a `penetrating` base: a clear
        plan first); none may predict more penetration than the base (candidates.escape_admission)."""
        mem, s, x = self.memory, self.settings, sample.x
        # FATROP solves the guesses itself, on the tier that holds the regions (measured on a 4-ellipse
        # van der Pol scene: the same plans, 12-14 ms for three guesses); the SQP paths stall from far
        # guesses: the reference solves them
        nlp = self.tiered if s.solver == "fatrop" else (self.cold_nlp or self.nlp)
        y_a = base.nlp.layout.y_a(base.w)
        make = self.escape.penetration_guesses if penetrating else self.escape.guesses
        guesses = make(x, y_a, sample.y_t, sample.par, self._regions)
        # a penetrating plan is a safety matter: all its guesses now; a stall's may take several samples
        batch, rest = (guesses, 0) if penetrating else guess_batch(guesses, mem.escape_next,
                                                                    s.escape_guesses_per_sample)
        report.phase = "escape"
        best, _, spent = search([guess_start(nlp, x, sample.par, g) for g in batch], sample.par, sample.time_left(),
                                report, "escape", s.feasibility_tolerance, base=base, admit=escape_admission(base),
                                allowance=sample.allowance)
        sample.seconds += spent
        report.kept = best.label
        mem.escape_next = 0
        if best is base and rest:  # the next batch on the next sample (still stalled: the base held)
            mem.escape_next = len(guesses) - rest
            report.more_next_sample = rest
        elif best is base and not penetrating:  # nothing better here: do not try again every sample at rest
            mem.escape_wait = ESCAPE_RETRY_SAMPLES
            mem.passage_due, mem.passage_next = self.passage.available, 0  # the long horizon next sample
        return best

    def _try_passage(self, sample: Sample, base: Candidate, previous_y_a: np.ndarray | None,
                     report: SearchReport) -> Candidate:
        """The sample after a vain stall escape: if y_a is still stalled in front of the region, the
        passage NLP's plan that passes it (entering the mode), else the base."""
        mem, s = self.memory, self.settings
        mem.passage_due = False
        y_a = base.nlp.layout.y_a(base.w)
        if not self.escape.should_try(y_a, previous_y_a, sample.y_t, sample.par):
            return base
        starts, next_guess, rest = self.passage.starts(sample.x, sample.y_t, sample.par, base, self._regions,
                                                       mem.passage_next, s.escape_guesses_per_sample)
        report.phase, mem.passage_next = "passage_try", 0
        entered, _, spent = search(starts, sample.par, sample.time_left(), report, "passage_try",
                                   s.feasibility_tolerance, admit=self.passage.admit(base, sample.par),
                                   allowance=sample.allowance)
        sample.seconds += spent
        if entered is None:
            if rest:  # the next batch on the next sample
                mem.passage_due, mem.passage_next, report.more_next_sample = True, next_guess, rest
            else:  # every guess tried in vain
                mem.escape_wait = ESCAPE_RETRY_SAMPLES
            report.kept = base.label
            return base
        mem.passage = report.entered_passage = True
        report.kept = entered.label
        return entered
