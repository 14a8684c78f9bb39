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
result's SearchReport. Run-time changes (regions, margins, settings) are core/sample/runtime_changes.py.
"""

from __future__ import annotations

import math
import time as clock
from collections.abc import Sequence

import numpy as np

from ..config.settings import ControllerSettings
from ..errors import InputError
from ..nlp.projection import TargetProjection
from ..nlp.search import VIOLATION_TOLERANCE, Candidate, SearchReport, Start, search
from ..nlp.stagewise import COLD_START_ITERATIONS, make_nlp
from ..nlp.tiers import TieredNlp
from ..nlp.tracking import SEARCH_SHARE, NlpBase, TrackingNlp
from ..nlp.worker import SolveWorker
from ..problem.models import Model
from ..problem.regions import Region
from .candidates import EscapeGuesses, escape_admission, guess_batch, guess_start
from .fallback import FallbackSelector
from .latency import LatencyPrediction
from .memory import Sample, SampleMemory
from .passage import Passage
from .runtime_changes import RuntimeChanges
from .status import StepStatus
from .step_result import Plan, StepResult, validate_vector
from .warm_start import initial_guess

#: samples without a new escape attempt after one that found no better plan (the scene is static)
ESCAPE_RETRY_SAMPLES = 10

#: solver status of a sample whose state lies outside the solve domain (no solver was called)
OUTSIDE_SOLVE_DOMAIN = "outside_solve_domain"

#: what a step may take beyond NmpcController.sample_budget(), s: the fallback's simulations and the
#: result's bookkeeping after the recovery solve's limit (test/test_time_bound.py holds every step to it)
TIME_BOUND_MARGIN = 0.05

#: the reference's time budget for a cold start (no previous plan): this multiple of max_solve_time
COLD_START_TIME_FACTOR = 10.0


class NmpcController(RuntimeChanges):
    """Avoidance-aware tracking NMPC (simplified scheme, paper section IV).

    The NLP is built once in the constructor; `step` only packs parameters and solves.
    """

    def __init__(self, settings: ControllerSettings | None = None, model: Model | None = None) -> None:
        self.settings = settings or ControllerSettings()
        self.nlp = make_nlp(self.settings, model)
        self.model = self.nlp.model
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
        #: the mismatch margin (core/sample/mismatch.py) the regions are packed with
        self.mismatch_margin = 0.0
        #: the state predicted over the loop's latency (core/sample/latency.py), also the mismatch's reference
        self.latency = LatencyPrediction(self.model, self.settings)
        self.escape = EscapeGuesses(self.cold_nlp or self.nlp, self.model, self.settings)
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
        self._input_lo = np.asarray(self.settings.input_min, float)
        self._input_hi = np.asarray(self.settings.input_max, float)
        #: y_t -> its nearest reachable output y* (core/nlp/projection.py): the target the NLP tracks
        self.project_target = TargetProjection(self.settings, self.model)
        # every solver call of the search runs in a child that is abandoned at the sample's deadline
        # (core/nlp/worker.py): built last, so that the child holds every NLP
        nlps = [self.nlp, self.cold_nlp, long_nlp, *(tier for _, tier in self.tiered.tiers)]
        self.worker = SolveWorker([nlp for nlp in nlps if nlp is not None])
        for nlp in nlps:
            if nlp is not None:
                nlp.worker = self.worker

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
        return self.passage.nlp if self.memory.passage and self.passage.nlp is not None else self.nlp

    def nlp_of_horizon(self, horizon: int) -> NlpBase | None:
        """The regular or the passage NLP whose horizon is `horizon` (None if neither)."""
        return next((nlp for nlp in (self.nlp, self.passage.nlp) if nlp is not None and nlp.layout.horizon == horizon),
                    None)

    def in_solve_domain(self, x: np.ndarray) -> bool:
        """Whether the state x [n] lies within `solve_domain_margin` box widths of the state box (each
        bounded coordinate): only such states are handed to a solver (docs/design.md, 'A hard time bound')."""
        lo, hi = np.asarray(self.settings.state_min, float), np.asarray(self.settings.state_max, float)
        with np.errstate(invalid="ignore"):  # inf - inf on an unbounded coordinate: no limit there
            span = self.settings.solve_domain_margin * np.where(np.isfinite(hi - lo), hi - lo, 0.0)
            inside = ((x >= lo - span) | ~np.isfinite(lo)) & ((x <= hi + span) | ~np.isfinite(hi))
        return bool(np.all(inside))

    def sample_budget(self) -> float:
        """The next step's time bound, s: max_solve_time, or for a cold start (no plan yet, or a re-seed
        through the cold-start solvers) COLD_START_TIME_FACTOR times it. The search's solver calls end by
        SEARCH_SHARE of it (core/nlp/worker.py), the fallback's recovery solve within the rest."""
        return self.settings.max_solve_time * (COLD_START_TIME_FACTOR if self._cold() else 1.0)

    def _cold(self) -> bool:
        """The next sample starts cold: a fast path without a plan (or re-seeding), nothing to continue."""
        mem = self.memory
        return self.cold_nlp is not None and mem.pending is None and (mem.plan is None or mem.reseed) and \
            not mem.passage

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
        )

    # -- the sample --------------------------------------------------------------------------
    def step(self, x: Sequence[float], y_t: Sequence[float], regions: Sequence[Region] | None = None,
             time: float | None = None, latency: float = 0.0, command: Sequence[float] | None = None
             ) -> StepResult:
        """Solve for the measured state x [n] and target y_t [p]; regions replace the current ones if given.

        `time` (s, the clock of the regions' stamps) is when x was measured. The plan starts from x
        predicted `latency` + `input_delay` s later (at most one sample; core/sample/latency.py) under
        `command` [m], the command in force (default: the last step's u; none yet: no prediction);
        moving regions are placed at that instant (see `slot_values`). Returns within `sample_budget()`
        + TIME_BOUND_MARGIN.

        Raises InputError for a wrong-size or non-finite x or y_t and RegionError for regions that
        do not fit; the controller's state is unchanged then.
        """
        sample = self._prepare(x, y_t, regions, time, latency, command)
        report = SearchReport()
        try:
            best, last = self._search(sample, report)
        finally:
            self.worker.deadline = math.inf  # a solve outside a sample (tools, tests) has no deadline
        if best is None:
            result = self._fall_back(sample, last)
        else:
            result = self._guard(sample, best, self._apply(sample, best, report))
        result.search, result.target = report, sample.y_t
        result.solve_time, result.delay, result.measured_state = sample.seconds, sample.delay, sample.measured
        self.memory.mismatch.expect(sample.x, result.u, sample.time, self.settings.sample_time - sample.delay,
                                    origin=(sample.measured, time, sample.command))
        self.memory.command = result.u.copy()
        return result

    def command_sent(self, at: float) -> None:
        """The last step's command left at `at` (s, the clock of `time`): the plant held the previous command
        until at + input_delay, the new one from then. The mismatch check (core/sample/mismatch.py) then
        compares the next measurement with the plan from that instant, so a slow sample is not model error."""
        self.memory.mismatch.acts_at(at + self.settings.input_delay, self.latency.advance)

    def _prepare(self, x: Sequence[float], y_t: Sequence[float], regions: Sequence[Region] | None,
                 time: float | None, latency: float, command: Sequence[float] | None) -> Sample:
        """Validate, predict x over the latency, project the target, pack the parameters and set the solver
        calls' deadline."""
        begin = clock.perf_counter()
        measured = validate_vector("state", x, self.model.n)
        y_t = validate_vector("target", y_t, self.model.p)
        if time is not None and not math.isfinite(time):
            raise InputError(f"time must be finite seconds, got {time}")
        in_force = self.memory.command if command is None else validate_vector("command", command, self.model.m)
        delay = self.latency.delay(latency, self.settings.input_delay, in_force)
        if regions is not None:
            self.set_regions(regions)
        self._track_mismatch(measured, time)
        x = self.latency.advance(measured, in_force, delay) if delay > 0 else measured
        if not np.all(np.isfinite(x)):  # the prediction overflowed (a state far outside Z): plan from x itself
            x, delay = measured, 0.0
        start = None if time is None else time + delay
        y_t = self.project_target(y_t)
        self.tiered.set_time(start, self.settings.predict_obstacles)
        budget = self.sample_budget()
        self.worker.deadline = deadline = begin + SEARCH_SHARE * budget
        return Sample(x, y_t, self.parameters(x, y_t, start), start, deadline, begin + budget, self.in_solve_domain(x),
                      measured=measured, delay=delay, command=in_force)

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
                                   stop_at_clear=True)
        sample.seconds += spent
        sample.regular = best or last
        if best is None or mem.passage:
            return best, last
        penetrating = s.mu > 0 and self.escape.available and best.depth > VIOLATION_TOLERANCE
        if penetrating or self._escape_due(best, previous_y_a, sample):
            best = self._escape(sample, best, penetrating, report)
        elif mem.passage_due:
            best = self._try_passage(sample, best, previous_y_a, report)
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
                      for guess in self.escape.cold_guesses(x, y_t)]
        # SQP paths try a cold start themselves (cheap, and it works on small problems); FATROP fails
        # slowly there (hundreds of ms): the reference solves it
        if s.solver.startswith("sqp"):
            starts.append(self._start("straight" if mem.plan is None else "shifted", self.nlp, sample, budget, True))
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
        y_a = base.nlp.layout.split_w(base.w)[2]
        return self.escape.should_try(y_a, previous_y_a, sample.y_t, sample.par)

    def _escape(self, sample: Sample, base: Candidate, penetrating: bool, report: SearchReport) -> Candidate:
        """The lowest-cost plan among the base and the escape guesses (for a `penetrating` base: a clear
        plan first); none may predict more penetration than the base (candidates.escape_admission)."""
        mem, s, x = self.memory, self.settings, sample.x
        # FATROP solves the guesses itself, on the tier that holds the regions (measured on a 4-ellipse
        # van der Pol scene: the same plans, 12-14 ms for three guesses); the SQP paths stall from far
        # guesses: the reference solves them
        nlp = self.tiered if s.solver == "fatrop" else (self.cold_nlp or self.nlp)
        y_a = base.nlp.layout.split_w(base.w)[2]
        make = self.escape.penetration_guesses if penetrating else self.escape.guesses
        guesses = make(x, y_a, sample.y_t, sample.par, self._regions)
        # a penetrating plan is a safety matter: all its guesses now; a stall's may take several samples
        batch, rest = (guesses, 0) if penetrating else guess_batch(guesses, mem.escape_next,
                                                                    s.escape_guesses_per_sample)
        report.phase = "escape"
        best, _, spent = search([guess_start(nlp, x, sample.par, g) for g in batch], sample.par, sample.time_left(),
                                report, "escape", s.feasibility_tolerance, base=base, admit=escape_admission(base))
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
        y_a = base.nlp.layout.split_w(base.w)[2]
        if not self.escape.should_try(y_a, previous_y_a, sample.y_t, sample.par):
            return base
        starts, next_guess, rest = self.passage.starts(sample.x, sample.y_t, sample.par, base, self._regions,
                                                       mem.passage_next, s.escape_guesses_per_sample)
        report.phase, mem.passage_next = "passage_try", 0
        entered, _, spent = search(starts, sample.par, sample.time_left(), report, "passage_try",
                                   s.feasibility_tolerance, admit=self.passage.admit(base, sample.par))
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

    def _apply(self, sample: Sample, best: Candidate, report: SearchReport) -> StepResult:
        """Keep `best` as the plan and answer its first input (status ok, or truncated for a budget-cut one)."""
        mem = self.memory
        mem.pending, mem.reseed = None, False
        report.kept = report.kept or best.label
        active = self.active_nlp
        lam_x, lam_g = best.lam_x, best.lam_g
        if best.nlp is not active:  # solved by another NLP (the reference, a tier): multipliers start from zero
            lam_x, lam_g = np.zeros(active.layout.n_w), np.zeros(active.lbg.size)
        U, X, y_a, _ = best.nlp.layout.split_w(best.w)
        x_a, u_a = (v.copy() for v in best.nlp.steady(best.w))
        costs = tuple(float(c[0]) for c in best.nlp.terms(best.w, sample.par))
        mem.plan = Plan(U.copy(), np.vstack([sample.x, X]), y_a.copy(), x_a, u_a, lam_x, lam_g, 0, costs)
        regular = sample.regular
        status = StepStatus.OK if best.solved else StepStatus.TRUNCATED if best.budget_cut else StepStatus.UNCONVERGED
        result = self._result(mem.plan, sample.x, 0, status, regular.solver_status, regular.iterations,
                              regular.budget_cut)
        result.horizon = best.nlp.layout.horizon
        return result

    def _guard(self, sample: Sample, best: Candidate, result: StepResult) -> StepResult:
        """A plan that predicts penetration (e.g. a region placed over the current state) gives way to the
        input that predicts the least violation (FallbackSelector.check_plan), and says so. An avoidable
        penetration is overridden for at most N samples in a row, so that a plan the solver keeps
        choosing does not hold the plant still for good. When even that input penetrates the regions as
        planned around (inflated by the margins), the choice is made again against the regions themselves:
        only if they cannot be avoided either is it `region_unavoidable` (else `margin_unavoidable`)."""
        mem, H = self.memory, self.fallback.horizon
        if not (self.settings.mu > 0 and best.depth > VIOLATION_TOLERANCE):
            return result
        choice = self.fallback.check_plan(sample.x, sample.par, result.inputs[:H], sample.end)
        if choice is not None and choice.unavoidable and self._given != self._regions:
            real = self.fallback.check_plan(sample.x, self._given_parameters(sample), result.inputs[:H], sample.end)
            sample.seconds += 0.0 if real is None else real.solve_time
            result.margin_unavoidable = real is None or not real.unavoidable
            if result.margin_unavoidable:
                why = "margin unavoidable (the regions themselves are avoidable)"
                result.fallback_reason = f"{why}; {real.reason if real else 'plan: clear of them'}"
                result.fallback_predicted = dict(real.predicted) if real else {}
                sample.seconds += choice.solve_time
                if real is None:
                    return result
                choice = real
        if choice is None or (not choice.unavoidable and mem.overrides >= self.nlp.layout.horizon):
            mem.overrides = 0
            return result
        result.region_unavoidable = choice.unavoidable
        result.predicted_violation = choice.violation
        if not result.margin_unavoidable:
            result.fallback_predicted = dict(choice.predicted)
            why = "region unavoidable from the current state" if choice.unavoidable else "plan predicts penetration"
            result.fallback_reason = f"{why}; {choice.reason}"
        sample.seconds += choice.solve_time
        if choice.kind != "plan":
            mem.overrides += not choice.unavoidable
            result.status = StepStatus(f"fallback_{choice.kind}")
            result.u, result.inputs, result.states = choice.inputs[0].copy(), choice.inputs.copy(), choice.states
        return result

    def _given_parameters(self, sample: Sample) -> np.ndarray:
        """The sample's parameters with the regions as given, without the margins they are planned around with."""
        return self.parameters(sample.x, sample.y_t, sample.time, slots=self.given_slot_values(sample.time))

    def _fall_back(self, sample: Sample, last: Candidate | None) -> StepResult:
        """No usable plan: the candidate input predicting the least violation (core/sample/fallback.py); the plan
        ages by one. A budget-cut iterate of the regular NLP is continued next sample; a fast path whose
        warm solve failed outright re-seeds through the cold-start starts."""
        mem, x, par = self.memory, sample.x, sample.par
        if last is not None:
            regular = last.nlp.regular if isinstance(last.nlp, TieredNlp) else last.nlp
            mem.pending = (last.w, last.lam_x, last.lam_g) if (
                last.finite and last.budget_cut and regular is self.active_nlp) else None
            mem.reseed = self.cold_nlp is not None and mem.pending is None and not mem.passage
        status, iterations, budget_cut = (OUTSIDE_SOLVE_DOMAIN, 0, False) if last is None else (
            last.solver_status, last.iterations, last.budget_cut)
        plan = mem.plan
        shifted = u_a = None
        N = H = self.fallback.horizon  # the selector simulates N inputs: of a long plan, its first N
        if plan is not None:
            plan.age += 1
            N = len(plan.inputs)
            shifted = np.vstack([plan.inputs[plan.age:], np.tile(plan.u_a, (min(plan.age, N), 1))])[:H]
            u_a = plan.u_a
        choice = self.fallback.choose(x, par, shifted, u_a, plan is not None and plan.age < N, sample.in_domain,
                                      sample.end)
        sample.seconds += choice.solve_time
        if plan is not None and choice.kind in ("shift", "steady"):
            result = self._result(plan, x, plan.age, StepStatus(f"fallback_{choice.kind}"), status, iterations,
                                  budget_cut)
        else:
            nan_p = np.full(self.model.p, np.nan) if plan is None else plan.y_a.copy()
            nan_n = np.full(self.model.n, np.nan) if plan is None else plan.x_a.copy()
            u_a_out = choice.inputs[0].copy() if plan is None else plan.u_a.copy()
            result = StepResult(choice.inputs[0].copy(), choice.states, choice.inputs.copy(), nan_p, nan_n, u_a_out,
                                math.nan, math.nan, math.nan, StepStatus(f"fallback_{choice.kind}"), status,
                                iterations, 0.0, budget_cut)
        result.fallback_reason, result.fallback_predicted = choice.reason, dict(choice.predicted)
        result.predicted_violation = choice.violation
        result.horizon = 0 if last is None else last.nlp.layout.horizon
        return result

    def _result(self, plan: Plan, x: np.ndarray, age: int, status: StepStatus, solver_status: str, iterations: int,
                budget_cut: bool) -> StepResult:
        """The result of applying `plan` aged by `age` samples at state x (the solve time is set by `step`)."""
        N = len(plan.inputs)  # the regular horizon, or the passage mode's
        # into the input box: a solver meets its bounds to its tolerance only (1e-8 beyond them seen)
        inputs = np.clip(np.vstack([plan.inputs[age:], np.tile(plan.u_a, (min(age, N), 1))]), self._input_lo,
                         self._input_hi)
        states = np.vstack([x, plan.states[age + 1:], np.tile(plan.x_a, (min(age, N), 1))])
        return StepResult(inputs[0].copy(), states, inputs, plan.y_a.copy(), plan.x_a.copy(), plan.u_a.copy(),
                          *plan.costs, status, solver_status, iterations, 0.0, budget_cut)

    def coast(self) -> StepResult | None:
        """A sample without a new measurement: the next input of the last plan (then u_a).

        The plan ages by one sample, so the next `step` shifts its warm start accordingly; the
        result's first state is the plan's prediction for now. None when there is no plan yet.
        Status FALLBACK_SHIFT (or FALLBACK_STEADY once the plan is used up), solver status
        'no_new_state'.
        """
        plan = self.memory.plan
        if plan is None:
            return None
        plan.age += 1
        N = len(plan.inputs)
        predicted = plan.states[plan.age] if plan.age <= N else plan.x_a
        status = StepStatus.FALLBACK_SHIFT if plan.age < N else StepStatus.FALLBACK_STEADY
        result = self._result(plan, predicted, plan.age, status, "no_new_state", 0, False)
        self.memory.command = result.u.copy()
        return result

    def set_safe_input(self, u: Sequence[float]) -> None:
        """The model's safe input [m], a fallback candidate (InputError if malformed or outside the input box)."""
        self.fallback.safe_input = self.fallback.check_safe_input(u)

    def check_safe_input(self, u: Sequence[float]) -> np.ndarray:
        """u as a safe input [m], or InputError if malformed or outside the input box."""
        return self.fallback.check_safe_input(u)
