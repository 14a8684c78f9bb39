"""Plants and the one offline closed-loop driver.

Two plants: the prediction model itself (the paper's Euler map), and the continuous dynamics
integrated accurately (scipy DOP853, rtol 1e-10) under zero-order hold of the command.

The driver (`ClosedLoop`, `drive`) runs any `Stepper` -- something whose `step(x, y_t, regions)`
returns an outcome with `u`, `solve_time` and `iterations` -- against a plant: NmpcController
itself, the benchmark's peers (Opti + IPOPT, do-mpc), anything else. `simulate`, `bench`,
`campaign` and the tests all drive their loops through it; `run_closed_loop` is the
controller-specific wrapper that also collects the controller's diagnostics.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from scipy.integrate import solve_ivp

from ..config.settings import ControllerSettings
from ..errors import ConfigError
from ..nlp.search import SearchReport
from ..problem.models import Model
from ..problem.regions import Region
from ..sample.controller import NmpcController
from ..sample.step_result import StepResult
from .certificate import StabilityCertificate
from .metrics import SETTLING_TOLERANCE, max_abs_product, settling_step

#: the metrics' old home: kept importable from here for existing callers
__all__ = ["PLANTS", "SETTLING_TOLERANCE", "ClosedLoop", "ClosedLoopRun", "ContinuousPlant", "DiscretePlant",
           "PLANT_INTEGRATIONS", "Plant", "StepOutcome", "Stepper", "Trajectory", "drive", "integration_plant",
           "make_plant", "max_abs_product", "run_closed_loop", "settling_step"]

PLANTS = ("euler", "continuous")
#: the plant node's `integration` values (nodes/plant.py): continuous ZOH, or one discrete step per sample
PLANT_INTEGRATIONS = ("continuous", "euler", "rk4")


class ContinuousPlant:
    """x' = f(x, u) integrated under zero-order hold; `advance(x, u, dt)` -> x after dt seconds."""

    def __init__(self, model: Model, rtol: float = 1e-10, atol: float = 1e-12) -> None:
        if model.discrete_map is not None:
            raise ConfigError(f"model {model.name} is a discrete map over {model.map_sample_time} s: there is no "
                              f"continuous plant to integrate; simulate its map (plant euler, integration euler)")
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

    def __init__(self, model: Model, sample_time: float, method: str = "euler", steps: int = 1) -> None:
        self._f = model.discrete(sample_time, method, steps)
        self.sample_time = sample_time

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        if not math.isclose(dt, self.sample_time):
            raise ValueError(f"the discrete plant advances by its sample time {self.sample_time}, not {dt}")
        return np.asarray(self._f(x, u)).ravel()


class DelayedPlant:
    """A plant whose commands act `delay` s after the state they answer: over each sample the previous
    command holds for `delay`, the new one for the rest (the real-time loop's latency, offline). Until the
    first command acts the plant holds its state (the plant node's `hold_until_command`). `dense` (s, 0:
    off) records the state every `dense` s in `path`, at `times` (s since the first advance), so that what
    happens between the samples is seen."""

    def __init__(self, plant: Plant, delay: float, dense: float = 0.0) -> None:
        self.plant, self.delay, self.dense = plant, delay, dense
        self.previous: np.ndarray | None = None
        self.path: list[np.ndarray] = []
        self.times: list[float] = []
        self.t = 0.0

    def _hold(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        pieces = max(1, math.ceil(dt / self.dense - 1e-9)) if self.dense > 0 else 1
        for _ in range(pieces):
            x = self.plant.advance(x, u, dt / pieces)
            self.t += dt / pieces
            if self.dense > 0:
                self.path.append(x)
                self.times.append(self.t)
        return x

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        u, wait = np.asarray(u, float), min(self.delay, dt)
        if self.previous is not None and wait > 0:
            x = self._hold(np.asarray(x, float), self.previous, wait)
        elif wait > 0:  # held before the first command: no motion
            if self.dense > 0:
                self.path.append(np.asarray(x, float))
                self.times.append(self.t)
            self.t += wait
        dt -= wait
        self.previous = u
        return self._hold(np.asarray(x, float), u, dt) if dt > 0 else np.asarray(x, float)


def make_plant(kind: str, model: Model, settings: ControllerSettings) -> Plant:
    """'euler' -> the prediction model's own discrete map (settings' discretisation); 'continuous' ->
    accurate ZOH integration."""
    if kind == "euler":
        return DiscretePlant(model, settings.sample_time, settings.discretization, settings.integration_steps)
    if kind == "continuous":
        return ContinuousPlant(model)
    raise ConfigError(f"plant must be one of {PLANTS}, got {kind!r}")


def integration_plant(integration: str, model: Model, sample_time: float) -> Plant:
    """The plant node's simulator for its `integration` parameter: 'continuous' -> ContinuousPlant,
    'euler' / 'rk4' -> one step of that method per `sample_time` (s), as nodes/plant.py runs them."""
    if integration == "continuous":
        return ContinuousPlant(model)
    if integration in PLANT_INTEGRATIONS:
        return DiscretePlant(model, sample_time, integration)
    raise ConfigError(f"plant integration must be one of {PLANT_INTEGRATIONS}, got {integration!r}")


class Plant(Protocol):
    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """State [n] after holding u [m] for dt s from x [n]."""
        ...


class StepOutcome(Protocol):
    """What the driver reads of a stepper's answer (NmpcController's StepResult, bench's Sample)."""

    u: np.ndarray  # command to apply [m]
    solve_time: float  # s
    iterations: int


class Stepper(Protocol):
    """A controller in the loop (NmpcController, a benchmark peer): built once, then stepped."""

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None,
             time: float | None = None) -> StepOutcome:
        """Command for the measured state x [n] at `time` (s) and target y_t [p]; regions replace the
        current set if not None (moving ones stamped on the same clock as `time`)."""
        ...


#: the target of sample k: fixed [p], or a function of k
TargetSchedule = Sequence[float] | Callable[[int], Sequence[float]]
#: the region set of sample k; None keeps the set in force
RegionSchedule = Callable[[int], Sequence[Region] | None]


@dataclass
class Trajectory:
    """What the driver recorded over K samples.

    Attributes: x [K+1, n] the states solved on plus the state after the last sample; u [K, m];
    targets [K, p]; regions [K] the set in force at each sample; outcomes [K] the stepper's
    answers; sample_time s; stopped: why the loop ended before its last sample (None if it did
    not), in which case the trajectory ends at the last state the stepper solved on.
    """

    x: np.ndarray
    u: np.ndarray
    targets: np.ndarray
    regions: list[tuple[Region, ...]]
    outcomes: list[Any]
    sample_time: float
    stopped: str | None = None

    @property
    def solve_time(self) -> np.ndarray:
        return np.array([o.solve_time for o in self.outcomes], float)

    @property
    def iterations(self) -> np.ndarray:
        return np.array([o.iterations for o in self.outcomes], int)


class ClosedLoop:
    """One stepper against one plant, advanced one sample at a time (measure, solve, hold u for Ts).

    `advance()` lets several loops run interleaved sample by sample (the benchmark does, so that a
    burst of load hits every variant alike); `run(steps)` runs them in one go.
    """

    def __init__(self, stepper: Stepper, plant: Plant, x0: Sequence[float], target: TargetSchedule,
                 sample_time: float, regions: RegionSchedule | None = None,
                 on_step: Callable[[int, Any], None] | None = None) -> None:
        x = np.asarray(x0, float).ravel()
        if not np.all(np.isfinite(x)):
            raise ConfigError(f"x0 must be finite numbers, got {list(x0)}")
        self.stepper, self.plant, self.sample_time = stepper, plant, sample_time
        self.target, self.regions, self.on_step = target, regions, on_step
        self._xs, self._us, self._targets, self._in_force, self._outcomes = [x], [], [], [], []
        self._current: tuple[Region, ...] = ()
        self._solved = 0
        self.stopped: str | None = None

    @property
    def k(self) -> int:
        """Samples completed."""
        return len(self._us)

    @property
    def x(self) -> np.ndarray:
        return self._xs[-1]

    def advance(self) -> Any:
        """Solve on the current state and advance the plant one sample; returns the outcome."""
        k = self.k
        y_t = np.asarray(self.target(k) if callable(self.target) else self.target, float)
        new = self.regions(k) if self.regions else None
        if new is not None:
            self._current = tuple(new)
        outcome = self.stepper.step(self.x, y_t, new, time=k * self.sample_time)
        self._solved += 1
        if self.on_step:
            self.on_step(k, outcome)
        x = self.plant.advance(self.x, outcome.u, self.sample_time)
        prepare = getattr(self.stepper, "prepare", None)  # the next sample solved ahead (feedback setting)
        if prepare is not None:
            prepare()
        self._xs.append(x)
        self._us.append(np.asarray(outcome.u, float))
        self._targets.append(y_t)
        self._in_force.append(self._current)
        self._outcomes.append(outcome)
        return outcome

    def run(self, steps: int, stop_on: tuple[type[BaseException], ...] = ()) -> Trajectory:
        """Advance `steps` samples; an exception of a `stop_on` type ends the loop early (see Trajectory)."""
        if steps < 1:
            raise ConfigError(f"steps must be >= 1, got {steps}")
        for _ in range(steps):
            try:
                self.advance()
            except stop_on as exc:
                self.stopped = f"{type(exc).__name__} at sample {self._solved}: {exc}"
                break
        return self.trajectory()

    def trajectory(self) -> Trajectory:
        """The samples so far; after a stop, up to the last state the stepper solved on."""
        K = self.k if self.stopped is None else min(self.k, self._solved - 1)
        return Trajectory(np.array(self._xs[:K + 1]), np.array(self._us[:K]).reshape(K, -1),
                          np.array(self._targets[:K]).reshape(K, -1), self._in_force[:K], self._outcomes[:K],
                          self.sample_time, self.stopped)


def drive(stepper: Stepper, plant: Plant, x0: Sequence[float], target: TargetSchedule, steps: int,
          sample_time: float, regions: RegionSchedule | None = None,
          stop_on: tuple[type[BaseException], ...] = ()) -> Trajectory:
    """`steps` samples of `stepper` against `plant` (see ClosedLoop)."""
    return ClosedLoop(stepper, plant, x0, target, sample_time, regions).run(steps, stop_on)


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
    regions: list[tuple[Region, ...]] = field(default_factory=list)  # [K] the set in force at each sample
    stopped: str | None = None  # why the loop ended early (see Trajectory), None if it ran every sample
    searches: list[SearchReport] = field(default_factory=list)  # [K] StepResult.search (core/nlp/search.py)
    # [K] StepResult.predicted_violation: of the applied fallback or bounded-violation input, else NaN
    predicted_violations: list[float] = field(default_factory=list)
    certificate: list[dict] = field(default_factory=list)  # [K] CertificateSample.as_dict() per sample
    # [K] the two phases (core/sample/feedback.py): s from a sample's start to the command where its prepared plan
    # answered (0 else), s of its preparation between the samples, and what became of it ('' if none was)
    feedback_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    preparation_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    feedback: list[str] = field(default_factory=list)
    # [K, 2] with `terminal: set`: V_f of each applied plan's last state and alpha(y_a) (StepResult.terminal_cost,
    # terminal_level); NaN with the equality
    terminal: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @classmethod
    def from_trajectory(cls, run: Trajectory, info: dict | None = None) -> ClosedLoopRun:
        """The controller's view of a driven trajectory whose outcomes are StepResults."""
        res = run.outcomes
        K = len(res)
        return cls(run.x, run.u, np.array([r.y_a for r in res]).reshape(K, -1), run.targets, run.solve_time,
                   run.iterations, [r.status for r in res], [r.solver_status for r in res],
                   np.array([(r.offset_cost, r.avoidance_cost, r.tracking_cost) for r in res]).reshape(K, 3),
                   run.sample_time, dict(info or {}), run.regions, run.stopped, [r.search for r in res],
                   [r.predicted_violation for r in res], feedback_time=np.array([r.feedback_time for r in res]),
                   preparation_time=np.array([r.preparation_time for r in res]),
                   feedback=[str(r.feedback or "") for r in res],
                   terminal=np.array([(r.terminal_cost, r.terminal_level) for r in res]).reshape(K, 2))

    @property
    def command_time(self) -> np.ndarray:
        """[K] s from each sample's state to its command: the solver time less the preparation, which ran between
        the samples, after the previous command (core/sample/controller.py `step`)."""
        if len(self.preparation_time) != len(self.solve_time):  # no phases recorded: all of it before the command
            return np.asarray(self.solve_time, dtype=float)
        return np.asarray(self.solve_time, dtype=float) - self.preparation_time

    def to_json(self) -> dict:
        """The JSON layout of `simulate --json` (lists of rows, solve time in ms)."""
        return {
            "x": self.x.tolist(),
            "u": self.u.tolist(),
            "y_a": self.y_a.tolist(),
            "target": self.targets.tolist(),
            "solve_ms": (self.solve_time * 1e3).tolist(),
            "feedback_ms": (self.feedback_time * 1e3).tolist(),
            "preparation_ms": (self.preparation_time * 1e3).tolist(),
            "feedback": self.feedback,
            "iterations": self.iterations.tolist(),
            "status": self.status,
            "solver_status": self.solver_status,
            "cost": {"offset": self.costs[:, 0].tolist(), "avoidance": self.costs[:, 1].tolist(),
                     "tracking": self.costs[:, 2].tolist()},
            "sample_time": self.sample_time,
            "info": self.info,
            "certificate": self.certificate,
            "terminal": {"cost": self.terminal[:, 0].tolist(), "level": self.terminal[:, 1].tolist()},
        }


def run_closed_loop(
    controller: NmpcController,
    x0: Sequence[float],
    target: TargetSchedule,
    steps: int,
    plant: str | Plant = "euler",
    regions: RegionSchedule | None = None,
    on_step: Callable[[int, StepResult], None] | None = None,
    stop_on: tuple[type[BaseException], ...] = (),
) -> ClosedLoopRun:
    """`steps` samples of the controller against the named plant ('euler' or 'continuous', see
    make_plant) or a given `Plant` (e.g. `integration_plant`).

    `target` and `regions` may be functions of the step index (a schedule); a regions function
    returning None keeps the current set. `stop_on`: see ClosedLoop.run. Sample k happens at time
    k Ts (s): moving regions are stamped on that clock.
    Every sample is scored by the stability certificate (core/loop/certificate.py) right after its
    step: `ClosedLoopRun.certificate`.
    """
    x = np.asarray(x0, float).ravel()
    if x.size != controller.model.n or not np.all(np.isfinite(x)):
        raise ConfigError(f"x0 must be {controller.model.n} finite numbers, got {list(x0)}")
    sim = make_plant(plant, controller.model, controller.settings) if isinstance(plant, str) else plant
    certificate, certified = StabilityCertificate(controller), []

    def observe(k: int, result: StepResult) -> None:
        y_t = np.asarray(target(k) if callable(target) else target, float)
        certified.append(certificate.observe(result, y_t, k * controller.settings.sample_time).as_dict())
        if on_step:
            on_step(k, result)

    loop = ClosedLoop(controller, sim, x, target, controller.settings.sample_time, regions, observe)
    run = ClosedLoopRun.from_trajectory(loop.run(steps, stop_on),
                                        {"plant": plant if isinstance(plant, str) else type(plant).__name__,
                                         "nlp_builds": controller.nlp_builds})
    run.certificate = certified[:len(run.u)]
    return run
