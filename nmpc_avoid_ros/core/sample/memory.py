"""The sample's records: what carries over to the next sample (SampleMemory, replaced whole by
`NmpcController.reset`), what one sample works on (Sample) and what it leaves for the next (Carry).

The memory is written by one function, `SampleMemory.advance`, at the end of each `step`, `prepare` and
`coast`: the sample's phases read the memory as it was when the sample began and record what they found in
the sample's Carry (the plan they kept, the iterate to continue, the passage mode, what became of the
escape and passage guesses, an override); `advance` turns that into the memory of the next sample, so that
the rules of what carries over read in one place."""

from __future__ import annotations

import time as clock
from dataclasses import dataclass, field

import numpy as np

from ..nlp.search import VIOLATION_TOLERANCE, Candidate
from .candidates import Guess
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
    passage_guess: the trajectory the passage's search found (core/sample/trajectory_guess.py), solved at the
        next passage guess's turn; None: none found.
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
    passage_guess: Guess | None = None
    mismatch: MismatchMargin = field(default_factory=MismatchMargin)
    command: np.ndarray | None = None
    last: Sample | None = None
    prepared: Prepared | None = None

    def carry(self) -> Carry:
        """A sample's working copy of what it may change, as the memory holds it now."""
        return Carry(self.plan, self.pending, self.reseed, self.passage, self.command, self.last, self.prepared,
                     self.passage_guess)

    def advance(self, carry: Carry) -> None:
        """The one writer of the memory: what the sample left in `carry` becomes the memory of the next sample."""
        self.plan, self.pending, self.reseed, self.passage = carry.plan, carry.pending, carry.reseed, carry.passage
        self.command, self.last, self.prepared = carry.command, carry.last, carry.prepared
        self.passage_guess = carry.passage_guess
        if carry.aged and self.plan is not None:  # no plan kept: the last one ages by the sample
            self.plan.age += 1
        if carry.waited:  # stalled, inside the wait after a vain escape: one sample of it spent
            self.escape_wait -= 1
        if carry.escape:  # the escape's guesses were solved
            self.escape_next = carry.escape_next if carry.escape == MORE else 0
            if carry.escape == VAIN:  # nothing better at a stall: wait, and try the long horizon next sample
                self.escape_wait = ESCAPE_RETRY_SAMPLES
                self.passage_due, self.passage_next = carry.passage_available, 0
        if carry.passage_try:  # a passage try was due: it is done, or its next batch due
            self.passage_due = carry.passage_try == MORE
            if carry.passage_try != NOT_STALLED:
                self.passage_next = carry.passage_next if carry.passage_try == MORE else 0
            if carry.passage_try == VAIN:
                self.escape_wait = ESCAPE_RETRY_SAMPLES
        if carry.overrides == RESET:
            self.overrides = 0
        elif carry.overrides == COUNTED:
            self.overrides += 1


#: what became of a sample's escape or passage guesses (Carry.escape, Carry.passage_try)
MORE, VAIN, DONE, ENTERED, NOT_STALLED = "more", "vain", "done", "entered", "not_stalled"
#: what a sample did to the count of overridden penetrating plans (Carry.overrides)
RESET, COUNTED = "reset", "counted"
#: samples without a new escape attempt after one that found no better plan (the scene is static)
ESCAPE_RETRY_SAMPLES = 10


@dataclass
class Carry:
    """What one sample leaves for the next (SampleMemory.advance turns it into the memory).

    The sample's working state, begun as the memory's (SampleMemory.carry) and changed by its phases:
    plan (a kept or answered plan replaces it; a passage hand-back shortens it), pending (the budget-cut
    iterate to continue), reseed, passage (the mode, entered or ended), command, last, prepared and
    passage_guess (as in SampleMemory). Then what the phases found: aged (no plan kept, the plan ages by one
    sample); waited (a stall inside the wait after a vain escape); escape (MORE: its next batch with
    escape_next, VAIN: nothing better at a stall, DONE: a plan kept or a penetrating base's guesses all
    tried; '' not run) and passage_available (the long horizon is there to try after a vain escape);
    passage_try (MORE with passage_next, VAIN, ENTERED, NOT_STALLED; '' not due); overrides (RESET or
    COUNTED; '' unchanged).
    """

    plan: Plan | None
    pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    reseed: bool
    passage: bool
    command: np.ndarray | None
    last: Sample | None
    prepared: Prepared | None
    passage_guess: Guess | None
    aged: bool = False
    waited: bool = False
    escape: str = ""
    escape_next: int = 0
    passage_available: bool = False
    passage_try: str = ""
    passage_next: int = 0
    overrides: str = ""


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
    command left (s, `command_sent`); stall_deferred: a step searched before its command in a loop that prepares
    (`feedback`): a stall's escape and passage guesses are left to the preparation after the command (a passage
    try before it held the command up to 0.3 s; a penetrating plan's escape still runs at once)."""

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
    stall_deferred: bool = False
    sent_at: float | None = None
    #: the depth its plans may predict and be clear (core/nlp/search.py `depth_allowance`)
    allowance: float = VIOLATION_TOLERANCE
    #: what it leaves for the next sample (set from the memory when the sample begins)
    carry: Carry | None = None

    def time_left(self) -> float:
        return self.deadline - clock.perf_counter()
