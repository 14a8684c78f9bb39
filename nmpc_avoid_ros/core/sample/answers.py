"""What a sample answers (a mixin of NmpcController, core/sample/controller.py): the best plan applied and
guarded, or the fallback; a sample without a new state coasts on the plan."""

from __future__ import annotations

import functools
import math

import numpy as np

from ..nlp.search import Candidate, SearchReport
from ..nlp.terminal import ShiftedTail
from ..nlp.tiers import TieredNlp
from .fallback import FallbackChoice
from .memory import COUNTED, RESET, Carry, Sample
from .status import StepStatus
from .step_result import Plan, StepResult
from .warm_start import steady_of

#: solver status of a sample whose state lies outside the solve domain (no solver was called)
OUTSIDE_SOLVE_DOMAIN = "outside_solve_domain"


class SampleAnswers:
    """Apply, guard, fall back and coast for NmpcController (every method reads its memory and selectors)."""

    def _apply(self, sample: Sample, best: Candidate, report: SearchReport) -> StepResult:
        """Keep `best` as the plan and answer its first input (status ok, or truncated for a budget-cut one)."""
        carry = sample.carry
        carry.pending, carry.reseed = None, False
        report.kept = report.kept or best.label
        active = self._active(carry)
        lam_x, lam_g = best.lam_x, best.lam_g
        if best.nlp is not active:  # solved by another NLP (the reference, a tier): multipliers start from zero
            lam_x, lam_g = np.zeros(active.layout.n_w), np.zeros(active.lbg.size)
        U, X, y_a, _ = best.nlp.layout.split_w(best.w)
        x_a, u_a = (v.copy() for v in best.nlp.steady(best.w))
        costs = tuple(float(c[0]) for c in best.nlp.terms(best.w, sample.par))
        carry.plan = self._continued(Plan(U.copy(), np.vstack([sample.x, X]), y_a.copy(), x_a, u_a, lam_x, lam_g, 0,
                                          costs, slacks=_solved_slacks(best)))
        regular = sample.regular
        status = StepStatus.OK if best.solved else StepStatus.TRUNCATED if best.budget_cut else StepStatus.UNCONVERGED
        result = self._result(carry.plan, sample.x, 0, status, regular.solver_status, regular.iterations,
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
        mem, H = self.memory, self.fallback.horizon  # mem.overrides: as the sample began; the count is the carry's
        if not (self.settings.mu > 0 and not best.clear):
            return result
        # N overrides in a row: an avoidable penetration's plan is applied; where the regions were unavoidable all
        # along, the summed squared excess ranks, so that the stop, which ties with a way out by the largest (the
        # first rows', no input changes them), does not hold the plant inside for good (a unicycle against a pillar)
        overridden_long = mem.overrides >= self.nlp.layout.horizon
        choice = self.fallback.check_plan(sample.x, sample.par, result.inputs[:H], sample.end, overridden_long)
        if choice is not None and choice.unavoidable and self._given != self._regions:
            real = self.fallback.check_plan(sample.x, self._given_parameters(sample), result.inputs[:H], sample.end,
                                            overridden_long)
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
        if choice is None or (not choice.unavoidable and overridden_long):
            sample.carry.overrides = RESET
            return result
        result.region_unavoidable = choice.unavoidable
        result.predicted_violation = choice.violation
        if not result.margin_unavoidable:
            result.fallback_predicted = dict(choice.predicted)
            why = "region unavoidable from the current state" if choice.unavoidable else "plan predicts penetration"
            result.fallback_reason = f"{why}; {choice.reason}"
        sample.seconds += choice.solve_time
        if choice.unavoidable or choice.kind != "plan":  # an unavoidable sample counts even when the plan is least
            sample.carry.overrides = COUNTED
        if choice.kind != "plan":
            result.status = StepStatus(f"fallback_{choice.kind}")
            result.u, result.inputs, result.states = choice.inputs[0].copy(), choice.inputs.copy(), choice.states
            self._follow(sample.carry, choice)
        return result

    def _given_parameters(self, sample: Sample) -> np.ndarray:
        """The sample's parameters with the regions as given, without the margins they are planned around with."""
        return self.parameters(sample.x, sample.y_t, sample.time, slots=self.given_slot_values(sample.time))

    def _fall_back(self, sample: Sample, last: Candidate | None) -> StepResult:
        """No usable plan: the candidate input predicting the least violation (core/sample/fallback.py); the plan
        ages by one (`shift`, or `steady` once it is used up), else the candidate becomes the plan (`_follow`). A
        budget-cut iterate of the regular NLP is continued next sample; a fast path whose
        warm solve failed outright re-seeds through the cold-start starts."""
        carry, x, par = sample.carry, sample.x, sample.par
        if last is not None:
            regular = last.nlp.regular if isinstance(last.nlp, TieredNlp) else last.nlp
            carry.pending = (last.w, last.lam_x, last.lam_g) if (
                last.finite and last.budget_cut and regular is self._active(carry)) else None
            carry.reseed = self.cold_nlp is not None and carry.pending is None and not carry.passage
        status, iterations, budget_cut = (OUTSIDE_SOLVE_DOMAIN, 0, False) if last is None else (
            last.solver_status, last.iterations, last.budget_cut)
        plan, carry.aged = carry.plan, True  # no plan kept: it ages by this sample
        shifted = u_a = local = None
        N = H = self.fallback.horizon  # the selector simulates N inputs: of a long plan, its first N
        age = 0 if plan is None else plan.age + 1
        if plan is not None:
            N = len(plan.inputs)
            # into the input box, as judged so applied (with the raw plan a shift fallback commanded beyond |u| <= 6)
            shifted = self._into_box(plan.shifted(age)[0][:H])
            # with terminal: set the steady candidate is the local controller from x (None: u_a held)
            local = self._tail.rollout(x, plan.y_a, plan.x_a, plan.u_a, H, self._input_lo, self._input_hi)
            u_a = self._into_box(plan.u_a) if local is None else local[0]
        choice = self.fallback.choose(x, par, shifted, u_a, plan is not None and age < N, sample.in_domain,
                                      sample.end)
        sample.seconds += choice.solve_time
        if plan is not None and choice.kind in ("shift", "steady"):
            result = self._result(plan, x, age, StepStatus(f"fallback_{choice.kind}"), status, iterations,
                                  budget_cut)
            # what is applied is the candidate as judged: rate-limited actuators following it, and `steady` holding
            # u_a (the plan's own next input here was the `shift` candidate's: campaign bicycle_world-0027 drove on
            # at full speed with it, judged 0.87 deep, where holding u_a, a stop, was clear)
            result.u, result.inputs, result.states = choice.inputs[0].copy(), choice.inputs.copy(), choice.states
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
        # the plan used up, `steady` is its own continuation (u_a held): it ages on as the paper's candidate
        if plan is not None and choice.kind != "shift" and (choice.kind != "steady" or age < N):
            self._follow(carry, choice)
        return result

    def _follow(self, carry: Carry, choice: FallbackChoice) -> None:
        """The next sample warm-starts from the fallback applied instead of the plan it replaced: its inputs [H, m]
        and predicted states as the plan, resting at the steady state of its last output (the terminal rows are
        the solver's to meet). The plan replaced predicted penetration, or led to a failed solve, and was
        inconsistent with the command applied (a rate row forbade its u(0)): its warm starts failed sample after
        sample (campaign bicycle_world-0027: five FATROP solves abandoned at the deadline, each followed by a
        re-seed through the cold-start solvers). Not in the passage mode (the long plan has its own horizon); else
        the regular NLP's plan: the candidates span its horizon (FallbackSelector.horizon)."""
        if carry.passage:
            return
        last, nlp = choice.states[-1], self.nlp
        x_a, u_a = steady_of(self.model, np.asarray(self.model.output(last, choice.inputs[-1]), float).ravel(), last)
        y_a = np.asarray(self.model.output(x_a, u_a), float).ravel()
        carry.plan = self._continued(Plan(choice.inputs.copy(), choice.states.copy(), y_a, x_a, u_a,
                                          np.zeros(nlp.layout.n_w), np.zeros(nlp.lbg.size)))
        carry.aged = False  # the plan applied now: the next warm start shifts it by one sample

    @functools.cached_property
    def _tail(self) -> ShiftedTail:
        """The plan's continuation after x(N): the local controller with `terminal: set` (core/nlp/terminal.py)."""
        return ShiftedTail(self.settings, self.model)

    def _continued(self, plan: Plan) -> Plan:
        """`plan` with its continuation after x(N) (Plan.tail) where the scheme is `terminal: set`: the shift of the
        warm start, of the fallback's `shift` candidate and of an aged plan then runs on with kappa(x, y_a) instead
        of holding u_a; with the equality unchanged (None)."""
        plan.tail = self._tail.rollout(plan.states[-1], plan.y_a, plan.x_a, plan.u_a, len(plan.inputs),
                                       self._input_lo, self._input_hi)
        return plan

    def _terminal_values(self, result: StepResult) -> StepResult:
        """`result` with V_f of its last state and alpha(y_a) (NaN with the equality: StepResult.terminal_cost)."""
        result.terminal_cost, result.terminal_level = self._tail.values(result.states[-1], result.y_a, result.x_a,
                                                                        result.u_a)
        return result

    def _into_box(self, inputs: np.ndarray) -> np.ndarray:
        """inputs [..., m] clipped into the input box: a solver meets its bounds to its tolerance only (1e-8 beyond
        them seen; 1e-7 in a fallback of test_flood_dds). np.clip's dispatch costs ~5 us."""
        return np.minimum(np.maximum(inputs, self._input_lo), self._input_hi)

    def _result(self, plan: Plan, x: np.ndarray, age: int, status: StepStatus, solver_status: str, iterations: int,
                budget_cut: bool) -> StepResult:
        """The result of applying `plan` aged by `age` samples at state x (the solve time is set by `step`)."""
        inputs, states = plan.shifted(age)  # of the regular horizon, or the passage mode's
        inputs = self._into_box(inputs)
        states[0] = x
        return StepResult(inputs[0].copy(), states, inputs, plan.y_a.copy(), plan.x_a.copy(), plan.u_a.copy(),
                          *plan.costs, status, solver_status, iterations, 0.0, budget_cut)

    def coast(self) -> StepResult | None:
        """A sample without a new measurement: the next input of the last plan (then u_a).

        The plan ages by one sample, so the next `step` shifts its warm start accordingly; the
        result's first state is the plan's prediction for now. None when there is no plan yet.
        Status FALLBACK_SHIFT (or FALLBACK_STEADY once the plan is used up), solver status
        'no_new_state'. Nothing is prepared after it (`prepare` needs a step's state of the last sample).
        """
        self._settle()  # an answered sample's bookkeeping, before its sample is forgotten below
        carry = self.memory.carry()
        # prepared for the sample this one replaces; and no preparation from the last step's state, now a sample old
        carry.prepared = carry.last = None
        plan = carry.plan
        if plan is None:
            self.memory.advance(carry)
            return None
        age, N = plan.age + 1, len(plan.inputs)
        predicted = plan.states[age] if age <= N else plan.x_a
        status = StepStatus.FALLBACK_SHIFT if age < N else StepStatus.FALLBACK_STEADY
        result = self._result(plan, predicted, age, status, "no_new_state", 0, False)
        carry.command, carry.aged = result.u.copy(), True
        self.memory.advance(carry)
        return self._terminal_values(result)


def _solved_slacks(best: Candidate) -> tuple[int, np.ndarray] | None:
    """Plan.slacks of a candidate: its NLP's id and slack values, where its w is in that NLP's own layout (a tier's
    solve comes back in the regular layout: None)."""
    if isinstance(best.nlp, TieredNlp):
        return None
    return id(best.nlp), best.w[best.nlp._slack_index].copy()
