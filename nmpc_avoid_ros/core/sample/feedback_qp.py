"""One QP where the feedback law's move is refused (core/sample/feedback.py).

The law is the tangential predictor on the prepared plan's active set; a miss of the predicted state by ~1e-3 on
a region's boundary flips the penalty's slack rows and the law refuses (`active_set_changed`), and a larger miss
leaves its move infeasible to second order (`infeasible`). acados' real-time iteration answers such a state with
one QP on a linearisation; so does this, at the law's move w̃ and the sample's parameters p (an SQP step from
the law's prediction):

    min_d  1/2 d' H_f d + grad f(w̃, p)' d
    s.t.   lbg - g(w̃, p) <= dg/dw(w̃, p) d <= ubg - g(w̃, p),   lbx - w̃ <= d <= ubx - w̃

with H_f the cost's Hessian (positive semi-definite: a sum of squares and the slacks' quadratic penalty; the
constraints' curvature dropped as on the SQP paths, core/nlp/gauss_newton.py). At the prepared state the move is
the prepared plan, a KKT point, and the QP leaves it there (its KKT conditions hold with the plan's multipliers,
whatever the Hessian). qpOASES solves it, hot from the prepared plan's own QP (`prime`). The moved plan w̃ + d
is checked on the nonlinear problem exactly as the law's answer is (feasible to the tolerance, slacks within the
sample's allowance); where it is not, or the QP fails, the sample searches as before.
"""

from __future__ import annotations

import math
import os
import sys
import time as clock
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..nlp.tracking import NlpBase

#: the QP solver (a CasADi conic plugin) and its options. qpOASES with sparse matrices, measured (second calls) on the
#: live van der Pol NLPs: tier 0 (47 variables, 186 rows) 0.3 ms, the passage NLP (219, 1333) 6.6 ms (dense 11.3);
#: ProxQP 1.5 and 2000 ms, qrqp 2.9 ms and no solution in 1000 iterations, OSQP no solution in 4000 iterations
QP_SOLVER = "qpoases"
#: qpOASES' bound on one QP whatever the parameters: its working-set changes (nWSR) per variable of the NLP. From a
#: cold start it adds the active rows one at a time (the passage NLP: 492 changes for 219 variables, 118 ms; tier 0:
#: 151 for 47), so each prepared plan's own QP is solved in the preparation (`prime`), and the sample's QP starts hot
#: from that working set (measured: 0-1 changes, 0.4 ms on tier 0, 6.9 ms on the passage NLP). Its CPUtime option
#: is not passed on by CasADi's interface (a QP set to 5 ms took 116): the changes are the bound
WORKING_SET_CHANGES_PER_VARIABLE = 5
QP_OPTIONS = {"printLevel": "none", "sparse": True, "error_on_fail": False}


class FeedbackQp:
    """The QP step of one NLP: its linearisation (one CasADi call) and its QP solver, built once."""

    def __init__(self, nlp: NlpBase) -> None:
        w, p, f, g = nlp.problem["x"], nlp.problem["p"], nlp.problem["f"], nlp.problem["g"]
        hessian = ca.hessian(f, w)[0]
        jacobian = ca.jacobian(g, w)
        self._linearisation = ca.Function("feedback_qp_linearisation", [w, p],
                                          [hessian, ca.gradient(f, w), g, jacobian])
        self._solver = _quietly(lambda: ca.conic("feedback_qp", QP_SOLVER, {"h": hessian.sparsity(),
                                                 "a": jacobian.sparsity()},
                                                 {**QP_OPTIONS, "nWSR": WORKING_SET_CHANGES_PER_VARIABLE * w.numel()}))
        self._check = ca.Function("feedback_qp_check", [w, p], [violation_function(nlp)(w, p), *nlp.steady.function(w)])
        self._nlp = nlp

    def prime(self, w: np.ndarray, par: np.ndarray) -> None:
        """In the preparation: solve the QP at the prepared plan w [n_w] and its parameters par [n_p] (no move: a KKT
        point), so that the sample's QP starts from its working set (qpOASES hot-starts from its last call's)."""
        self._solve(w, par)

    def _solve(self, w: np.ndarray, par: np.ndarray) -> np.ndarray | None:
        """The QP's step d [n_w] at (w, par), None where qpOASES failed."""
        nlp = self._nlp
        hessian, gradient, g, jacobian = self._linearisation(w, par)
        g = np.asarray(g).ravel()
        solution = self._solver(h=hessian, g=gradient, a=jacobian, lba=nlp.lbg - g, uba=nlp.ubg - g,
                                lbx=nlp.lbx - w, ubx=nlp.ubx - w)
        return np.asarray(solution["x"]).ravel() if self._solver.stats()["success"] else None

    def step(self, w: np.ndarray, par: np.ndarray, deadline: float) -> QpStep | None:
        """The plan w [n_w] moved by the QP at parameters par [n_p], checked; None where the QP failed. Nothing is
        tried once `deadline` (time.perf_counter s) has passed; the QP's work is bounded by
        WORKING_SET_CHANGES_PER_VARIABLE."""
        if deadline - clock.perf_counter() <= 0:
            return None
        d = self._solve(w, par)
        if d is None:
            return None
        moved = w + d
        violation, x_a, u_a = self._check(moved, par)
        slacks = self._nlp._slack_index
        slack = float(np.max(moved[slacks])) if slacks.size else -math.inf
        return QpStep(moved, float(violation), slack, np.asarray(x_a).ravel(), np.asarray(u_a).ravel())


@dataclass
class QpStep:
    """A plan moved by the QP: w [n_w], its largest constraint violation and slack, and its x_a [n], u_a [m]."""

    w: np.ndarray
    violation: float
    slack: float
    x_a: np.ndarray
    u_a: np.ndarray


def violation_function(nlp: NlpBase) -> ca.Function:
    """(w, p) -> the largest violation of the NLP's constraints and bounds (0 if feasible), one CasADi call."""
    w, p, g = nlp.problem["x"], nlp.problem["p"], nlp.problem["g"]
    rows = []
    for values, lower, upper in ((g, nlp.lbg, nlp.ubg), (w, nlp.lbx, nlp.ubx)):
        low, high = np.flatnonzero(np.isfinite(lower)), np.flatnonzero(np.isfinite(upper))
        rows += [ca.DM(lower[low]) - values[low.tolist()], values[high.tolist()] - ca.DM(upper[high])]
    return ca.Function("violation", [w, p], [ca.mmax(ca.vertcat(*rows, 0))])


def _quietly(make: Callable[[], ca.Function]) -> ca.Function:
    """make() with the process's standard output sent to /dev/null: qpOASES prints its copyright banner when a solver
    is built (its printLevel applies only after), on every controller's start."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            return make()
    finally:
        os.dup2(saved, 1)
        os.close(saved)
