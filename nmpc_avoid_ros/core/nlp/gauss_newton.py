"""The Hessian of the SQP paths (solver sqp, sqp_hpipm): the cost's own, with the terminal cost as least squares.

The SQP paths drop the constraints' curvature (the dynamics, the avoidance rows) and use the cost's Hessian. The
equality scheme's cost is a sum of squares whose Hessian is positive semi-definite, and it is used exactly. With
`terminal: set` the cost also has V_f = e' P(y_a) e (e = x(N) - x_a), whose exact Hessian is indefinite (the terms
of P'(y_a) and P''(y_a) couple e and y_a; measured on the paper's run: 4 and 1 of 50 samples solved). There V_f
is written as |r|^2 with the residual r = R(y_a) e, R the upper Cholesky factor of the fitted P (R'R = P,
`upper_cholesky`), and it contributes the Gauss-Newton term 2 J'J (J = dr/dw) instead: positive semi-definite by
construction. The set's row
V_f / alpha - 1 = |r / sqrt(alpha)|^2 - 1 keeps its curvature in the same form, 2 lam J_a'J_a with
J_a = d(r / sqrt(alpha))/dw and lam its multiplier (>= 0 where the row is active; negative ones clipped):
positive semi-definite too. Measured on the paper's run (docs/terminal_set.md), with the row's curvature dropped
like the other rows' the sqp paths ended 9-13 of 50 samples unsolved, most in recovery fallbacks (the set row is
active while y_a heads for the target); with it the same samples as IPOPT's loop, and as many `unconverged` ones
(a feasible iterate applied) as the equality on these paths. The stage-wise NLP (core/nlp/stagewise.py) hands the
residuals and the cost without V_f to make_solver (core/nlp/tracking.py) under the problem's key GAUSS_NEWTON;
nothing else reads it.
"""

from __future__ import annotations

import casadi as ca

#: the problem dict's key of (cost without V_f, residual r with |r|^2 = V_f, index of the first set row in g, the set
#: rows' residuals), for the SQP paths
GAUSS_NEWTON = "gauss_newton"


def upper_cholesky(p: ca.SX) -> ca.SX:
    """R [n, n], upper triangular with R'R = P, of a symmetric positive definite CasADi matrix P [n, n] (n small)."""
    n = p.shape[0]
    r = ca.SX(n, n)
    for i in range(n):
        r[i, i] = ca.sqrt(p[i, i] - ca.sumsqr(r[:i, i]))
        for j in range(i + 1, n):
            r[i, j] = (p[i, j] - ca.dot(r[:i, i], r[:i, j])) / r[i, i]
    return r


def plain_problem(nlp: dict) -> tuple[dict, tuple | None]:
    """(the problem nlpsol takes: x, p, f, g; the GAUSS_NEWTON entry or None)."""
    return {key: nlp[key] for key in ("x", "p", "f", "g")}, nlp.get(GAUSS_NEWTON)


def sqp_hessian(nlp: dict, gauss_newton: tuple | None) -> ca.Function:
    """hess_lag for sqpmethod: lam_f times the cost's Hessian (constraint curvature dropped); with `gauss_newton`
    = (cost without V_f, residual r, first set row i, the set rows' residuals r_j) the Hessian of the former plus
    2 J'J of r, and 2 max(0, lam_g[i + j]) J_j'J_j of each set row's."""
    lam_f = ca.SX.sym("lam_f")
    lam_g = ca.SX.sym("lam_g", nlp["g"].numel())
    if gauss_newton is None:
        hessian = lam_f * ca.hessian(nlp["f"], nlp["x"])[0]
    else:
        rest, residual, first_row, row_residuals = gauss_newton
        jacobian = ca.jacobian(residual, nlp["x"])
        hessian = lam_f * (ca.hessian(rest, nlp["x"])[0] + 2 * ca.mtimes(jacobian.T, jacobian))
        for j, row in enumerate(row_residuals):
            jacobian = ca.jacobian(row, nlp["x"])
            hessian += 2 * ca.fmax(lam_g[first_row + j], 0) * ca.mtimes(jacobian.T, jacobian)
    return ca.Function("nlp_hess_l", [nlp["x"], nlp["p"], lam_f, lam_g], [hessian],
                       ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
