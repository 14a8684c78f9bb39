"""The sample's records: what carries over to the next sample (SampleMemory, replaced whole by
`NmpcController.reset`) and what one sample works on (Sample)."""

from __future__ import annotations

import time as clock
from dataclasses import dataclass, field

import numpy as np

from ..nlp.search import VIOLATION_TOLERANCE, Candidate
from .feedback import Prepared
from .mismatch import MismatchMargin
from .status import FeedbackOutcome
from .step_result import Plan


@dataclass
class SampleMemory:
    """The controller's state between samples.

    plan: the last accepted plan (None: the next sample starts cold).
    pending: the last iterate (w, lam_x, lam_g) of a budget-cut solve that could not be applied: the
        next sample continues the optimisation from it (shifted) instead of starting over.
    reseed: a warm solve of a fast path failed outright (no usable iterate, no budget cut to go on
        from): the next sample re-seeds through the cold-start starts, else the fast path can stall on
        its own shifted guess sample after sample (measured in the campaign).
    escape_wait: samples to wait before the next escape attempt (one found nothing better).
    escape_next: with escape_guesses_per_sample, the index of the next escape guess to solve.
    overrides: consecutive samples whose avoidable plan penetration was overridden.
    passage: in the passage mode (the plan is the long NLP's, core/sample/passage.py).
    passage_due: the short escape found nothing: try the long NLP on the next stalled sample.
    passage_next: with guesses per sample, the index of the next passage guess to solve.
    mismatch: the one-step prediction errors measured and the margin they add (core/sample/mismatch.py).
    command: the last command answered [m] (a step's or `coast`'s u), in force while the next state ages
        (core/sample/latency.py); None before the first.
    last: the last step's sample (what `prepare` predicts the next one from); None before the first.
    prepared: the plan solved ahead for the next sample and its feedback law (core/sample/feedback.py);
        the plan is also `plan`, with age -1 (it is for the sample to come).
    """

    plan: Plan | None = None
    pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    reseed: bool = False
    escape_wait: int = 0
    escape_next: int = 0
    overrides: int = 0
    passage: bool = False
    passage_due: bool = False
    passage_next: int = 0
    mismatch: MismatchMargin = field(default_factory=MismatchMargin)
    command: np.ndarray | None = None
    last: Sample | None = None
    prepared: Prepared | None = None


@dataclass
class Sample:
    """One sample after `prepare`: the state x [n] planned from (the measured one predicted `delay` s
    ahead under `command` [m], core/sample/latency.py), tracked target y_t [p] (projected), parameters,
    the time of x (s, the regions' clock), the deadline of the search's solver calls and the end of the
    sample's budget (time.perf_counter s: the fallback's recovery solve ends by it), whether x is in the
    solve domain; then what the search adds: its solver seconds and the regular candidate. begin: when the
    sample began (time.perf_counter s); feedback: what became of a prepared plan (None: there was none);
    measured_at: the measurement's time (s, or None); settled: its mismatch bookkeeping is done (a sample
    answered by its prepared plan does it after its command, `NmpcController._settle`), sent_at: when its
    command left (s, `command_sent`)."""

    x: np.ndarray
    y_t: np.ndarray
    par: np.ndarray
    time: float | None
    deadline: float
    end: float
    in_domain: bool
    seconds: float = 0.0
    regular: Candidate | None = None
    measured: np.ndarray | None = None
    delay: float = 0.0
    command: np.ndarray | None = None
    begin: float = 0.0
    feedback: FeedbackOutcome | None = None
    measured_at: float | None = None
    settled: bool = True
    sent_at: float | None = None
    #: the depth its plans may predict and be clear (core/nlp/search.py `depth_allowance`)
    allowance: float = VIOLATION_TOLERANCE

    def time_left(self) -> float:
        return self.deadline - clock.perf_counter()
