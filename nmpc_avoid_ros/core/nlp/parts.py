"""The parts of the tracking NLP that every formulation shares: the index layout of w and of the
parameter vector, the symbols and CasADi functions of the problem (`ProblemParts`, built by
`problem_parts`), the size checks and the region-depth function.

Split from core/nlp/tracking.py (which builds the multiple-shooting NLP and its solver) so that the
between-sample rows (core/nlp/between.py) and the other formulations read these without importing
the solver layer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..errors import ConfigError
from ..problem.expressions import parse_keep_in
from ..problem.models import Model
from ..problem.regions import SlotLayout


@dataclass
class NlpLayout:
    """Index bookkeeping of w and of the parameter vector."""

    n: int
    m: int
    p: int
    horizon: int
    n_keep_in: int
    slot_size: int
    closed_form: bool
    n_slack: int

    @property
    def n_w(self) -> int:
        extra = 0 if self.closed_form else self.n + self.m
        return self.m * self.horizon + self.n * self.horizon + self.p + extra + self.n_slack

    @property
    def n_param(self) -> int:
        return self.n + self.p + 2 + self.n + self.m + self.n_keep_in + self.slot_size

    def split_w(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """w -> U [N, m], X [N, n] (x(1..N)), y_a [p], (x_a, u_a) stacked or None."""
        N, n, m, p = self.horizon, self.n, self.m, self.p
        w = np.asarray(w, float).ravel()
        U = w[: m * N].reshape(N, m)
        X = w[m * N: m * N + n * N].reshape(N, n)
        y_a = self.y_a(w)
        start = m * N + n * N + p
        rest = None if self.closed_form else w[start:start + n + m]
        return U, X, y_a, rest

    def y_a(self, w: np.ndarray) -> np.ndarray:
        """The artificial output y_a [p] of w (split_w's third part: a view of w where w is a float array)."""
        start = (self.m + self.n) * self.horizon
        return np.asarray(w, float).ravel()[start:start + self.p]

    def join_w(self, U: np.ndarray, X: np.ndarray, y_a: np.ndarray, rest: np.ndarray | None,
               x0: np.ndarray | None = None) -> np.ndarray:
        """Inverse of split_w (x0 is not a variable here); the slacks are zero (see NlpBase.fill_slacks)."""
        parts = [np.ravel(U), np.ravel(X), np.ravel(y_a)]
        if not self.closed_form:
            parts.append(np.ravel(rest))
        parts.append(np.zeros(self.n_slack))
        return np.concatenate(parts)


@dataclass
class ProblemParts:
    """Symbols and functions shared by every formulation of one settings structure.

    Attributes:
        par: the parameter vector (see `parameters` for its order), and its pieces x0, y_t,
            kappa, mu, q, r, keep_active, u_prev and rate_on (input_rate_max), slot_par.
        avoidance: (x [n], u [m], elapsed s) -> active * g of every keep-in expression and obstacle
            slot [n_depth] (> 0 inside a region to avoid), moving obstacles taken `elapsed` s after
            x(0): stage k at k Ts, and the steady state x_a (= x(N)) at N Ts.
        chord: (x_a [n], x_b [n], u [m], elapsed_a, elapsed_b) -> c^2 [n_depth] of the chord between two
            sub-step states per region (ellipses; 0 for the others), core/nlp/between.py.
        hard_g: Function (x, u) -> hard inequalities g <= 0 [n_hard]; hard_uses_u per row.
        slot_layout, output_frame_available, closed_form, n_keep_in.
    """

    par: ca.SX
    x0: ca.SX
    y_t: ca.SX
    kappa: ca.SX
    mu: ca.SX
    q: ca.SX
    r: ca.SX
    keep_active: ca.SX
    slot_par: ca.SX
    avoidance: object
    chord: object
    hard_g: ca.Function
    hard_uses_u: list[bool]
    n_hard: int
    n_keep_in: int
    n_depth: int
    slot_layout: SlotLayout
    output_frame_available: bool
    closed_form: bool
    u_prev: ca.SX  # [m] the command in force, with input_rate_max (else empty)
    rate_on: ca.SX  # [1] 1 when there is one (else empty)
    output_weights: np.ndarray | None = None  # [p] W of V_o (settings.output_weights); None: the paper's |.|^2
    rate_limited: tuple[int, ...] = ()  # the inputs input_rate_max limits (a finite rate)
    rate_step: tuple[float, ...] = ()  # their largest change per sample, rate * sample_time

    def rate_rows(self, u: ca.SX, before: ca.SX, first: bool) -> tuple[ca.SX, list[float], list[float]]:
        """The rows |u - before| <= rate Ts of the limited inputs (u [m]; before [m], or only the limited inputs as
        a stage-wise v(k) carries them; `first`: before is the command in force, the rows on only where there is
        one, rate_on) with their lower and upper bounds; empty without limits."""
        limited = list(self.rate_limited)
        change = u[limited] - (before if before.numel() == len(limited) else before[limited])
        return self.rate_on * change if first else change, [-step for step in self.rate_step], list(self.rate_step)

    def offset_cost(self, y_a: ca.SX) -> ca.SX:
        """V_o = kappa |y_a - y_t|_W^2 (the paper's kappa |y_a - y_t|^2, to the last operation, without weights)."""
        dy = y_a - self.y_t
        if self.output_weights is None:
            return self.kappa * ca.dot(dy, dy)
        return self.kappa * ca.dot(self.output_weights * dy, dy)


def keep_in_bends(expressions: list[ca.SX], x: ca.SX, u: ca.SX) -> np.ndarray:
    """Per keep-in expression g(x, u), the largest b with g along a chord <= (1 - t) g(a) + t g(b) + t (1 - t)
    b |b - a|^2 (the chord rows of core/nlp/between.py): for a quadratic g, max(0, largest eigenvalue of
    -H / 2), H its constant Hessian in x (|x1 x2| <= 2: 1/2; a convex g: 0); 0 for an expression that is
    not quadratic in x."""
    bends = np.zeros(len(expressions))
    for i, g in enumerate(expressions):
        hessian = ca.hessian(g, x)[0]
        if not ca.depends_on(hessian, ca.vertcat(x, u)):
            bends[i] = max(0.0, float(np.max(np.linalg.eigvalsh(-np.asarray(ca.DM(hessian)))))) / 2
    return bends


def check_sizes(settings: ControllerSettings, model: Model) -> None:
    """ConfigError when bounds, weights or planes do not fit the model's dimensions."""
    for name, size in (("state_min", model.n), ("state_max", model.n), ("input_min", model.m),
                       ("input_max", model.m), ("state_weights", model.n), ("input_weights", model.m)):
        if len(getattr(settings, name)) != size:
            raise ConfigError(f"{name} needs {size} values for model {model.name}, got {len(getattr(settings, name))}")
    if settings.input_rate_max and len(settings.input_rate_max) != model.m:
        raise ConfigError(f"input_rate_max needs {model.m} values for model {model.name} (or none: off), got "
                          f"{len(settings.input_rate_max)}")
    if settings.output_weights and len(settings.output_weights) != model.p:
        raise ConfigError(f"output_weights needs {model.p} values for model {model.name} (or none: all 1), got "
                          f"{len(settings.output_weights)}")
    if settings.horizon < model.n and settings.terminal == "equality":  # a terminal set needs no N-step rest
        raise ConfigError(f"horizon {settings.horizon} is below the {model.n} states of {model.name}: with the "
                          f"terminal equality x(N) = x_a a plan of fewer than n steps cannot in general bring the "
                          f"state to rest")
    if max(settings.plane) >= model.n:
        raise ConfigError(f"plane {settings.plane} indexes beyond the {model.n} states of {model.name}")


def problem_parts(settings: ControllerSettings, model: Model) -> ProblemParts:
    """Parse the regions and make the parameter symbols of one settings structure."""
    s, mdl = settings, model
    n, m, p = mdl.n, mdl.m, mdl.p
    slots = SlotLayout(s.max_ellipses, s.max_polygons, s.max_polygon_vertices)
    output_frame_available = p >= 2 and max(s.output_plane) < p
    # keep-in expressions over the model's names, as one Function g(x, u) -> [n_keep]
    xs, us = ca.SX.sym("x", n), ca.SX.sym("u", m)
    symbols = mdl.symbol_table(xs, us)
    keep_in = [parse_keep_in(text, symbols) for text in s.keep_in]
    hard = [parse_keep_in(text, symbols) for text in s.constraints]
    keep_g = ca.Function("keep_in_g", [xs, us], [ca.vertcat(*[k.g for k in keep_in]) if keep_in else ca.SX(0, 1)])
    hard_g = ca.Function("hard_g", [xs, us], [ca.vertcat(*[k.g for k in hard]) if hard else ca.SX(0, 1)])
    hard_uses_u = [bool(ca.depends_on(k.g, us)) for k in hard]
    x0 = ca.SX.sym("x0", n)
    y_t = ca.SX.sym("y_t", p)
    kappa = ca.SX.sym("kappa")
    mu = ca.SX.sym("mu")
    q = ca.SX.sym("q", n)
    r = ca.SX.sym("r", m)
    keep_active = ca.SX.sym("keep_active", len(keep_in))
    slot_par = ca.SX.sym("slots", slots.size)
    # with input_rate_max: the command in force u_prev [m] and whether there is one (the slots stay last)
    u_prev = ca.SX.sym("u_prev", m if s.input_rate_max else 0)
    rate_on = ca.SX.sym("rate_on", 1 if s.input_rate_max else 0)
    rate_limited = tuple(i for i, rate in enumerate(s.input_rate_max) if math.isfinite(rate))
    par = ca.vertcat(x0, y_t, kappa, mu, q, r, keep_active, u_prev, rate_on, slot_par)

    def points(x, u):
        """(state-plane point, output-plane point or None) of x under u."""
        return x[list(s.plane)], mdl.output(x, u)[list(s.output_plane)] if output_frame_available else None

    def avoidance(x, u, elapsed: float = 0.0, keep_in_margin: float | None = None):
        """The region functions g at one point (keep-in expressions, then obstacle slots), with
        moving obstacles where they are `elapsed` s after x(0) (stage k: k Ts); the keep-in expressions
        tightened by `keep_in_margin` (default: the settings')."""
        margin = s.keep_in_margin if keep_in_margin is None else keep_in_margin
        return ca.vertcat(keep_active * (keep_g(x, u) + margin),
                          slots.depths(slot_par, *points(x, u), elapsed))

    bends = keep_in_bends([k.g for k in keep_in], xs, us)

    def chord(xa, xb, u, elapsed_a: float, elapsed_b: float):
        """Per region, c^2 of the chord x_a -> x_b under u (core/nlp/between.py): for an ellipse its squared
        normalised length, for a keep-in expression `keep_in_bends` |x_b - x_a|^2, 0 for polygons."""
        d = xb - xa
        return ca.vertcat(keep_active * bends * ca.dot(d, d),
                          slots.chords(slot_par, points(xa, u), points(xb, u), elapsed_a, elapsed_b))

    return ProblemParts(par, x0, y_t, kappa, mu, q, r, keep_active, slot_par, avoidance, chord, hard_g, hard_uses_u,
                        len(hard), len(keep_in), len(keep_in) + slots.max_ellipses + slots.max_polygons, slots,
                        output_frame_available, s.use_closed_form_steady_state and mdl.steady_state is not None,
                        u_prev, rate_on, np.array(s.output_weights, float) if s.output_weights else None,
                        rate_limited, tuple(float(s.input_rate_max[i]) * s.sample_time for i in rate_limited))


def command_index(parameter_count: int, slot_size: int, m: int, rate_limited: bool) -> np.ndarray:
    """Indices of the command in force u_prev [m] in the parameter vector `par` above (of parameter_count entries,
    the slot block of slot_size last, rate_on just before it); empty without input_rate_max (`rate_limited` False)."""
    end = parameter_count - slot_size - 1
    return np.arange(end - m, end) if rate_limited else np.zeros(0, int)


def depth_function(parts: ProblemParts, model: Model, keep_in_margin: float | None = None) -> ca.Function:
    """(x [n], u [m], p [n_param], elapsed s) -> region functions g [n_depth] (> 0 inside a region to
    avoid), moving obstacles where they are `elapsed` s after x(0) (stage k: k Ts; steady state: N Ts);
    the keep-in expressions tightened by `keep_in_margin` (default: the settings', as planned)."""
    xs, us, elapsed = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m), ca.SX.sym("elapsed")
    return ca.Function("region_depth", [xs, us, parts.par, elapsed], [parts.avoidance(xs, us, elapsed, keep_in_margin)])
