"""The feedback law of a prepared solution: how its plan moves with the state it starts from.

Why: a converged solve takes FATROP 0.5-20 ms on the live configs; acados' real-time iteration answers
the same problem in tens of microseconds because, between samples, it prepares the problem for the
state it expects and, when the state arrives, only corrects for the difference. Here the preparation
solves the NLP to convergence for the predicted state x̄ (core/sample/feedback.py) and this module turns
that solution into a law for any nearby state x: the tangential predictor of parametric NLP
sensitivity (Fiacco 1976; the advanced-step NMPC of Zavala & Biegler 2009):

    [H   A_a'] [dw]     [H_p  ]
    [A_a  0  ] [dl] = - [A_a,p] dp,     dp = p(x) - p(x̄)

with H the Hessian of the Lagrangian f + lam_g' g, A_a the Jacobian of the active constraints and
bounds (equalities, inequalities at a bound) and dp the change of the parameters the law follows (the
caller's columns: core/sample/feedback.py follows x(0), the command in force and each obstacle slot's
stamp offset, what moves with time). The active set is read from the
solution itself (a row within `ACTIVE_TOLERANCE` of a bound), so a plan solved on another NLP of the
same problem (an ellipse tier, the reference) gets a law too; the multipliers solve the KKT system on
that set (rows with a wrong-signed multiplier leave it), regularised so that dependent rows (a slack
bounded by nine copies of the same row of an empty slot) share theirs.

The law answers only where it is right: the active constraints keep the sign of their multipliers
(else the active set changes: a QP, not this); the caller checks the corrected plan w + dw on the
nonlinear problem at the new parameters (core/sample/feedback.py). Elsewhere the sample searches.
"""

from __future__ import annotations

import functools
import os
import tempfile
import time as clock
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .codegen import problem_digest
from .native_threads import scratch, start_native

#: a constraint row or bound this close to its bound (scaled by 1 + |bound|) counts as active
ACTIVE_TOLERANCE = 1e-6
#: the stationarity residual |grad f + A_a' lam| allowed, relative to 1 + |grad f|: above it the
#: active set read from the solution is not the solution's (e.g. a solve stopped short), no law
STATIONARITY_TOLERANCE = 1e-3
#: rounds of dropping the rows whose least-squares multiplier has the wrong sign
ACTIVE_SET_ROUNDS = 8
#: regularisation of the KKT matrix: primal (a flat direction such as an unused slack's) and dual
#: (dependent active rows share their multiplier)
REGULARISATION = 1e-9
#: an active multiplier may cross zero by this much (relative to 1 + its size) before the law refuses
MULTIPLIER_TOLERANCE = 1e-6


class KktSensitivity:
    """The derivatives of one NLP's KKT conditions (CasADi Functions built once, in the constructor).

    `columns` are the parameters the law follows (indices into the NLP's parameter vector). With a `cache`
    folder the two Functions are read from it when this problem and these columns were built before, else
    built and saved there (by a thread with `background`): the symbolic derivatives are most of the build (the
    passage NLP of the live van der Pol config: 2.5 s to build, 0.27 s to load; files of 15-20 MB).
    """

    def __init__(self, problem: dict, columns: np.ndarray, cache: Path | None = None, background: bool = False
                 ) -> None:
        self.columns = np.asarray(columns, dtype=int)
        paths = None if cache is None else _cached_paths(problem, self.columns, cache)
        if paths is not None and all(path.exists() for path in paths):
            try:
                self._first, self._second = (ca.Function.load(str(path)) for path in paths)
                return
            except RuntimeError:  # a damaged file: built again and replaced
                pass
        self._first, self._second = _kkt_functions(problem, self.columns)
        if paths is not None:
            save = functools.partial(_save_all, (self._first, self._second), paths)
            if background:  # 0.1-0.3 s of writing each: a first start does not wait for it
                start_native(save, name="kkt-save")
            else:
                save()

    def law(self, w: np.ndarray, par: np.ndarray, bounds: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
            ) -> FeedbackLaw | str:
        """The law at the solution w [n_w] of the NLP at parameters par, or why there is none (text for
        people: the active set read from w does not satisfy the KKT conditions, or the KKT matrix is singular).

        bounds: (lbx, ubx, lbg, ubg) of the NLP.
        """
        begin = clock.perf_counter()
        lbx, ubx, lbg, ubg = bounds
        grad_f, g, A, A_p = self._first(w, par)
        grad_f, g = np.asarray(grad_f).ravel(), np.asarray(g).ravel()
        A, A_p = sp.csr_matrix(A.sparse()), np.asarray(A_p)
        rows, lower_rows = _active(g, lbg, ubg)
        bound, lower_bound = _active(w, lbx, ubx)
        n_w, n_rows = w.size, rows.size
        candidates = sp.vstack([A[rows], sp.eye(n_w, format="csr")[bound]], format="csr")
        row_p = np.vstack([A_p[rows], np.zeros((bound.size, self.columns.size))])  # bounds do not depend on p
        sign = np.where(np.concatenate([lower_rows, lower_bound]), -1.0, 1.0)  # CasADi: lam <= 0 at a lower bound
        equality = np.concatenate([lbg[rows] == ubg[rows], lbx[bound] == ubx[bound]])
        keep = np.arange(candidates.shape[0])
        identity = sp.eye(n_w, format="csc")
        # the multipliers solve [[I, J'], [J, -dI]] [d; lam] = [-grad f; 0]: at a KKT point d = 0 and lam is the
        # least-squares multiplier, shared by dependent rows (nine copies of an empty slot's row bound one
        # slack); the identity, not the Hessian, so that the mu-sized curvature of the slacks does not mix
        # into lam through d. Rows read as active whose multiplier has the wrong sign are not (a row a hair
        # from its bound): dropped, and solved again.
        for _ in range(ACTIVE_SET_ROUNDS):
            factor = _factor(identity, candidates[keep])
            if isinstance(factor, str):
                return factor
            lam = factor.solve(np.concatenate([-grad_f, np.zeros(keep.size)]))[n_w:]
            wrong = ~equality[keep] & (sign[keep] * lam < -MULTIPLIER_TOLERANCE * (1.0 + np.abs(lam)))
            if not wrong.any():
                break
            keep = keep[~wrong]
        else:
            return f"no consistent active set in {ACTIVE_SET_ROUNDS} rounds"
        jacobian = candidates[keep]
        residual = np.linalg.norm(grad_f + jacobian.T @ lam)
        if residual > STATIONARITY_TOLERANCE * (1.0 + np.linalg.norm(grad_f)):
            return f"the active set read from the plan leaves a stationarity residual of {residual:.2g}"
        kept_rows = keep[keep < n_rows]
        lam_g = np.zeros(g.size)
        np.add.at(lam_g, rows[kept_rows], lam[:kept_rows.size])
        H, H_p = self._second(w, par, lam_g)
        factor = _factor(sp.csc_matrix(H.sparse()), jacobian)
        if isinstance(factor, str):
            return factor
        solution = factor.solve(-np.vstack([np.asarray(H_p), row_p[keep]]))
        if not np.all(np.isfinite(solution)):
            return "the KKT matrix is singular"
        # each active multiplier keeps its sign
        sign, scale, ineq = sign[keep], 1.0 + np.abs(lam), ~equality[keep]
        return FeedbackLaw(
            w=w.copy(), par=par.copy(), columns=self.columns, dw=np.asfortranarray(solution[:n_w]),
            multiplier=(sign * lam / scale)[ineq], multiplier_change=np.asfortranarray(
                (sign[:, None] * solution[n_w:] / scale[:, None])[ineq]),
            seconds=clock.perf_counter() - begin)


def _kkt_functions(problem: dict, columns: np.ndarray) -> tuple[ca.Function, ca.Function]:
    """kkt_first: (w, p) -> grad f, g, dg/dw, dg/dp[:, columns]; kkt_second: (w, p, lam_g) -> the Hessian of the
    Lagrangian in w and its gradient's derivative in p[columns]."""
    w, p, f, g = problem["x"], problem["p"], problem["f"], problem["g"]
    lam = ca.SX.sym("lam_g", g.numel())
    lagrangian = f + ca.dot(lam, g)
    grad = ca.gradient(lagrangian, w)
    picked = columns.tolist()
    first = ca.Function("kkt_first", [w, p], [ca.gradient(f, w), g, ca.jacobian(g, w), ca.jacobian(g, p)[:, picked]])
    second = ca.Function("kkt_second", [w, p, lam], [ca.hessian(lagrangian, w)[0], ca.jacobian(grad, p)[:, picked]])
    return first, second


def _cached_paths(problem: dict, columns: np.ndarray, folder: Path) -> tuple[Path, Path]:
    """Where the cache holds the two Functions of `problem` and `columns`, named as compiled solvers are
    (core/nlp/codegen.py `problem_digest`, with the columns)."""
    key = problem_digest(problem, columns.astype(np.int64).tobytes())
    return folder / f"kkt_{key}_first.casadi", folder / f"kkt_{key}_second.casadi"


def _save_all(functions: tuple[ca.Function, ...], paths: tuple[Path, ...]) -> None:
    for function, path in zip(functions, paths):
        _save_atomically(function, path)


def _save_atomically(function: ca.Function, path: Path) -> None:
    """Save `function` to `path` whole or not at all (processes that start together read a complete file; one
    that ends meanwhile removes the partial file: `scratch`); a cache that cannot be written is no error: the next
    start builds again."""
    partial: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, name = tempfile.mkstemp(dir=path.parent, suffix=".part")
        os.close(handle)
        partial = Path(name)
        with scratch(partial):
            function.save(name)
            os.chmod(name, 0o644)  # as the compiled solvers beside it (mkstemp's is 0600)
            os.replace(partial, path)
    except (OSError, RuntimeError):
        if partial is not None:
            partial.unlink(missing_ok=True)


def _factor(hessian: sp.csc_matrix, jacobian: sp.csr_matrix) -> spla.SuperLU | str:
    """The sparse LU of the regularised KKT matrix [[H + dI, J'], [J, -dI]], or why there is none."""
    n, k = hessian.shape[0], jacobian.shape[0]
    kkt = sp.bmat([[hessian + REGULARISATION * sp.eye(n), jacobian.T], [jacobian, -REGULARISATION * sp.eye(k)]],
                  format="csc")
    try:
        # a symmetric fill-reducing order: the KKT matrix is symmetric (measured on the live van der Pol NLP: LU
        # factors of 3100 entries against 5900 with the default COLAMD, and solves 20x faster)
        return spla.splu(kkt, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as error:  # exactly singular
        return f"the KKT matrix is singular ({error})"


def _active(values: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the rows at a bound (equalities included) and, for each, whether it is the lower one."""
    with np.errstate(invalid="ignore"):
        at_lower = np.isfinite(lower) & (values - lower <= ACTIVE_TOLERANCE * (1.0 + np.abs(lower)))
        at_upper = np.isfinite(upper) & (upper - values <= ACTIVE_TOLERANCE * (1.0 + np.abs(upper)))
    rows = np.flatnonzero(at_lower | at_upper)
    return rows, at_lower[rows] & ~at_upper[rows]


@dataclass
class FeedbackLaw:
    """A prepared solution w [n_w] at parameters par and its first-order change dw = dw_dp @ dp.

    columns: the parameters followed (indices into par); dw [n_w, len(columns)];
    multiplier [k]: the active inequalities' multipliers, signed so that >= 0 keeps each active,
    scaled by 1 + |lam|; multiplier_change [k, len(columns)] their change; seconds: time to build it.
    A sample applies it in one generated call (core/sample/feedback.py `answer_function`): w + dw dp, and the
    checks that the active set holds (multiplier + multiplier_change dp >= 0) and the moved plan is feasible.
    """

    w: np.ndarray
    par: np.ndarray
    columns: np.ndarray
    dw: np.ndarray
    multiplier: np.ndarray
    multiplier_change: np.ndarray
    seconds: float = 0.0
    #: the plan's cost terms (V_o, V_a, tracking) [3] and their Jacobians [3, n_w], [3, n_p] (the caller's)
    costs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
