"""Reachability of a campaign target: Y_r, the best reachable and admissible points, passages.

* best reachable point y*: the projection of y_t onto Y_r, the outputs of steady states in
  lambda * Z (paper eq. 4-5): the controller's own TargetProjection (core/nlp/projection.py), y_t
  itself when it is within 1e-6 (OUT_OF_REACH) of Y_r: the target is reachable iff y* = y_t.
* best admissible point y~: the point of Y_r nearest to y_t whose steady state is outside every
  region (ellipses and keep-in expressions); y* unless a region covers y*'s steady state, else
  found on a grid over Y_r (1e-3 in 1-d; 0.05 then refined to 0.002 in 2-d).
* passage: is there an admissible way from where a run stopped to y~ (van der Pol: an x1-slice
  corridor with x2 of the right sign; planar outputs: a connected free path on a 5 cm grid)?
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from ...core.config.settings import ControllerSettings
from ...core.errors import ConfigError
from ...core.loop.metrics import keep_in_function, keep_in_values, region_depth
from ...core.nlp.projection import TargetProjection
from ...core.problem.expressions import parse_keep_in
from ...core.problem.models import Model
from ...core.problem.regions import Ellipse, Region

#: numerical slack of the lambda * Z test of a candidate steady state (the projection's accuracy)
ADMISSIBLE_SLACK = 1e-6


class ReachableSet:
    """Y_r of one configuration (steady outputs with (x_s, u_s) in lambda * Z, paper eq. 4-5).

    Needs the model's closed-form steady-state maps g_x, g_u, or its `steady_guess` from x = 0 where every
    output has a steady state of that form (the unicycle: at rest, heading 0, a heading its box leaves free).
    """

    def __init__(self, settings: ControllerSettings, model: Model) -> None:
        self.settings, self.model = settings, model
        lam = settings.steady_state_scale
        if model.steady_state is not None:
            y = ca.SX.sym("y", model.p)
            xs, us = (ca.vertcat(v) for v in model.steady_state(y))
            closed_form = ca.Function("steady", [y], [xs, us])
            self.steady = lambda Y: tuple(np.asarray(v).reshape(-1, Y.shape[1]) for v in closed_form.map(Y.shape[1])(Y))
        elif model.steady_guess is not None:
            self.steady = self._guessed_steady
        else:
            raise ConfigError(f"campaign: model {model.name} has no steady-state map (closed form or steady_guess)")
        xsym, usym = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m)
        table = model.symbol_table(xsym, usym)
        hard = [parse_keep_in(t, table).g for t in settings.constraints]
        keep = [parse_keep_in(t, table).g for t in settings.keep_in]
        self.hard = ca.Function("hard", [xsym, usym], [ca.vertcat(*hard) if hard else ca.SX(0, 1)])
        self.keep = ca.Function("keep", [xsym, usym], [ca.vertcat(*keep) if keep else ca.SX(0, 1)])
        self.lo = lam * np.array([*settings.state_min, *settings.input_min], float)
        self.hi = lam * np.array([*settings.state_max, *settings.input_max], float)
        self._projection = TargetProjection(settings, model)
        self.box = self._output_box()

    def _guessed_steady(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x_s [n, K], u_s [m, K]) of outputs Y [p, K] from the model's steady_guess at x = 0."""
        rest = np.zeros(self.model.n)
        pairs = [self.model.steady_guess(y, rest) for y in Y.T]
        return np.array([x for x, _ in pairs], float).T, np.array([u for _, u in pairs], float).T

    def project(self, y_t: Sequence[float]) -> np.ndarray:
        """y* [p]: the point of Y_r nearest to y_t (Euclidean), as the controller projects its target."""
        return self._projection(y_t)

    def _output_box(self) -> np.ndarray:
        """[p, 2] bounds of Y_r (projections of far-away points along each axis)."""
        far = 1e4
        box = np.zeros((self.model.p, 2))
        for i in range(self.model.p):
            for j, sign in enumerate((-1.0, 1.0)):
                y = np.zeros(self.model.p)
                y[i] = sign * far
                box[i, j] = self.project(y)[i]
        return box

    def admissible(self, Y: np.ndarray, regions: Sequence[Region]) -> np.ndarray:
        """For candidate outputs Y [K, p]: steady state in lambda * Z and outside every region [K] bool."""
        Y = np.atleast_2d(np.asarray(Y, float))
        K = len(Y)
        xs, us = self.steady(Y.T)
        z = np.vstack([xs, us])
        ok = np.all((z >= self.lo[:, None] - ADMISSIBLE_SLACK) & (z <= self.hi[:, None] + ADMISSIBLE_SLACK), axis=0)
        lam = self.settings.steady_state_scale
        if self.hard.size1_out(0):
            ok &= np.all(np.asarray(self.hard.map(K)(xs / lam, us / lam)).reshape(-1, K) <= ADMISSIBLE_SLACK, axis=0)
        if self.keep.size1_out(0):
            ok &= np.all(np.asarray(self.keep.map(K)(xs, us)).reshape(-1, K) <= 0, axis=0)
        s = self.settings
        for region in regions:
            plane, source = (s.plane, xs) if region.frame == "state" else (s.output_plane, Y.T)
            point = np.vstack([source[plane[0]], source[plane[1]]])
            ok &= region_depth(region, point) <= 0
        return ok

    def best_admissible(self, y_t: Sequence[float], y_star: np.ndarray, regions: Sequence[Region]) -> np.ndarray:
        """y~ [p]: nearest to y_t among admissible outputs (y* itself when admissible)."""
        y_t = np.asarray(y_t, float)
        if self.admissible(y_star[None, :], regions)[0]:
            return y_star
        # an angle output (a pose's heading) leaves the steady state's admissibility to the other outputs: it is
        # taken as y*'s, and the nearest point is searched over the rest
        angles = [i for i, _ in self.model.angle_outputs]
        free = [i for i in range(self.model.p) if i not in angles]

        def full(points: np.ndarray) -> np.ndarray:
            grid = np.tile(y_star, (len(points), 1))
            grid[:, free] = points
            return grid

        box = self.box[free]
        if len(free) == 1:
            grid = np.arange(box[0, 0], box[0, 1] + 5e-4, 1e-3)[:, None]
            return self._nearest(full(grid), y_t, regions)
        if len(free) == 2:
            axes = [np.arange(lo, hi + 0.025, 0.05) for lo, hi in box]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
            coarse = self._nearest(full(grid), y_t, regions)
            if not np.all(np.isfinite(coarse)):
                return coarse
            fine = [np.clip(np.arange(c - 0.1, c + 0.1 + 1e-3, 0.002), lo, hi)
                    for c, (lo, hi) in zip(coarse[free], box)]
            grid = np.stack(np.meshgrid(*fine, indexing="ij"), -1).reshape(-1, 2)
            return self._nearest(full(grid), y_t, regions)
        raise ConfigError(f"campaign: best admissible point for {len(free)}-d outputs is not implemented")

    def _nearest(self, grid: np.ndarray, y_t: np.ndarray, regions: Sequence[Region]) -> np.ndarray:
        ok = self.admissible(grid, regions)
        if not np.any(ok):
            return np.full(self.model.p, np.nan)
        cand = grid[ok]
        return cand[np.argmin(np.linalg.norm(cand - y_t, axis=1))]


def vdp_passage(x_end: np.ndarray, y_goal: np.ndarray, regions: Sequence[Region],
                settings: ControllerSettings | None = None) -> bool:
    """Is there an admissible corridor in the (x1, x2) plane from x1 = x_end[0] to x1 = y_goal?

    Moving x1 right needs x2 > 0 (left: x2 < 0), with |x2| <= 2 and |x1 x2| <= 2. The corridor is
    open when every x1 slice (step 0.01) between the two has such an x2 outside all ellipses
    (continuous-time reasoning; an Euler step could jump a thin slice) and, with `settings`, inside its
    keep-in expressions as planned (g + keep_in_margin <= 0: the live config's |x2| <= 1.99 rows too).
    """
    a, b = float(x_end[0]), float(y_goal[0])
    if abs(b - a) < 1e-9:
        return True
    sign = 1.0 if b > a else -1.0
    x1 = np.linspace(a, b, max(2, int(abs(b - a) / 0.01) + 1))
    frac = np.linspace(1e-3, 1.0, 200)
    X1 = np.repeat(x1, frac.size)
    X2 = sign * np.tile(frac, x1.size) * np.repeat(np.minimum(2.0, 2.0 / np.maximum(np.abs(x1), 1e-9)), frac.size)
    free = np.ones(X1.size, bool)
    for region in regions:
        free &= region_depth(region, np.vstack([X1, X2])) <= 0
    if settings is not None and settings.keep_in:
        points, model = np.column_stack([X1, X2]), settings.build_model()
        keep = keep_in_values(settings, model, points, np.zeros((len(points), model.m)))
        free &= np.all(keep + settings.keep_in_margin <= 0, axis=1)
    return bool(np.all(free.reshape(x1.size, frac.size).any(axis=1)))


#: the trajectory search of `trajectory_passage`: inputs held this long (s), checked at this many RK4 sub-steps,
#: this many input levels across the input box, one state kept per cell of this size (state units), searched over
#: this much plant time (s)
SEARCH_INTERVAL, SEARCH_SUBSTEPS, SEARCH_LEVELS, SEARCH_CELL, SEARCH_TIME = 0.1, 2, 25, 0.01, 40.0
#: depth (region and keep-in g) a searched trajectory may reach: where the controller judges a plan clear
SEARCH_DEPTH = 1e-3


def trajectory_passage(x_end: np.ndarray, y_goal: np.ndarray, regions: Sequence[Region],
                       settings: ControllerSettings) -> bool:
    """Is there a trajectory of the model from x_end past (in x1, towards y_goal) every region in the x1 span between,
    clear of the regions (as given: pass them inflated by the planning margin) and inside the keep-in sets with
    keep_in_margin, under inputs in the box? From there nothing blocks the way to y_goal's steady state. A search
    over inputs held SEARCH_INTERVAL s (SEARCH_LEVELS levels per input), every RK4
    sub-step state checked, keeping the first state that reaches each SEARCH_CELL cell of the state space. A way
    it finds is a real trajectory of the model; one it misses may exist (a corridor a few cells wide, or one that
    needs a finer input). For models of two states (van der Pol): the cells span the whole state.

    The geometric corridor (`vdp_passage`) asks only for free x2 of the right sign in every x1 slice; the
    dynamics may not hold the state there (vdp-0020: x2 in [0.33, 0.43] at x1 = 4.6 needs u = 12, the box
    gives 6), and the controller then rightly stops: no clear way exists for it."""
    model = settings.build_model()
    if model.n != 2:
        raise ConfigError(f"trajectory_passage searches a state of 2 (van der Pol), not {model.n}")
    path = model.discrete_path(SEARCH_INTERVAL, "rk4", SEARCH_SUBSTEPS)
    lo, hi = np.array(settings.input_min, float), np.array(settings.input_max, float)
    levels = np.array(np.meshgrid(*[np.linspace(a, b, SEARCH_LEVELS) for a, b in zip(lo, hi)])).reshape(model.m, -1)
    # the goal is past the regions, not y_goal's steady state itself: near the input bound its last approach is
    # slow (45 s from x1 = 5.5 to 5.89 at u <= 6), which is not the question here
    start, end = float(np.asarray(x_end, float)[0]), float(np.asarray(y_goal, float)[0])
    sign = 1.0 if end >= start else -1.0
    beyond = start
    for region in regions:
        lo_x1, hi_x1 = _x1_extent(region)
        if hi_x1 >= min(start, end) and lo_x1 <= max(start, end):
            beyond = max(beyond, hi_x1) if sign > 0 else min(beyond, lo_x1)
    beyond = min(beyond, end) if sign > 0 else max(beyond, end)
    if sign * (beyond - start) <= 0:
        return True
    x_lo, x_hi = np.array(settings.state_min, float), np.array(settings.state_max, float)
    keep_g = keep_in_function(settings, model)
    plane = list(settings.plane)
    frontier = np.asarray(x_end, float).reshape(2, 1)
    seen = {tuple(np.floor(frontier[:, 0] / SEARCH_CELL).astype(int))}
    for _ in range(int(SEARCH_TIME / SEARCH_INTERVAL)):
        if not frontier.size:
            return False
        starts = np.repeat(frontier, levels.shape[1], axis=1)
        inputs = np.tile(levels, frontier.shape[1])
        points = np.asarray(path.map(starts.shape[1])(starts, inputs)).reshape(2, -1, SEARCH_SUBSTEPS)
        flat = points.transpose(0, 2, 1).reshape(2, -1)  # every sub-step state, [2, steps * K] by sub-step
        ok = np.all(np.isfinite(flat), axis=0) & np.all((flat >= x_lo[:, None]) & (flat <= x_hi[:, None]), axis=0)
        for region in regions:
            ok &= region_depth(region, flat[plane]) <= SEARCH_DEPTH
        if keep_g is not None:  # the inputs in flat's order: each sub-step's K columns in turn
            g = np.asarray(keep_g.map(flat.shape[1])(flat, np.tile(inputs, SEARCH_SUBSTEPS)))
            ok &= np.all(g + settings.keep_in_margin <= SEARCH_DEPTH, axis=0)
        clear = ok.reshape(SEARCH_SUBSTEPS, -1).all(axis=0)
        ends = points[:, :, -1][:, clear]
        if ends.size and np.any(sign * (ends[0] - beyond) >= 0):
            return True
        cells = np.floor(ends / SEARCH_CELL).astype(int)
        fresh = []
        for j, cell in enumerate(map(tuple, cells.T)):
            if cell not in seen:
                seen.add(cell)
                fresh.append(j)
        frontier = ends[:, fresh]
    return False


def _x1_extent(region: Region) -> tuple[float, float]:
    """The x1 span of a region's points (an ellipse: its rotated box; other regions: their vertices)."""
    if isinstance(region, Ellipse):
        a, b = region.semi_axes
        half = float(np.hypot(a * np.cos(region.yaw), b * np.sin(region.yaw)))
        return region.center[0] - half, region.center[0] + half
    xs = np.asarray(region.vertices, float)[:, 0]
    return float(xs.min()), float(xs.max())


#: cells (of planar_passage's grid) around a point searched for the free component it belongs to
BOUNDARY_CELLS = 2


def planar_passage(y_end: np.ndarray, y_goal: np.ndarray, regions: Sequence[Region], half_width: float = 10.0,
                   cell: float = 0.05) -> bool:
    """Are y_end and y_goal in one connected component of the free plane [-w, w]^2 minus ellipses?

    A point in an occupied cell within `BOUNDARY_CELLS` of a free one belongs to the nearest free cell's
    component: a robot that stopped skimming a region, on its (inflated) boundary, rounds into it."""
    from scipy.ndimage import label

    axis = np.arange(-half_width, half_width + cell / 2, cell)
    PX, PY = np.meshgrid(axis, axis, indexing="ij")
    free = np.ones(PX.shape, bool)
    for region in regions:
        free &= (region_depth(region, np.vstack([PX.ravel(), PY.ravel()])) <= 0).reshape(PX.shape)
    labels, _ = label(free)

    def component(pt: np.ndarray) -> int:
        i, j = (int(np.clip(round((c + half_width) / cell), 0, axis.size - 1)) for c in pt[:2])
        lo_i, lo_j = max(i - BOUNDARY_CELLS, 0), max(j - BOUNDARY_CELLS, 0)
        near = labels[lo_i:i + BOUNDARY_CELLS + 1, lo_j:j + BOUNDARY_CELLS + 1]
        ii, jj = np.nonzero(near)
        if not ii.size:
            return 0
        k = int(np.argmin((ii + lo_i - i) ** 2 + (jj + lo_j - j) ** 2))
        return int(near[ii[k], jj[k]])

    a, b = component(y_end), component(y_goal)
    return bool(a and b and a == b)
