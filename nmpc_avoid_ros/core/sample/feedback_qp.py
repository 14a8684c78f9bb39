"""One QP where the feedback law does not hold because the active set changed (core/sample/feedback.py).

The law is the tangential predictor on the prepared plan's active set; a miss of the predicted state by ~1e-3 on
a region's boundary flips the penalty's slack rows, and the law refuses (`active_set_changed`). acados' real-time
iteration answers such a state with one QP on the linearisation at its prepared iterate; so does this: at the
prepared plan w̄ and the sample's parameters p,

    min_d  1/2 d' (H_f + delta I) d + grad f(w̄, p)' d
    s.t.   lbg - g(w̄, p) <= dg/dw(w̄, p) d <= ubg - g(w̄, p),   lbx - w̄ <= d <= ubx - w̄

with H_f the cost's Hessian (positive semi-definite: a sum of squares and the slacks' quadratic penalty; the
constraints' curvature dropped as on the SQP paths, core/nlp/gauss_newton.py) and delta a small regularisation.
At p = p̄ its solution is d = 0 (w̄ is a KKT point: the QP's KKT conditions hold there with the plan's
multipliers, whatever the Hessian), so it moves the plan only as far as the parameters moved. qpOASES (dense, its
working set bounded by QP_WORKING_SET_CHANGES and its CPU time by the sample's deadline) solves it. The moved plan
w̄ + d is checked on the nonlinear problem exactly as the law's answer is (feasible to the tolerance, slacks within
the sample's allowance); where it is not, or the QP fails, the sample searches as before.
"""

from __future__ import annotations

import math
import time as clock

import casadi as ca
import numpy as np

from ..nlp.tracking import NlpBase

#: the QP solver (a CasADi conic plugin): ProxQP's proximal iterations take the cost's semi-definite Hessian as it is
#: (a state only the dynamics bind has no curvature); measured on the live van der Pol tier-0 QP (47 variables, 186
#: rows): ProxQP 1.6-1.9 ms, qrqp 2.9, qpOASES 4-5 (and a banner on stdout at each construction), DAQP and OSQP failed
QP_SOLVER = "proxqp"
#: ProxQP's iterations per QP: the bound of its work whatever the parameters
QP_MAX_ITERATIONS = 200


class FeedbackQp:
    """The QP step of one NLP: its linearisation (one CasADi call) and its qpOASES solver, built once."""

    def __init__(self, nlp: NlpBase) -> None:
        w, p, f, g = nlp.problem["x"], nlp.problem["p"], nlp.problem["f"], nlp.problem["g"]
        hessian = ca.hessian(f, w)[0]
        jacobian = ca.jacobian(g, w)
        self._linearisation = ca.Function("feedback_qp_linearisation", [w, p],
                                          [hessian, ca.gradient(f, w), g, jacobian])
        self._solver = ca.conic("feedback_qp", QP_SOLVER, {"h": hessian.sparsity(), "a": jacobian.sparsity()},
                                {"error_on_fail": False, QP_SOLVER: {"max_iter": QP_MAX_ITERATIONS}})
        self._check = ca.Function("feedback_qp_check", [w, p], [violation_function(nlp)(w, p), *nlp.steady.function(w)])
        self._nlp = nlp

    def step(self, w: np.ndarray, par: np.ndarray, deadline: float) -> tuple[np.ndarray | None, float, float]:
        """(the plan w [n_w] moved by the QP at parameters par [n_p], or None where the QP failed; its largest
        constraint violation; its largest slack). The QP's CPU time ends by `deadline` (time.perf_counter s)."""
        left = deadline - clock.perf_counter()
        if left <= 0:
            return None, math.inf, math.inf
        nlp = self._nlp
        hessian, gradient, g, jacobian = self._linearisation(w, par)
        solution = self._solver(h=hessian, g=gradient, a=jacobian,
                                lba=nlp.lbg - np.asarray(g).ravel(), uba=nlp.ubg - np.asarray(g).ravel(),
                                lbx=nlp.lbx - w, ubx=nlp.ubx - w)
        if not self._solver.stats()["success"]:
            return None, math.inf, math.inf
        moved = w + np.asarray(solution["x"]).ravel()
        violation = float(self._check(moved, par)[0])
        slacks = nlp._slack_index
        slack = float(np.max(moved[slacks])) if slacks.size else -math.inf
        return moved, violation, slack

    def steady(self, w: np.ndarray, par: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x_a [n], u_a [m] of the plan w."""
        _, x_a, u_a = self._check(w, par)
        return np.asarray(x_a).ravel(), np.asarray(u_a).ravel()


def violation_function(nlp: NlpBase) -> ca.Function:
    """(w, p) -> the largest violation of the NLP's constraints and bounds (0 if feasible), one CasADi call."""
    w, p, g = nlp.problem["x"], nlp.problem["p"], nlp.problem["g"]
    rows = []
    for values, lower, upper in ((g, nlp.lbg, nlp.ubg), (w, nlp.lbx, nlp.ubx)):
        low, high = np.flatnonzero(np.isfinite(lower)), np.flatnonzero(np.isfinite(upper))
        rows += [ca.DM(lower[low]) - values[low.tolist()], values[high.tolist()] - ca.DM(upper[high])]
    return ca.Function("violation", [w, p], [ca.mmax(ca.vertcat(*rows, 0))])
