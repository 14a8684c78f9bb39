"""Terminal ingredients of the paper's general scheme (eq. 7-8, Assumption 3.2-3.4), computed offline.

For a nonlinear model whose steady state has a closed form (x_a, u_a) = (g_x(y_a), g_u(y_a)) with one output
(p = 1), over the steady outputs y_a whose steady state lies in lambda Z:

* local controller  kappa(x, y_a) = u_a + K(y_a) (x - x_a), K the discrete LQR gain of the linearisation
  (A(y_a), B(y_a)) of the prediction map at the steady state, for the stage cost's Q, R;
* terminal cost     V_f = (x - x_a)' P(y_a) (x - x_a),  P = (1 + margin) P_lqr: the LQR's value matrix
  inflated, so the linearisation decreases V_f by (1 + margin) l and the nonlinearity may use the rest;
* terminal set      Omega = {(x, y_a): V_f <= alpha(y_a)}.

P(y_a) is a Chebyshev polynomial fit (in y_a) of the LQR's value matrix at Chebyshev-Lobatto nodes, so P
and alpha are smooth CasADi expressions of y_a: the NLP carries them without a rebuild when y_t or the
regions change. K(y_a) is computed from the fitted P (the LQR gain formula), so it is continuous too.

alpha(y_a) is certified at every point of a uniform grid of y_a (`CERTIFIED_POINTS`): for every x in
{V_f <= alpha} with u = kappa(x, y_a)
  (a) x in the state box and u in the input box of Z (exact: the ellipsoid's extent along each axis);
  (b) V_f(f(x, u)) - V_f(x) <= -l(x - x_a, u - u_a), which also keeps f(x, u) in the set (invariance).
(b) is proven from the Taylor remainder of f around the steady state: |r_i| <= 1/2 ||H_i|| |z|^2 with H_i
the Hessian of f_i over the box that contains the ellipsoid and its inputs, bounded by interval arithmetic
(core/problem/intervals.py), and the margin matrix D = P - A_K' P A_K - Q - K' R K > 0 of the fitted P:
    -e'De + 2 |P^1/2 A_K e| |P^1/2 r| + |P^1/2 r|^2 <= 0   for all V_f(e) <= alpha.
Those bounds prove a core; on the shell around it (b) is proven by branch and bound (core/problem/annulus.py),
up to the largest alpha that (a) allows. Between the grid points the fitted alpha is checked at the midpoints
with the same certificate (sampled: a midpoint's own certified alpha must be at least the fitted one).

A linear model (`compute_linear_ingredients`), with any number of outputs, has one P and K, no remainder, and
its set is written as one exact row per finite bound of Z. docs/terminal_set.md says the same.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
from scipy.linalg import solve_discrete_are

from ..errors import ConfigError
from .annulus import shell_decreases
from .intervals import interval_evaluate
from .model import Model

#: the default margin: P = (1 + margin) P_lqr (docs/terminal_set.md compares margins)
MARGIN = 1000.0
#: Chebyshev-Lobatto nodes at which the LQR is solved, and the degree of P's fit
FIT_NODES = 41
FIT_DEGREE = 24
#: uniform grid of y_a at which alpha is certified; the fitted alpha's degree (of log alpha)
CERTIFIED_POINTS = 241
ALPHA_DEGREE = 40
#: bisection steps on log alpha per grid point: of the norm-bound certificate, then of the shell around it
BISECTION_STEPS = 40
SHELL_STEPS = 6
#: the fitted alpha stays this factor below every certified value (grid and midpoints)
ALPHA_SAFETY = 0.98
#: the fits are evaluated at y_a held within this multiple of the steady range's half-width around its centre
T_HELD = 1.02


@dataclass
class TerminalIngredients:
    """P(y_a), alpha(y_a) for y_a in [y_low, y_high] (p = 1) and how they were certified.

    p_coefficients: Chebyshev coefficients [n, n, FIT_DEGREE + 1] of P in t = (y_a - centre) / half_width;
    log_alpha_coefficients: [ALPHA_DEGREE + 1] of log alpha in t; margin, q [n], r [m]: what P was made for;
    grid_y [K], grid_alpha [K]: the certified alpha at the grid (fitted alpha <= it); midpoint_ratio: the
    smallest certified / fitted alpha at the grid's midpoints (sampled; >= 1 where the fit holds there);
    seconds: the computation's wall time; cache: 'computed' or 'hit' (set by the caller that cached it).
    box_rows [k, 3]: a linear model's set (`compute_linear_ingredients`): P constant (degree 0), no decrease limit
    (log_alpha_coefficients empty), and per finite bound of Z a row (index j in z = (x, u), bound b_j, weight w_j):
    the level (b_j - z_s,j)^2 / w_j keeps the ellipsoid on the right side of that bound."""

    y_low: float
    y_high: float
    margin: float
    q: np.ndarray
    r: np.ndarray
    p_coefficients: np.ndarray
    log_alpha_coefficients: np.ndarray
    grid_y: np.ndarray
    grid_alpha: np.ndarray
    midpoint_ratio: float
    fit_error: float
    seconds: float
    cache: str = field(default="computed", compare=False)
    box_rows: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def _t(self, y):
        """y_a scaled to [-1, 1] over [y_low, y_high], held at +-T_HELD beyond: the fits are polynomials of high
        degree that overflow far outside (a solver's iterate may leave lambda Z for a while; measured: NaN in the
        NLP's derivatives), and the hold is a kink only where no plan is feasible."""
        t = (y - (self.y_high + self.y_low) / 2) / ((self.y_high - self.y_low) / 2)
        return ca.fmin(ca.fmax(t, -T_HELD), T_HELD) if isinstance(t, ca.SX) else float(np.clip(t, -T_HELD, T_HELD))

    def cost_matrix(self, y_a: float | np.ndarray) -> np.ndarray:
        """P(y_a) [n, n]."""
        t = float(self._t(float(np.ravel(y_a)[0])))
        return np.polynomial.chebyshev.chebval(t, np.moveaxis(self.p_coefficients, -1, 0))

    def levels(self, y_a, z_s) -> list:
        """The levels whose minimum is alpha(y_a): the certified decrease limit (nonlinear models) and one per box
        row (linear models); z_s = (x_a, u_a) [n + m]; numbers or CasADi expressions."""
        levels = []
        if self.log_alpha_coefficients.size:
            t = self._t(y_a[0] if isinstance(y_a, ca.SX) else float(np.ravel(y_a)[0]))
            exponent = _clenshaw(self.log_alpha_coefficients, t)
            levels.append(ca.exp(exponent) if isinstance(exponent, ca.SX) else float(np.exp(exponent)))
        for j, bound, weight in self.box_rows:
            levels.append((bound - z_s[int(j)]) ** 2 / weight)
        return levels

    def alpha(self, y_a: float | np.ndarray, z_s: np.ndarray | None = None) -> float:
        """alpha(y_a), the level of the terminal set (V_f units); z_s = (x_a, u_a), needed with box rows."""
        return float(min(self.levels(y_a, z_s)))

    def symbolic(self, y_a: ca.SX) -> ca.SX:
        """P(y_a) [n, n] as a CasADi expression of y_a (Clenshaw's recurrence in its first entry)."""
        t = self._t(y_a[0])
        n = self.p_coefficients.shape[0]
        p = ca.SX(n, n)
        for i in range(n):
            for j in range(i, n):
                p[i, j] = p[j, i] = _clenshaw(self.p_coefficients[i, j], t)
        return p

    def to_dict(self) -> dict[str, Any]:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items() if k != "cache"}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TerminalIngredients:
        arrays = ("q", "r", "p_coefficients", "log_alpha_coefficients", "grid_y", "grid_alpha", "box_rows")
        return cls(**{k: (np.asarray(v, float) if k in arrays else v) for k, v in data.items()})


def _clenshaw(coefficients: np.ndarray, t):
    """sum_k c_k T_k(t), numbers or CasADi expressions."""
    b1 = b2 = 0.0
    for c in coefficients[:0:-1]:
        b1, b2 = 2 * t * b1 - b2 + float(c), b1
    return t * b1 - b2 + float(coefficients[0])


class TerminalProblem:
    """The pieces the computation needs of a model, a discrete prediction map and Z (p = 1, closed form)."""

    def __init__(self, model: Model, step: ca.Function, q, r, state_min, state_max, input_min, input_max,
                 scale: float) -> None:
        if model.steady_state is None:
            raise ConfigError(f"terminal: set needs the closed-form steady state g_x, g_u of the model; {model.name} "
                              "has none (its steady states are constraints, eq. 8e-8f): use terminal: equality")
        self.model, self.n, self.m, self.step = model, model.n, model.m, step
        self.q, self.r = np.diag(np.asarray(q, float)), np.diag(np.asarray(r, float))
        self.box = [np.asarray(b, float) for b in (state_min, state_max, input_min, input_max)]
        self.scale = scale
        x, u, y = ca.SX.sym("x", self.n), ca.SX.sym("u", self.m), ca.SX.sym("y", model.p)
        nxt = step(x, u)
        z = ca.vertcat(x, u)
        self.jacobians = ca.Function("AB", [x, u], [ca.jacobian(nxt, x), ca.jacobian(nxt, u)])
        hessians = [ca.hessian(nxt[i], z)[0] for i in range(self.n)]
        self.hessians = ca.Function("H", [x, u], [ca.vertcat(*[ca.vec(ca.densify(h)) for h in hessians])])
        x_s, u_s = model.steady_state(y)
        self.steady = ca.Function("steady", [y], [ca.vertcat(x_s), ca.vertcat(u_s)])
        a_s, b_s = self.jacobians(ca.vertcat(x_s), ca.vertcat(u_s))
        #: f is linear: no remainder, and one LQR for every steady state (compute_linear_ingredients)
        self.linear = all(ca.densify(h).is_zero() for h in hessians) and not ca.depends_on(ca.vertcat(
            ca.vec(a_s), ca.vec(b_s)), y)
        if model.p != 1 and not self.linear:
            raise ConfigError(f"terminal: set is computed for nonlinear models with one output (p = 1); {model.name} "
                              f"has p = {model.p} (docs/terminal_set.md): use terminal: equality")

    def steady_state(self, y: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x_s, u_s = self.steady(y)
        return np.asarray(x_s, float).ravel(), np.asarray(u_s, float).ravel()

    def linearisation(self, y: float) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.jacobians(*self.steady_state(y))
        return np.asarray(a, float), np.asarray(b, float)

    def output_range(self) -> tuple[float, float]:
        """The steady outputs whose steady state lies in lambda Z: a scan of h over lambda times the state box."""
        lo, hi = (np.clip(b, -1e3, 1e3) * self.scale for b in self.box[:2])
        corners = np.array(np.meshgrid(*zip(lo, hi))).reshape(self.n, -1).T
        ys = [float(np.asarray(self.model.output(c, np.zeros(self.m))).ravel()[0]) for c in corners]
        scan = np.linspace(min(ys), max(ys), 2001)
        inside = np.array([self._in_scaled_box(*self.steady_state(y)) for y in scan])
        if not inside.any():
            raise ConfigError("terminal: set: no steady state lies in lambda Z")
        index = np.flatnonzero(inside)
        if index[-1] - index[0] + 1 != index.size:
            raise ConfigError("terminal: set: the steady outputs in lambda Z are not one interval")
        return float(scan[index[0]]), float(scan[index[-1]])

    def _in_scaled_box(self, x_s, u_s) -> bool:
        lam, (x_lo, x_hi, u_lo, u_hi) = self.scale, self.box
        tol = 1e-9
        return bool(np.all(lam * x_lo - tol <= x_s) and np.all(x_s <= lam * x_hi + tol)
                    and np.all(lam * u_lo - tol <= u_s) and np.all(u_s <= lam * u_hi + tol))

    def gain(self, y: float, p: np.ndarray, margin: float) -> np.ndarray:
        """K [m, n] of the LQR formula with P = (1 + margin) P_lqr: -((1 + margin) R + B'PB)^-1 B'PA."""
        a, b = self.linearisation(y)
        return -np.linalg.solve((1 + margin) * self.r + b.T @ p @ b, b.T @ p @ a)

    def certified_alpha(self, y: float, p: np.ndarray, margin: float) -> float:
        """The largest alpha (bisection on log alpha) for which (a) and (b) of the module docstring hold at y; 0 if
        the margin matrix D is not positive definite."""
        x_s, u_s = self.steady_state(y)
        a, b = self.linearisation(y)
        k = self.gain(y, p, margin)
        a_k = a + b @ k
        stage = self.q + k.T @ self.r @ k
        d = p - a_k.T @ p @ a_k - stage
        p_inv = np.linalg.inv(p)
        w, v = np.linalg.eigh(p)
        if w[0] <= 0:
            return 0.0
        root_inv = v @ np.diag(w ** -0.5) @ v.T  # P^-1/2
        delta = np.linalg.eigvalsh(root_inv @ d @ root_inv)[0]
        if delta <= 0:
            return 0.0
        a_gain = np.sqrt(max(np.linalg.eigvalsh(root_inv @ a_k.T @ p @ a_k @ root_inv)[-1], 0.0))
        # z = (e, K e) = M P^-1/2 w with |w|^2 = V_f(e): |z| <= spread |w| entrywise
        spread = np.abs(np.vstack([np.eye(self.n), k]) @ root_inv)
        x_extent = np.sqrt(np.diag(p_inv))  # per unit alpha: |e_j| <= sqrt(alpha) x_extent_j
        u_extent = np.sqrt(np.diag(k @ p_inv @ k.T))
        x_lo, x_hi, u_lo, u_hi = self.box
        room = np.concatenate([np.minimum(x_hi - x_s, x_s - x_lo) / x_extent, np.minimum(u_hi - u_s, u_s - u_lo)
                               / np.maximum(u_extent, 1e-300)])
        alpha_box = float(np.min(room)) ** 2 if np.all(room > 0) else 0.0
        if not alpha_box > 0:
            return 0.0
        alpha_box = min(alpha_box, 1e12)

        def decreases(alpha: float) -> bool:
            s = np.sqrt(alpha)
            bounds = interval_evaluate(self.hessians, [x_s - s * x_extent, u_s - s * u_extent],
                                       [x_s + s * x_extent, u_s + s * u_extent])[0]
            size = self.n + self.m
            # |r_i| <= c_i V_f(e), c_i = 1/2 |spread' |H_i| spread|_2; then |P^1/2 r| <= sqrt(c'|P|c) V_f(e)
            c = np.array([0.5 * np.linalg.norm(spread.T @ np.max(np.abs(bounds[i * size * size:(i + 1) * size * size]),
                                                                 axis=1).reshape(size, size) @ spread, 2)
                          for i in range(self.n)])
            remainder = np.sqrt(c @ np.abs(p) @ c)
            return 2 * a_gain * remainder * s + remainder ** 2 * alpha <= delta

        if decreases(alpha_box):
            return alpha_box
        lo, hi = np.log(alpha_box) - 40.0, np.log(alpha_box)
        if not decreases(np.exp(lo)):
            return 0.0
        for _ in range(BISECTION_STEPS):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if decreases(np.exp(mid)) else (lo, mid)
        # around the proven set, the shell by branch and bound (core/problem/annulus.py), up to the box limit
        near = float(np.exp(lo))

        def shell(alpha: float) -> bool:
            return shell_decreases(self.step, self.q, self.r, p, k, x_s, u_s, near, alpha)

        if shell(alpha_box):
            return alpha_box
        lo, hi = np.log(near), np.log(alpha_box)
        for _ in range(SHELL_STEPS):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if shell(np.exp(mid)) else (lo, mid)
        return float(np.exp(lo))


def compute_linear_ingredients(problem: TerminalProblem, margin: float = MARGIN) -> TerminalIngredients:
    """A linear model's ingredients, for any number of outputs: one P = (1 + margin) P_lqr and K for every steady
    state (A, B do not depend on it), D = margin (Q + K'RK) > 0 and no remainder, so V_f decreases by at least l in
    all of R^n (proven, no grid); the set is the largest sublevel set inside Z, one level per finite bound (exact)."""
    start = time.perf_counter()
    y0 = np.zeros(problem.model.p)
    a, b = problem.linearisation(y0)
    try:
        p = (1 + margin) * solve_discrete_are(a, b, problem.q, problem.r)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ConfigError(f"terminal: set: the LQR of {problem.model.name} has no stabilising solution ({exc}): "
                          "the model is not stabilisable (paper Assumption 5): use terminal: equality") from exc
    k = problem.gain(y0, p, margin)
    p_inv = np.linalg.inv(p)
    weights = np.concatenate([np.diag(p_inv), np.diag(k @ p_inv @ k.T)])
    lower = np.concatenate([problem.box[0], problem.box[2]])  # (x_min, u_min), (x_max, u_max) over z = (x, u)
    upper = np.concatenate([problem.box[1], problem.box[3]])
    # a row whose coordinate the ellipsoid does not move (weight 0) bounds nothing
    rows = [(j, bound, weights[j]) for bounds in (lower, upper) for j, bound in enumerate(bounds)
            if np.isfinite(bound) and weights[j] > 0]
    box_rows = np.array([row for row in rows if np.isfinite(row[1])], float).reshape(-1, 3)
    return TerminalIngredients(-1.0, 1.0, margin, np.diag(problem.q).copy(), np.diag(problem.r).copy(), p[:, :, None],
                               np.zeros(0), np.zeros(0), np.zeros(0), np.inf, 0.0, time.perf_counter() - start,
                               box_rows=box_rows)


def compute_terminal_ingredients(problem: TerminalProblem, margin: float = MARGIN) -> TerminalIngredients:
    """P(y_a) and a certified alpha(y_a) over the steady outputs in lambda Z (module docstring); a linear model's
    by `compute_linear_ingredients`. ConfigError where the LQR has no stabilising solution (Assumption 5 fails) or
    no alpha > 0 is certified."""
    if problem.linear:
        return compute_linear_ingredients(problem, margin)
    start = time.perf_counter()
    y_low, y_high = problem.output_range()
    centre, half = (y_high + y_low) / 2, max((y_high - y_low) / 2, 1e-9)
    nodes = np.cos(np.pi * np.arange(FIT_NODES) / (FIT_NODES - 1))  # Chebyshev-Lobatto in t
    values = []
    for t in nodes:
        a, b = problem.linearisation(centre + half * t)
        try:
            values.append(solve_discrete_are(a, b, problem.q, problem.r))
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise ConfigError(f"terminal: set: the LQR of {problem.model.name}'s linearisation at y_a = "
                              f"{centre + half * t:.4g} has no stabilising solution ({exc}); the linearisation is "
                              "not stabilisable there (paper Assumption 5): use terminal: equality") from exc
    values = (1 + margin) * np.array(values)  # [FIT_NODES, n, n]
    coefficients = np.polynomial.chebyshev.chebfit(nodes, values.reshape(FIT_NODES, -1), FIT_DEGREE)
    p_coefficients = np.moveaxis(coefficients.reshape(FIT_DEGREE + 1, problem.n, problem.n), 0, -1)
    p_coefficients = (p_coefficients + np.swapaxes(p_coefficients, 0, 1)) / 2
    ingredients = TerminalIngredients(y_low, y_high, margin, np.diag(problem.q).copy(), np.diag(problem.r).copy(),
                                      p_coefficients, np.zeros(1), np.zeros(0), np.zeros(0), 0.0, 0.0, 0.0)
    check = np.linspace(-1, 1, 4 * FIT_NODES + 1)
    ingredients.fit_error = float(max(
        np.max(np.abs(ingredients.cost_matrix(centre + half * t) - (1 + margin) * solve_discrete_are(
            *problem.linearisation(centre + half * t), problem.q, problem.r)))
        / np.max(np.abs(ingredients.cost_matrix(centre + half * t))) for t in check[1::8]))
    grid_y = np.linspace(y_low, y_high, CERTIFIED_POINTS)
    grid_alpha = np.array([problem.certified_alpha(y, ingredients.cost_matrix(y), margin) for y in grid_y])
    if not np.all(grid_alpha > 0):
        where = grid_y[grid_alpha <= 0]
        raise ConfigError(f"terminal: set: no terminal set certified at y_a = {where[0]:.4g} ({where.size} of "
                          f"{grid_y.size} grid points): use terminal: equality")
    t_grid = (grid_y - centre) / half
    log_fit = np.polynomial.chebyshev.chebfit(t_grid, np.log(grid_alpha), ALPHA_DEGREE)
    shift = float(np.max(np.polynomial.chebyshev.chebval(t_grid, log_fit) - np.log(grid_alpha)))
    log_fit[0] -= shift - np.log(ALPHA_SAFETY)
    ingredients.log_alpha_coefficients = log_fit
    midpoints = (grid_y[1:] + grid_y[:-1]) / 2
    ratios = np.array([problem.certified_alpha(y, ingredients.cost_matrix(y), margin) / ingredients.alpha(y)
                       for y in midpoints])
    if ratios.min() < 1:  # the fit overshoots between the grid points: lower it to the midpoints' certificates
        log_fit[0] += np.log(ratios.min())
        ratios = ratios / ratios.min()
    ingredients.grid_y, ingredients.grid_alpha = grid_y, grid_alpha
    ingredients.midpoint_ratio = float(ratios.min())
    ingredients.seconds = time.perf_counter() - start
    return ingredients


def local_controller(problem: TerminalProblem, ingredients: TerminalIngredients, x: np.ndarray,
                     y_a: float | np.ndarray) -> np.ndarray:
    """kappa(x, y_a) = u_a + K(y_a) (x - x_a) [m]."""
    x_s, u_s = problem.steady_state(y_a)
    k = problem.gain(y_a, ingredients.cost_matrix(y_a), ingredients.margin)
    return u_s + k @ (np.asarray(x, float) - x_s)
