"""The sample's search phases (a mixin of NmpcController, core/sample/controller.py): the regular starts, then
the local-minimum escape guesses or the passage NLP's guesses from the plan found, all through the one
`search` (core/nlp/search.py) within the sample's deadline."""

from __future__ import annotations

import math
import time as clock

import numpy as np

from ..nlp.search import Candidate, SearchReport, Start, search
from ..nlp.stagewise import COLD_START_ITERATIONS
from ..nlp.tiers import TieredNlp
from ..nlp.tracking import NlpBase
from .guess_starts import escape_admission, guess_batch, guess_start
from .memory import DONE, ENTERED, ESCAPE_RETRY_SAMPLES, MORE, NOT_STALLED, VAIN, Carry, Sample, SampleMemory
from .warm_start import initial_guess

__all__ = ["ESCAPE_RETRY_SAMPLES", "SearchPhases"]

#: the passage's trajectory search (core/sample/trajectory_guess.py) ends by this share of the sample's time left
TRAJECTORY_SHARE = 0.9


class SearchPhases:
    """The search of NmpcController's sample (every method reads the controller's NLPs, settings and memory, and
    records what it found in the sample's Carry: core/sample/memory.py)."""

    def _active(self, state: SampleMemory | Carry) -> NlpBase:
        """The regular solve's NLP in the mode `state` holds (the memory, or a sample's carry: the mode it entered or
        ended): the passage mode's long one while in it, else the solver path's."""
        return self.passage.nlp if state.passage and self.passage.nlp is not None else self.nlp

    def _cold(self, state: SampleMemory | Carry) -> bool:
        """A sample from `state` starts cold: a fast path without a plan (or re-seeding), nothing to continue."""
        return self.cold_nlp is not None and state.pending is None and (state.plan is None or state.reseed) and \
            not state.passage

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
        mem, s, carry = self.memory, self.settings, sample.carry
        if not sample.in_domain:
            report.phase = "no_solve"
            return None, None
        previous_y_a = None if carry.plan is None else carry.plan.y_a.copy()
        if carry.passage and self.passage.can_hand_back(carry.plan, self.nlp.layout.horizon):
            # the long plan reaches its x_a within N samples: its first N stages are a regular plan
            carry.plan, carry.pending, carry.passage = self.passage.hand_back(carry.plan, self.nlp), None, False
            report.phase = "passage_ended"
        starts, phase = self._regular_starts(sample)
        report.phase = "passage_ended" if report.phase == "passage_ended" else phase
        best, last, spent = search(starts, sample.par, sample.time_left(), report, phase, s.feasibility_tolerance,
                                   stop_at_clear=True, allowance=sample.allowance)
        sample.seconds += spent
        sample.regular = best or last
        if best is None or carry.passage:
            return best, last
        penetrating = s.mu > 0 and self.escape.available and not best.clear
        # the passage's guesses, once due, run to their end before the escape's wait counts down again: else a
        # new escape cycle began after ESCAPE_RETRY_SAMPLES searches (fewer with feedback's two searches a
        # sample) and its vain end restarted the passage at its first guess, so later ones were never tried
        if penetrating:
            best = self._escape(sample, best, True, report)
        elif sample.stall_deferred:
            pass  # the preparation after the command tries them (Sample.stall_deferred)
        elif mem.passage_due:
            best = self._try_passage(sample, best, previous_y_a, report)
        elif self._escape_due(best, previous_y_a, sample):
            best = self._escape(sample, best, False, report)
        return best, last

    def _regular_starts(self, sample: Sample) -> tuple[list[Start], str]:
        """The sample's first starts and their phase: the passage mode's shifted long plan; a budget-cut
        iterate continued; a cold start's guesses (on an ellipse tier: a car-like model's rollout, the resting
        plan, then the straight line; then the SQP path itself; then the reference, core/nlp/tiers.py and
        docs/design.md); or the shifted plan (on the tier that holds the regions)."""
        carry, s, x, y_t = sample.carry, self.settings, sample.x, sample.y_t
        if carry.passage:
            return [self._start("passage", self._active(carry), sample, s.max_iterations)], "passage"
        if carry.pending is not None:
            return [self._start("continued", self.nlp, sample, s.max_iterations)], "continue"
        if not self._cold(carry):
            label = "straight" if carry.plan is None else "shifted"
            return [self._start(label, self.tiered, sample, s.max_iterations)], "warm"
        budget = max(s.max_iterations, COLD_START_ITERATIONS)
        starts = []
        if self.tiered.tier is not None and carry.plan is None and self.escape.available:
            starts = [guess_start(self.tiered, x, sample.par, guess, budget=budget, cold=True)
                      for guess in self.cold_guesses(x, y_t)]
        # SQP paths try a first start themselves (cheap, and it works on small problems); FATROP fails slowly there
        # (hundreds of ms): the reference solves it. A re-seed goes to the reference at once: its warm start is the
        # shifted plan that just failed, and with a command in force its budget is the warm one (`sample_budget`),
        # which a second try from that plan used up (the robot's SQP path: every re-seed abandoned at 160 ms)
        if s.solver.startswith("sqp") and carry.plan is None:
            starts.append(self._start("straight", self.nlp, sample, budget, True))
        # a fast path's cold start gets its real-time budget, not the cold one, so that the reference always has
        # its turn: FATROP did not return from some starts of a car-like robot at rest (campaign bicycle-0024:
        # every sample's 1.2 s went to it, the car never moved; IPOPT solved the same sample in 14 iterations)
        for start in starts:
            start.time_limit = s.max_solve_time
        starts.append(self._start("reference", self.cold_nlp, sample, budget, True))
        return starts, "cold"

    def _start(self, label: str, nlp: NlpBase, sample: Sample, budget: int, cold: bool = False) -> Start:
        """A start of `nlp` from the warm-start rules (core/sample/warm_start.py) at this sample."""
        regular, carry = nlp.regular if isinstance(nlp, TieredNlp) else nlp, sample.carry
        w0, lam_x0, lam_g0 = initial_guess(regular, sample.x, sample.y_t, carry.plan, carry.pending,
                                           self.settings, self.model, keep_duals=regular is self._active(carry),
                                           tail=self._tail)
        return Start(label, nlp, regular.fill_slacks(w0, sample.par), lam_x0, lam_g0, budget, cold)

    def _escape_due(self, base: Candidate, previous_y_a: np.ndarray | None, sample: Sample) -> bool:
        """Try escape guesses now? Stalled in front of a blocking region, and not tried in vain just before (a
        sample inside that wait spends one of it: Carry.waited)."""
        if self.memory.escape_wait > 0:
            sample.carry.waited = True
            return False
        y_a = base.nlp.layout.y_a(base.w)
        return self.escape.should_try(y_a, previous_y_a, sample.y_t, sample.par)

    def _escape(self, sample: Sample, base: Candidate, penetrating: bool, report: SearchReport) -> Candidate:
        """The lowest-cost plan among the base and the escape guesses (for a `penetrating` base: a clear
        plan first); none may predict more penetration than the base (guess_starts.escape_admission)."""
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
        carry = sample.carry
        carry.escape = DONE
        if best is base and rest:  # the next batch on the next sample (still stalled: the base held)
            carry.escape, carry.escape_next = MORE, len(guesses) - rest
            report.more_next_sample = rest
        elif best is base and not penetrating:  # nothing better here: do not try again every sample at rest
            carry.escape, carry.passage_available = VAIN, self.passage.available  # the long horizon next sample
        return best

    def _try_passage(self, sample: Sample, base: Candidate, previous_y_a: np.ndarray | None,
                     report: SearchReport) -> Candidate:
        """The sample after a vain stall escape: if y_a is still stalled in front of the region, the
        passage NLP's plan that passes it (entering the mode), else the base."""
        mem, s, carry = self.memory, self.settings, sample.carry
        carry.passage_try = NOT_STALLED
        y_a = base.nlp.layout.y_a(base.w)
        if not self.escape.should_try(y_a, previous_y_a, sample.y_t, sample.par):
            return base
        begin = clock.perf_counter()
        # the trajectory search may take what is left but a share for a solve in the same turn
        starts, next_guess, rest, carry.passage_guess = self.passage.starts(
            sample.x, sample.y_t, sample.par, base, self._regions, mem.passage_next, s.escape_guesses_per_sample,
            begin + TRAJECTORY_SHARE * sample.time_left(), carry.passage_guess)
        sample.seconds += clock.perf_counter() - begin
        report.phase = "passage_try"
        entered, _, spent = search(starts, sample.par, sample.time_left(), report, "passage_try",
                                   s.feasibility_tolerance, admit=self.passage.admit(base, sample.par),
                                   allowance=sample.allowance)
        sample.seconds += spent
        if entered is None:
            if rest:  # the next batch on the next sample
                carry.passage_try, carry.passage_next, report.more_next_sample = MORE, next_guess, rest
            else:  # every guess tried in vain
                carry.passage_try = VAIN
            report.kept = base.label
            return base
        carry.passage_try, carry.passage = ENTERED, True
        report.entered_passage = True
        report.kept = entered.label
        return entered
