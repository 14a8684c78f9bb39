"""The same NLP as core/nlp/tracking.py, written stage by stage for structure-exploiting solvers.

FATROP and the SQP/HPIPM paths solve optimal-control problems whose variables and constraints
come in stages, each coupled only to the next by the dynamics. The tracking problem has one
global variable, the artificial output y_a; it becomes a constant state (y(k+1) = y(k)), and
everything that depends on it is written per stage with that stage's copy. Per stage k:

    states   x(k) [n], y(k) [p] (+ v(k) [m], the input before u(k), with input_rate_max)
    controls u(k) [m], s(k) [n_depth]   (+ s_a [n_depth] at k = 0)     for k < N
    gap      x(k+1) - f(x(k), u(k)) = 0, y(k+1) - y(k) = 0 (, v(k+1) - u(k) = 0)   for k < N
    path     k = 0: x(0) = measured x0 (v(0) = the command in force); s_a >= depth(x_a, u_a);
             (x_a, u_a) in lambda Z; hard(x_a/lambda)
             |u(k) - v(k)| <= input_rate_max Ts (at k = 0 only with a command in force: rate_on)
             s(k) >= depth(x(k), u(k)) and >= depth at the integration_steps - 1 sub-step states
             towards x(k+1); hard(x(k), u(k)) for k >= 1 (and rows that use u at k = 0)
             k = N: x(N) = x_a(y(N))                                     (terminal equality)
             terminal: set instead: at k = N-1, with x(N) = f(x(N-1), u(N-1)): V_f / alpha - 1 <= 0
             and s_N >= depth(x(N)) (a control of stage N-1), cost V_f + mu |s_N|^2 (core/nlp/terminal.py)
    cost     k = 0: kappa |y(0) - y_t|^2 + 2 mu |s_a|^2   (x(N) = x_a, so F(x(N)) = F(x_a))
             |x(k) - x_a(y(k))|_Q^2 + |u(k) - u_a(y(k))|_R^2 + mu |s(k)|^2

with x_a, u_a = g_x(y), g_u(y) (the closed-form steady state, which this formulation needs).
The optimum equals the multiple-shooting NLP's: x(0) is fixed by an equality instead of being a
parameter, and V_a's terms at x(N) and x_a are merged. The slacks have no bound s >= 0 (min s^2
subject to s >= g already gives max(0, g)), and SLACK_REGULARISATION |s|^2 keeps them pinned
when mu = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..errors import ConfigError
from ..problem.models import Model
from .between import between_samples, worst_of
from .gauss_newton import GAUSS_NEWTON
from .parts import check_sizes, depth_function, problem_parts
from .terminal import terminal_constraint, terminal_residual
from .tracking import SLACK_REGULARISATION, Buffered, NlpBase, TrackingNlp

#: iteration budget of a cold start (no previous plan), also in core/sample/controller.py
COLD_START_ITERATIONS = 200

#: FATROP's pivot tolerance (absolute, default 1e-5) for the rank of a stage's equality rows over its controls, for a
#: model with `rest` rows. The terminal equality x(N) = x_a reaches back through the dynamics, and FATROP eliminates
#: it stage by stage over each stage's controls with a pivoted LU. Near rest the car's heading and sideways rows
#: depend on the controls in proportion to v (steering: about sample_time v / wheelbase), so an iterate with v ~ 1e-4
#: passed the default tolerance with a tiny pivot, and the huge elimination factors made the reduced Hessian
#: indefinite for every primal regularisation: FATROP 1.1.8's inertia correction has no upper limit, so it never
#: returned (campaign scene bicycle-0024, test/test_cold_start.py: from the resting plan, and from the shifted plans
#: near its goal, with integration_steps 4 and 2). At 1e-3 such rows pass on to the stage before (at last to y_a,
#: which holds them), as at rest.
RANK_TOLERANCE = 1e-3
#: the iteration cap of such a model's cold FATROP starts (each still cut at max_solve_time, Start.time_limit): the
#: car at rest facing away from its goal among 4 ellipses with steering-rate limits needed ~220 (0.14 s), 200 stopped
#: it short every sample (docs/campaign/bicycle/README.md)
FAST_COLD_ITERATIONS = 1000
#: the barrier parameter a warm FATROP solve of such a model starts from: the car-like robot's median shifted plan
#: among 4 ellipses took 10 iterations from FATROP's default 0.1, 6 from 1e-2, 4 from 1e-3 (BENCHMARKS.md). Cold
#: starts keep the default (from the resting plan 1e-3 did not converge in 200 iterations)
WARM_BARRIER = 1e-3


@dataclass
class StagewiseLayout:
    """Index bookkeeping of the stage-wise w: stage k starts at `stage_start[k]`."""

    n: int
    m: int
    p: int
    horizon: int
    n_keep_in: int
    n_depth: int
    n_w: int
    stage_start: np.ndarray  # [N + 1]
    closed_form: bool = True
    #: the number of rate-limited inputs (input_rate_max finite): each stage carries them before its own as v(k)
    n_prev: int = 0

    def __post_init__(self) -> None:
        n, m, p, N, r = self.n, self.m, self.p, self.horizon, self.n_prev
        starts = np.asarray(self.stage_start)
        # index arrays of x(0..N) [N+1, n], y(0..N) [N+1, p], v(0..N) [N+1, r] and u(0..N-1) [N, m] in w
        self.x_index = starts[:, None] + np.arange(n)
        self.y_index = starts[:, None] + n + np.arange(p)
        self.prev_index = starts[:, None] + n + p + np.arange(r)
        self.u_index = starts[:N, None] + n + p + r + np.arange(m)

    def split_w(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, None]:
        """w -> U [N, m], X [N, n] (x(1..N)), y_a [p], None."""
        w = np.asarray(w, float).ravel()
        return w[self.u_index], w[self.x_index[1:]], self.y_a(w), None

    def y_a(self, w: np.ndarray) -> np.ndarray:
        """The artificial output y_a [p] of w: stage 0's copy (split_w's third part)."""
        return np.asarray(w, float).ravel()[self.y_index[0]]

    def join_w(self, U: np.ndarray, X: np.ndarray, y_a: np.ndarray, rest: None = None,
               x0: np.ndarray | None = None) -> np.ndarray:
        """Inverse of split_w with x(0) = x0 (zeros if None); slacks and v(k) zero (StagewiseNlp.fill_slacks)."""
        w = np.zeros(self.n_w)
        w[self.x_index[1:]] = np.reshape(X, (self.horizon, self.n))
        if x0 is not None:
            w[self.x_index[0]] = np.ravel(x0)
        w[self.y_index] = np.ravel(y_a)
        w[self.u_index] = np.reshape(U, (self.horizon, self.m))
        return w


class StagewiseNlp(NlpBase):
    """Stage-wise NLP and its solver (FATROP or SQP); the controller uses it like TrackingNlp."""

    def __init__(self, settings: ControllerSettings, model: Model | None = None) -> None:
        self.settings = settings
        self.model = model or settings.build_model()
        check_sizes(settings, self.model)
        if not (settings.use_closed_form_steady_state and self.model.steady_state is not None):
            raise ConfigError(f"solver {settings.solver!r} needs the closed-form steady state of the model "
                              "(use_closed_form_steady_state: true); use solver ipopt otherwise")
        self._build()

    def _build(self) -> None:
        s, mdl = self.settings, self.model
        n, m, p, N = mdl.n, mdl.m, mdl.p, s.horizon
        parts = problem_parts(s, mdl)
        self.slot_layout = parts.slot_layout
        self.output_frame_available = parts.output_frame_available
        nd, lam = parts.n_depth, s.steady_state_scale
        path = mdl.discrete_path(s.sample_time, s.discretization, s.integration_steps)
        regularise = SLACK_REGULARISATION

        def steady(y):
            x_a, u_a = mdl.steady_state(y)
            return ca.vertcat(x_a), ca.vertcat(u_a)

        X = [ca.SX.sym(f"x{k}", n) for k in range(N + 1)]
        Y = [ca.SX.sym(f"y{k}", p) for k in range(N + 1)]
        # input_rate_max couples u(k) to u(k-1): each stage carries the rate-limited inputs before its own as a
        # state v(k) (only those: a car limited in steering alone carries one state, not two)
        limited = list(parts.rate_limited)
        r = len(limited)
        V = [ca.SX.sym(f"v{k}", r) for k in range(N + 1)]
        U = [ca.SX.sym(f"u{k}", m) for k in range(N)]
        S = [ca.SX.sym(f"s{k}", nd) for k in range(N)]
        s_a = ca.SX.sym("s_a", nd)
        # terminal: set: x(N) = f(x(N-1), u(N-1)) is not x_a; its slack, V_f and the set row sit at stage N-1
        # (a stage's rows may use only its own variables, and stage N has no controls)
        with_set = s.terminal == "set"
        s_n = ca.SX.sym("s_n", nd if with_set else 0)
        inf = np.inf
        w, lbw, ubw, g, lbg, ubg = [], [], [], [], [], []
        slack_vars, slack_depths, stage_start, g_start = [], [], [], []
        cost = v_offset = tracking = 0
        offset = 0
        for k in range(N + 1):
            stage_start.append(offset)
            g_start.append(len(lbg))
            x_a, u_a = steady(Y[k])
            inside = 0 < k < N  # x(0) is measured, x(N) is tied to x_a
            w += [X[k], Y[k], V[k]]
            lbw += list(s.state_min) if inside else [-inf] * n
            ubw += list(s.state_max) if inside else [inf] * n
            lbw += [-inf] * (p + r)
            ubw += [inf] * (p + r)
            if k == N:
                if not with_set:
                    g.append(X[N] - x_a)  # terminal equality (eq. 20h)
                    lbg += [0.0] * n
                    ubg += [0.0] * n
                    if parts.rate_limited:  # u_a within a rate step of u(N-1) = v(N): the shifted plan stays feasible
                        rows, lo, hi = parts.rate_rows(u_a, V[N], first=False)
                        g.append(rows)
                        lbg += lo
                        ubg += hi
                offset += n + p + r
                break
            last = with_set and k == N - 1
            controls = [U[k], S[k]] + ([s_a] if k == 0 else []) + ([s_n] if last else [])
            blocks = 1 + (k == 0) + last
            w += controls
            # no s >= 0 bound: min mu s^2 s.t. s >= g already gives s = max(0, g), and the bound
            # made the QPs degenerate (s >= 0 and s >= g both active on a region's boundary)
            lbw += list(s.input_min) + [-inf] * nd * blocks
            ubw += list(s.input_max) + [inf] * nd * blocks
            offset += n + p + r + m + nd * blocks
            # gap-closing constraints first: FATROP's structure detection expects them so
            points = path(X[k], U[k])
            g.append(ca.vertcat(X[k + 1] - points[:, -1], Y[k + 1] - Y[k], V[k + 1] - U[k][limited] if r else V[k + 1]))
            lbg += [0.0] * (n + p + r)
            ubg += [0.0] * (n + p + r)
            if k == 0:
                g.append(ca.vertcat(X[0] - parts.x0, V[0] - parts.u_prev[limited] if r else V[0]))
                lbg += [0.0] * (n + r)
                ubg += [0.0] * (n + r)
                depth_a = parts.avoidance(x_a, u_a, N * s.sample_time)  # x_a = x(N): obstacles at t_N
                g.append(s_a - depth_a)
                lbg += [0.0] * nd
                ubg += [inf] * nd
                g.append(ca.vertcat(x_a, u_a))  # (x_a, u_a) in lambda Z
                lbg += [lam * v for v in (*s.state_min, *s.input_min)]
                ubg += [lam * v for v in (*s.state_max, *s.input_max)]
                if parts.n_hard:
                    g.append(parts.hard_g(x_a / lam, u_a / lam))
                    lbg += [-inf] * parts.n_hard
                    ubg += [0.0] * parts.n_hard
                v_offset = parts.offset_cost(Y[0])
                counted = 1 if with_set else 2  # with the equality F(x(N)) = F(x_a): one slack counted twice
                cost += v_offset + counted * parts.mu * ca.dot(s_a, s_a) + regularise * ca.dot(s_a, s_a)
                slack_vars.append(s_a)
                slack_depths.append(depth_a)
            if parts.rate_limited:  # |u(k) - u(k-1)| <= rate Ts; u(-1) the command in force, where there is one
                rows, lo, hi = parts.rate_rows(U[k], V[k], first=k == 0)
                g.append(rows)
                lbg += lo
                ubg += hi
            depth = parts.avoidance(X[k], U[k], k * s.sample_time)
            between = between_samples(parts, X[k], points, U[k], k * s.sample_time, s.sample_time)
            for rows in (depth, *between):  # one slack per region bounds g at x(k) and on the way on
                g.append(S[k] - rows)
                lbg += [0.0] * nd
                ubg += [inf] * nd
            depth = worst_of(depth, between)
            rows = [i for i in range(parts.n_hard) if k > 0 or parts.hard_uses_u[i]]
            if rows:
                g.append(parts.hard_g(X[k], U[k])[rows])
                lbg += [-inf] * len(rows)
                ubg += [0.0] * len(rows)
            if last:
                x_n = points[:, -1]
                depth_n = parts.avoidance(x_n, u_a, N * s.sample_time)
                v_f, rows, lo, hi = terminal_constraint(s, mdl, x_n, x_a, Y[k], u_a)
                g += [s_n - depth_n, rows]
                lbg += [0.0] * nd + lo
                ubg += [inf] * nd + hi
                cost += (parts.mu + regularise) * ca.dot(s_n, s_n)  # + V_f below (the SQP paths need it apart)
                residual, row_residuals = terminal_residual(s, mdl, x_n, x_a, Y[k], u_a)
                gauss_newton = (residual, len(lbg) - len(lo), row_residuals)  # the set rows' first index in g
                tracking += v_f
            dx, du = X[k] - x_a, U[k] - u_a
            stage = ca.dot(parts.q * dx, dx) + ca.dot(parts.r * du, du)
            tracking += stage
            cost += stage + (parts.mu + regularise) * ca.dot(S[k], S[k])
            slack_vars.append(S[k])
            slack_depths.append(depth)
        w = ca.vertcat(*w)
        g = ca.vertcat(*g)
        cost_without_v_f = cost
        if with_set:
            cost = cost + v_f
            slack_vars.append(s_n)
            slack_depths.append(depth_n)
        all_depths = ca.vertcat(*slack_depths)
        # the reported V_a is the paper's, with x(N) = x_a counted twice as in the cost (the equality)
        v_avoid = parts.mu * (ca.sumsqr(ca.fmax(0, ca.vertcat(*slack_depths[1:])))
                              + counted * ca.sumsqr(ca.fmax(0, depth_a)))
        self.lbx, self.ubx = np.array(lbw, float), np.array(ubw, float)
        self.lbg, self.ubg = np.array(lbg, float), np.array(ubg, float)
        self.layout = StagewiseLayout(n, m, p, N, parts.n_keep_in, nd, w.numel(), np.array(stage_start), n_prev=r)
        par = parts.par
        g_start.append(len(lbg))
        stages = {"nx": [n + p + r] * (N + 1),
                  "nu": [int(stage_start[k + 1] - stage_start[k] - n - p - r) for k in range(N)] + [0],
                  "ng": [int(g_start[k + 1] - g_start[k]) - (n + p + r if k < N else 0) for k in range(N + 1)]}
        self.problem = {"x": w, "p": par, "f": cost, "g": g}
        # the SQP paths' Gauss-Newton Hessian takes V_f as the least squares |residual|^2 (core/nlp/gauss_newton.py)
        problem = {**self.problem, GAUSS_NEWTON: (cost_without_v_f, *gauss_newton)} if with_set else self.problem
        if s.solver == "fatrop" and mdl.rest is not None:
            # a model whose equilibria need `rest` (its heading does not move at v = 0): FATROP's rank test of the
            # stages' equality rows, and a warm solve's barrier (RANK_TOLERANCE, WARM_BARRIER); cold starts keep
            # FATROP's own barrier, on a twin solver of the same compiled library
            self.fatrop_options = {"linsol_lu_fact_tol": RANK_TOLERANCE}
            cold = s.replace(max_iterations=max(s.max_iterations, FAST_COLD_ITERATIONS))
            self.cold_solver, _ = self._make_solver(problem, cold, stages)
            self.fatrop_options = {**self.fatrop_options, "mu_init": WARM_BARRIER}
        self.solver, self.solver_info = self._make_solver(problem, s, stages)
        if s.solver.startswith("sqp") and s.max_iterations < COLD_START_ITERATIONS:
            # a real-time budget is too small for a cold start: the same solver (and compiled
            # library) with the cold-start budget gets the first sample
            self.cold_solver, _ = self._make_solver(problem, s.replace(max_iterations=COLD_START_ITERATIONS), stages)
        x_a0, u_a0 = steady(Y[0])
        self.terms = Buffered(ca.Function("terms", [w, par], [v_offset, v_avoid, tracking]))
        self.steady = Buffered(ca.Function("steady", [w], [x_a0, u_a0]))
        self.constraint_values = Buffered(ca.Function("constraints", [w, par], [g]))
        self._slack_value = Buffered(ca.Function("slack_of", [w, par], [ca.fmax(0, all_depths)]))
        self.region_depth = depth_function(parts, mdl)
        # where the slack variables sit in w, in the order of all_depths
        index = ca.Function("index", [w], [ca.vertcat(*slack_vars)])
        probe = np.arange(w.numel(), dtype=float)
        self._slack_index = np.asarray(index(probe), dtype=int).ravel()
        # v(0..N) of a guess: the command in force, then the plan's own inputs (the gap rows hold from the start)
        carried = ca.vertcat(*(u[limited] for u in (parts.u_prev, *U))) if r else None
        self._prev_value = Buffered(ca.Function("prev_of", [w, par], [carried])) if r else None
        # blocks of the uniform stages 1..N-1 (N-2 with the terminal set, whose rows sit at stage N-1), for the dual
        # shift
        self._last_uniform = N - 2 if with_set else N - 1
        self._x_blocks = {k: slice(stage_start[k], stage_start[k + 1]) for k in range(1, self._last_uniform + 1)}
        self._g_blocks = {k: slice(g_start[k], g_start[k + 1]) for k in range(1, self._last_uniform + 1)}

    def fill_slacks(self, w: np.ndarray, par: np.ndarray) -> np.ndarray:
        """NlpBase.fill_slacks, and with input_rate_max each stage's v(k): the input before its own."""
        if self._prev_value is not None:
            index = self.layout.prev_index
            w[index] = np.reshape(np.asarray(self._prev_value(w, par)[0]), index.shape)
        return super().fill_slacks(w, par)

    def shift_duals(self, lam_x: np.ndarray, lam_g: np.ndarray, shift: int) -> tuple[np.ndarray, np.ndarray]:
        """Duals of stage k+shift moved to stage k, as the primal guess is shifted.

        Stages 1..N-1 have identical variable and constraint layouts (1..N-2 with the terminal set), so their
        multipliers move block by block; stage 0 (x0 equality, s_a, lambda Z) and the last stages keep their own.
        """
        last = self._last_uniform
        if shift <= 0 or last < 2:
            return lam_x, lam_g
        lam_x, lam_g = lam_x.copy(), lam_g.copy()
        xs = self._x_blocks
        gs = self._g_blocks
        for k in range(1, last):
            src = min(k + shift, last)
            lam_x[xs[k]] = lam_x[xs[src]]
            lam_g[gs[k]] = lam_g[gs[src]]
        return lam_x, lam_g


def make_nlp(settings: ControllerSettings, model: Model | None = None) -> NlpBase:
    """The formulation of the settings' solver path: multiple shooting (ipopt) or stage-wise."""
    if settings.solver == "ipopt":
        return TrackingNlp(settings, model)
    model = model or settings.build_model()
    if model.steady_state is None:
        # the stage-wise paths carry y_a as a state and need x_a = g_x(y_a) in closed form
        raise ConfigError(f"solver {settings.solver!r} needs a closed-form steady state, which model "
                          f"{model.name!r} has not (its heading at rest is free): use solver 'ipopt'")
    return StagewiseNlp(settings, model)
