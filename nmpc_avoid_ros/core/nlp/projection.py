"""The nearest reachable output: a target's projection onto Y_r, the outputs of steady states in lambda Z.

Why: the offset cost kappa |y_a - y_t|^2 pulls y_a towards the target with a force that grows
with the target's distance. y_a itself cannot leave Y_r (paper eq. 4-5: (x_a, u_a) in lambda Z),
so for a target outside Y_r the offset cost's own choice at rest is its projection y*; but a
target of 1e6 pulls so hard during the transient that the pull outweighs the avoidance penalty
mu F (measured on the paper's plant: |x1 x2| up to 4.8 with status ok). Tracking y* instead of y_t
leaves every target inside Y_r untouched (y* = y_t), ends at the same y* for every target outside
it (y_t = 8 and y_t = 1e6 both give 5.94 on the paper's example) and bounds the pull by the size of
Y_r, so a target far out of reach is as safe as one at the edge of reach (docs/design.md,
"Targets out of reach").

How: min |h(x_s, u_s) - y_t|^2 over steady states (x_s, u_s) with f(x_s, u_s) = 0 (the continuous
dynamics' equilibrium, which equals the closed-form g_x, g_u where a model has them), (x_s, u_s) in
lambda Z and the hard constraints at (x_s, u_s) / lambda: one small IPOPT problem, built once,
solved when the target changes (the last answer is kept).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..problem.models import Model
from .parts import problem_parts
from .stop_at import StopAt

#: a projection further than this (output units, inf-norm) from y_t means y_t was out of reach
OUT_OF_REACH = 1e-6
#: wall-time cap of one projection, s (a small problem: ~1 ms; the cap only guards absurd inputs)
PROJECTION_TIME = 0.05
#: IPOPT statuses of a projection cut short by the deadline or its cap: not kept
CUT_SHORT = frozenset({"User_Requested_Stop", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded"})


class TargetProjection:
    """y_t [p] -> y* [p], the point of Y_r nearest to y_t (Euclidean, weighted by output_weights), cached per target."""

    def __init__(self, settings: ControllerSettings, model: Model) -> None:
        n, m, lam = model.n, model.m, settings.steady_state_scale
        x, u, y_t = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("y_t", model.p)
        hard_g = problem_parts(settings, model).hard_g
        hard = hard_g(x / lam, u / lam)
        rest = model.equilibrium(x, u)  # rows of full rank at rest (the unicycle's dynamics lose rank there)
        g = ca.vertcat(rest, hard)
        self._output = ca.Function("projection_output", [x, u], [model.output(x, u)])
        # nearest in V_o's own metric |.|_W (the NLP's offset settles y_a there)
        weights = np.sqrt(settings.output_weights) if settings.output_weights else 1.0
        problem = {"x": ca.vertcat(x, u), "p": y_t, "f": ca.sumsqr(weights * (model.output(x, u) - y_t)), "g": g}
        self._stop_at = StopAt(n + m, g.numel(), model.p, "projection_stop_at")
        self._solver = ca.nlpsol("target_projection", "ipopt", problem, {
            "print_time": False, "error_on_fail": False, "iteration_callback": self._stop_at,
            "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-12, "bound_relax_factor": 0.0,
                      "max_wall_time": PROJECTION_TIME}})
        #: solvers constructed here (NmpcController.nlp_builds counts them)
        self.solver_builds = 1
        self._lbx = lam * np.array([*settings.state_min, *settings.input_min], float)
        self._ubx = lam * np.array([*settings.state_max, *settings.input_max], float)
        self._lbg = np.concatenate([np.zeros(rest.numel()), np.full(hard.numel(), -np.inf)])
        self._ubg = np.zeros(rest.numel() + hard.numel())
        self._n = n
        # the origin's steady state lies in lambda Z (Z contains the origin): a feasible first guess
        self._start = np.clip(np.zeros(n + m), self._lbx, self._ubx)
        self._last: tuple[tuple[float, ...], np.ndarray] | None = None
        # y_t in reach by its closed-form steady state (g_x, g_u in lambda Z, the hard constraints held): y* = y_t
        # without the solve (3.3 ms of the car's first sample; the solve answers y_t itself there too)
        self._in_reach: ca.Function | None = None
        if model.steady_state is not None:
            x_s, u_s = model.steady_state(y_t)
            z_s = ca.vertcat(x_s, u_s)
            excess = ca.vertcat(ca.DM(self._lbx) - z_s, z_s - ca.DM(self._ubx), hard_g(x_s / lam, u_s / lam))
            self._in_reach = ca.Function("projection_in_reach", [y_t], [ca.mmax(excess)])

    def __call__(self, y_t: Sequence[float], end: float = math.inf) -> np.ndarray:
        """y* [p] for the target y_t [p] (a copy; y_t itself where the projection fails). The solve ends by
        `end` (time.perf_counter s: the sample's deadline) or PROJECTION_TIME, whichever comes first; one cut
        short answers y_t and is not kept (the next sample solves it again)."""
        y_t = np.asarray(y_t, float).ravel()
        key = tuple(y_t.tolist())
        if self._last is not None and self._last[0] == key:
            return self._last[1].copy()
        if self._in_reach is not None and float(self._in_reach(y_t)) <= 0.0:
            self._last = (key, y_t.copy())
            return y_t.copy()
        self._stop_at.end = end
        sol = self._solver(x0=self._start, p=y_t, lbx=self._lbx, ubx=self._ubx, lbg=self._lbg, ubg=self._ubg)
        z = np.asarray(sol["x"]).ravel()
        y_star = np.asarray(self._output(z[:self._n], z[self._n:])).ravel()
        stats = self._solver.stats()
        if not stats["success"] or not np.all(np.isfinite(y_star)) or np.max(np.abs(y_star - y_t)) <= OUT_OF_REACH:
            y_star = y_t.copy()  # in reach: the target itself, to the last bit (the paper's loops are unchanged)
        if stats["return_status"] not in CUT_SHORT:
            self._last = (key, y_star)
        return y_star.copy()
