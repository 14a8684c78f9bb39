"""`campaign`: Monte Carlo evidence over random scenarios -> one JSON plus summary plots.

    python -m nmpc_avoid_ros campaign --out out/campaign [--vdp 500] [--robot 200] [--seed 0] [--jobs N]

Scenarios (each drawn from its own generator seeded by (seed, model, index), so a scenario never
depends on how many others there are or which ran before):

* van der Pol (config/van_der_pol.yaml): x0 uniform in the box |x1| <= 6, |x2| <= 2 with
  |x1 x2| <= 2; y_t uniform in [-8, 8] (the reachable outputs are |y| <= 0.99 * 6 = 5.94, so about a
  quarter of the targets are unreachable); 0-4 random ellipses in the (x1, x2) plane besides
  |x1 x2| <= 2, half of them placed near the path from x0 to the target, none containing x0.
* mobile robot (config/mobile_robot.yaml): start position uniform in [-9, 9]^2 with a random
  velocity (speed <= 1 m/s), goal uniform in [-11, 11]^2 (reachable: [-9.9, 9.9]^2); 0-4 random
  ellipses in the output (position) plane, 60 % of them near the straight start-goal segment.

Definitions (per scenario; y is the output, K the last sample):

* best reachable point y*: the projection of y_t onto Y_r, the outputs of steady states in
  lambda * Z (paper eq. 4-5), computed by a small IPOPT problem min |y - y_t|^2 s.t.
  (g_x(y), g_u(y)) in lambda * Z (box and hard constraints); reachable iff |y* - y_t| < 1e-6.
* best admissible point y~: the point of Y_r nearest to y_t whose steady state is outside every
  region (ellipses and keep-in expressions); equal to y* unless a region covers y*'s steady state,
  else found on a grid over Y_r (1e-3 in 1-d; 0.05 then refined to 0.002 in 2-d).
* at rest: the state moved less than REST_TOLERANCE (inf-norm) over the last REST_WINDOW samples.
* converged: |y - y*| < SETTLING_TOLERANCE (0.05) from some sample on, to the end (settled at y*).
* near: |y_K - y*| < NEAR_TOLERANCE (0.1) (the target itself if reachable, else y*);
  near_admissible: |y_K - y~| < NEAR_TOLERANCE.
* stop short (paper Remark 1): at rest but not converged; the distance is |y_K - y*|. Cause
  'obstacle_covers_target' if it stopped at y~ != y* (the avoidance cost moves the equilibrium);
  otherwise it stopped short of y~ too, 'no_passage' when the regions leave no admissible way from
  where it stopped to y~ (van der Pol: no x1 slice corridor with x2 of the right sign; robot: no
  connected free path on a 5 cm grid), else 'local_minimum' (a way exists, the loop did not find it).
* penetration: the largest g over the sampled states (keep-in g, e.g. |x1 x2| - 2, and ellipse
  depth 1 - r^2 in normalised radius), 0 if never inside; from bag.analysis.run_metrics.
* solver failure: a sample whose solver status is not Solve_Succeeded/Solved_To_Acceptable_Level
  (budget cuts with a feasible iterate count here, as 'truncated'); fallback: a sample that applied
  the controller's fallback. Recursive feasibility: among samples k >= 1 whose predecessor's solve
  was usable (ok/truncated), the share whose own solve was usable.

Results: campaign.jsonl (one line per finished scenario, with its trajectory; a rerun skips the
ids it holds), campaign.json (per-scenario records without trajectories, plus the summary) and
PNG plots, all in --out.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from ..bag.analysis import RecordedRun, run_metrics
from ..core.closed_loop import PLANTS, SETTLING_TOLERANCE, ClosedLoopRun, run_closed_loop, settling_step
from ..core.controller import SOLVED, NmpcController, StepResult
from ..core.errors import ConfigError, NmpcError
from ..core.expressions import parse_keep_in
from ..core.models import Model, make_model
from ..core.regions import Ellipse, Region, _ellipse_g
from ..core.settings import ControllerSettings, default_config_path, load_params_file

#: the state must move less than this (inf-norm) over the last REST_WINDOW samples to be "at rest"
REST_TOLERANCE = 5e-3
REST_WINDOW = 10
#: "ends near" a point: the final output is closer than this (output units)
NEAR_TOLERANCE = 0.1
#: a target is reachable when its projection onto Y_r moves it less than this
REACHABLE_TOLERANCE = 1e-6
#: numerical slack of the lambda * Z test of a candidate steady state (the projection's accuracy)
ADMISSIBLE_SLACK = 1e-6
#: budget of the X_N membership probe of a start whose first real solve failed
PROBE_ITERATIONS = 1000
PROBE_SOLVE_TIME = 20.0
#: an ellipse never contains the initial point: its depth there is below -START_MARGIN
START_MARGIN = 0.2
JSONL_NAME = "campaign.jsonl"
JSON_NAME = "campaign.json"
META_NAME = "campaign_meta.json"
USABLE = ("ok", "truncated")
#: one character per sample in the stored trace
STATUS_CODES = {"ok": ".", "truncated": "t", "fallback_shift": "s", "fallback_steady": "S", "fallback_safe": "X"}


@dataclass(frozen=True)
class Family:
    """One model family of the campaign: its config, run length and scenario generator."""

    key: str
    config: Path
    steps: int
    generate: Callable[[np.random.Generator, ControllerSettings, Model], dict[str, Any]]


# -- reachable set: Y_r of lambda * Z and the best reachable / admissible points ----------------

class ReachableSet:
    """Y_r of one configuration (steady outputs with (x_s, u_s) in lambda * Z, paper eq. 4-5).

    Needs the model's closed-form steady-state maps g_x, g_u (both campaign models have them).
    """

    def __init__(self, settings: ControllerSettings, model: Model) -> None:
        if model.steady_state is None:
            raise ConfigError(f"campaign: model {model.name} has no closed-form steady state")
        self.settings, self.model = settings, model
        lam = settings.steady_state_scale
        y = ca.SX.sym("y", model.p)
        xs, us = (ca.vertcat(v) for v in model.steady_state(y))
        self.steady = ca.Function("steady", [y], [xs, us])
        xsym, usym = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m)
        table = model.symbol_table(xsym, usym)
        hard = [parse_keep_in(t, table).g for t in settings.constraints]
        keep = [parse_keep_in(t, table).g for t in settings.keep_in]
        self.hard = ca.Function("hard", [xsym, usym], [ca.vertcat(*hard) if hard else ca.SX(0, 1)])
        self.keep = ca.Function("keep", [xsym, usym], [ca.vertcat(*keep) if keep else ca.SX(0, 1)])
        self.lo = lam * np.array([*settings.state_min, *settings.input_min], float)
        self.hi = lam * np.array([*settings.state_max, *settings.input_max], float)
        y_t = ca.SX.sym("y_t", model.p)
        g = [ca.vertcat(xs, us)]
        lbg, ubg = list(self.lo), list(self.hi)
        if hard:
            g.append(self.hard(xs / lam, us / lam))
            lbg += [-np.inf] * len(hard)
            ubg += [0.0] * len(hard)
        nlp = {"x": y, "p": y_t, "f": ca.sumsqr(y - y_t), "g": ca.vertcat(*g)}
        self._proj = ca.nlpsol("projection", "ipopt", nlp, {"print_time": False, "ipopt": {
            "print_level": 0, "sb": "yes", "tol": 1e-12, "bound_relax_factor": 0.0}})
        self._lbg, self._ubg = np.array(lbg), np.array(ubg)
        self.box = self._output_box()

    def project(self, y_t: Sequence[float]) -> np.ndarray:
        """y* [p]: the point of Y_r nearest to y_t (Euclidean)."""
        y_t = np.asarray(y_t, float)
        sol = self._proj(x0=y_t, p=y_t, lbg=self._lbg, ubg=self._ubg)
        return np.asarray(sol["x"]).ravel()

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
        xs, us = (np.asarray(v).reshape(-1, K) for v in self.steady.map(K)(Y.T))
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
        p = self.model.p
        if p == 1:
            grid = np.arange(self.box[0, 0], self.box[0, 1] + 5e-4, 1e-3)[:, None]
            return self._nearest(grid, y_t, regions)
        if p == 2:
            axes = [np.arange(lo, hi + 0.025, 0.05) for lo, hi in self.box]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
            coarse = self._nearest(grid, y_t, regions)
            if not np.all(np.isfinite(coarse)):
                return coarse
            fine = [np.clip(np.arange(c - 0.1, c + 0.1 + 1e-3, 0.002), lo, hi)
                    for c, (lo, hi) in zip(coarse, self.box)]
            grid = np.stack(np.meshgrid(*fine, indexing="ij"), -1).reshape(-1, 2)
            return self._nearest(grid, y_t, regions)
        raise ConfigError(f"campaign: best admissible point for {p}-d outputs is not implemented")

    def _nearest(self, grid: np.ndarray, y_t: np.ndarray, regions: Sequence[Region]) -> np.ndarray:
        ok = self.admissible(grid, regions)
        if not np.any(ok):
            return np.full(self.model.p, np.nan)
        cand = grid[ok]
        return cand[np.argmin(np.linalg.norm(cand - y_t, axis=1))]


def region_depth(region: Region, points: np.ndarray) -> np.ndarray:
    """g of an ellipse at points [2, K] (> 0 inside), vectorised; other regions point by point."""
    if isinstance(region, Ellipse):
        return np.asarray(_ellipse_g(points, region.slot_values()), float)
    return np.array([region.depth(pt) for pt in points.T])


# -- scenario generators ------------------------------------------------------------------------

def _ellipse_dict(e: Ellipse) -> dict[str, Any]:
    return {"center": list(e.center), "semi_axes": list(e.semi_axes), "yaw": e.yaw, "frame": e.frame}


def _place_ellipses(rng: np.random.Generator, count: int, start: np.ndarray, draw: Callable[[], Ellipse]
                    ) -> list[dict[str, Any]]:
    """`count` ellipses from `draw`, redrawn while one contains `start` (depth > -START_MARGIN)."""
    out = []
    for _ in range(count):
        for _attempt in range(200):
            e = draw()
            if e.depth(start) < -START_MARGIN:
                out.append(_ellipse_dict(e))
                break
    return out


def vdp_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """x0 in the box with |x1 x2| <= 2, y_t ~ U[-8, 8], 0-4 state-plane ellipses not containing x0."""
    lo, hi = np.array(settings.state_min), np.array(settings.state_max)
    while True:
        x0 = rng.uniform(lo, hi)
        if abs(x0[0] * x0[1]) <= 2.0:
            break
    y_t = float(rng.uniform(-8.0, 8.0))
    end = float(np.clip(y_t, lo[0] * settings.steady_state_scale, hi[0] * settings.steady_state_scale))

    def draw() -> Ellipse:
        if rng.random() < 0.5:  # near the way from x0 to the target's steady state
            c = (rng.uniform(min(x0[0], end), max(x0[0], end)), rng.uniform(-1.2, 1.2))
        else:
            c = (rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]))
        return Ellipse(c, (rng.uniform(0.3, 1.5), rng.uniform(0.15, 0.8)), rng.uniform(0, math.pi), "state")

    ellipses = _place_ellipses(rng, int(rng.integers(0, 5)), x0[list(settings.plane)], draw)
    return {"x0": x0.tolist(), "target": [y_t], "ellipses": ellipses}


def robot_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """Start in [-9, 9]^2 with speed <= 1 m/s, goal ~ U[-11, 11]^2, 0-4 output-plane ellipses."""
    start = rng.uniform(-9.0, 9.0, 2)
    heading, speed = rng.uniform(0, 2 * math.pi), rng.uniform(0.0, 1.0)
    x0 = np.array([*start, speed * math.cos(heading), speed * math.sin(heading)])
    goal = rng.uniform(-11.0, 11.0, 2)
    end = np.clip(goal, -9.9, 9.9)

    def draw() -> Ellipse:
        if rng.random() < 0.6:  # across the straight way to the goal
            c = start + rng.uniform(0.25, 0.75) * (end - start) + rng.normal(0.0, 0.5, 2)
        else:
            c = rng.uniform(-9.0, 9.0, 2)
        return Ellipse(tuple(c), (rng.uniform(0.4, 2.0), rng.uniform(0.4, 2.0)), rng.uniform(0, math.pi), "output")

    ellipses = _place_ellipses(rng, int(rng.integers(0, 5)), start, draw)
    return {"x0": x0.tolist(), "target": goal.tolist(), "ellipses": ellipses}


def vdp_passage(x_end: np.ndarray, y_goal: np.ndarray, regions: Sequence[Region]) -> bool:
    """Is there an admissible corridor in the (x1, x2) plane from x1 = x_end[0] to x1 = y_goal?

    Moving x1 right needs x2 > 0 (left: x2 < 0), with |x2| <= 2 and |x1 x2| <= 2. The corridor is
    open when every x1 slice (step 0.01) between the two has such an x2 outside all ellipses
    (continuous-time reasoning; an Euler step could jump a thin slice).
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
    return bool(np.all(free.reshape(x1.size, frac.size).any(axis=1)))


def planar_passage(y_end: np.ndarray, y_goal: np.ndarray, regions: Sequence[Region], half_width: float = 10.0,
                   cell: float = 0.05) -> bool:
    """Are y_end and y_goal in one connected component of the free plane [-w, w]^2 minus ellipses?"""
    from scipy.ndimage import label

    axis = np.arange(-half_width, half_width + cell / 2, cell)
    PX, PY = np.meshgrid(axis, axis, indexing="ij")
    free = np.ones(PX.shape, bool)
    for region in regions:
        free &= (region_depth(region, np.vstack([PX.ravel(), PY.ravel()])) <= 0).reshape(PX.shape)
    labels, _ = label(free)

    def cell_of(pt: np.ndarray) -> tuple[int, int]:
        i, j = (int(np.clip(round((c + half_width) / cell), 0, axis.size - 1)) for c in pt[:2])
        return i, j

    a, b = labels[cell_of(y_end)], labels[cell_of(y_goal)]
    return bool(a and b and a == b)


def families(vdp_config: Path | None = None, robot_config: Path | None = None, vdp_steps: int = 80,
             robot_steps: int = 140) -> dict[str, Family]:
    """The two model families of the campaign, keyed 'vdp' and 'robot' (steps: samples per run)."""
    shipped = default_config_path().parent
    vdp = Path(vdp_config) if vdp_config else shipped / "van_der_pol.yaml"
    robot = Path(robot_config) if robot_config else shipped / "mobile_robot.yaml"
    return {"vdp": Family("vdp", vdp, vdp_steps, vdp_scenario),
            "robot": Family("robot", robot, robot_steps, robot_scenario)}


FAMILY_CODES = {"vdp": 1, "robot": 2}


def load_settings(config: Path, max_solve_time: float | None = None) -> ControllerSettings:
    """Controller settings of a params file, optionally with another solver wall-time budget (s)."""
    settings = ControllerSettings.from_params(load_params_file(config).section("controller"))
    return settings.replace(max_solve_time=max_solve_time) if max_solve_time else settings


def make_specs(fam: Family, count: int, seed: int, settings: ControllerSettings, plant: str) -> list[dict[str, Any]]:
    """Scenario specs 0..count-1 of one family (ids '<family>-0000', ...), reproducible from seed."""
    model = make_model(settings.model)
    specs = []
    for i in range(count):
        rng = np.random.default_rng([seed, FAMILY_CODES[fam.key], i])
        spec = fam.generate(rng, settings, model)
        specs.append({"id": f"{fam.key}-{i:04d}", "family": fam.key, "index": i, "config": str(fam.config),
                      "steps": fam.steps, "plant": plant, **spec})
    return specs


# -- one scenario (runs in a worker; one controller per config, built once and reused) ----------

_WORKER: dict[str, Any] = {"max_solve_time": None, "cache": {}}


def _worker_init(max_solve_time: float | None) -> None:
    _WORKER["max_solve_time"] = max_solve_time
    _WORKER["cache"] = {}


def _tools(config: str) -> tuple[NmpcController, ReachableSet, NmpcController]:
    """(controller, reachable set, feasibility probe) of a config, built once per worker process."""
    cache = _WORKER["cache"]
    if config not in cache:
        settings = load_settings(Path(config), _WORKER["max_solve_time"])
        controller = NmpcController(settings)
        probe = NmpcController(settings.replace(mu=0.0, max_iterations=PROBE_ITERATIONS,
                                                max_solve_time=PROBE_SOLVE_TIME))
        cache[config] = (controller, ReachableSet(settings, controller.model), probe)
    return cache[config]


def start_feasibility(probe: NmpcController, x0: Sequence[float], y_t: Sequence[float]) -> str:
    """Is x0 in X_N (the NLP's feasible set)? A cold solve with mu = 0 (V_a is soft, so X_N does not
    depend on mu or y_t) and a generous budget: 'feasible', 'infeasible' or 'unknown'."""
    probe.reset()
    res = probe.step(x0, y_t, ())
    if res.status in USABLE:
        return "feasible"
    return "infeasible" if res.solver_status == "Infeasible_Problem_Detected" else "unknown"


def _vec(values: Iterable[float], digits: int = 9) -> list[float]:
    return [round(float(v), digits) for v in values]


def closed_loop(controller: NmpcController, spec: dict[str, Any], regions: Sequence[Region]
                ) -> tuple[ClosedLoopRun, str | None]:
    """run_closed_loop of the scenario; if it stops early (e.g. the plant state became non-finite and
    the controller refused it), the samples completed before, and why it stopped."""
    done: list[StepResult] = []
    try:
        run = run_closed_loop(controller, spec["x0"], spec["target"], spec["steps"], spec["plant"],
                              regions=lambda k: regions if k == 0 else None, on_step=lambda k, res: done.append(res))
        return run, None
    except (NmpcError, ArithmeticError, RuntimeError, ValueError) as exc:
        error = f"{type(exc).__name__} at sample {len(done)}: {exc}"
    if len(done) < 2:
        raise RuntimeError(f"closed loop stopped before two samples: {error}")
    used = done[:-1]  # the states each sample solved on: x(0..K); the last result closes x(K)
    x = np.array([res.states[0] for res in done])
    return ClosedLoopRun(
        x, np.array([r.u for r in used]), np.array([r.y_a for r in used]),
        np.tile(np.asarray(spec["target"], float), (len(used), 1)), np.array([r.solve_time for r in used]),
        np.array([r.iterations for r in used]), [r.status for r in used], [r.solver_status for r in used],
        np.array([(r.offset_cost, r.avoidance_cost, r.tracking_cost) for r in used]),
        controller.settings.sample_time, {"plant": spec["plant"]}), error


def run_scenario(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one scenario's closed loop and score it; the record (with its 'trace') is JSON-ready.

    Never raises: an unexpected error gives a record with 'crashed': the message.
    """
    try:
        return _run_scenario(spec)
    except Exception as exc:  # noqa: BLE001 - one bad scenario must not end the campaign
        return {"id": spec["id"], "family": spec["family"], "index": spec["index"],
                "spec": {k: spec[k] for k in ("x0", "target", "ellipses", "steps", "plant")},
                "crashed": f"{type(exc).__name__}: {exc}"}


def _run_scenario(spec: dict[str, Any]) -> dict[str, Any]:
    start = time.perf_counter()
    controller, reach, probe = _tools(spec["config"])
    settings, model = controller.settings, controller.model
    controller.reset()
    regions = [Ellipse(tuple(e["center"]), tuple(e["semi_axes"]), e["yaw"], e["frame"]) for e in spec["ellipses"]]
    y_t = np.asarray(spec["target"], float)
    run, stopped = closed_loop(controller, spec, regions)
    K = len(run.u)
    us = np.vstack([run.u, run.u[-1:]])
    y = np.array([np.asarray(model.output(x, u)).ravel() for x, u in zip(run.x, us)])
    y_star = reach.project(y_t)
    y_free = reach.best_admissible(y_t, y_star, regions)
    reachable = bool(np.linalg.norm(y_star - y_t) < REACHABLE_TOLERANCE)
    blocked_target = bool(not np.all(np.isfinite(y_free)) or np.linalg.norm(y_free - y_star) > REACHABLE_TOLERANCE)

    err_best = np.linalg.norm(y - y_star, axis=1)
    err_free = np.linalg.norm(y - y_free, axis=1) if np.all(np.isfinite(y_free)) else np.full(len(y), np.nan)
    motion = float(np.max(np.abs(run.x[-REST_WINDOW - 1:] - run.x[-1])))
    at_rest = motion < REST_TOLERANCE
    settle = settling_step(err_best, 0.0, SETTLING_TOLERANCE)
    near_free = bool(err_free[-1] < SETTLING_TOLERANCE)
    stop_short = bool(at_rest and settle is None)
    cause, passage = None, None
    if stop_short:
        if blocked_target and near_free:
            cause = "obstacle_covers_target"
        else:
            passage = bool(np.all(np.isfinite(y_free)) and (
                vdp_passage(run.x[-1], y_free, regions) if spec["family"] == "vdp"
                else planar_passage(y[-1], y_free, regions)))
            cause = "local_minimum" if passage else "no_passage"

    # penetration, reusing the bag metrics: keep-in expressions alone, then the ellipses alone
    recorded = RecordedRun(path=Path(spec["id"]), finished=True, t=np.arange(K) * settings.sample_time,
                           x=run.x[:-1], u=run.u, y_a=run.y_a, targets=run.targets, regions=[tuple(regions)] * K,
                           solve_ms=run.solve_time * 1e3, status=run.status, final_state=run.x[-1],
                           sample_time=settings.sample_time)
    keep_metrics = run_metrics(RecordedRun(**{**recorded.__dict__, "regions": [()] * K}), settings)
    obstacle_metrics = (run_metrics(recorded, settings.replace(keep_in=())) if regions else
                        {"max_penetration": 0.0, "min_clearance": None})

    usable = [s in USABLE for s in run.status]
    x0_status = "feasible" if usable[0] else start_feasibility(probe, spec["x0"], y_t)
    pairs = sum(usable[k - 1] for k in range(1, K))
    kept = sum(usable[k - 1] and usable[k] for k in range(1, K))
    failures = sum(s not in SOLVED for s in run.solver_status)
    fallbacks = {kind: run.status.count(kind) for kind in ("fallback_shift", "fallback_steady", "fallback_safe")}
    solve_ms = run.solve_time * 1e3
    examples = [{"step": k, "status": s, "solver_status": ss}
                for k, (s, ss) in enumerate(zip(run.status, run.solver_status)) if s != "ok"][:5]
    clearances = [c for c in (keep_metrics["min_clearance"], obstacle_metrics["min_clearance"]) if c is not None]
    record = {
        "id": spec["id"], "family": spec["family"], "index": spec["index"],
        "spec": {k: spec[k] for k in ("x0", "target", "ellipses", "steps", "plant")},
        "n_ellipses": len(regions), "stopped_early": stopped,
        "reachable": reachable, "y_star": _vec(y_star), "y_admissible": _vec(y_free),
        "target_covered": blocked_target,
        "final_state": _vec(run.x[-1]), "final_y": _vec(y[-1]),
        "error_to_target": float(np.linalg.norm(y[-1] - y_t)),
        "error_to_best": float(err_best[-1]), "error_to_admissible": float(err_free[-1]),
        "final_motion": motion, "at_rest": bool(at_rest),
        "settling_step": settle,
        "stop_short": stop_short, "stop_short_distance": float(err_best[-1]) if stop_short else None,
        "stop_short_beyond_admissible": float(err_free[-1]) if stop_short else None, "stop_short_cause": cause,
        "passage_to_admissible": passage,
        "final_avoidance_cost": float(run.costs[-1, 1]), "final_offset_cost": float(run.costs[-1, 0]),
        "max_penetration": float(max(keep_metrics["max_penetration"], obstacle_metrics["max_penetration"])),
        "max_penetration_keep_in": float(keep_metrics["max_penetration"]),
        "max_penetration_obstacles": float(obstacle_metrics["max_penetration"]),
        "min_clearance": float(min(clearances)) if clearances else None,
        "samples": K, "ok": run.status.count("ok"), "truncated": run.status.count("truncated"),
        "solver_failures": int(failures), "fallbacks": int(sum(fallbacks.values())), "fallback_kinds": fallbacks,
        "initial_feasible": bool(usable[0]), "x0_in_feasible_set": x0_status,
        "rf_pairs": int(pairs), "rf_kept": int(kept),
        "non_ok_examples": examples,
        "solve_ms": {"median": float(np.median(solve_ms)), "p99": float(np.percentile(solve_ms, 99)),
                     "max": float(np.max(solve_ms))},
        "budget_exhausted": int(sum(s in ("Maximum_Iterations_Exceeded", "Maximum_WallTime_Exceeded",
                                          "Maximum_CpuTime_Exceeded") for s in run.solver_status)),
        "wall_s": time.perf_counter() - start,
        "trace": {"x": [_vec(r, 6) for r in run.x], "solve_ms": _vec(solve_ms, 3),
                  "status": "".join(STATUS_CODES.get(s, "?") for s in run.status)},
    }
    return classify(record)


def classify(record: dict[str, Any]) -> dict[str, Any]:
    """Set the derived flags converged / near / near_target / near_admissible / stop_short from the
    record's raw measures (so that a rebuilt campaign.json always uses the current definitions)."""
    if record.get("crashed"):
        return record
    record["converged"] = record["settling_step"] is not None and not record.get("stopped_early")
    record["near"] = bool(record["error_to_best"] < NEAR_TOLERANCE)
    record["near_target"] = bool(record["error_to_target"] < NEAR_TOLERANCE)
    err = record["error_to_admissible"]
    record["near_admissible"] = bool(err is not None and err < NEAR_TOLERANCE)  # NaN/None: no admissible point
    record["stop_short"] = bool(record["at_rest"] and not record["converged"] and not record.get("stopped_early"))
    return record


# -- summary -----------------------------------------------------------------------------------

def _share(flags: Sequence[bool]) -> float | None:
    return float(np.mean(flags)) if len(flags) else None


def _stats(values: Sequence[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "max": None}
    return {"median": float(np.median(values)), "max": float(np.max(values))}


def summarize(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Summary of one family's records (shares are fractions in [0, 1]; distances in output units)."""
    crashed = [r for r in records if r.get("crashed")]
    records = [r for r in records if not r.get("crashed")]
    n = len(records)
    if not n:
        return {"scenarios": 0, "crashed": len(crashed)}
    diverged = [r for r in records if r.get("stopped_early")]
    finished = [r for r in records if not r.get("stopped_early")] or records
    reach = [r for r in records if r["reachable"]]
    unreach = [r for r in records if not r["reachable"]]
    short = [r for r in records if r["stop_short"]]
    pairs = sum(r["rf_pairs"] for r in records)
    worst = max(finished, key=lambda r: r["max_penetration"])
    causes: dict[str, int] = {}
    for r in short:
        causes[r["stop_short_cause"]] = causes.get(r["stop_short_cause"], 0) + 1
    return {
        "scenarios": n,
        "crashed": len(crashed),
        "stopped_early": len(diverged),
        "reachable_targets": len(reach),
        "with_ellipses": sum(r["n_ellipses"] > 0 for r in records),
        "target_covered_by_region": sum(r["target_covered"] for r in records),
        "share_converged": _share([r["converged"] for r in records]),
        "share_near": _share([r["near"] for r in records]),
        "share_near_target_reachable": _share([r["near"] for r in reach]),
        "share_near_best_unreachable": _share([r["near"] for r in unreach]),
        "share_near_admissible": _share([r["near_admissible"] for r in records]),
        "share_converged_no_ellipse": _share([r["converged"] for r in records if r["n_ellipses"] == 0]),
        "share_at_rest": _share([r["at_rest"] for r in records]),
        "not_at_rest": sum(not r["at_rest"] for r in records),
        "max_penetration": float(worst["max_penetration"]),
        "max_penetration_scenario": worst["id"] if worst["max_penetration"] > 0 else None,
        "max_penetration_keep_in": float(max(r["max_penetration_keep_in"] for r in finished)),
        "max_penetration_obstacles": float(max(r["max_penetration_obstacles"] for r in finished)),
        "max_penetration_scope": "runs that did not stop early",
        "runs_with_penetration_over_1e-3": sum(r["max_penetration"] > 1e-3 for r in records),
        "samples": sum(r["samples"] for r in records),
        "solver_failures": sum(r["solver_failures"] for r in records),
        "truncated": sum(r["truncated"] for r in records),
        "fallbacks": sum(r["fallbacks"] for r in records),
        "fallback_kinds": {k: sum(r["fallback_kinds"][k] for r in records)
                           for k in ("fallback_shift", "fallback_steady", "fallback_safe")},
        "runs_with_fallback": sum(r["fallbacks"] > 0 for r in records),
        "runs_with_solver_failure": sum(r["solver_failures"] > 0 for r in records),
        "first_solve_failed": sum(not r["initial_feasible"] for r in records),
        "first_solve_failed_x0_feasible": sum(not r["initial_feasible"] and r["x0_in_feasible_set"] == "feasible"
                                              for r in records),
        "x0_infeasible": sum(r["x0_in_feasible_set"] == "infeasible" for r in records),
        "x0_feasibility_unknown": sum(r["x0_in_feasible_set"] == "unknown" for r in records),
        "recursive_feasibility_rate": float(sum(r["rf_kept"] for r in records) / pairs) if pairs else None,
        "recursive_feasibility_pairs": int(pairs),
        "stop_short": len(short),
        "stop_short_causes": causes,
        "stop_short_distance": _stats([r["stop_short_distance"] for r in short]),
        "stop_short_beyond_admissible": _stats([r["stop_short_beyond_admissible"] for r in short
                                                if r["stop_short_beyond_admissible"] is not None
                                                and math.isfinite(r["stop_short_beyond_admissible"])]),
        "solve_ms_max": float(max(r["solve_ms"]["max"] for r in records)),
        "solve_ms_median_of_medians": float(np.median([r["solve_ms"]["median"] for r in records])),
        "budget_exhausted": sum(r["budget_exhausted"] for r in records),
        "examples": {
            "stop_short": [r["id"] for r in short][:5],
            "stopped_early": [f"{r['id']}: {r['stopped_early']}" for r in diverged][:5],
            "crashed": [f"{r['id']}: {r['crashed']}" for r in crashed][:5],
            "not_at_rest": [r["id"] for r in records if not r["at_rest"]][:5],
            "fallback": [r["id"] for r in records if r["fallbacks"]][:5],
            "first_solve_failed": [r["id"] for r in records if not r["initial_feasible"]][:5],
            "x0_infeasible": [r["id"] for r in records if r["x0_in_feasible_set"] == "infeasible"][:5],
        },
    }


# -- files --------------------------------------------------------------------------------------

def read_jsonl(path: Path) -> dict[str, dict[str, Any]]:
    """Finished records by id; a torn last line (an interrupted write) is ignored."""
    done: dict[str, dict[str, Any]] = {}
    if not path.exists():
        return done
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and "id" in rec:
            done[rec["id"]] = rec
    return done


def _repair_tail(path: Path) -> None:
    """Cut a torn last line so that appended records start on a line of their own."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        path.write_bytes(data[: data.rfind(b"\n") + 1])


def _check_meta(out: Path, meta: dict[str, Any]) -> None:
    path = out / META_NAME
    if path.exists():
        old = json.loads(path.read_text())
        diff = sorted(k for k in meta if old.get(k) != meta[k])
        if diff:
            raise ConfigError(f"{out} holds a campaign with other {', '.join(diff)} "
                              f"({', '.join(f'{k}={old.get(k)!r}' for k in diff)}); use another --out")
    else:
        path.write_text(json.dumps(meta, indent=2))


def _run_all(todo: list[dict[str, Any]], jobs: int, max_solve_time: float | None, sink: Callable[[dict], None],
             progress: bool) -> None:
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc="campaign", unit="scenario", disable=not progress, dynamic_ncols=True)
    try:
        if jobs <= 1:
            _worker_init(max_solve_time)
            for spec in todo:
                sink(run_scenario(spec))
                bar.update()
        else:
            ctx = multiprocessing.get_context("spawn")
            with ctx.Pool(jobs, initializer=_worker_init, initargs=(max_solve_time,)) as pool:
                for rec in pool.imap_unordered(run_scenario, todo, chunksize=1):
                    sink(rec)
                    bar.update()
    finally:
        bar.close()


def _interleave(groups: Sequence[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """The families mixed in proportion (each group keeps its order), so the bar's rate is even."""
    keyed = [((i + 0.5) / len(g), gi, spec) for gi, g in enumerate(groups) for i, spec in enumerate(g)]
    return [spec for _, _, spec in sorted(keyed, key=lambda t: (t[0], t[1]))]


def build_output(out: Path, specs: Sequence[dict[str, Any]], meta: dict[str, Any], plots: bool = True
                 ) -> dict[str, Any]:
    """campaign.json (records without traces, summary per family) and plots, from the JSONL."""
    done = read_jsonl(out / JSONL_NAME)
    records = [classify(done[s["id"]]) for s in specs if s["id"] in done]
    plotted = [r for r in records if not r.get("crashed")]
    summary = {fam: summarize([r for r in records if r["family"] == fam])
               for fam in dict.fromkeys(s["family"] for s in specs)}
    result = {"meta": meta, "definitions": DEFINITIONS, "summary": summary,
              "scenarios": [{k: v for k, v in r.items() if k != "trace"} for r in records]}
    (out / JSON_NAME).write_text(json.dumps(_strict(result), indent=1, allow_nan=False))
    head = {"meta": meta, "definitions": DEFINITIONS, "summary": summary}
    (out / "summary.json").write_text(json.dumps(_strict(head), indent=2, allow_nan=False))
    if plots and plotted:
        from .campaign_plots import write_plots

        write_plots(out, plotted, {s["family"]: s["config"] for s in specs})
    return result


def _strict(value: Any) -> Any:
    """The value with NaN/inf floats replaced by None (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_strict(v) for v in value]
    return value


DEFINITIONS = {
    "best_reachable": "y*: projection of y_t onto Y_r = outputs of steady states in lambda*Z (IPOPT, tol 1e-12)",
    "reachable": f"|y* - y_t| < {REACHABLE_TOLERANCE:g}",
    "best_admissible": "y~: nearest point to y_t of Y_r whose steady state lies outside all regions (grid search)",
    "at_rest": f"state moved < {REST_TOLERANCE:g} (inf-norm) over the last {REST_WINDOW} samples",
    "converged": f"|y - y*| < {SETTLING_TOLERANCE:g} from some sample on, to the end",
    "near": f"|y_K - y*| < {NEAR_TOLERANCE:g} (y* = y_t for a reachable target)",
    "stop_short": "at rest but not converged; distance |y_K - y*|; cause obstacle_covers_target (stopped at y~ != y*), "
                  "no_passage (no admissible way to y~ exists) or local_minimum (one exists)",
    "penetration": "max over sampled states of g (keep-in: expression value, e.g. |x1 x2|-2; ellipse: 1 - r^2), 0 "
                   "if never inside",
    "solver_failure": "sample whose IPOPT status is not Solve_Succeeded / Solved_To_Acceptable_Level",
    "stopped_early": "the closed loop ended before its last sample (e.g. the plant state became non-finite); such "
                     "runs count as not converged and are left out of max_penetration",
    "fallback": "sample that applied the controller's fallback (shift, steady or safe input)",
    "x0_in_feasible_set": "x0 in X_N: the first solve was usable, or a cold probe solve with mu=0 and a 1000-iteration/"
                          "20 s budget succeeded ('infeasible' if IPOPT detected infeasibility, else 'unknown')",
    "recursive_feasibility_rate": "P(solve k usable | solve k-1 usable), usable = status ok or truncated",
}


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines of the per-family summaries."""
    lines = []
    pct = lambda v: "n/a" if v is None else f"{100 * v:.1f}%"  # noqa: E731
    for fam, s in summary.items():
        if not s.get("scenarios"):
            lines.append(f"{fam}: no scenarios")
            continue
        ss = s["stop_short_distance"]
        lines += [
            f"{fam}: {s['scenarios']} scenarios ({s['reachable_targets']} reachable targets, "
            f"{s['with_ellipses']} with ellipses, {s['target_covered_by_region']} with y* covered by a region; "
            f"stopped early {s['stopped_early']}, crashed {s['crashed']})",
            f"  converged {pct(s['share_converged'])}  near y_t/y* {pct(s['share_near'])} "
            f"(reachable {pct(s['share_near_target_reachable'])}, unreachable {pct(s['share_near_best_unreachable'])})"
            f"  near y~ {pct(s['share_near_admissible'])}  not at rest {s['not_at_rest']}",
            f"  max penetration {s['max_penetration']:.3g} (keep-in {s['max_penetration_keep_in']:.3g}, "
            f"ellipses {s['max_penetration_obstacles']:.3g}; runs > 1e-3: {s['runs_with_penetration_over_1e-3']})",
            f"  samples {s['samples']}: solver failures {s['solver_failures']} (truncated {s['truncated']}), "
            f"fallbacks {s['fallbacks']} in {s['runs_with_fallback']} runs, recursive feasibility "
            f"{pct(s['recursive_feasibility_rate'])}",
            f"  first solve failed {s['first_solve_failed']} (x0 in X_N: {s['first_solve_failed_x0_feasible']}; "
            f"x0 outside X_N {s['x0_infeasible']}, unknown {s['x0_feasibility_unknown']})",
            f"  stop short {s['stop_short']} {s['stop_short_causes']} distance median "
            f"{_fmt(ss['median'])} max {_fmt(ss['max'])}; solve max {s['solve_ms_max']:.0f} ms",
        ]
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="campaign", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="output directory (rerun with it to resume)")
    ap.add_argument("--vdp", type=int, default=500, help="number of van der Pol scenarios (default 500)")
    ap.add_argument("--robot", type=int, default=200, help="number of mobile-robot scenarios (default 200)")
    ap.add_argument("--seed", type=int, default=0, help="campaign seed (default 0)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: all cores)")
    ap.add_argument("--plant", choices=PLANTS, default="euler",
                    help="euler: the prediction model (the paper's nominal setting, default); continuous: ZOH+DOP853")
    ap.add_argument("--vdp-steps", type=int, default=80, help="samples per van der Pol run (default 80 = 40 s)")
    ap.add_argument("--robot-steps", type=int, default=140, help="samples per robot run (default 140 = 35 s)")
    ap.add_argument("--vdp-config", type=Path, help="van der Pol params file (default: the shipped one)")
    ap.add_argument("--robot-config", type=Path, help="mobile-robot params file (default: the shipped one)")
    ap.add_argument("--max-solve-time", type=float,
                    help="override the configs' solver wall-time budget, s (default: keep the configs' values)")
    ap.add_argument("--stop-after", type=int, help=argparse.SUPPRESS)  # testing: run at most this many new ones
    ap.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if min(args.vdp, args.robot) < 0 or min(args.jobs, args.vdp_steps, args.robot_steps) < 1:
        print("campaign: error: --vdp/--robot must be >= 0, --jobs and the steps >= 1", file=sys.stderr)
        return 2
    started = time.perf_counter()
    try:
        fams = families(args.vdp_config, args.robot_config, args.vdp_steps, args.robot_steps)
        groups = []
        for fam, count in ((fams["vdp"], args.vdp), (fams["robot"], args.robot)):
            settings = load_settings(fam.config, args.max_solve_time)
            groups.append(make_specs(fam, count, args.seed, settings, args.plant))
        meta = {"seed": args.seed, "plant": args.plant, "max_solve_time": args.max_solve_time,
                "configs": {f.key: str(f.config) for f in fams.values()},
                "steps": {f.key: f.steps for f in fams.values()}}
        args.out.mkdir(parents=True, exist_ok=True)
        _check_meta(args.out, meta)
    except (NmpcError, OSError) as exc:
        print(f"campaign: error: {exc}", file=sys.stderr)
        return 2
    specs = [s for g in groups for s in g]
    jsonl = args.out / JSONL_NAME
    _repair_tail(jsonl)
    done = read_jsonl(jsonl)
    todo = [s for s in _interleave(groups) if s["id"] not in done]
    if args.stop_after is not None:
        todo = todo[: args.stop_after]
    print(f"campaign: {len(specs) - len(todo)} of {len(specs)} scenarios already done, {len(todo)} to run "
          f"with {min(args.jobs, max(1, len(todo)))} job(s) -> {args.out}", flush=True)
    with jsonl.open("a") as sink_file:
        def sink(record: dict[str, Any]) -> None:
            sink_file.write(json.dumps(record) + "\n")
            sink_file.flush()

        try:
            if todo:
                _run_all(todo, min(args.jobs, len(todo)), args.max_solve_time, sink, not args.no_progress)
        except KeyboardInterrupt:
            print("campaign: interrupted; rerun with the same --out to resume", file=sys.stderr)
            return 130
    result = build_output(args.out, specs, meta, plots=not args.no_plots)
    print(format_summary(result["summary"]))
    missing = len(specs) - len(result["scenarios"])
    print(f"campaign: {len(result['scenarios'])} scenarios in {args.out / JSON_NAME}"
          f"{f' ({missing} still to run)' if missing else ''}; this invocation took "
          f"{time.perf_counter() - started:.0f} s")
    return 0
