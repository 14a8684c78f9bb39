"""The NLP of the simplified tracking scheme with avoidance (paper eq. 19-20), built once.

Decision vector w (multiple shooting, so the dynamics are equality constraints):
    u(0..N-1) [m*N], x(1..N) [n*N], y_a [p]  (+ x_a [n], u_a [m] without a closed-form g_x, g_u),
    slacks [(N+2) * n_regions] of the avoidance penalty (see below)
Parameter vector (everything that may change between samples without a rebuild):
    x(0) [n], y_t [p], kappa, mu, diag Q [n], diag R [m], keep-in active flags [n_keep],
    obstacle slots [SlotLayout.size]
Cost:
    V_o + V_a + sum_{j<N} |x(j) - x_a|_Q^2 + |u(j) - u_a|_R^2,
    V_o = kappa |y_a - y_t|^2,  V_a = mu F(x_a) + sum_{j=0..N} mu F(x(j)),  F = sum max(0, g)^2
    (with integration_steps M > 1, F(x(j)) for j < N takes each region's worst g over x(j) and the
    M - 1 sub-step states on the way to x(j+1): avoidance between the samples; M = 1 is the paper's)
Constraints:
    x(j+1) = f(x(j), u(j)); x(N) = x_a (terminal: set: V_f <= alpha, cost + V_f, core/nlp/terminal.py);
    (x(j), u(j)) in Z for j = 1..N-1 (x(0) is measured, not decided: only u(0) is bounded at j = 0); (x_a, u_a)
    in lambda Z; without closed form the equilibrium f_c(x_a, u_a) = 0 and y_a = h(x_a, u_a) (eq. 8e-8f, with
    the continuous right-hand side, which has the same equilibria as the Euler map and is better scaled).
The penalty max(0, g)^2 is written with slacks s >= max(0, g) and cost mu s^2: the same optimum,
but a twice-differentiable NLP (measured: far fewer IPOPT iterations near region boundaries).
"""

from __future__ import annotations

import functools
import math
import time
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from ..config.settings import SOLVERS, ControllerSettings
from ..errors import ConfigError
from ..problem.models import Model
from . import background
from .between import between_samples, worst_of
from .buffered import Buffered
from .gauss_newton import plain_problem, sqp_hessian
from .parts import NlpLayout, check_sizes, depth_function, problem_parts
from .terminal import terminal_constraint
from .worker import ABANDONED

if TYPE_CHECKING:
    from .worker import SolveWorker

#: the share of a sample's time bound (NmpcController.sample_budget) that the search's solver calls may
#: use: IPOPT's own wall-time limit, and the deadline at which a call in the worker is abandoned; the
#: fallback's recovery solve is limited to the rest (core/sample/fallback.py)
SEARCH_SHARE = 0.8
#: a cold start's time bound (no previous plan): this multiple of max_solve_time (NmpcController.sample_budget)
COLD_START_TIME_FACTOR = 10.0

#: return statuses after which the solution is used as is (IPOPT, sqpmethod; FATROP reports 0)
SOLVED = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level", "0"})
#: statuses that mean the iteration or time budget cut the solve
BUDGET_EXHAUSTED = frozenset({"Maximum_Iterations_Exceeded", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded",
                              ABANDONED})


class NlpBase:
    """What the controller needs from any formulation (multiple shooting or stage-wise).

    Subclasses set: layout (split_w/join_w, horizon, n_keep_in, n_w), solver, solver_info (see make_solver), lbx,
    ubx, lbg, ubg, terms (w, p) -> (V_o, V_a, tracking), steady (w) -> (x_a, u_a), constraint_values (w, p) -> g,
    slot_layout, output_frame_available, problem, and `_slack_index` with `_slack_value` (w, p) -> max(0, depth).
    """

    settings: ControllerSettings
    solver: ca.Function
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    _slack_index: np.ndarray
    #: the symbolic problem {"x": w, "p": par, "f": cost, "g": g} the solver was built from (core/nlp/sensitivity.py)
    problem: dict

    def parameters(self, x0: np.ndarray, y_t: np.ndarray, slots: np.ndarray, *, kappa: float, mu: float,
                   state_weights: np.ndarray, input_weights: np.ndarray, keep_in_active: np.ndarray,
                   command: np.ndarray | None = None) -> np.ndarray:
        """Pack the parameter vector: x0 [n], y_t [p], kappa, mu, diag Q [n], diag R [m], keep-in flags, with
        input_rate_max the command in force [m] and 1 (None: zeros and 0, u(0) unlimited), slots."""
        rate = [] if not self.settings.input_rate_max else \
            [np.zeros(len(input_weights)), [0.0]] if command is None else [command, [1.0]]
        return np.concatenate([x0, y_t, [kappa, mu], state_weights, input_weights, keep_in_active, *rate, slots])

    @property
    def parameter_count(self) -> int:
        """Length of the parameter vector (the solver's 'p' input)."""
        return int(self.solver.size1_in(self.solver.index_in("p")))

    def violation(self, w: np.ndarray, par: np.ndarray) -> float:
        """Largest violation of the constraints and bounds at w (0 if feasible)."""
        g = self.constraint_values(w, par)[0]
        viol = np.concatenate([self.lbg - g, g - self.ubg, self.lbx - w, w - self.ubx, [0.0]])
        return float(np.max(viol[np.isfinite(viol)]))

    #: the same solver with a cold-start iteration budget (where the run-time budget is smaller)
    cold_solver: ca.Function | None = None
    #: where `solve` runs: None here, else a SolveWorker's child that can be abandoned (core/nlp/worker.py)
    worker: SolveWorker | None = None

    def solve(self, w0: np.ndarray, par: np.ndarray, lam_x0: np.ndarray, lam_g0: np.ndarray, cold: bool = False,
              time_limit: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, float]:
        """One solver call from the guess (`cold`: with `cold_solver` where there is one). Returns copies of w [n_w],
        lam_x [n_w], lam_g [n_g], the solver's stats and the wall time of the solver call alone, s.

        Through `Function.buffer()` with arrays bound once (a dict call costs ~0.15 ms more, measured). With a
        `worker` (core/nlp/worker.py) it runs in the worker's child, abandoned at the sample's deadline or after
        `time_limit` s, whichever comes first (in this process a call ends by its solver's own limits); compiled
        solvers that landed are swapped in before it (core/nlp/background.py).
        """
        if self.worker is not None:
            return self.worker.solve(self, w0, par, lam_x0, lam_g0, cold, self.worker.deadline,
                                     time.perf_counter() + time_limit)
        background.load_ready()
        return self.solve_here(w0, par, lam_x0, lam_g0, cold)

    def solve_here(self, w0: np.ndarray, par: np.ndarray, lam_x0: np.ndarray, lam_g0: np.ndarray, cold: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, float]:
        """`solve` in this process, whatever the worker (the worker's child calls this)."""
        call = self._cold_solver_call if cold and self.cold_solver is not None else self._solver_call
        results = call(w0, par, lam_x0, lam_g0)
        return results[0].copy(), results[3].copy(), results[4].copy(), call.stats(), call.seconds

    @functools.cached_property
    def _solver_call(self) -> Buffered:
        return self._buffered(self.solver)

    @functools.cached_property
    def _cold_solver_call(self) -> Buffered:
        return self._buffered(self.cold_solver)

    def _buffered(self, solver: ca.Function) -> Buffered | background.SwappableCall:
        """The solver with its bounds bound once; called with (x0, p, lam_x0, lam_g0). An interpreted
        solver whose library compiles in the background runs as its compiled twin once that is loaded
        (core/nlp/background.py)."""
        if list(solver.name_in()) != ["x0", "p", "lbx", "ubx", "lbg", "ubg", "lam_x0", "lam_g0"] or \
                list(solver.name_out()[:6]) != ["x", "f", "g", "lam_x", "lam_g", "lam_p"]:
            raise ConfigError(f"unexpected solver signature {solver.name_in()} -> {solver.name_out()}")
        fixed = {2: self.lbx, 3: self.ubx, 4: self.lbg, 5: self.ubg}
        if background.is_tracked(solver):
            return background.SwappableCall(solver, lambda f: Buffered(f, fixed=fixed, densify=False))
        return Buffered(solver, fixed=fixed, densify=False)

    #: (x [n], u [m], p, elapsed s) -> region functions g [n_depth], set by the subclass's build
    region_depth: ca.Function

    def max_depth(self, w: np.ndarray, par: np.ndarray) -> float:
        """Deepest predicted penetration of any active region over the plan w (0 if outside all)."""
        if not self._slack_index.size:
            return 0.0
        return float(np.max(self._slack_value(w, par)[0]))

    #: solvers this formulation has constructed (each make_solver call); NmpcController.nlp_builds sums them
    solver_builds: int = 0
    fatrop_options: dict = {}  #: FATROP options beyond make_solver's (core/nlp/stagewise.py sets them)

    def _make_solver(self, problem: dict, settings: ControllerSettings,
                     stages: dict[str, list[int]] | None = None) -> tuple[ca.Function, dict]:
        """make_solver for this formulation's constraints, counted in solver_builds."""
        self.solver_builds += 1
        return make_solver(problem, settings, self.lbg == self.ubg, stages, self.fatrop_options)

    def fill_slacks(self, w: np.ndarray, par: np.ndarray) -> np.ndarray:
        """w with its slacks set to max(0, depth) of its own states (the tightest feasible slacks)."""
        if self._slack_index.size:
            w[self._slack_index] = self._slack_value(w, par)[0]
        return w

    def shift_duals(self, lam_x: np.ndarray, lam_g: np.ndarray, shift: int) -> tuple[np.ndarray, np.ndarray]:
        """Multipliers for a primal guess shifted by `shift` samples (unchanged by default)."""
        return lam_x, lam_g


class TrackingNlp(NlpBase):
    """The NLP and its solver for one settings structure. Building is the expensive part.

    Attributes:
        layout: index bookkeeping.
        solver: CasADi nlpsol Function (x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) -> solution.
        terms: Function (w, p) -> (V_o, V_a, tracking) for reporting.
        steady: Function (w) -> (x_a [n], u_a [m]).
        lbx, ubx, lbg, ubg: numeric bounds (numpy).
    """

    def __init__(self, settings: ControllerSettings, model: Model | None = None) -> None:
        self.settings = settings
        self.model = model or settings.build_model()
        self._check_sizes()
        self._build()

    def _check_sizes(self) -> None:
        check_sizes(self.settings, self.model)

    def _build(self) -> None:
        s, mdl = self.settings, self.model
        n, m, p, N = mdl.n, mdl.m, mdl.p, s.horizon
        parts = problem_parts(s, mdl)
        closed_form = parts.closed_form
        self.slot_layout = parts.slot_layout
        self.output_frame_available = parts.output_frame_available
        hard = range(parts.n_hard)
        hard_g, hard_uses_u = parts.hard_g, parts.hard_uses_u
        layout = NlpLayout(n, m, p, N, parts.n_keep_in, parts.slot_layout.size, closed_form, (N + 2) * parts.n_depth)
        self.layout = layout
        x0, mu, q, r, par = parts.x0, parts.mu, parts.q, parts.r, parts.par
        avoidance = parts.avoidance

        # decision variables
        U = ca.SX.sym("U", m, N)
        X = ca.SX.sym("X", n, N)
        y_a = ca.SX.sym("y_a", p)
        if closed_form:
            x_a, u_a = mdl.steady_state(y_a)
            x_a, u_a = ca.vertcat(x_a), ca.vertcat(u_a)
            w = ca.vertcat(ca.vec(U), ca.vec(X), y_a)
        else:
            x_a, u_a = ca.SX.sym("x_a", n), ca.SX.sym("u_a", m)
            w = ca.vertcat(ca.vec(U), ca.vec(X), y_a, x_a, u_a)

        path = mdl.discrete_path(s.sample_time, s.discretization, s.integration_steps)

        states = [x0] + [X[:, j] for j in range(N)]
        g, lbg, ubg = [], [], []
        tracking = 0
        ts = s.sample_time
        depth = [avoidance(x_a, u_a, N * ts)]  # x_a = x(N): moving obstacles where they are at t_N
        between = [[]]  # per depth block: g at the sub-step states its slack also bounds
        for j in range(N):
            points = path(states[j], U[:, j])
            g.append(states[j + 1] - points[:, -1])
            lbg += [0.0] * n
            ubg += [0.0] * n
            dx = states[j] - x_a
            du = U[:, j] - u_a
            tracking += ca.dot(q * dx, dx) + ca.dot(r * du, du)
            depth.append(avoidance(states[j], U[:, j], j * ts))
            between.append(between_samples(parts, states[j], points, U[:, j], j * ts, ts))
            if hard:
                rows = [i for i in hard if j > 0 or hard_uses_u[i]]
                if rows:
                    g.append(hard_g(states[j], U[:, j])[rows])
                    lbg += [-np.inf] * len(rows)
                    ubg += [0.0] * len(rows)
        depth.append(avoidance(states[N], u_a, N * ts))
        between.append([])
        if s.input_rate_max:  # |u(j) - u(j-1)| <= rate Ts, u(-1) the command in force (rows where rate is finite)
            # and with the terminal equality |u_a - u(N-1)| too: the shifted plan (u(1..N-1), u_a), the candidate of the
            # paper's decrease argument (docs/certificate.md), then meets the rate rows as the plan did
            for j in range(N + (s.terminal != "set")):
                u_j = U[:, j] if j < N else u_a
                rows, lo, hi = parts.rate_rows(u_j, U[:, j - 1] if j else parts.u_prev, first=j == 0)
                g.append(rows)
                lbg, ubg = lbg + lo, ubg + hi
        # F = max(0, g)^2 is only C1, which costs IPOPT many iterations near region boundaries.
        # The smooth equivalent: slacks s >= 0, s >= g, cost s^2 (at the optimum s = max(0, g)).
        # Between samples a stage's slack also bounds g at its sub-step states: s = the worst of them.
        nd = parts.n_depth
        slack = ca.SX.sym("slack", len(depth) * nd)
        w = ca.vertcat(w, slack)
        for block, (at_sample, extras) in enumerate(zip(depth, between)):
            for rows in (at_sample, *extras):
                g.append(slack[block * nd:(block + 1) * nd] - rows)
                lbg += [0.0] * nd
                ubg += [np.inf] * nd
        depth = ca.vertcat(*[worst_of(d, e) for d, e in zip(depth, between)])
        terminal_cost, rows, lo, hi = terminal_constraint(s, mdl, states[N], x_a, y_a, u_a)  # eq. 20h, or 8g
        g.append(rows)
        lbg, ubg = lbg + lo, ubg + hi
        lam = s.steady_state_scale
        # (x_a, u_a) in lambda Z: boxes scaled by lambda, inequalities evaluated at z / lambda
        g.append(ca.vertcat(x_a, u_a))
        lbg += [lam * v for v in (*s.state_min, *s.input_min)]
        ubg += [lam * v for v in (*s.state_max, *s.input_max)]
        if hard:
            g.append(hard_g(x_a / lam, u_a / lam))
            lbg += [-np.inf] * parts.n_hard
            ubg += [0.0] * parts.n_hard
        if not closed_form:
            # the equilibrium as rows of full rank at rest (Model.equilibrium: the unicycle's f loses rank there,
            # and IPOPT failed in 26 % of its samples with Error_In_Step_Computation)
            rest = mdl.equilibrium(x_a, u_a)
            g.append(rest)
            g.append(y_a - mdl.output(x_a, u_a))
            lbg += [0.0] * (rest.numel() + p)
            ubg += [0.0] * (rest.numel() + p)

        v_offset = parts.offset_cost(y_a)
        tracking = tracking if terminal_cost is None else tracking + terminal_cost  # V_N = V_o + V_a + tracking
        cost = v_offset + mu * ca.dot(slack, slack) + tracking
        v_avoid = mu * ca.sumsqr(ca.fmax(0, depth))

        # variable bounds: u(j) in U for all j, x(1..N-1) in X; x(N) is tied to x_a
        inf = np.inf
        x_lo = np.tile(s.state_min, (N, 1))
        x_hi = np.tile(s.state_max, (N, 1))
        x_lo[-1], x_hi[-1] = -inf, inf
        lbx = [np.tile(s.input_min, N), x_lo.ravel(), np.full(p, -inf)]
        ubx = [np.tile(s.input_max, N), x_hi.ravel(), np.full(p, inf)]
        if not closed_form:
            lbx.append(np.full(n + m, -inf))
            ubx.append(np.full(n + m, inf))
        lbx.append(np.zeros(layout.n_slack))
        ubx.append(np.full(layout.n_slack, inf))
        self.lbx, self.ubx = np.concatenate(lbx), np.concatenate(ubx)
        self.lbg, self.ubg = np.array(lbg, float), np.array(ubg, float)

        nlp = {"x": w, "p": par, "f": cost, "g": ca.vertcat(*g)}
        self.problem = nlp
        self.solver, self.solver_info = self._make_solver(nlp, s)
        self.terms = Buffered(ca.Function("terms", [w, par], [v_offset, v_avoid, tracking]))
        self.steady = Buffered(ca.Function("steady", [w], [x_a, u_a]))
        self.constraint_values = Buffered(ca.Function("constraints", [w, par], [ca.vertcat(*g)]))
        self._slack_value = Buffered(ca.Function("slack_of", [w, par], [ca.fmax(0, depth)]))
        self._slack_index = np.arange(layout.n_w - layout.n_slack, layout.n_w)
        self.region_depth = depth_function(parts, mdl)


#: weight of the slacks' own regularisation in the stage-wise paths (mu = 0 leaves them free
#: otherwise, a flat direction); it only pins s = max(0, g)
SLACK_REGULARISATION = 1e-6

#: iteration cap of the QP solver inside each SQP iteration
QP_ITERATION_CAP = 100

#: the CasADi plugin of each solver path
_PLUGINS = {"ipopt": "ipopt", "fatrop": "fatrop", "sqp": "sqpmethod", "sqp_hpipm": "sqpmethod"}

#: iterations in a row with the KKT error below acceptable_tolerance after which IPOPT or FATROP stop there
ACCEPTABLE_ITERATIONS = 5

def make_solver(nlp: dict, settings: ControllerSettings, equality: np.ndarray,
                stages: dict[str, list[int]] | None = None, fatrop: dict | None = None) -> tuple[ca.Function, dict]:
    """nlpsol for the chosen solver path with its budget (iterations; wall time where supported).

    `equality` flags the constraints with lbg == ubg (FATROP needs to know them); `stages` gives the stage
    dimensions nx, nu, ng [N + 1] of a stage-wise problem (HPIPM needs them); `fatrop`: FATROP's further options.
    With settings.codegen the oracles are generated, compiled and cached (see core/nlp/codegen.py); with
    settings.codegen_background a library missing from the cache compiles in the background and the solver is
    interpreted until it is swapped in (core/nlp/background.py). Returns the solver and {"codegen": bool,
    "library": path or None, "cache_hit": bool or None, "background": interpreted until its library is compiled}.
    """
    path = settings.solver
    nlp, gauss_newton = plain_problem(nlp)  # the SQP paths' least-squares V_f (core/nlp/gauss_newton.py)
    if path not in _PLUGINS:
        raise ConfigError(f"unknown solver {path!r}; known: {', '.join(SOLVERS)}")
    plugin = _PLUGINS[path]
    opts: dict = {"print_time": False, "error_on_fail": False}
    if path == "ipopt":
        opts["ipopt"] = {"print_level": 0, "sb": "yes", "max_iter": settings.max_iterations,
                         "max_wall_time": SEARCH_SHARE * settings.max_solve_time, "tol": settings.tolerance}
        if settings.acceptable_tolerance > 0:
            opts["ipopt"].update(acceptable_tol=settings.acceptable_tolerance, acceptable_iter=ACCEPTABLE_ITERATIONS)
    elif path == "fatrop":
        opts.update({"structure_detection": "auto", "equality": [bool(e) for e in equality],
                     "fatrop": {"print_level": 0, "max_iter": settings.max_iterations, "tol": settings.tolerance,
                                **(fatrop or {})}})
        if settings.acceptable_tolerance > 0:
            opts["fatrop"].update(tol_acceptable=settings.acceptable_tolerance, acceptable_iter=ACCEPTABLE_ITERATIONS)
    else:
        qpsol = "qrqp" if path == "sqp" else "hpipm"
        qp_opts: dict = {"error_on_fail": False}
        if qpsol == "hpipm":
            if stages is None:
                raise ConfigError("solver sqp_hpipm needs the stage-wise formulation")
            qp_opts.update({"N": len(stages["nx"]) - 1, **stages, "hpipm": {"iter_max": 50, "warm_start": 1}})
        if qpsol == "qrqp":
            # the active-set QP can cycle on degenerate samples; a cap bounds its worst case and
            # the SQP goes on from the partial step (measured: one sample took 2 s uncapped)
            qp_opts.update({"print_iter": False, "print_header": False, "print_info": False,
                            "max_iter": QP_ITERATION_CAP})
        # the cost is a sum of squares and the constraints carry the curvature we drop: the
        # Gauss-Newton Hessian is the cost's own, positive semi-definite (V_f as least squares:
        # core/nlp/gauss_newton.py; measured against the exact Hessian with regularisation: fewer iterations
        # on the paper problem, but neither converges reliably on the mobile robot at N = 20: use fatrop there)
        hessian = sqp_hessian(nlp, gauss_newton)
        opts.update({"qpsol": qpsol, "qpsol_options": qp_opts, "hess_lag": hessian, "max_iter": settings.max_iterations,
                     "print_header": False, "print_iteration": False, "print_status": False,
                     "tol_pr": settings.tolerance, "tol_du": max(settings.tolerance, 1e-6)})
    if not settings.codegen:
        return ca.nlpsol("nmpc", plugin, nlp, opts), {"codegen": False, "library": None, "cache_hit": None,
                                                      "background": False}
    from .codegen import cache_dir, compiled_library, library_path, structure_hash

    key = structure_hash(f"{plugin}:{path}", nlp)
    folder = cache_dir(settings.cache_dir)
    if settings.codegen_background:
        solver = background.interpreted_while_compiling(key, folder, plugin, nlp, opts)
        if solver is not None:
            return solver, {"codegen": True, "library": str(library_path(key, folder)), "cache_hit": False,
                            "background": True}
    job = background.pending(library_path(key, folder))  # compiling in the background: wait for it, not again
    if job is not None:
        job.done.wait()
    library, hit = compiled_library(key, folder, lambda: ca.nlpsol("nmpc", plugin, nlp, opts))
    return ca.nlpsol("nmpc", plugin, str(library), opts), {"codegen": True, "library": str(library), "cache_hit": hit,
                                                           "background": False}
