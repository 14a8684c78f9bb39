"""The NMPC controller: one sample = prepare -> one search over ordered starts -> apply or fall back -> guard.

`NmpcController.step` reads as the sample does (docs/design.md, "The sample"):

* prepare: validate x and y_t, measure the last sample's one-step prediction error and widen the obstacles
  by it (core/sample/mismatch.py), track y_t's nearest reachable output (core/nlp/projection.py), pack the
  parameters, set the deadline of the sample's solver calls (core/nlp/worker.py);
* search (core/nlp/search.py, one budget rule and one ranking): the regular starts (the shifted plan;
  a cold start's resting plan, straight line and reference; a budget-cut iterate continued; the
  passage mode's long plan), then, from the plan found, the local-minimum escape guesses (a plan
  that stalls in front of a blocking region, or predicts penetration: core/sample/candidates.py) or the
  passage NLP's guesses (core/sample/passage.py);
* apply the best plan, or fall back (core/sample/fallback.py: the shifted plan, u_a, the safe input or a
  recovery solve, whichever predicts the least violation);
* guard: a plan that still predicts penetration gives way to the least-violating input.

What carries over between samples is one SampleMemory (core/sample/memory.py); what the search did is the
result's SearchReport. Run-time changes (regions, margins, settings) are core/sample/runtime_changes.py; the
preparation between samples and the feedback answer from its plan, core/sample/preparation.py.
"""

from __future__ import annotations

import math
import time as clock
from collections.abc import Callable, Sequence

import numpy as np

from ..config.settings import ControllerSettings
from ..errors import InputError
from ..nlp.codegen import cache_dir
from ..nlp.projection import TargetProjection
from ..nlp.search import SearchReport
from ..nlp.stagewise import COLD_START_ITERATIONS, make_nlp
from ..nlp.tiers import TieredNlp
from ..nlp.tracking import COLD_START_TIME_FACTOR, SEARCH_SHARE, NlpBase, TrackingNlp
from ..nlp.worker import SolveWorker
from ..problem.assumptions import assumption_5_warnings
from ..problem.models import Model
from ..problem.regions import Region
from .answers import SampleAnswers
from .candidates import EscapeGuesses, Guess
from .fallback import FallbackSelector
from .feedback import FeedbackLaws
from .latency import LatencyPrediction
from .memory import Sample, SampleMemory
from .passage import Passage
from .preparation import Preparation
from .runtime_changes import RuntimeChanges
from .search_phases import SearchPhases
from .step_result import StepResult, validate_vector

#: what a step may take beyond NmpcController.sample_budget(), s: the fallback's simulations and the
#: result's bookkeeping after the recovery solve's limit (test/test_time_bound.py holds every step to it)
TIME_BOUND_MARGIN = 0.05


class NmpcController(Preparation, SearchPhases, SampleAnswers, RuntimeChanges):
    """Avoidance-aware tracking NMPC (simplified scheme, paper section IV).

    The NLP is built once in the constructor; `step` only packs parameters and solves.
    """

    def __init__(self, settings: ControllerSettings | None = None, model: Model | None = None,
                 cold_guesses: Callable[[np.ndarray, np.ndarray], list[Guess]] | None = None) -> None:
        """`cold_guesses` (x [n], y_t [p]) -> the guesses a cold start tries in order on an ellipse tier (default: the
        resting plan and the straight line, core/sample/candidates.py); a seam for a user's own and for tests."""
        self.settings = settings or ControllerSettings()
        self.nlp = make_nlp(self.settings, model)
        self.model = self.nlp.model
        s = self.settings
        #: where the paper's assumptions fail for this model and Z (core/problem/assumptions.py), for people
        self.assumption_warnings = assumption_5_warnings(
            self.model, self.model.discrete(s.sample_time, s.discretization, s.integration_steps), s.state_min,
            s.state_max, s.input_min, s.input_max, s.steady_state_scale)
        # A cold start (no previous plan) begins from a straight line that may cross obstacles,
        # far from any solution: there the fast paths' line searches stall (measured: SQP beside
        # an ellipse; FATROP on the mobile robot for N >= 10) and a real-time budget is too small.
        # Where an ellipse tier holds the regions, the fast path solves it on the tier from a plan
        # resting at the plant's output, then the straight line (_regular_starts); otherwise, or
        # when neither is usable, the reference IPOPT formulation with a cold-start budget solves it.
        # The fast path continues from the plan.
        self.cold_nlp: NlpBase | None = None
        if self.settings.solver != "ipopt":
            cold = self.settings.replace(solver="ipopt", max_iterations=max(self.settings.max_iterations,
                                                                            COLD_START_ITERATIONS),
                                         max_solve_time=self.settings.max_solve_time * COLD_START_TIME_FACTOR)
            self.cold_nlp = TrackingNlp(cold, self.model)
        self._given: tuple[Region, ...] = ()  # as set
        self._regions: tuple[Region, ...] = ()  # as planned around: inflated by region_margin
        self._moving = False
        self._slots = np.zeros(self.nlp.slot_layout.size)
        self._keep_in_active = np.ones(self.nlp.layout.n_keep_in)
        self.memory = SampleMemory()
        self._domain: tuple[ControllerSettings, np.ndarray, np.ndarray] | None = None  # in_solve_domain's box
        #: the mismatch margin (core/sample/mismatch.py) the regions are packed with
        self.mismatch_margin = 0.0
        #: the state predicted over the loop's latency (core/sample/latency.py), also the mismatch's reference
        self.latency = LatencyPrediction(self.model, self.settings)
        self.escape = EscapeGuesses(self.cold_nlp or self.nlp, self.model, self.settings)
        self.cold_guesses = cold_guesses or self.escape.cold_guesses
        # the passage mode's NLP: the same problem with the longer horizon, built here once
        long_nlp = None
        if self.settings.escape_horizon:
            long_nlp = make_nlp(self.settings.replace(horizon=self.settings.escape_horizon, escape_horizon=0),
                                self.model)
        self.passage = Passage(long_nlp, self.nlp, self.model, self.settings)
        self.fallback = FallbackSelector(self.nlp, self.model, self.settings)
        # the regular NLP solved on the smallest ellipse tier that holds the regions (core/nlp/tiers.py)
        self.tiered = TieredNlp(self.settings, self.model, self.nlp, make_nlp)
        self.tiered.set_regions(self._regions)  # no regions yet: the smallest tier
        #: the feedback laws of prepared plans (core/sample/feedback.py, `feedback`): the regular NLP's and its tiers'
        #: (a plan's on the tier holding the regions), and the passage NLP's, by a thread with codegen_background
        s, cache = self.settings, cache_dir(self.settings.cache_dir)
        later = [long_nlp] if long_nlp is not None else []
        self.feedback_laws = FeedbackLaws([self.nlp, *(tier for _, tier in self.tiered.tiers)],
                                          cache if s.codegen else None, s.codegen_background, later,
                                          derivatives_in=cache) if s.feedback else None
        self._input_lo = np.asarray(self.settings.input_min, float)
        self._input_hi = np.asarray(self.settings.input_max, float)
        #: y_t -> its nearest reachable output y* (core/nlp/projection.py): the target the NLP tracks
        self.project_target = TargetProjection(self.settings, self.model)
        self.project_target(np.zeros(self.model.p))  # IPOPT's first call here, before the solve worker forks
        # every solver call of the search runs in a child that is abandoned at the sample's deadline
        # (core/nlp/worker.py): built last, so that the child holds every NLP
        nlps = [self.nlp, self.cold_nlp, long_nlp, *(tier for _, tier in self.tiered.tiers)]
        self.worker = SolveWorker([nlp for nlp in nlps if nlp is not None])
        for nlp in nlps:
            if nlp is not None:
                nlp.worker = self.worker
        self.worker.start()

    @property
    def nlp_builds(self) -> int:
        """How many solvers (CasADi nlpsol Functions) this controller has constructed.

        Counted where each is built (`solver_builds` of NlpBase and FallbackSelector): the solver
        path's own, a fast path's copy with the cold-start budget, the fast paths' cold-start
        reference (IPOPT), the fallback's recovery solve, the passage mode's long NLP and the target
        projection (core/nlp/projection.py). All are built in the constructor: nothing at run time (a
        target, obstacles, mu, the weights, entering or leaving the passage mode) adds to it.
        """
        parts = (self.nlp, self.cold_nlp, self.fallback, self.passage, self.tiered, self.project_target)
        return sum(part.solver_builds for part in parts if part is not None)

    @property
    def active_nlp(self) -> NlpBase:
        """The NLP of the regular solve: the passage mode's long one while in it, else the solver path's."""
        return self._active(self.memory)

    def nlp_of_horizon(self, horizon: int) -> NlpBase | None:
        """The regular or the passage NLP whose horizon is `horizon` (None if neither)."""
        return next((nlp for nlp in (self.nlp, self.passage.nlp) if nlp is not None and nlp.layout.horizon == horizon),
                    None)

    def in_solve_domain(self, x: np.ndarray) -> bool:
        """Whether the state x [n] lies within `solve_domain_margin` box widths of the state box (each
        bounded coordinate): only such states are handed to a solver (docs/design.md, 'A hard time bound')."""
        settings = self.settings
        if self._domain is None or self._domain[0] is not settings:  # recomputed when the settings change
            lo, hi = np.asarray(settings.state_min, float), np.asarray(settings.state_max, float)
            with np.errstate(invalid="ignore"):  # inf - inf on an unbounded coordinate: no limit there
                span = settings.solve_domain_margin * np.where(np.isfinite(hi - lo), hi - lo, 0.0)
                self._domain = (settings, np.where(np.isfinite(lo), lo - span, -np.inf),
                                np.where(np.isfinite(hi), hi + span, np.inf))
        _, low, high = self._domain
        return bool(np.all((x >= low) & (x <= high)))

    def sample_budget(self, before_command: bool = True) -> float:
        """The next step's time bound, s: max_solve_time, x COLD_START_TIME_FACTOR for a cold start from the safe input
        (none yet, or a fallback's), not under another command (the plant follows it); calls end by SEARCH_SHARE.
        With `feedback` and a command in force, a step's search before its command ends by `command_budget`;
        `before_command` False: a preparation's (max_solve_time)."""
        mem, s = self.memory, self.settings
        if not before_command:
            return s.max_solve_time
        if self.feedback_laws is not None and s.command_budget > 0 and mem.command is not None:
            return min(s.command_budget, s.max_solve_time)
        first = self._cold(mem) and (mem.command is None or np.array_equal(mem.command, self.fallback.safe_input))
        return s.max_solve_time * (COLD_START_TIME_FACTOR if first else 1.0)

    def reset(self) -> None:
        """Forget everything carried between samples (the next step starts cold)."""
        self.memory = SampleMemory()

    def parameters(self, x: np.ndarray, y_t: np.ndarray, time: float | None = None,
                   slots: np.ndarray | None = None) -> np.ndarray:
        """The NLP parameter vector for state x [n] valid at `time` (s) and target y_t [p] with the current
        settings and regions (see `slot_values`; `slots` replaces them, e.g. `given_slot_values`)."""
        s = self.settings
        return self.nlp.parameters(
            x, y_t, self.slot_values(time) if slots is None else slots, kappa=s.kappa, mu=s.mu,
            state_weights=np.asarray(s.state_weights, float),
            input_weights=np.asarray(s.input_weights, float), keep_in_active=self._keep_in_active,
            # in force while the plan's u(0) takes over (input_rate_max); none yet: the safe input the plant rests on
            command=self.fallback.safe_input if self.memory.command is None else self.memory.command,
        )

    # -- the sample --------------------------------------------------------------------------
    def step(self, x: Sequence[float], y_t: Sequence[float], regions: Sequence[Region] | None = None,
             time: float | None = None, latency: float = 0.0, command: Sequence[float] | None = None,
             search_latency: float | None = None) -> StepResult:
        """Solve for the measured state x [n] and target y_t [p]; regions replace the current ones if given.

        `time` (s, the clock of the regions' stamps) is when x was measured. The plan starts from x
        predicted `latency` + `input_delay` s later (at most one sample; core/sample/latency.py) under
        `command` [m], the command in force (default: the last step's u; none yet: no prediction);
        moving regions are placed at that instant (see `slot_values`). A sample prepared by `prepare` is
        answered from its plan where the feedback law holds (core/sample/feedback.py), else searched; a
        caller that holds a searched sample's command longer (the node's `command_latency`) gives that
        latency as `search_latency` (default `latency`). Returns within `sample_budget()` + TIME_BOUND_MARGIN.

        Raises InputError for a wrong-size or non-finite x or y_t and RegionError for regions that
        do not fit; the controller's state is unchanged then.
        """
        searched = latency if search_latency is None else search_latency
        prepared = self.memory.prepared
        sample = self._prepare(x, y_t, regions, time, searched if prepared is None else latency, command)
        result = None if prepared is None else self._feedback(sample, prepared)
        if result is None:
            if prepared is not None:  # the law did not hold: the mismatch now, and a searched sample's latency
                outcome = sample.feedback
                sample = self._prepare(x, y_t, None, time, searched, command, prepared_used=True)
                sample.feedback = outcome
            result = self._solve(sample)
        if prepared is not None:
            result.preparation_time = prepared.seconds
        result.target = sample.y_t
        result.solve_time = sample.seconds + result.preparation_time
        result.delay, result.measured_state = sample.delay, sample.measured
        self._terminal_values(result)
        carry = sample.carry
        carry.command, carry.last, carry.prepared = result.u.copy(), sample, None
        self.memory.advance(carry)
        sample.settled = not result.answered
        if sample.settled:
            self._expect(sample)
        return result

    def _expect(self, sample: Sample) -> None:
        """The mismatch check of the next measurement expects the plan applied at `sample` (its u in memory)."""
        self.memory.mismatch.expect(sample.x, self.memory.command, sample.time,
                                    self.settings.sample_time - sample.delay,
                                    origin=(sample.measured, sample.measured_at, sample.command))

    def _solve(self, sample: Sample) -> StepResult:
        """The sample searched: its plan applied and guarded, or the fallback."""
        report = SearchReport()
        sample.stall_deferred = self.feedback_laws is not None  # to the preparation, after the command (Sample)
        best, last = self._search_within(sample, report)
        if best is None:
            result = self._fall_back(sample, last)
        else:
            result = self._guard(sample, best, self._apply(sample, best, report))
        result.search, result.feedback = report, sample.feedback
        return result

    def command_sent(self, at: float) -> None:
        """The last step's command left at `at` (s, the clock of `time`): the plant held the previous command
        until at + input_delay, the new one from then. The mismatch check (core/sample/mismatch.py) then
        compares the next measurement with the plan from that instant, so a slow sample is not model error."""
        last = self.memory.last
        if last is not None and not last.settled:  # after the expectation `_settle` sets
            last.sent_at = at
            return
        self.memory.mismatch.acts_at(at + self.settings.input_delay, self.latency.advance)

    def _prepare(self, x: Sequence[float], y_t: Sequence[float], regions: Sequence[Region] | None,
                 time: float | None, latency: float, command: Sequence[float] | None,
                 prepared_used: bool = False) -> Sample:
        """Validate, predict x over the latency, project the target, pack the parameters and set the solver
        calls' deadline (`_sample`). `prepared_used`: the prepared plan was tried for this state (its law did not
        hold): the sample is searched, the mismatch measured now."""
        begin = clock.perf_counter()
        measured = validate_vector("state", x, self.model.n)
        y_t = validate_vector("target", y_t, self.model.p)
        if time is not None and not math.isfinite(time):
            raise InputError(f"time must be finite seconds, got {time}")
        in_force = self.memory.command if command is None else validate_vector("command", command, self.model.m)
        delay = self.latency.delay(latency, self.settings.input_delay, in_force)
        if regions is not None:
            self.set_regions(regions)
        self._settle()
        # else after the command (`_settle`): the prepared plan has its margin
        if self.memory.prepared is None or prepared_used:
            self._track_mismatch(measured, time)
        x = self.latency.advance(measured, in_force, delay) if delay > 0 else measured
        if not np.all(np.isfinite(x)):  # the prediction overflowed (a state far outside Z): plan from x itself
            x, delay = measured, 0.0
        start = None if time is None else time + delay
        # the projection ends by the search's deadline too: every solver call of a sample by the one deadline
        # an angle in y_t (unicycle_pose's yaw) the short way round from the robot's heading, then y* (in reach)
        y_t = self.project_target(self.model.nearest_target(y_t, x), end=begin + SEARCH_SHARE * self.sample_budget())
        sample = self._sample(x, y_t, start, begin, measured=measured, delay=delay, command=in_force)
        sample.measured_at = time  # (whether its mismatch bookkeeping waits for `prepare`: `step` sets `settled`)
        return sample

    def _sample(self, x: np.ndarray, y_t: np.ndarray, start: float | None, begin: float, *, measured: np.ndarray,
                delay: float, command: np.ndarray | None, before_command: bool = True) -> Sample:
        """The sample planned from x [n] at `start` (s) towards the tracked target y_t [p], begun at `begin`
        (time.perf_counter): its parameters and the deadline of its solver calls."""
        self.tiered.set_time(start, self.settings.predict_obstacles)
        budget, par = self.sample_budget(before_command), self.parameters(x, y_t, start)
        return Sample(x, y_t, par, start, begin + SEARCH_SHARE * budget, begin + budget, self.in_solve_domain(x),
                      measured=measured, delay=delay, command=command, begin=begin,
                      allowance=self.fallback.allowance(x, command, par), carry=self.memory.carry())

    def set_safe_input(self, u: Sequence[float]) -> None:
        """The model's safe input [m], a fallback candidate (InputError if malformed or outside the input box)."""
        self.fallback.safe_input = self.fallback.check_safe_input(u)

    def check_safe_input(self, u: Sequence[float]) -> np.ndarray:
        """u as a safe input [m], or InputError if malformed or outside the input box."""
        return self.fallback.check_safe_input(u)
