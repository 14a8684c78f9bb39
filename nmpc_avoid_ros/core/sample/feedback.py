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

import logging
import threading
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ..errors import ConfigError
from ..nlp.buffered import Buffered
from ..nlp.codegen import compiled_function, function_library
from ..nlp.search import VIOLATION_TOLERANCE, SearchReport
from ..nlp.sensitivity import FeedbackLaw, KktSensitivity
from ..nlp.tracking import NlpBase
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
class LinearCosts:
    """The cost terms (V_o, V_a, tracking) [3] of a plan w [n_w] at parameters par [n_p], and their Jacobians
    [3, n_w], [3, n_p]: a moved plan's terms to first order, like the plan itself, without evaluating them
    (40 us interpreted on the live van der Pol NLP; the moved plan's answer takes about 100)."""

    values: np.ndarray
    by_w: np.ndarray
    by_p: np.ndarray
    w: np.ndarray
    par: np.ndarray

    def at(self, w: np.ndarray, par: np.ndarray) -> tuple[float, float, float]:
        values = self.values + self.by_w @ (w - self.w) + self.by_p @ (par - self.par)
        return float(values[0]), float(values[1]), float(values[2])


@dataclass
class Prepared:
    """A sample solved ahead: the plan for the state x [n] predicted at `time` (s, the regions' clock, or
    None) with the delay `delay` (s) of the sample it is for; its NLP and law (or why there is none);
    seconds: the preparation's solver time plus building the law; costs: its cost terms, to move with it."""

    plan: Plan
    nlp: NlpBase
    law: FeedbackLaw | None
    why: str
    x: np.ndarray
    time: float | None
    delay: float
    seconds: float
    costs: LinearCosts | None = None
    report: SearchReport | None = None  # what the preparation's search did (the answered sample's `search`)


class FeedbackLaws:
    """The KKT sensitivity of each NLP given (the controller gives its regular one), its feasibility test of a moved
    plan and the Jacobians of its cost terms; all built in the constructor (core/nlp/sensitivity.py)."""

    def __init__(self, nlps: list[NlpBase], compiled_in: Path | None = None, background: bool = False) -> None:
        """`compiled_in`: the feasibility tests are compiled and cached there (core/nlp/codegen.py; None: not);
        `background`: one missing from the cache is compiled by a thread while the interpreted one serves (a first
        start waits for nothing, as the solvers with codegen_background)."""
        self._sensitivity: dict[int, KktSensitivity] = {}
        self._violation: dict[int, Buffered] = {}
        self._cost_jacobian: dict[int, ca.Function] = {}
        for nlp in nlps:
            n, size, count = nlp.layout.n, nlp.slot_layout.size, nlp.parameter_count
            # x(0), the command in force (input_rate_max) and each slot's stamp - t_0 (what moves with time; a new
            # region set is searched)
            commands = np.arange(count - size - 1 - nlp.layout.m, count - size - 1) if nlp.settings.input_rate_max \
                else np.zeros(0, int)
            followed = np.concatenate([np.arange(n), commands, count - size + nlp.slot_layout.time_offsets])
            self._sensitivity[id(nlp)] = KktSensitivity(nlp.problem, followed)
            w, p = nlp.problem["x"], nlp.problem["p"]
            terms = ca.vertcat(*nlp.terms.function(w, p))  # V_o, V_a, tracking
            self._cost_jacobian[id(nlp)] = ca.Function("cost_jacobian", [w, p], [terms, ca.jacobian(terms, w),
                                                                                 ca.jacobian(terms, p)])
            violation = _violation_function(nlp)
            if compiled_in is None:
                self._violation[id(nlp)] = Buffered(violation)
            elif background and not function_library(violation, compiled_in).exists():
                self._violation[id(nlp)] = Buffered(violation)
                threading.Thread(target=self._compile, args=(id(nlp), violation, compiled_in), daemon=True,
                                 name="feasibility-test-compile").start()
            else:
                self._violation[id(nlp)] = Buffered(compiled_function(violation, compiled_in))

    def _compile(self, key: int, violation: ca.Function, folder: Path) -> None:
        """Compile a feasibility test and swap it in (one dict assignment: a feedback call uses either)."""
        try:
            self._violation[key] = Buffered(compiled_function(violation, folder))
        except ConfigError as error:  # the interpreted test serves on, as a failed solver compile does
            log.warning(f"the feedback law's feasibility test stays interpreted: {error}")

    def prepare(self, nlp: NlpBase, plan: Plan, par: np.ndarray) -> FeedbackLaw | str:
        """The law of `plan` (solved at par) in `nlp`'s layout, or why there is none."""
        if id(nlp) not in self._sensitivity:
            return "no law for this NLP (the passage mode's long one: its samples search)"
        layout = nlp.layout
        rest = None if layout.closed_form else np.concatenate([plan.x_a, plan.u_a])
        w = nlp.fill_slacks(layout.join_w(plan.inputs, plan.states[1:], plan.y_a, rest, x0=plan.states[0]), par)
        return self._sensitivity[id(nlp)].law(w, par, (nlp.lbx, nlp.ubx, nlp.lbg, nlp.ubg))

    def costs(self, nlp: NlpBase, w: np.ndarray, par: np.ndarray) -> LinearCosts:
        """The cost terms of the plan w at par, and their first-order change (for a moved plan's, cheaply)."""
        values, by_w, by_p = (np.asarray(v) for v in self._cost_jacobian[id(nlp)](w, par))
        return LinearCosts(values.ravel(), by_w, by_p, w.copy(), par.copy())

    def answer(self, prepared: Prepared, par: np.ndarray, feasibility_tolerance: float,
               allowance: float = VIOLATION_TOLERANCE) -> tuple[np.ndarray | None, FeedbackOutcome]:
        """The prepared plan's w moved to the parameters `par` of the sample that arrived, or None and why
        (the moved plan's slacks must be within `allowance`, as a searched plan's depth to be clear: the sample's
        `depth_allowance`, core/nlp/search.py; inf: not checked)."""
        law = prepared.law
        if law is None:
            return None, FeedbackOutcome.NO_LAW
        change = law.change(par)
        if change is None:
            return None, FeedbackOutcome.INPUTS_CHANGED
        w = law.predict(change)
        if w is None:
            return None, FeedbackOutcome.ACTIVE_SET_CHANGED
        nlp = prepared.nlp
        # the slacks bound every region row (s >= g), so feasible slacks within the tolerance keep it clear
        slack_ok = not nlp._slack_index.size or float(np.max(w[nlp._slack_index])) <= allowance
        tolerance = max(feasibility_tolerance, MOVED_PLAN_TOLERANCE)
        if not slack_ok or float(self._violation[id(nlp)](w, par)[0][0]) > tolerance:
            return None, FeedbackOutcome.INFEASIBLE
        return w, FeedbackOutcome.ANSWERED


def _violation_function(nlp: NlpBase) -> ca.Function:
    """(w, p) -> the largest violation of the NLP's constraints and bounds (0 if feasible), one CasADi call."""
    w, p, g = nlp.problem["x"], nlp.problem["p"], nlp.problem["g"]
    rows = []
    for values, lower, upper in ((g, nlp.lbg, nlp.ubg), (w, nlp.lbx, nlp.ubx)):
        low, high = np.flatnonzero(np.isfinite(lower)), np.flatnonzero(np.isfinite(upper))
        rows += [ca.DM(lower[low]) - values[low.tolist()], values[high.tolist()] - ca.DM(upper[high])]
    return ca.Function("violation", [w, p], [ca.mmax(ca.vertcat(*rows, 0))])

