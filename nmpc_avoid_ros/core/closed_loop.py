"""Plants and the offline closed loop.

Two plants: the prediction model itself (the paper's Euler map), and the continuous dynamics
integrated accurately (scipy DOP853, rtol 1e-10) under zero-order hold of the command.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from .controller import NmpcController, StepResult
from .errors import ConfigError
from .models import Model
from .regions import Region

PLANTS = ("euler", "continuous")
#: settled: |y - y_t| below this from some sample on, for good (the paper scenario's criterion)
SETTLING_TOLERANCE = 0.05


class ContinuousPlant:
    """x' = f(x, u) integrated under zero-order hold; `advance(x, u, dt)` -> x after dt seconds."""

    def __init__(self, model: Model, rtol: float = 1e-10, atol: float = 1e-12) -> None:
        self.model = model
        self._f = model.dynamics
        self.rtol, self.atol = rtol, atol

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """State [n] after holding input u [m] for dt s from x [n]."""
        u = np.asarray(u, float)
        f = self._f

        def rhs(_t: float, state: np.ndarray) -> np.ndarray:
            return np.asarray(f(state, u)).ravel()

        sol = solve_ivp(rhs, (0.0, dt), np.asarray(x, float), method="DOP853", rtol=self.rtol, atol=self.atol)
        if not sol.success:
            raise RuntimeError(f"plant integration failed: {sol.message}")
        return sol.y[:, -1]


class DiscretePlant:
    """The prediction model's own discrete map as the plant (what the paper's example simulates)."""

    def __init__(self, model: Model, sample_time: float, method: str = "euler") -> None:
        self._f = model.discrete(sample_time, method)
        self.sample_time = sample_time

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        if not math.isclose(dt, self.sample_time):
            raise ValueError(f"the discrete plant advances by its sample time {self.sample_time}, not {dt}")
        return np.asarray(self._f(x, u)).ravel()


def make_plant(kind: str, controller: NmpcController) -> ContinuousPlant | DiscretePlant:
    """'euler' -> the controller's own prediction model; 'continuous' -> accurate ZOH integration."""
    s = controller.settings
    if kind == "euler":
        return DiscretePlant(controller.model, s.sample_time, s.discretization)
    if kind == "continuous":
        return ContinuousPlant(controller.model)
    raise ConfigError(f"plant must be one of {PLANTS}, got {kind!r}")


@dataclass
class ClosedLoopRun:
    """A closed-loop run of K steps: x [K+1, n], u [K, m], y_a [K, p], per-step diagnostics."""

    x: np.ndarray
    u: np.ndarray
    y_a: np.ndarray
    targets: np.ndarray
    solve_time: np.ndarray
    iterations: np.ndarray
    status: list[str]
    solver_status: list[str]
    costs: np.ndarray  # [K, 3]: V_o, V_a, tracking
    sample_time: float
    info: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """The JSON layout of `simulate --json` (lists of rows, solve time in ms)."""
        return {
            "x": self.x.tolist(),
            "u": self.u.tolist(),
            "y_a": self.y_a.tolist(),
            "target": self.targets.tolist(),
            "solve_ms": (self.solve_time * 1e3).tolist(),
            "iterations": self.iterations.tolist(),
            "status": self.status,
            "solver_status": self.solver_status,
            "cost": {"offset": self.costs[:, 0].tolist(), "avoidance": self.costs[:, 1].tolist(),
                     "tracking": self.costs[:, 2].tolist()},
            "sample_time": self.sample_time,
            "info": self.info,
        }


def run_closed_loop(
    controller: NmpcController,
    x0: Sequence[float],
    target: Sequence[float] | Callable[[int], Sequence[float]],
    steps: int,
    plant: str = "euler",
    regions: Callable[[int], Sequence[Region] | None] | None = None,
    on_step: Callable[[int, StepResult], None] | None = None,
) -> ClosedLoopRun:
    """Run `steps` samples: measure, solve, apply u under ZOH for one sample time.

    `target` and `regions` may be functions of the step index (a schedule); a regions function
    returning None keeps the current set.
    """
    if steps < 1:
        raise ConfigError(f"steps must be >= 1, got {steps}")
    sim = make_plant(plant, controller)
    dt = controller.settings.sample_time
    model = controller.model
    x = np.asarray(x0, float).ravel()
    if x.size != model.n or not np.all(np.isfinite(x)):
        raise ConfigError(f"x0 must be {model.n} finite numbers, got {list(x0)}")
    xs = [x]
    us, yas, targets, times, iters, statuses, solver_statuses, costs = [], [], [], [], [], [], [], []
    for k in range(steps):
        y_t = np.asarray(target(k) if callable(target) else target, float)
        res = controller.step(x, y_t, regions(k) if regions else None)
        if on_step:
            on_step(k, res)
        x = sim.advance(x, res.u, dt)
        xs.append(x)
        us.append(res.u)
        yas.append(res.y_a)
        targets.append(y_t)
        times.append(res.solve_time)
        iters.append(res.iterations)
        statuses.append(res.status)
        solver_statuses.append(res.solver_status)
        costs.append((res.offset_cost, res.avoidance_cost, res.tracking_cost))
    return ClosedLoopRun(np.array(xs), np.array(us), np.array(yas), np.array(targets), np.array(times),
                         np.array(iters), statuses, solver_statuses, np.array(costs), dt,
                         {"plant": plant, "nlp_builds": controller.nlp_builds})


def settling_step(values: np.ndarray, reference: float, tolerance: float) -> int | None:
    """First index from which |values - reference| < tolerance for good (None if never)."""
    inside = np.abs(np.asarray(values, float) - reference) < tolerance
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return 0 if outside.size == 0 else int(outside[-1] + 1)


def max_abs_product(x: np.ndarray) -> float:
    """max |x1 x2| over a state trajectory [K, n] (the paper's energy-rate measure)."""
    return float(np.max(np.abs(x[:, 0] * x[:, 1])))


