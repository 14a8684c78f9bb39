"""The two peers of the benchmark: the paper's formulation in CasADi Opti + IPOPT, and do-mpc.

Both solve the problem of core/nlp/tracking.py (paper eq. 19-20, simplified scheme):

    min  kappa |y_a - y_t|^2 + mu sum_{z in x(0..N), x_a} F(z) + sum_{j<N} |x(j) - x_a|_Q^2 + |u(j) - u_a|_R^2
    s.t. x(0) = measured, x(j+1) = f(x(j), u(j))        (f: the Euler/RK4 map of the model)
         u(j) in U (j = 0..N-1), x(j) in X (j = 1..N-1; x(0) is measured and not constrained)
         x(N) = x_a, (x_a, u_a) in lambda Z, x_a = g_x(y_a), u_a = g_u(y_a)
    F = sum over keep-in expressions and obstacle slots of max(0, g)^2

with the same region semantics (keep-in expressions parsed by core.expressions.parse_keep_in over
model.symbol_table, obstacles in core.regions.SlotLayout parameter slots, so an obstacle change
is a parameter change and never a rebuild) and the same cold start and shifted warm start as
our controller. What differs is the tool and the formulation details our controller improves on
(the penalty max(0, g)^2 written directly instead of with slacks, MX graphs, do-mpc's overhead).

Failure policy of both peers (what a user of these tools would do): if the solver does not
report success, its last iterate is applied when finite (Sample.failed = True, fallback = False);
otherwise the shifted previous plan is applied (u(age) of the last accepted plan, then u_a;
fallback = True), or zero clipped to the input box without any plan.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from time import perf_counter

import casadi as ca
import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.errors import ConfigError
from ..core.nlp.tracking import BUDGET_EXHAUSTED, SOLVED  # the statuses that count as solved, or budget-cut
from ..core.problem.expressions import parse_keep_in
from ..core.problem.models import Model
from ..core.problem.regions import Region, SlotLayout
from ..core.sample.step_result import shifted_rows
from .variants import Sample, StepperFactory


def ipopt_options(settings: ControllerSettings) -> dict[str, float | int | str]:
    """IPOPT options of both peers: silent, with the iteration and wall-time budget of the settings.

    tol is the settings' tolerance (1e-8 in both shipped configs, IPOPT's own default).
    """
    return {"print_level": 0, "sb": "yes", "max_iter": settings.max_iterations,
            "max_wall_time": settings.max_solve_time, "tol": settings.tolerance}


class ProblemPieces:
    """The parts of the problem both peers build from (settings, model), as core/nlp/tracking.py does.

    Attributes:
        f: discrete map (x [n], u [m]) -> x+ [n] (model.discrete with the settings' method).
        depth: Function (x [n], u [m], keep_active [n_keep], slots [slot_size]) -> g [n_depth],
            keep-in expressions then obstacle slots; the penalty is F = sum max(0, g)^2.
        hard: Function (x, u) -> hard constraint values [n_hard] (<= 0), hard_uses_u per row.
        slot_layout, output_frame_available: as in core.nlp.TrackingNlp.
        closed_form: True when x_a = g_x(y_a), u_a = g_u(y_a) are used (else eq. 8e-8f).
    """

    def __init__(self, settings: ControllerSettings, model: Model | None = None) -> None:
        self.settings = s = settings
        self.model = mdl = model or settings.build_model()
        for name, size in (("state_min", mdl.n), ("state_max", mdl.n), ("input_min", mdl.m),
                           ("input_max", mdl.m), ("state_weights", mdl.n), ("input_weights", mdl.m)):
            if len(getattr(s, name)) != size:
                raise ConfigError(f"{name} needs {size} values for model {mdl.name}, got {len(getattr(s, name))}")
        self.n, self.m, self.p, self.N = mdl.n, mdl.m, mdl.p, s.horizon
        self.closed_form = s.use_closed_form_steady_state and mdl.steady_state is not None
        self.f = mdl.discrete(s.sample_time, s.discretization, s.integration_steps)
        self.slot_layout = SlotLayout(s.max_ellipses, s.max_polygons, s.max_polygon_vertices)
        self.output_frame_available = mdl.p >= 2 and max(s.output_plane) < mdl.p
        xs, us = ca.SX.sym("x", mdl.n), ca.SX.sym("u", mdl.m)
        symbols = mdl.symbol_table(xs, us)
        keep_in = [parse_keep_in(text, symbols).g for text in s.keep_in]
        hard = [parse_keep_in(text, symbols).g for text in s.constraints]
        self.n_keep = len(keep_in)
        keep_active = ca.SX.sym("keep_active", self.n_keep)
        slots = ca.SX.sym("slots", self.slot_layout.size)
        output_point = mdl.output(xs, us)[list(s.output_plane)] if self.output_frame_available else None
        keep = keep_active * ca.vertcat(*keep_in) if keep_in else ca.SX(0, 1)
        depth = ca.vertcat(keep, self.slot_layout.depths(slots, xs[list(s.plane)], output_point))
        self.depth = ca.Function("depth", [xs, us, keep_active, slots], [depth])
        self.hard = ca.Function("hard", [xs, us], [ca.vertcat(*hard) if hard else ca.SX(0, 1)])
        self.n_hard = len(hard)
        self.hard_uses_u = [bool(ca.depends_on(g, us)) for g in hard]
        self.u_lo = np.asarray(s.input_min, float)
        self.u_hi = np.asarray(s.input_max, float)

    def steady(self, y_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Numeric g_x(y_a) [n], g_u(y_a) [m] (zeros without a closed form, as our controller)."""
        if self.model.steady_state is None:
            return np.zeros(self.n), np.zeros(self.m)
        x_s, u_s = self.model.steady_state(ca.DM(np.asarray(y_a, float)))
        return np.asarray(ca.DM(x_s), float).ravel(), np.asarray(ca.DM(u_s), float).ravel()

    def pack(self, regions: Sequence[Region]) -> np.ndarray:
        """Obstacle slot values [slot_size] (RegionError if they do not fit)."""
        return self.slot_layout.pack(list(regions), self.output_frame_available)


@dataclass
class Plan:
    """An accepted solution: U [N, m], X [N+1, n] (x(0) the measurement), y_a [p], x_a [n], u_a [m]."""

    U: np.ndarray
    X: np.ndarray
    y_a: np.ndarray
    x_a: np.ndarray
    u_a: np.ndarray
    age: int = 0


def initial_guess(pieces: ProblemPieces, plan: Plan | None, x: np.ndarray,
                  y_t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(U [N, m], X [N+1, n], y_a [p], x_a [n], u_a [m]) to start from; the same rule as our controller.

    With a plan: shifted by age + 1 samples (u(1..N-1), then u_a; x(2..N), then x_a) and x(0) the
    measurement. Without: y_a = y_t, its steady state clipped to Z, a straight line of states to x_a.
    """
    N, s = pieces.N, pieces.settings
    if plan is None:
        y_a = np.asarray(y_t, float).copy()
        x_a, u_a = pieces.steady(y_a)
        x_a = np.clip(x_a, s.state_min, s.state_max)
        u_a = np.clip(u_a, pieces.u_lo, pieces.u_hi)
        ramp = np.linspace(0, 1, N + 1)[:, None]
        return np.tile(u_a, (N, 1)), (1 - ramp) * x + ramp * x_a, y_a, x_a, u_a
    shift = plan.age + 1
    U, X = shifted_rows(plan.U, plan.u_a, shift), shifted_rows(plan.X, plan.x_a, shift)
    X[0] = x
    return U, X, plan.y_a.copy(), plan.x_a.copy(), plan.u_a.copy()


def fallback_input(pieces: ProblemPieces, plan: Plan | None) -> np.ndarray:
    """The shifted previous plan's input now (ages the plan), u_a once used up, else 0 clipped."""
    if plan is None:
        return np.clip(np.zeros(pieces.m), pieces.u_lo, pieces.u_hi)
    plan.age += 1
    return plan.U[plan.age].copy() if plan.age < pieces.N else plan.u_a.copy()


class OptiIpoptPaper:
    """The paper's formulation in casadi.Opti + IPOPT, as a user following the paper writes it.

    Decision variables U [m, N], X [n, N+1] (X[:, 0] == x0 as an equality, no bounds on x(0)),
    y_a [p] (+ x_a, u_a with f_c(x_a, u_a) = 0, y_a = h(x_a, u_a) without closed form). MX graph,
    every constraint (bounds included) an Opti constraint, the penalty mu * max(0, g)^2 written
    directly (non-smooth second derivative: no slack reformulation). Parameters: x0, y_t, kappa,
    mu, diag Q, diag R, keep-in flags, obstacle slots. Warm start: opti.set_initial of the shifted
    previous primal solution. Sample.solve_time is the wall time of opti.solve() alone, s.

    Attributes:
        builds: how many times the Opti problem was built (1; regions never rebuild).
        statuses: IPOPT return status per step.
        plan: the last finite solution (None before one), the next sample's warm start.
    """

    def __init__(self, settings: ControllerSettings, model: Model | None = None, expand: bool = False) -> None:
        self.pieces = ProblemPieces(settings, model)
        self.settings = settings
        self.expand = expand
        self.builds = 0
        self.statuses: list[str] = []
        self.plan: Plan | None = None
        self._build()

    def _build(self) -> None:
        pc, s = self.pieces, self.settings
        n, m, p, N = pc.n, pc.m, pc.p, pc.N
        opti = ca.Opti()
        U, X, y_a = opti.variable(m, N), opti.variable(n, N + 1), opti.variable(p)
        x0, y_t = opti.parameter(n), opti.parameter(p)
        kappa, mu = opti.parameter(), opti.parameter()
        q, r = opti.parameter(n), opti.parameter(m)
        keep_active = opti.parameter(pc.n_keep) if pc.n_keep else ca.DM(0, 1)
        slots = opti.parameter(pc.slot_layout.size) if pc.slot_layout.size else ca.DM(0, 1)
        if pc.closed_form:
            x_a, u_a = (ca.vertcat(v) for v in pc.model.steady_state(y_a))
            x_var = u_var = None
        else:
            x_a = x_var = opti.variable(n)
            u_a = u_var = opti.variable(m)
            opti.subject_to(pc.model.dynamics(x_a, u_a) == 0)
            opti.subject_to(y_a == pc.model.output(x_a, u_a))

        def penalty(x, u):
            return mu * ca.sumsqr(ca.fmax(0, pc.depth(x, u, keep_active, slots)))

        opti.subject_to(X[:, 0] == x0)
        cost = kappa * ca.sumsqr(y_a - y_t) + penalty(x_a, u_a)
        for j in range(N):
            opti.subject_to(X[:, j + 1] == pc.f(X[:, j], U[:, j]))
            dx, du = X[:, j] - x_a, U[:, j] - u_a
            cost += ca.dot(q * dx, dx) + ca.dot(r * du, du) + penalty(X[:, j], U[:, j])
            opti.subject_to(opti.bounded(pc.u_lo, U[:, j], pc.u_hi))
            if j > 0:
                opti.subject_to(opti.bounded(np.asarray(s.state_min), X[:, j], np.asarray(s.state_max)))
            rows = [i for i in range(pc.n_hard) if j > 0 or pc.hard_uses_u[i]]
            if rows:
                opti.subject_to(pc.hard(X[:, j], U[:, j])[rows] <= 0)
        cost += penalty(X[:, N], u_a)
        opti.subject_to(X[:, N] == x_a)
        lam = s.steady_state_scale
        opti.subject_to(opti.bounded(lam * np.array([*s.state_min, *s.input_min]), ca.vertcat(x_a, u_a),
                                     lam * np.array([*s.state_max, *s.input_max])))
        if pc.n_hard:
            opti.subject_to(pc.hard(x_a / lam, u_a / lam) <= 0)
        opti.minimize(cost)
        opti.solver("ipopt", {"print_time": False, "expand": self.expand}, ipopt_options(s))
        opti.set_value(kappa, s.kappa)
        opti.set_value(mu, s.mu)
        opti.set_value(q, np.asarray(s.state_weights, float))
        opti.set_value(r, np.asarray(s.input_weights, float))
        if pc.n_keep:
            opti.set_value(keep_active, np.ones(pc.n_keep))
        if pc.slot_layout.size:
            opti.set_value(slots, np.zeros(pc.slot_layout.size))
        self.opti = opti
        self._vars = (U, X, y_a, x_var, u_var)
        self._x0, self._y_t, self._slots = x0, y_t, slots
        self._steady = (x_a, u_a)
        self.builds += 1

    def set_regions(self, regions: Sequence[Region]) -> None:
        """Replace the obstacles: a parameter change of the slots, never a rebuild."""
        values = self.pieces.pack(regions)
        if self.pieces.slot_layout.size:
            self.opti.set_value(self._slots, values)

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None,
             time: float | None = None) -> Sample:
        """Command for the measured state x [n] and target y_t [p]; see the class docstring. `time` is
        accepted for the Stepper protocol: the peers do not predict moving obstacles."""
        x, y_t = np.asarray(x, float).ravel(), np.asarray(y_t, float).ravel()
        if regions is not None:
            self.set_regions(regions)
        opti = self.opti
        U, X, y_a, x_var, u_var = self._vars
        opti.set_value(self._x0, x)
        opti.set_value(self._y_t, y_t)
        U0, X0, ya0, xa0, ua0 = initial_guess(self.pieces, self.plan, x, y_t)
        opti.set_initial(U, U0.T)
        opti.set_initial(X, X0.T)
        opti.set_initial(y_a, ya0)
        if x_var is not None:
            opti.set_initial(x_var, xa0)
            opti.set_initial(u_var, ua0)
        start = perf_counter()
        try:
            sol = opti.solve()
        except RuntimeError:
            sol = opti.debug
        solve_time = perf_counter() - start
        stats = opti.stats()
        status = str(stats.get("return_status", "unknown"))
        self.statuses.append(status)
        iterations = int(stats.get("iter_count", -1))
        values = [np.atleast_1d(np.asarray(sol.value(v), float)) for v in (U, X, y_a, *self._steady)]
        failed = status not in SOLVED
        cut = status in BUDGET_EXHAUSTED
        if all(np.all(np.isfinite(v)) for v in values):
            Uv, Xv, yav, xav, uav = values
            Uv, Xv = Uv.reshape(self.pieces.m, -1).T, Xv.reshape(self.pieces.n, -1).T
            self.plan = Plan(Uv, Xv, yav.ravel(), xav.ravel(), uav.ravel())
            return Sample(Uv[0].copy(), solve_time, iterations, failed=failed, budget_exhausted=cut)
        u = fallback_input(self.pieces, self.plan)
        return Sample(u, solve_time, iterations, failed=True, fallback=True, budget_exhausted=cut)


def _import_do_mpc():
    """do_mpc, imported quietly (its optional features warn at import)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import do_mpc  # noqa: PLC0415 - optional, heavy: only when a do-mpc peer is built
    return do_mpc


class DoMpcPeer:
    """The same problem in do-mpc 5.1.2 (model type 'discrete', IPOPT through do-mpc's MPC class).

    Made equivalent as follows:
    - states [x (n), y_a (p)] with x+ = f(x, u) (the core model's Euler/RK4 map) and y_a+ = y_a:
      the artificial output is an extra constant state. do-mpc fixes the whole initial state
      (opt_x['_x', 0] = opt_p['_x0']); through its documented low-level route (prepare_nlp,
      edit nlp_cons_lb/ub, create_nlp) the bounds of the y_a rows of that equality are set to
      -inf/+inf, so y_a(0) is a free decision variable as in the paper (x(0) stays fixed).
    - terminal equality x(N) = g_x(y_a): do-mpc 5.1.2 has no terminal constraint (set_nl_cons acts
      on stages 0..N-1 only, and `terminal_bounds` are constant boxes), so it is appended to
      nlp_cons with lb = ub = 0 in the same low-level step (exact, not a terminal cost).
    - (x_a, u_a) in lambda Z and the hard constraints at (x_a, u_a) / lambda: appended once, on
      y_a(0), in the same step (do-mpc's state bounds would repeat them at every stage).
    - state bounds (do-mpc bounds x(1..N-1); x(N) is left free: use_terminal_bounds False) and
      input bounds u(0..N-1) through mpc.bounds, exactly the sets of our NLP; y_a unbounded.
    - lterm = |x - x_a|_Q^2 + |u - u_a|_R^2 + mu F(x, u) (stages 0..N-1), mterm = kappa |y_a - y_t|^2
      + mu F(x(N), u_a) + mu F(x_a, u_a); rterm set to zero explicitly (set_rterm(u=0): no
      input-rate term, as in the paper; it also skips do-mpc's 2 s warning sleep).
    - y_t, kappa, mu, diag Q, diag R, keep-in flags and obstacle slots are tvp (the same value at
      every stage); tvp_fun returns a template that is refilled only when they change.
    - warm start: shifted=True sets mpc.opt_x_num from the shifted previous solution before
      make_step; shifted=False keeps do-mpc's default (the previous solution, unshifted). Both use
      do-mpc's own dual warm start (previous lam_x, lam_g, as our controller passes them) and the
      same cold start as our controller at the first sample.
    - quiet: IPOPT print_level 0, print_time False (record_time True, for IPOPT's own wall time);
      store_full_solution and store_lagr_multiplier False, no solver stats stored per step.

    Sample.solve_time is the wall time of mpc.make_step (what a do-mpc user pays per sample);
    `solver_times` holds IPOPT's own t_wall_total per step and `make_step_times` the former.

    Attributes:
        builds: how many times the MPC was set up (1; regions never rebuild).
        statuses, make_step_times, solver_times: per step.
        plan: the last finite solution (None before one), the next sample's warm start.
    """

    def __init__(self, settings: ControllerSettings, model: Model | None = None, shifted: bool = True) -> None:
        self.pieces = ProblemPieces(settings, model)
        if not self.pieces.closed_form:
            raise ConfigError("the do-mpc peer needs the model's closed-form steady state (g_x, g_u)")
        self.settings = settings
        self.shifted = shifted
        self.builds = 0
        self.statuses: list[str] = []
        self.make_step_times: list[float] = []
        self.solver_times: list[float] = []
        self.plan: Plan | None = None
        self._build()

    def _build(self) -> None:
        do_mpc = _import_do_mpc()
        pc, s = self.pieces, self.settings
        n, m, p, N = pc.n, pc.m, pc.p, pc.N
        model = do_mpc.model.Model("discrete", "SX")
        x = model.set_variable("_x", "x", shape=(n, 1))
        y_a = model.set_variable("_x", "y_a", shape=(p, 1))
        u = model.set_variable("_u", "u", shape=(m, 1))
        tvp = {"y_t": p, "kappa": 1, "mu": 1, "q": n, "r": m, "keep_active": pc.n_keep,
               "slots": pc.slot_layout.size}
        tv = {name: model.set_variable("_tvp", name, shape=(size, 1)) if size else ca.SX(0, 1)
              for name, size in tvp.items()}
        model.set_rhs("x", pc.f(x, u))
        model.set_rhs("y_a", y_a)
        model.setup()

        mpc = do_mpc.controller.MPC(model)
        mpc.settings.n_horizon = N
        mpc.settings.t_step = s.sample_time
        mpc.settings.store_full_solution = False
        mpc.settings.store_lagr_multiplier = False
        mpc.settings.store_solver_stats = []
        mpc.settings.nlpsol_opts = {"print_time": False, "record_time": True,
                                    **{f"ipopt.{k}": v for k, v in ipopt_options(s).items()}}

        x_a, u_a = (ca.vertcat(v) for v in pc.model.steady_state(y_a))

        def penalty(xx, uu):
            return tv["mu"] * ca.sumsqr(ca.fmax(0, pc.depth(xx, uu, tv["keep_active"], tv["slots"])))

        dx, du = x - x_a, u - u_a
        lterm = ca.dot(tv["q"] * dx, dx) + ca.dot(tv["r"] * du, du) + penalty(x, u)
        mterm = tv["kappa"] * ca.sumsqr(y_a - tv["y_t"]) + penalty(x, u_a) + penalty(x_a, u_a)
        mpc.set_objective(mterm=mterm, lterm=lterm)
        mpc.set_rterm(u=0.0)  # no input-rate penalty, as in the paper (and no 2 s warning sleep)
        mpc.bounds["lower", "_x", "x"] = np.asarray(s.state_min, float)
        mpc.bounds["upper", "_x", "x"] = np.asarray(s.state_max, float)
        mpc.bounds["lower", "_u", "u"] = pc.u_lo
        mpc.bounds["upper", "_u", "u"] = pc.u_hi
        self._tvp = mpc.get_tvp_template()
        self._tvp["_tvp", :, "kappa"] = s.kappa
        self._tvp["_tvp", :, "mu"] = s.mu
        self._tvp["_tvp", :, "q"] = ca.DM(np.asarray(s.state_weights, float))
        self._tvp["_tvp", :, "r"] = ca.DM(np.asarray(s.input_weights, float))
        if pc.n_keep:
            self._tvp["_tvp", :, "keep_active"] = ca.DM(np.ones(pc.n_keep))
        self._y_t_set: np.ndarray | None = None
        mpc.set_tvp_fun(lambda t_now: self._tvp)

        # the low-level route: edit the NLP between prepare_nlp and create_nlp (do-mpc's bound
        # check calls numpy on CasADi values, which CasADi 3.8 flags with a FutureWarning once)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            mpc.prepare_nlp()
        labels = model._x.labels()
        ya_rows = [i for i, lab in enumerate(labels) if lab.startswith("[y_a")]
        if len(ya_rows) != p or mpc.nlp_cons[0].shape[0] != n + p:  # the initial-state block
            raise RuntimeError(f"unexpected do-mpc NLP layout: initial-state rows {labels}")
        lb0, ub0 = np.array(mpc.nlp_cons_lb[0], float), np.array(mpc.nlp_cons_ub[0], float)
        lb0[ya_rows], ub0[ya_rows] = -np.inf, np.inf
        mpc.nlp_cons_lb[0], mpc.nlp_cons_ub[0] = lb0, ub0
        opt_x = mpc.opt_x_unscaled
        x_N, y_a_N = opt_x["_x", N, 0, -1, "x"], opt_x["_x", N, 0, -1, "y_a"]
        y_a_0 = opt_x["_x", 0, 0, -1, "y_a"]
        extra = [(x_N - ca.vertcat(pc.model.steady_state(y_a_N)[0]), np.zeros(n), np.zeros(n))]
        x_a0, u_a0 = (ca.vertcat(v) for v in pc.model.steady_state(y_a_0))
        lam = s.steady_state_scale
        extra.append((ca.vertcat(x_a0, u_a0), lam * np.array([*s.state_min, *s.input_min]),
                      lam * np.array([*s.state_max, *s.input_max])))
        for j in range(N):
            rows = [i for i in range(pc.n_hard) if j > 0 or pc.hard_uses_u[i]]
            if rows:
                g = pc.hard(opt_x["_x", j, 0, -1, "x"], opt_x["_u", j, 0, "u"])[rows]
                extra.append((g, np.full(len(rows), -np.inf), np.zeros(len(rows))))
        if pc.n_hard:
            extra.append((pc.hard(x_a0 / lam, u_a0 / lam), np.full(pc.n_hard, -np.inf), np.zeros(pc.n_hard)))
        for g, lo, hi in extra:
            mpc.nlp_cons.append(g)
            mpc.nlp_cons_lb.append(lo.reshape(-1, 1))
            mpc.nlp_cons_ub.append(hi.reshape(-1, 1))
        mpc.create_nlp()

        # flat indices of x(k) [n + p] and u(k) [m] in opt_x, for the shifted warm start
        index = mpc._opt_x(0)
        index.master = ca.DM(np.arange(mpc.n_opt_x, dtype=float))
        self._ix = np.array([np.asarray(index["_x", k, 0, -1], float).ravel() for k in range(N + 1)], int)
        self._iu = np.array([np.asarray(index["_u", k, 0], float).ravel() for k in range(N)], int)
        mpc.set_initial_guess()
        self.mpc = mpc
        self.builds += 1

    def set_regions(self, regions: Sequence[Region]) -> None:
        """Replace the obstacles: new values in the tvp template, never a rebuild."""
        values = self.pieces.pack(regions)
        if self.pieces.slot_layout.size:
            self._tvp["_tvp", :, "slots"] = ca.DM(values)

    def _write_guess(self, U: np.ndarray, X: np.ndarray, y_a: np.ndarray) -> None:
        w = np.array(self.mpc.opt_x_num.cat, float).ravel()
        w[self._ix] = np.hstack([X, np.tile(y_a, (X.shape[0], 1))])
        w[self._iu] = U
        self.mpc.opt_x_num.master = ca.DM(w)

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None,
             time: float | None = None) -> Sample:
        """Command for the measured state x [n] and target y_t [p]; see the class docstring. `time` is
        accepted for the Stepper protocol: the peers do not predict moving obstacles."""
        pc, mpc = self.pieces, self.mpc
        x, y_t = np.asarray(x, float).ravel(), np.asarray(y_t, float).ravel()
        if regions is not None:
            self.set_regions(regions)
        if self._y_t_set is None or not np.array_equal(self._y_t_set, y_t):
            self._tvp["_tvp", :, "y_t"] = ca.DM(y_t)
            self._y_t_set = y_t
        U0, X0, ya0, _, _ = initial_guess(pc, self.plan, x, y_t)
        if self.shifted or self.plan is None:
            self._write_guess(U0, X0, ya0)
        start = perf_counter()
        u0 = mpc.make_step(np.concatenate([x, ya0]).reshape(-1, 1))
        wall = perf_counter() - start
        stats = mpc.solver_stats
        status = str(stats.get("return_status", "unknown"))
        self.statuses.append(status)
        self.make_step_times.append(wall)
        self.solver_times.append(float(stats.get("t_wall_total", np.nan)))
        iterations = int(stats.get("iter_count", -1))
        failed, cut = status not in SOLVED, status in BUDGET_EXHAUSTED
        w = np.array(mpc.opt_x_num.cat, float).ravel()
        if np.all(np.isfinite(w)):
            Xs = w[self._ix]
            self.plan = Plan(w[self._iu].reshape(pc.N, pc.m), Xs[:, :pc.n], Xs[0, pc.n:].copy(),
                              *pc.steady(Xs[0, pc.n:]))
            return Sample(np.asarray(u0, float).ravel(), wall, iterations, failed=failed, budget_exhausted=cut)
        u = fallback_input(pc, self.plan)
        if self.plan is not None:  # never leave a non-finite iterate as the next initial guess
            U1, X1, ya1, _, _ = initial_guess(pc, self.plan, x, y_t)
            self._write_guess(U1, X1, ya1)
        return Sample(u, wall, iterations, failed=True, fallback=True, budget_exhausted=cut)


def do_mpc_unshifted(settings: ControllerSettings, model: Model | None = None) -> DoMpcPeer:
    """do-mpc with its default warm start (the previous solution, unshifted)."""
    return DoMpcPeer(settings, model, shifted=False)


#: the peers by benchmark name
PEERS: dict[str, StepperFactory] = {
    "opti_ipopt_paper": OptiIpoptPaper,
    "do_mpc": DoMpcPeer,
    "do_mpc_unshifted": do_mpc_unshifted,
}
