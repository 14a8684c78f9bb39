"""The NMPC controller: one bounded solve per sample, shifted warm start, escape and fallback.

Escape (core/candidates.py): when y_a has stalled in front of a region that covers the steady
states on the way to the target, more initial guesses are solved and the lowest-cost plan is kept;
when they find nothing better, the passage mode (core/passage.py) tries the same problem with the
longer horizon `escape_horizon` and, once it plans past the region, solves that one until the
state rests beyond it.
Fallback (core/fallback.py, docs/design.md): when a solve fails or its budget runs out without a
usable iterate, the input among the shifted plan, u_a of the last plan, the safe input and a short
recovery solve that predicts the least violation over the next samples.
"""

from __future__ import annotations

import math
import time as clock
from collections.abc import Sequence

import numpy as np

from .candidates import EscapeGuesses, Solution, guess_batch, lowest_cost, plan_cost
from .errors import ConfigError, InputError
from .fallback import VIOLATION_TOLERANCE, FallbackSelector
from .models import Model, make_model
from .nlp import SEARCH_SHARE, NlpBase, TrackingNlp
from .passage import Passage
from .projection import TargetProjection
from .regions import Region
from .settings import RUNTIME_FIELDS, ControllerSettings
from .stagewise import COLD_START_ITERATIONS, StagewiseNlp
from .status import StepStatus
from .step_result import Attempt, Plan, StepResult, attempt, validate_vector
from .tiers import Tiers
from .warm_start import initial_guess
from .worker import SolveWorker

#: samples without a new escape attempt after one that found no better plan (the scene is static)
ESCAPE_RETRY_SAMPLES = 10

#: solver status of a sample whose state lies outside the solve domain (no solver was called)
OUTSIDE_SOLVE_DOMAIN = "outside_solve_domain"

#: what a step may take beyond NmpcController.sample_budget(), s: the fallback's simulations and the
#: result's bookkeeping after the recovery solve's limit (test/test_time_bound.py holds every step to it)
TIME_BOUND_MARGIN = 0.05

#: the reference's time budget for a cold start (no previous plan): this multiple of max_solve_time
COLD_START_TIME_FACTOR = 10.0


def make_nlp(settings: ControllerSettings, model: Model | None = None) -> NlpBase:
    """The formulation of the settings' solver path: multiple shooting (ipopt) or stage-wise."""
    if settings.solver == "ipopt":
        return TrackingNlp(settings, model)
    model = model or make_model(settings.model)
    if model.steady_state is None:
        # the stage-wise paths carry y_a as a state and need x_a = g_x(y_a) in closed form
        raise ConfigError(f"solver {settings.solver!r} needs a closed-form steady state, which model "
                          f"{model.name!r} has not (its heading at rest is free): use solver 'ipopt'")
    return StagewiseNlp(settings, model)


class NmpcController:
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
        # resting at the plant's output, then the straight line (Tiers.cold_start); otherwise, or
        # when neither is usable, the reference IPOPT formulation with a cold-start budget solves it.
        # The fast path continues from the plan.
        self.cold_nlp: NlpBase | None = None
        if self.settings.solver != "ipopt":
            cold = self.settings.replace(solver="ipopt", max_iterations=max(self.settings.max_iterations,
                                                                            COLD_START_ITERATIONS),
                                         max_solve_time=self.settings.max_solve_time * COLD_START_TIME_FACTOR)
            self.cold_nlp = TrackingNlp(cold, self.model)
        self._regions: tuple[Region, ...] = ()
        self._moving = False
        self._slots = np.zeros(self.nlp.slot_layout.size)
        self._keep_in_active = np.ones(self.nlp.layout.n_keep_in)
        self._plan: Plan | None = None
        # the last iterate of a budget-cut solve that could not be applied: the next sample
        # continues the optimisation from it (shifted) instead of starting over
        self._pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # a warm solve of the fast path failed outright (no usable iterate, no budget cut to go
        # on from): the next sample re-seeds through the cold-start solvers, else the fast path
        # can stall on its own shifted guess sample after sample (measured in the campaign)
        self._reseed = False
        self.escape = EscapeGuesses(self.cold_nlp or self.nlp, self.model, self.settings)
        # samples to wait before the next escape attempt (one that found nothing better)
        self._escape_wait = 0
        # with escape_guesses_per_sample: the index of the next escape guess to solve (its batch)
        self._escape_next = 0
        self._overrides = 0  # consecutive samples whose avoidable plan penetration was overridden
        self._start_report: list[str] = []  # a cold start's guesses on a tier, this sample (for `escape`)
        # the passage mode's NLP: the same problem with the longer horizon, built here once
        long_nlp = None
        if self.settings.escape_horizon:
            long_nlp = make_nlp(self.settings.replace(horizon=self.settings.escape_horizon, escape_horizon=0),
                                self.model)
        self.passage = Passage(long_nlp, self.nlp, self.model, self.settings)
        self.fallback = FallbackSelector(self.nlp, self.model, self.settings)
        self.tiers = Tiers(self.settings, self.model, self.nlp, make_nlp)
        self._tier_slots: dict[int, np.ndarray] = {}  # static slots per tier NLP (id), packed once per region set
        self._input_lo = np.asarray(self.settings.input_min, float)
        self._input_hi = np.asarray(self.settings.input_max, float)
        #: y_t -> its nearest reachable output y* (core/projection.py): the target the NLP tracks
        self.project_target = TargetProjection(self.settings, self.model)
        # every solver call of the search runs in a child that is abandoned at the sample's deadline
        # (core/worker.py): built last, so that the child holds every NLP
        nlps = [self.nlp, self.cold_nlp, long_nlp, *(tier for _, tier in self.tiers.nlps)]
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
        projection (core/projection.py). All are
        built in the constructor: nothing at run time (a target, obstacles, mu, the weights, entering
        or leaving the passage mode) adds to it.
        """
        parts = (self.nlp, self.cold_nlp, self.fallback, self.passage, self.tiers, self.project_target)
        return sum(part.solver_builds for part in parts if part is not None)

    @property
    def active_nlp(self) -> NlpBase:
        """The NLP of the regular solve: the passage mode's long one while in it, else the solver path's."""
        return self.passage.nlp if self.passage.active and self.passage.nlp is not None else self.nlp

    def nlp_of_horizon(self, horizon: int) -> NlpBase | None:
        """The regular or the passage NLP whose horizon is `horizon` (None if neither)."""
        return next((nlp for nlp in (self.nlp, self.passage.nlp) if nlp is not None and nlp.layout.horizon == horizon),
                    None)

    # -- run-time changes (never rebuild) ---------------------------------------------------
    @property
    def regions(self) -> tuple[Region, ...]:
        return self._regions

    def set_regions(self, regions: Sequence[Region]) -> None:
        """Replace the obstacle regions (RegionError if they do not fit the slots; nothing changes then)."""
        slots = self.nlp.slot_layout.pack(list(regions), self.nlp.output_frame_available, predict=False)
        self._regions, self._slots = tuple(regions), slots
        self._tier_slots = {}
        self._moving = any(r.moving for r in self._regions)

    def slot_values(self, time: float | None = None, nlp: NlpBase | None = None) -> np.ndarray:
        """The obstacle slot parameters of a sample whose x(0) is valid at `time` (s), in the slot
        layout of `nlp` (default: the regular NLP; else an ellipse tier, core/tiers.py).

        With `predict_obstacles` on, moving regions are placed where they are at `time` and
        predicted stage by stage (time None: each pose counts as valid at x(0)); off, every region
        stays where it was at its stamp. Static regions only: the slots packed once per region set.
        """
        nlp = nlp or self.nlp
        if self._moving and self.settings.predict_obstacles:
            return nlp.slot_layout.pack(list(self._regions), nlp.output_frame_available, time)
        if nlp is self.nlp:
            return self._slots
        if id(nlp) not in self._tier_slots:
            self._tier_slots[id(nlp)] = nlp.slot_layout.pack(list(self._regions), nlp.output_frame_available,
                                                             predict=False)
        return self._tier_slots[id(nlp)]

    def set_keep_in_active(self, active: Sequence[bool]) -> None:
        """Switch the configured algebraic regions on or off (one flag per `keep_in` entry)."""
        flags = np.asarray(active, dtype=float).ravel()
        if flags.size != self.nlp.layout.n_keep_in:
            raise ConfigError(f"expected {self.nlp.layout.n_keep_in} keep-in flags, got {flags.size}")
        self._keep_in_active = flags

    def checked_settings(self, **changes: float | Sequence[float]) -> ControllerSettings:
        """The settings with run-time fields changed, validated but not applied (ConfigError says why)."""
        structural = sorted(set(changes) - RUNTIME_FIELDS)
        if structural:
            raise ConfigError(f"changing {', '.join(structural)} needs a new controller (NLP rebuild)")
        new = self.settings.replace(**changes)
        for name, size in (("state_weights", self.model.n), ("input_weights", self.model.m)):
            if len(getattr(new, name)) != size:
                raise ConfigError(f"{name} needs {size} values, got {len(getattr(new, name))}")
        return new

    def update_settings(self, **changes: float | Sequence[float]) -> None:
        """Change run-time fields (mu, kappa, weights, predict_obstacles) for the next step; nothing is rebuilt."""
        self.settings = self.checked_settings(**changes)

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
        SEARCH_SHARE of it (core/worker.py), the fallback's recovery solve within the rest."""
        cold = self.cold_nlp is not None and self._pending is None and (self._plan is None or self._reseed)
        return self.settings.max_solve_time * (COLD_START_TIME_FACTOR if cold else 1.0)

    def reset(self) -> None:
        """Forget the last plan (the next step starts cold)."""
        self._plan = None
        self._pending = None
        self._reseed = False
        self._escape_wait = 0
        self._escape_next = 0
        self._overrides = 0
        self.passage.active = self.passage.due = False
        self.passage.next_guess = 0

    def parameters(self, x: np.ndarray, y_t: np.ndarray, time: float | None = None) -> np.ndarray:
        """The NLP parameter vector for state x [n] measured at `time` (s) and target y_t [p] with the
        current settings and regions (see `slot_values`)."""
        s = self.settings
        return self.nlp.parameters(
            x, y_t, self.slot_values(time), kappa=s.kappa, mu=s.mu, state_weights=np.asarray(s.state_weights, float),
            input_weights=np.asarray(s.input_weights, float), keep_in_active=self._keep_in_active,
        )

    # -- the sample --------------------------------------------------------------------------
    def step(self, x: Sequence[float], y_t: Sequence[float], regions: Sequence[Region] | None = None,
             time: float | None = None) -> StepResult:
        """Solve for the measured state x [n] and target y_t [p]; regions replace the current ones if given.

        `time` (s, the clock of the regions' stamps) is when x was measured: moving regions are
        predicted from it (see `slot_values`).

        Raises InputError for a wrong-size or non-finite x or y_t and RegionError for regions that
        do not fit; the controller's state is unchanged then.
        """
        begin = clock.perf_counter()
        x = validate_vector("state", x, self.model.n)
        y_t = validate_vector("target", y_t, self.model.p)
        if time is not None and not math.isfinite(time):
            raise InputError(f"time must be finite seconds, got {time}")
        if regions is not None:
            self.set_regions(regions)
        s = self.settings
        y_t = self.project_target(y_t)
        par = self.parameters(x, y_t, time)
        self.worker.deadline = begin + SEARCH_SHARE * self.sample_budget()
        if not self.in_solve_domain(x):
            result = self._fallback(x, par, OUTSIDE_SOLVE_DOMAIN, 0, 0.0, False, recover=False)
            result.target = y_t
            return result
        previous_y_a = None if self._plan is None else self._plan.y_a.copy()
        escape = "passage" if self.passage.active else ""
        if self.passage.active and self.passage.can_hand_back(self._plan, self.nlp.layout.horizon):
            # the long plan reaches its x_a within N samples (at rest beyond the region at the latest):
            # its first N stages are a plan of the regular NLP, which takes over
            self._plan, self._pending, escape = self.passage.hand_back(self._plan, self.nlp), None, "passage ended"
        self._start_report = []
        attempt = self._solve(x, y_t, par, time)
        escape = "; ".join(self._start_report) or escape
        if not attempt.usable:
            self._pending = (attempt.w, attempt.lam_x, attempt.lam_g) if (
                attempt.finite and attempt.budget_cut and attempt.nlp is self.active_nlp) else None
            self._reseed = self.cold_nlp is not None and self._pending is None and not self.passage.active
            result = self._fallback(x, par, attempt.solver_status, attempt.iterations, attempt.solve_time,
                                    attempt.budget_cut)
            result.escape, result.horizon, result.target = escape, attempt.nlp.layout.horizon, y_t
            return result
        self._pending = None
        self._reseed = False
        # the plan's predicted depth, once: the checks below and the escape's base read it (mu = 0: no
        # avoidance, left unknown until an escape needs it)
        depth = attempt.nlp.max_depth(attempt.w, par) if s.mu > 0 else math.nan
        best = Solution(attempt.w, attempt.lam_x, attempt.lam_g, attempt.nlp, attempt.solved, math.nan, depth)
        solve_time = attempt.solve_time
        # a plan that predicts penetration is a local optimum of the penalty (x_a at an ellipse's
        # centre, where its gradient vanishes; a squeeze between two regions): look for one that is clear
        # (in the passage mode the long plan goes on: no guesses; the mode ends as above)
        penetrating = s.mu > 0 and self.escape.available and not self.passage.active and depth > VIOLATION_TOLERANCE
        if self.passage.active:
            pass
        elif penetrating or self._escape_due(best, previous_y_a, y_t, par):
            best, tried, spent = self._escape(x, y_t, par, best, s.max_solve_time - solve_time, penetrating, time)
            solve_time += spent
            escape = f"{best.label}; tried: " + "; ".join(tried)
        elif self.passage.due:
            best, tried, spent = self._try_passage(x, y_t, par, best, previous_y_a, s.max_solve_time - solve_time)
            solve_time += spent
            escape = f"{best.label}; tried: " + "; ".join(tried) if tried else escape
        lam_x, lam_g = best.lam_x, best.lam_g
        active = self.active_nlp
        if best.nlp is not active:  # solved by the reference: the fast path's multipliers start from zero
            lam_x, lam_g = np.zeros(active.layout.n_w), np.zeros(active.lbg.size)
        plan = self._accept(x, best.w, par, lam_x, lam_g, best.nlp)
        status = StepStatus.OK if best.solved else StepStatus.TRUNCATED
        result = self._result(plan, x, 0, status, attempt.solver_status, attempt.iterations, solve_time,
                              attempt.budget_cut)
        result.escape, result.horizon, result.target = escape, best.nlp.layout.horizon, y_t
        # a region the plan cannot avoid (e.g. one placed over the current state): the input that
        # predicts the least violation, and say so; the cheap depth check first (mu = 0: no avoidance;
        # every candidate an escape or the passage mode kept carries its own depth)
        if s.mu > 0 and best.depth > VIOLATION_TOLERANCE:
            self._bound_violation(x, par, result)
        return result

    def _bound_violation(self, x: np.ndarray, par: np.ndarray, result: StepResult) -> None:
        """Replace a plan that predicts penetration by the least-violating input (FallbackSelector.check_plan).

        An avoidable penetration is overridden for at most N samples in a row, so that a plan the
        solver keeps choosing is not held off for good (the plant would stand still).
        """
        choice = self.fallback.check_plan(x, par, result.inputs[:self.fallback.horizon])  # a long plan: its first N
        if choice is None or (not choice.unavoidable and self._overrides >= self.nlp.layout.horizon):
            self._overrides = 0
            return
        result.region_unavoidable = choice.unavoidable
        result.predicted_violation = choice.violation
        why = "region unavoidable from the current state" if choice.unavoidable else "plan predicts penetration"
        result.fallback_reason = f"{why}; {choice.reason}"
        result.solve_time += choice.solve_time
        if choice.kind != "plan":
            self._overrides += not choice.unavoidable
            result.status = StepStatus(f"fallback_{choice.kind}")
            result.u, result.inputs, result.states = choice.inputs[0].copy(), choice.inputs.copy(), choice.states

    def _solve(self, x: np.ndarray, y_t: np.ndarray, par: np.ndarray, time: float | None = None) -> Attempt:
        """The sample's regular solve: the fast path from the shifted plan (cold: the cold-start solvers;
        an ellipse tier where one holds the regions, core/tiers.py)."""
        s = self.settings
        cold = self.cold_nlp is not None and self._pending is None and (self._plan is None or self._reseed) and \
            not self.passage.active
        # not after a budget-cut sample (the regular NLP continues its iterate) nor in the passage mode
        tier = None if self._pending is not None or self.passage.active else self.tiers.pick(self._regions)
        if tier is not None and not cold and self._plan is not None:
            # the regular NLP with fewer (empty) slots; the plan comes back in its layout
            return self.tiers.solve(tier, self._initial_guess(x, y_t, tier)[0], x, par,
                                    self.slot_values(time, tier), s)
        elapsed = 0.0
        if tier is not None and cold and self._plan is None and self.escape.available:
            # no plan yet: the fast path on the tier (Tiers.cold_start)
            result, self._start_report, elapsed = self.tiers.cold_start(
                tier, self.escape.cold_guesses(x, y_t), x, par, self.slot_values(time, tier), s, VIOLATION_TOLERANCE)
            if result is not None:
                return result
        # SQP paths try a cold start themselves first (cheap, and it works on small problems);
        # FATROP fails slowly there (hundreds of ms), so it goes to the reference at once
        if not cold:
            nlps = [self.active_nlp]
        elif s.solver.startswith("sqp"):
            nlps = [self.nlp, self.cold_nlp]
        else:
            nlps = [self.cold_nlp]
        # a cold start runs with the cold-start budget (StagewiseNlp.cold_solver, the reference's build)
        budget = max(s.max_iterations, COLD_START_ITERATIONS) if cold else s.max_iterations
        for nlp in nlps:
            w0, lam_x0, lam_g0 = self._initial_guess(x, y_t, nlp)
            result = attempt(nlp, nlp.fill_slacks(w0, par), par, lam_x0, lam_g0, budget, s.feasibility_tolerance, cold)
            elapsed += result.solve_time
            if result.usable:
                break
        result.solve_time = elapsed
        return result

    def _escape_due(self, base: Solution, previous_y_a: np.ndarray | None, y_t: np.ndarray, par: np.ndarray) -> bool:
        """Try escape guesses now? Stalled in front of a blocking region, and not tried in vain just before."""
        if self._escape_wait > 0:
            self._escape_wait -= 1
            return False
        y_a = base.nlp.layout.split_w(base.w)[2]
        return self.escape.should_try(y_a, previous_y_a, y_t, par)

    def _escape(self, x: np.ndarray, y_t: np.ndarray, par: np.ndarray, base: Solution, time_left: float,
                penetrating: bool = False, time: float | None = None) -> tuple[Solution, list[str], float]:
        """The lowest-cost plan among the base and the escape guesses (for a `penetrating` base: a
        clear plan first, see candidates.lowest_cost)."""
        # FATROP solves the guesses itself (measured on a 4-ellipse van der Pol scene: the same plans,
        # 12-14 ms for three guesses); the SQP paths stall from far guesses: the reference solves them
        nlp = self.nlp if self.settings.solver == "fatrop" else (self.cold_nlp or self.nlp)
        base.cost = plan_cost(base.nlp, base.w, par)
        if math.isnan(base.depth):
            base.depth = base.nlp.max_depth(base.w, par)
        y_a = base.nlp.layout.split_w(base.w)[2]
        if penetrating:
            guesses = self.escape.penetration_guesses(x, y_a, y_t, par, self._regions)
        else:
            guesses = self.escape.guesses(x, y_a, y_t, par, self._regions)
        # a penetrating plan is a safety matter: all its guesses now; a stall's may take several samples
        batch, rest = (guesses, 0) if penetrating else guess_batch(guesses, self._escape_next,
                                                                    self.settings.escape_guesses_per_sample)
        tier = self.tiers.pick(self._regions) if nlp is self.nlp else None  # an ellipse tier solves them faster
        guess_par = par if tier is None else self.tiers.parameters(par, self.slot_values(time, tier))
        best, tried, spent = lowest_cost(tier or nlp, x, guess_par, base, batch, time_left,
                                         self.settings.feasibility_tolerance, VIOLATION_TOLERANCE)
        if tier is not None and best is not base:
            best = self.tiers.regular_solution(best, x, par)
        self._escape_next = 0
        if best is base and rest:  # the next batch on the next sample (still stalled: the base held)
            self._escape_next = len(guesses) - rest
            tried.append(f"{rest} more next sample")
        elif best is base and not penetrating:  # nothing better here: do not try again every sample while at rest
            self._escape_wait = ESCAPE_RETRY_SAMPLES
            self.passage.due = self.passage.available  # the long horizon next sample (its own budget)
            self.passage.next_guess = 0
        return best, tried, spent

    def _try_passage(self, x: np.ndarray, y_t: np.ndarray, par: np.ndarray, base: Solution,
                     previous_y_a: np.ndarray | None, time_left: float) -> tuple[Solution, list[str], float]:
        """The sample after a vain stall escape: if y_a is still stalled in front of the region, the
        passage NLP's plan that passes it (entering the mode), else the base."""
        self.passage.due = False
        y_a = base.nlp.layout.split_w(base.w)[2]
        if not self.escape.should_try(y_a, previous_y_a, y_t, par):
            return base, [], 0.0
        entered, tried, spent = self.passage.attempt(x, y_t, par, base, self._regions, time_left,
                                                     self.settings.feasibility_tolerance,
                                                     self.settings.escape_guesses_per_sample)
        if entered is None:
            if not self.passage.due:  # every guess tried in vain (else the next batch on the next sample)
                self._escape_wait = ESCAPE_RETRY_SAMPLES
            return base, tried, spent
        self.passage.active = True
        return entered, tried, spent

    def coast(self) -> StepResult | None:
        """A sample without a new measurement: the next input of the last plan (then u_a).

        The plan ages by one sample, so the next `step` shifts its warm start accordingly; the
        result's first state is the plan's prediction for now. None when there is no plan yet.
        Status FALLBACK_SHIFT (or FALLBACK_STEADY once the plan is used up), solver status
        'no_new_state'.
        """
        plan = self._plan
        if plan is None:
            return None
        plan.age += 1
        N = len(plan.inputs)
        predicted = plan.states[plan.age] if plan.age <= N else plan.x_a
        status = StepStatus.FALLBACK_SHIFT if plan.age < N else StepStatus.FALLBACK_STEADY
        return self._result(plan, predicted, plan.age, status, "no_new_state", 0, 0.0, False)

    def _accept(self, x: np.ndarray, w: np.ndarray, par: np.ndarray, lam_x: np.ndarray, lam_g: np.ndarray,
                nlp: NlpBase) -> Plan:
        U, X, y_a, _ = nlp.layout.split_w(w)
        x_a, u_a = (v.copy() for v in nlp.steady(w))
        costs = tuple(float(c[0]) for c in nlp.terms(w, par))
        self._plan = Plan(U.copy(), np.vstack([x, X]), y_a.copy(), x_a, u_a, lam_x, lam_g, 0, costs)
        return self._plan

    def _initial_guess(self, x: np.ndarray, y_t: np.ndarray, nlp: NlpBase) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The guess (w, lam_x, lam_g) for `nlp` at state x and target y_t (core/warm_start.py); the
        plan's multipliers only where `nlp` is the one that made it."""
        return initial_guess(nlp, x, y_t, self._plan, self._pending, self.settings, self.model,
                             keep_duals=nlp is self.active_nlp)

    def set_safe_input(self, u: Sequence[float]) -> None:
        """The model's safe input [m], one of the fallback's candidates (InputError if malformed or
        outside the input box)."""
        self.fallback.safe_input = self.check_safe_input(u)

    def check_safe_input(self, u: Sequence[float]) -> np.ndarray:
        """u as a safe input [m], or InputError if malformed or outside the input box."""
        u = validate_vector("safe_input", u, self.model.m)
        if np.any(u < self._input_lo) or np.any(u > self._input_hi):
            raise InputError(f"safe_input {u.tolist()} is outside the input box")
        return u

    def _fallback(self, x: np.ndarray, par: np.ndarray, solver_status: str, iterations: int, solve_time: float,
                  budget_cut: bool, recover: bool = True) -> StepResult:
        """The candidate input predicting the least violation (core/fallback.py); the plan ages by one."""
        plan = self._plan
        shifted = u_a = None
        N = H = self.fallback.horizon  # the selector simulates N inputs: of a long plan, its first N
        if plan is not None:
            plan.age += 1
            N = len(plan.inputs)
            shifted = np.vstack([plan.inputs[plan.age:], np.tile(plan.u_a, (min(plan.age, N), 1))])[:H]
            u_a = plan.u_a
        choice = self.fallback.choose(x, par, shifted, u_a, plan is not None and plan.age < N, recover)
        solve_time += choice.solve_time
        if plan is not None and choice.kind in ("shift", "steady"):
            result = self._result(plan, x, plan.age, StepStatus(f"fallback_{choice.kind}"), solver_status, iterations,
                                  solve_time, budget_cut)
        else:
            nan_p = np.full(self.model.p, np.nan) if plan is None else plan.y_a.copy()
            nan_n = np.full(self.model.n, np.nan) if plan is None else plan.x_a.copy()
            u_a_out = choice.inputs[0].copy() if plan is None else plan.u_a.copy()
            result = StepResult(choice.inputs[0].copy(), choice.states, choice.inputs.copy(), nan_p, nan_n, u_a_out,
                                math.nan, math.nan, math.nan, StepStatus(f"fallback_{choice.kind}"), solver_status,
                                iterations, solve_time, budget_cut)
        result.fallback_reason = choice.reason
        result.predicted_violation = choice.violation
        return result

    def _result(self, plan: Plan, x: np.ndarray, age: int, status: StepStatus, solver_status: str, iterations: int,
                solve_time: float, budget_cut: bool) -> StepResult:
        N = len(plan.inputs)  # the regular horizon, or the passage mode's
        # into the input box: a solver meets its bounds to its tolerance only (1e-8 beyond them seen)
        inputs = np.clip(np.vstack([plan.inputs[age:], np.tile(plan.u_a, (min(age, N), 1))]), self._input_lo,
                         self._input_hi)
        states = np.vstack([x, plan.states[age + 1:], np.tile(plan.x_a, (min(age, N), 1))])
        return StepResult(inputs[0].copy(), states, inputs, plan.y_a.copy(), plan.x_a.copy(), plan.u_a.copy(),
                          *plan.costs, status, solver_status, iterations, solve_time, budget_cut)
