"""The sample in two phases: preparation between the samples, feedback when the state arrives.

With `feedback: true` a caller that calls `NmpcController.prepare()` after sending each command gets
this (docs/design.md, 'Preparation and feedback'):

* preparation (`prepare`): the state the plan predicts for the next sample's planning instant, x̄,
  goes through the whole sample (the search with its escapes and passage, one time bound); a
  converged, clear plan becomes the prepared plan, with its feedback law (core/nlp/sensitivity.py);
* feedback (the next `step`): the law moves the prepared plan to the state that arrived; if the
  inputs are the prepared ones (target, weights, regions and margins; moving regions are followed),
  no active constraint leaves its active set, and the moved plan is feasible to MOVED_PLAN_TOLERANCE
  with its slacks within VIOLATION_TOLERANCE (clear, as a searched plan must be), its first input is
  the command: no solver runs. Otherwise the sample searches as before,
  warm-started from the prepared plan.

The plan the law starts from is the same converged solution a searched sample would apply for x̄, so
the closed loop is the searched one's to first order in x - x̄ (measured on the paper's run, live
config: commands within 1e-10 of a full solve at the same state; docs/design.md).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ..nlp.buffered import Buffered
from ..nlp.codegen import serve_compiled
from ..nlp.native_threads import start_native
from ..nlp.parts import command_index
from ..nlp.search import VIOLATION_TOLERANCE, SearchReport
from ..nlp.sensitivity import MULTIPLIER_TOLERANCE, FeedbackLaw, KktSensitivity
from ..nlp.tracking import NlpBase
from .feedback_qp import FeedbackQp, violation_function
from .status import FeedbackOutcome
from .step_result import Plan

log = logging.getLogger(__name__)

#: the solver status of a sample its prepared plan answered: no solver ran in it (its preparation's did)
ANSWERED_STATUS = "feedback"

#: the largest constraint violation of a moved plan (state and region-function units): its gaps are second
#: order in the state's distance from the predicted one (1e-5 for a 2e-3 miss on the paper's plant), far
#: below the penetration tolerance VIOLATION_TOLERANCE, and its first input is clipped into the input box
MOVED_PLAN_TOLERANCE = 1e-4


@dataclass
class Moved:
    """The prepared plan moved to the sample's parameters by its law: w [n_w] in the law NLP's layout, its steady
    state x_a [n] and input u_a [m], and its cost terms (V_o, V_a, tracking) at those parameters (the certificate's
    V_N), all from the one compiled call of the answer."""

    w: np.ndarray
    x_a: np.ndarray
    u_a: np.ndarray
    costs: tuple[float, float, float]


@dataclass
class Prepared:
    """A sample solved ahead: the plan for the state x [n] predicted at `time` (s, the regions' clock, or
    None) with the delay `delay` (s) of the sample it is for; its NLP and law (or why there is none);
    seconds: the preparation's solver time plus building the law."""

    plan: Plan
    nlp: NlpBase
    law: FeedbackLaw | None
    why: str
    x: np.ndarray
    time: float | None
    delay: float
    seconds: float
    report: SearchReport | None = None  # what the preparation's search did (the answered sample's `search`)


class FeedbackLaws:
    """The KKT sensitivity of each NLP given (the controller gives its regular one and its tiers) and its answer: one
    CasADi Function (answer_function) that moves a prepared plan by its law and checks it, bound to the law once
    when it is prepared; all built in the constructor, the `later` ones possibly by a thread (core/nlp/sensitivity.py).
    """

    def __init__(self, nlps: list[NlpBase], compiled_in: Path | None = None, background: bool = False,
                 later: Sequence[NlpBase] = (), derivatives_in: Path | None = None) -> None:
        """`compiled_in`: the answers are compiled and cached there (core/nlp/codegen.py; None: not);
        `derivatives_in`: the laws' KKT derivatives are saved there and read back by later starts
        (core/nlp/sensitivity.py; None: built each time); `background`: an answer missing from the cache is
        compiled by a thread while the interpreted one serves (a first start waits for nothing, as the solvers with
        codegen_background), and the laws of the `later` NLPs (the passage mode's long one: 2.5 s of symbolic
        derivatives on an empty cache) are built by a thread too; until then their plans have no law."""
        self._sensitivity: dict[int, KktSensitivity] = {}
        self._answer: dict[int, _Answer] = {}
        self._cost_jacobian: dict[int, ca.Function] = {}
        self._qp: dict[int, FeedbackQp] = {}  # where the law's move is refused: one QP (core/sample/feedback_qp.py)
        self._compiled_in, self._derivatives_in, self._background = compiled_in, derivatives_in, background
        for nlp in nlps:
            self._add(nlp)
        if later and background:
            # CasADi's symbolic work releases the interpreter lock: the samples go on meanwhile (measured: the
            # main thread's longest wait 3 ms during a 1.2 s Jacobian)
            start_native(self._add_later, list(later), name="feedback-laws")
        else:
            for nlp in later:
                self._add(nlp)

    def _add_later(self, nlps: Sequence[NlpBase]) -> None:
        """The `later` laws, on a thread: one that fails leaves its NLP's plans without a law (they search), said."""
        for nlp in nlps:
            try:
                self._add(nlp)
            except Exception as error:  # noqa: BLE001 - a thread's exception would vanish: say it, serve on
                log.warning(f"no feedback law for the NLP of horizon {nlp.layout.horizon} (its samples search): "
                            f"{type(error).__name__}: {error}")

    def _add(self, nlp: NlpBase) -> None:
        """Build the law of `nlp` and its answer; the sensitivity goes in last, as `prepare` looks for it first."""
        n, size, count = nlp.layout.n, nlp.slot_layout.size, nlp.parameter_count
        # x(0), the command in force (input_rate_max) and each slot's stamp - t_0 (what moves with time; a new
        # region set is searched)
        commands = command_index(count, size, nlp.layout.m, bool(nlp.settings.input_rate_max))
        followed = np.concatenate([np.arange(n), commands, count - size + nlp.slot_layout.time_offsets])
        sensitivity = KktSensitivity(nlp.problem, followed, self._derivatives_in, self._background)
        w, p = nlp.problem["x"], nlp.problem["p"]
        terms = ca.vertcat(*nlp.terms.function(w, p))  # V_o, V_a, tracking
        self._cost_jacobian[id(nlp)] = ca.Function("cost_jacobian", [w, p], [terms, ca.jacobian(terms, w),
                                                                             ca.jacobian(terms, p)])
        serve_compiled(answer_function(nlp, followed), self._compiled_in, self._background,
                       functools.partial(self._install, id(nlp)), "the feedback law's answer")
        if nlp.settings.feedback_qp:
            self._qp[id(nlp)] = FeedbackQp(nlp)
        self._sensitivity[id(nlp)] = sensitivity

    def _install(self, key: int, answer: ca.Function) -> None:
        """Serve `answer` for the NLP `key` (one dict assignment: a feedback call uses either; the new one is bound to
        its law at its first call)."""
        self._answer[key] = _Answer(answer)

    def built(self, nlp: NlpBase) -> bool:
        """`nlp` has its law's derivatives and answer (a `later` one: once its thread built them)."""
        return id(nlp) in self._sensitivity

    def prepare(self, nlp: NlpBase, plan: Plan, par: np.ndarray) -> FeedbackLaw | str:
        """The law of `plan` (solved at par) in `nlp`'s layout, or why there is none; a law is bound to the answer."""
        if not self.built(nlp):
            return "its law not built yet (the passage mode's long NLP, built by a thread in the background)"
        layout = nlp.layout
        rest = None if layout.closed_form else np.concatenate([plan.x_a, plan.u_a])
        w = nlp.fill_slacks(layout.join_w(plan.inputs, plan.states[1:], plan.y_a, rest, x0=plan.states[0]), par)
        if plan.slacks is not None and plan.slacks[0] == id(nlp):  # the solver's own: a KKT point as it left it
            w[nlp._slack_index] = plan.slacks[1]
        law = self._sensitivity[id(nlp)].law(w, par, (nlp.lbx, nlp.ubx, nlp.lbg, nlp.ubg))
        if not isinstance(law, str):
            # the cost terms move with the plan to first order, like the plan itself (exact ones would cost the
            # answer as much again: they integrate the sub-steps as the feasibility test does)
            law.costs = tuple(np.asarray(v) for v in self._cost_jacobian[id(nlp)](law.w, par))
            self._answer[id(nlp)].bind(law)
            if id(nlp) in self._qp:  # the QP of a sample its law refuses starts from this plan's
                self._qp[id(nlp)].prime(law.w, par)
        return law

    def answer(self, prepared: Prepared, par: np.ndarray, feasibility_tolerance: float,
               allowance: float = VIOLATION_TOLERANCE, deadline: float = math.inf
               ) -> tuple[Moved | None, FeedbackOutcome]:
        """The prepared plan moved to the parameters `par` of the sample that arrived (in the law NLP's layout), or
        None and why (the moved plan's slacks must be within `allowance`, as a searched plan's depth to be clear:
        the sample's `depth_allowance`, core/nlp/search.py; inf: not checked). One compiled call; where the law's
        move is refused, one QP on its linearisation with the setting feedback_qp (`answered_qp`; not tried once
        `deadline`, time.perf_counter s, has passed)."""
        law = prepared.law
        if law is None:
            return None, FeedbackOutcome.NO_LAW
        answer = self._answer[id(prepared.nlp)]
        if answer.law is not law:  # swapped in by a compile since the law was prepared
            answer.bind(law)
        w, others, step, slack, violation, x_a, u_a, costs = answer.call(par)
        if others[0] != 0.0:
            return None, FeedbackOutcome.INPUTS_CHANGED
        tolerance = max(feasibility_tolerance, MOVED_PLAN_TOLERANCE)
        if law.multiplier.size and np.min(law.multiplier + law.multiplier_change @ step) < -MULTIPLIER_TOLERANCE:
            return self._qp_answer(prepared, w, par, tolerance, allowance, deadline, FeedbackOutcome.ACTIVE_SET_CHANGED)
        # the slacks bound every region row (s >= g), so feasible slacks within the tolerance keep it clear
        if slack[0] > allowance or violation[0] > tolerance:
            return self._qp_answer(prepared, w, par, tolerance, allowance, deadline, FeedbackOutcome.INFEASIBLE)
        return Moved(w.copy(), x_a.copy(), u_a.copy(), (float(costs[0]), float(costs[1]), float(costs[2]))), \
            FeedbackOutcome.ANSWERED

    def _qp_answer(self, prepared: Prepared, start: np.ndarray, par: np.ndarray, tolerance: float, allowance: float,
                   deadline: float, why: FeedbackOutcome) -> tuple[Moved | None, FeedbackOutcome]:
        """Where the law's move `start` [n_w] is refused (`why`: its active set changed, or it is infeasible), one QP
        on the linearisation at it (core/sample/feedback_qp.py), checked as the law's answer; else None, `why`."""
        nlp = prepared.nlp
        qp = self._qp.get(id(nlp))  # None: the setting feedback_qp off
        moved = None if qp is None else qp.step(start, par, deadline)
        if moved is None or moved.slack > allowance or moved.violation > tolerance:
            return None, why
        costs = tuple(float(c[0]) for c in nlp.terms(moved.w, par))
        return Moved(moved.w, moved.x_a, moved.u_a, costs), FeedbackOutcome.ANSWERED_QP


def answer_function(nlp: NlpBase, followed: np.ndarray) -> ca.Function:
    """(par [n_p]; bound: the law's par̄ [n_p], w̄ [n_w], dw [n_w, c], and its plan's cost terms [3] with their
    Jacobians [3, n_w], [3, n_p]) -> the moved plan w = w̄ + dw dp [n_w], the largest change of a parameter the law
    does not follow (0: none), dp [c], the largest slack, the largest constraint violation (0: feasible), x_a [n],
    u_a [m] and the cost terms [3] to first order. dp is the change of the c `followed` parameters. One call of
    generated code answers a sample (the feasibility test is most of it: 5.5 us on the paper's run, compiled)."""
    n_w, n_p, c = nlp.layout.n_w, nlp.parameter_count, followed.size
    par, ref_par, ref_w = ca.SX.sym("par", n_p), ca.SX.sym("ref_par", n_p), ca.SX.sym("ref_w", n_w)
    dw = ca.SX.sym("dw", n_w, c)
    costs, costs_by_w, costs_by_p = ca.SX.sym("costs", 3), ca.SX.sym("costs_by_w", 3, n_w), ca.SX.sym("by_p", 3, n_p)
    dp = par - ref_par
    step = dp[followed.tolist()]
    w = ref_w + ca.mtimes(dw, step)
    others = np.setdiff1d(np.arange(n_p), followed)
    other_change = ca.mmax(ca.fabs(dp[others.tolist()])) if others.size else ca.SX(0)
    slacks = nlp._slack_index
    slack = ca.mmax(w[slacks.tolist()]) if slacks.size else ca.SX(-np.inf)
    x_a, u_a = nlp.steady.function(w)
    moved_costs = costs + ca.mtimes(costs_by_w, w - ref_w) + ca.mtimes(costs_by_p, dp)
    outputs = [w, other_change, step, slack, violation_function(nlp)(w, par), x_a, u_a, moved_costs]
    return ca.Function("feedback_answer", [par, ref_par, ref_w, dw, costs, costs_by_w, costs_by_p],
                       [ca.densify(out) for out in outputs])


class _Answer:
    """An answer_function called with par alone, and the law whose data are bound to it."""

    def __init__(self, function: ca.Function) -> None:
        fixed = {i: np.zeros(function.nnz_in(i)) for i in range(1, function.n_in())}
        self.call = Buffered(function, fixed=fixed, densify=False)
        self.law: FeedbackLaw | None = None

    def bind(self, law: FeedbackLaw) -> None:
        """Bind `law`: its point, its change, its plan's cost terms and their Jacobians."""
        assert law.costs is not None
        for index, value in enumerate((law.par, law.w, law.dw, *law.costs), start=1):
            self.call.bind(index, value)
        self.law = law
