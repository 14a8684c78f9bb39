"""The preparation and feedback phases of NmpcController's sample (a mixin, core/sample/controller.py).

Between samples, after a command left, `prepare` solves the next sample ahead for the state the command leads
to: the whole search within max_solve_time (escapes and passage included), and a feedback law for the plan
found (core/sample/feedback.py). When the state arrives, `_feedback` answers from that law, no solver call;
where the law does not hold, `step` searches before its command (within `command_budget` when it is set).
"""

from __future__ import annotations

import math
import time as clock

import numpy as np

from ..nlp.search import SearchReport
from .feedback import ANSWERED_STATUS, Prepared
from .memory import Sample
from .status import FeedbackOutcome, StepStatus
from .step_result import Plan, StepResult

#: a preparation whose search took more than this share of the sample time builds no feedback law (a law takes 2-30
#: ms; the next state must not wait for it). At 0.5, a passage try that ran its whole budget in each preparation
#: (live campaign vdp-0161: 321 ms of a 0.5 s sample) left every sample after it to search before its command
LAW_TIME_SHARE = 0.85


class Preparation:
    """`prepare` and `_feedback` of NmpcController (they read the controller's NLPs, settings, laws and memory)."""

    def _settle(self) -> None:
        """What a sample answered by its prepared plan left for after its command (its command leaves first): the
        mismatch measured at its state, the next expectation, and when its command left (`command_sent`)."""
        last = self.memory.last
        if last is None or last.settled:
            return
        last.settled = True
        self._track_mismatch(last.measured, last.measured_at)
        self._expect(last)
        if last.sent_at is not None:
            self.command_sent(last.sent_at)

    @property
    def prepared(self) -> Prepared | None:
        """The plan prepared for the next sample (`prepare`), or None."""
        return self.memory.prepared

    def prepare(self, latency: float | None = None) -> Prepared | None:
        """Between samples, after the last step's command left: solve the next sample ahead (`feedback` setting).

        The next sample is expected one sample_time after the last, its state predicted `latency` + input_delay
        s past its measurement (default: the last sample's delay), as `step` will with that latency. That state,
        the last sample's moved along the model under the command it sent (its plan's x(1), or where a fallback
        or a budget-cut plan leads), goes through the whole sample (the search, within max_solve_time: also
        after a step whose search `command_budget` cut before its command); a converged, clear plan is kept with
        its feedback law, and the next `step` answers from it when the law holds (core/sample/feedback.py).
        Returns what was prepared; None with the setting off or nothing to predict from (no step or no command
        yet)."""
        mem, s = self.memory, self.settings
        begin = clock.perf_counter()
        self._settle()
        last = mem.last
        if self.feedback_laws is None or last is None or mem.command is None:
            return None
        delay = last.delay if latency is None else self.latency.delay(latency, s.input_delay, mem.command)
        # the state one sample on under the command: a fresh plan's x(1), else (a fallback, an aged or budget-cut
        # plan) the last state moved along the model
        plan = mem.plan
        x = self.latency.shift(plan.states[1], mem.command, delay - last.delay) if plan is not None and plan.age == 0 \
            else self.latency.shift(last.x, mem.command, s.sample_time + delay - last.delay)
        start = None if last.time is None else last.time + s.sample_time + delay - last.delay
        sample = self._sample(x, last.y_t, start, begin, measured=x, delay=delay, command=mem.command,
                              before_command=False)
        if not (sample.in_domain and np.all(np.isfinite(x))):
            return None
        report, carry = SearchReport(), sample.carry
        best = self._search_within(sample, report)[0]
        if best is None:
            mem.advance(carry)  # what the search found (escape and passage guesses tried, a hand-back)
            return None
        self._apply(sample, best, report)
        nlp, par = self.tiered.holding(self._active(carry), sample.par)
        # an unconverged plan (e.g. FATROP stopped at an acceptable point) gets a law where its KKT residual allows
        # (with mu = 0 nothing is avoided: a penetrating plan is the problem's answer, as the guard holds)
        # the law is built after a search that left some of the sample (LAW_TIME_SHARE; without it that sample
        # searches, warm-started from this plan)
        if clock.perf_counter() - begin > LAW_TIME_SHARE * s.sample_time:
            law = "no time left in the sample for the law"
        elif best.clear or s.mu == 0:
            law = self.feedback_laws.prepare(nlp, carry.plan, par)
        else:
            law = "the prepared plan penetrates"
        carry.plan.age = -1  # the plan of the sample to come
        ready = not isinstance(law, str)
        carry.prepared = Prepared(carry.plan, nlp, law if ready else None, "" if ready else law, x, start, delay,
                                  clock.perf_counter() - begin, report)
        mem.advance(carry)
        return mem.prepared

    def _feedback(self, sample: Sample, prepared: Prepared) -> StepResult | None:
        """The prepared plan moved to this sample's state by its law, as the result; None (the sample searches)
        where the law does not hold (core/sample/feedback.py), with why in `sample.feedback`."""
        assert self.feedback_laws is not None
        s = self.settings
        nlp, par = self.tiered.holding(self._active(sample.carry), sample.par)
        if prepared.law is not None and nlp is not prepared.nlp:  # the regions moved to another tier, a mode changed
            sample.feedback = FeedbackOutcome.INPUTS_CHANGED
            return None
        moved, outcome = self.feedback_laws.answer(prepared, par, s.feasibility_tolerance,
                                                   sample.allowance if s.mu > 0 else math.inf, sample.deadline) \
            if sample.in_domain else (None, FeedbackOutcome.INFEASIBLE)
        sample.feedback = outcome
        if moved is None:
            return None
        plan = prepared.plan
        U, X, y_a, _ = nlp.layout.split_w(moved.w)
        sample.carry.plan = self._continued(Plan(U, np.vstack([sample.x, X]), y_a, moved.x_a, moved.u_a,
                                                 plan.lam_x, plan.lam_g, 0, moved.costs))
        result = self._result(sample.carry.plan, sample.x, 0, StepStatus.OK, ANSWERED_STATUS, 0, False)
        result.horizon, result.feedback = nlp.layout.horizon, outcome
        # what was searched for this sample, ahead of it (escapes and passage included: the campaign counts them)
        result.search = prepared.report or SearchReport(phase="feedback", kept="prepared")
        result.feedback_time = sample.seconds = clock.perf_counter() - sample.begin
        return result
