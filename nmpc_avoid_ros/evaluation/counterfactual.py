"""Closed-loop counterfactual replay: a recorded run driven again through the plant model under a new tuning.

From the state of the bag's first solved sample, the one closed-loop driver (core/loop/closed_loop.py)
runs as many samples as the bag has, with the bag's timeline: the target and the regions in force
at each recorded sample, and the run-time settings the controller's diagnostics reported (mu,
kappa), except those the caller overrides. The states now react to the changed controller, unlike
`replay --resolve`, which re-solves the recorded states one by one.

Moving regions are re-stamped onto the driver's clock (sample k at k Ts): a region stamped at
recorded time s is stamped s - t_0, with t_0 the controller's time of the first sample.

The plant is the one the bag recorded (`recorded_plant`: the plant node's model, integration and
sample time, bag/node_parameters.py), so that a replay with nothing changed reproduces the bag.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..bag.analysis import RecordedRun, run_metrics
from ..bag.mcap_io import Bag
from ..bag.node_parameters import RecordedSetup, plant_sample_time
from ..core.config.settings import RUNTIME_FIELDS, SETTINGS, ControllerSettings
from ..core.errors import ConfigError
from ..core.loop.closed_loop import PLANT_INTEGRATIONS, ClosedLoopRun, Plant, integration_plant, run_closed_loop
from ..core.loop.metrics import max_abs_product, outputs, penetration, time_stats, tracking
from ..core.problem.models import make_model
from ..core.problem.regions import Region
from ..core.sample.controller import NmpcController
from ..core.sample.status import StepStatus
from .recorded_timing import RecordedTiming, TimedPlant, recorded_timing

#: the metrics compared side by side (and tabulated by a sweep), in this order
COMPARED = ("settling_step", "final_error", "max_penetration", "max_abs_x1x2", "solve_ms_median", "solve_ms_max",
            "fallbacks", "certificate_violations")


@dataclass
class PlantChoice:
    """The plant a replay drives: the plant node's `integration` (PLANT_INTEGRATIONS) of `model`, and why.

    `step`: s the plant advances per command when that is its own lockstep sample time rather than
    the controller's (None: the controller's). `timing`: a real-time plant's steps and late commands
    as recorded (evaluation/recorded_timing.py; None: every sample lasts sample_time and its command
    holds from its start). `source`: where the choice comes from (the bag, a flag, or what was
    assumed and why); `notes`: the timing, and what the replay cannot reproduce (noise).
    """

    integration: str
    model: str
    source: str
    step: float | None = None
    notes: list[str] = dataclasses.field(default_factory=list)
    timing: RecordedTiming | None = None

    def build(self, settings: ControllerSettings) -> Plant:
        """The core plant (ConfigError when its model does not fit the controller's state and input)."""
        model, ctrl = make_model(self.model), make_model(settings.model)
        if (model.n, model.m) != (ctrl.n, ctrl.m):
            raise ConfigError(f"the plant's model {model.name} (n={model.n}, m={model.m}) does not fit the "
                              f"controller's {ctrl.name} (n={ctrl.n}, m={ctrl.m})")
        plant = integration_plant(self.integration, model, self.step or settings.sample_time)
        if self.timing is not None:
            return TimedPlant(plant, self.timing)
        return plant if self.step is None else _OwnStep(plant, self.step)


class _OwnStep:
    """A lockstep plant whose sample time is not the controller's: `step` s per command whatever dt is asked."""

    def __init__(self, plant: Plant, step: float) -> None:
        self.plant, self.step = plant, step

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        return self.plant.advance(x, u, self.step)


def recorded_plant(bag: Bag, setup: RecordedSetup, settings: ControllerSettings, flag: str | None = None,
                   run: RecordedRun | None = None) -> PlantChoice:
    """The plant of the recording: `flag` (replay --plant) if given, else the plant node's parameters in the
    bag, else an assumption said out loud (a bag without them predates the recorder's parameter
    records): no /clock in the bag -> the plant ran in real time, which only its continuous
    integration can; with /clock -> lockstep, taken to be the euler plant of the lockstep demo.

    With `run`, a continuous plant that ran in real time gets the recording's timing (`with_timing`).
    """
    choice = _plant_choice(bag, setup, settings, flag)
    real_time = not (setup.plant or {}).get("lockstep", bool(bag.topics.get("/clock")))
    if run is not None and real_time and choice.integration == "continuous":
        with_timing(choice, bag, setup, run, settings)
    return choice


def with_timing(choice: PlantChoice, bag: Bag, setup: RecordedSetup, run: RecordedRun,
                settings: ControllerSettings) -> None:
    """Give `choice` the real-time plant's recorded steps and late commands, or a note why not. The
    plant's step is 1 / its publish_rate (without its parameters: the median gap of the recorded
    states' log times, rounded to a whole rate in Hz; the check against the states catches a wrong one)."""
    rate = (setup.plant or {}).get("publish_rate")
    if not isinstance(rate, int | float) or not rate > 0:
        name = next((t for t in sorted(bag.topics) if t == "/state" or t.endswith("/state")), None)
        times = np.array([t for t, _ in bag.topics.get(name, [])] if name else [], float)
        rate = round(1e9 / float(np.median(np.diff(times)))) if len(times) > 2 else 0
    if not rate:
        choice.notes.append("no recorded timing (too few recorded states): every sample lasts sample_time")
        return
    plant = integration_plant("continuous", make_model(choice.model), settings.sample_time)
    timing, line = recorded_timing(bag, run, plant, 1.0 / rate, settings.sample_time)
    choice.timing = timing
    choice.notes.append(line if timing is not None else f"no recorded timing ({line}): every sample lasts "
                                                         "sample_time")


def _plant_choice(bag: Bag, setup: RecordedSetup, settings: ControllerSettings, flag: str | None) -> PlantChoice:
    plant = setup.plant or {}
    model = str(plant.get("model", settings.model))
    if flag is not None:
        return PlantChoice(flag, model, "--plant")
    if not plant:
        clocked = bool(bag.topics.get("/clock"))
        why = ("the plant ran in lockstep (the bag has /clock), as the lockstep demo's euler plant" if clocked else
               "the plant ran in real time (no /clock in the bag), which only the continuous integration can")
        return PlantChoice("euler" if clocked else "continuous", model,
                           f"assumed: the bag records no plant parameters (recorded before the recorder kept "
                           f"them); {why}; --plant to choose")
    integration = plant.get("integration")
    if integration not in PLANT_INTEGRATIONS:
        raise ConfigError(f"the bag's plant {setup.plant_node} has integration {integration!r}, not one of "
                          f"{', '.join(PLANT_INTEGRATIONS)}: give --plant")
    step = plant_sample_time(plant, settings.sample_time) if plant.get("lockstep") else None
    choice = PlantChoice(integration, model, f"the bag's {setup.plant_node} parameters",
                         None if step is None or math.isclose(step, settings.sample_time) else step)
    noise = plant.get("process_noise_std") or 0.0
    if noise:
        choice.notes.append(f"the recorded plant added process noise (std {noise:g}); the replay has none")
    return choice


@dataclass
class Counterfactual:
    """One counterfactual run: what changed, the run, its metrics, and its distance to the recording."""

    label: str
    changes: dict[str, Any]
    run: ClosedLoopRun
    metrics: dict[str, Any]
    #: max |x_counterfactual(k) - x_recorded(k)| over the recorded states (k = 0..K, or K-1 without a final state)
    max_state_error: float


def sweepable(name: str) -> None:
    """ConfigError unless `name` is a scalar numeric run-time setting (what a sweep may vary)."""
    if name not in SETTINGS:
        raise ConfigError(f"--sweep: unknown setting {name!r}; run-time settings: {', '.join(sorted(RUNTIME_FIELDS))}")
    if name not in RUNTIME_FIELDS:
        raise ConfigError(f"--sweep: {name} is structural (it changes the NLP, a new controller per value): "
                          f"sweep a run-time setting ({', '.join(sorted(RUNTIME_FIELDS))})")
    if SETTINGS[name].kind not in ("float", "int"):
        raise ConfigError(f"--sweep: {name} is not a single number ({SETTINGS[name].kind})")


def parse_sweep(text: str) -> tuple[str, list[float]]:
    """'NAME=V1,V2,...' -> (NAME, values); ConfigError for a malformed text or a setting that cannot be swept."""
    name, sep, values = text.partition("=")
    name = name.strip()
    if not sep or not values.strip():
        raise ConfigError(f"--sweep needs NAME=V1,V2,..., got {text!r}")
    sweepable(name)
    try:
        parsed = [float(v) for v in values.split(",")]
    except ValueError:
        raise ConfigError(f"--sweep {name}: values must be numbers, got {values!r}") from None
    for value in parsed:  # checked against the setting's declaration (range, finiteness)
        SETTINGS[name].coerce(int(value) if SETTINGS[name].kind == "int" and value.is_integer() else value)
    return name, parsed


def restamped(regions: Sequence[Region], t0: float) -> tuple[Region, ...]:
    """Moving regions with their stamps moved from the recording's clock to the driver's (t0 -> 0)."""
    return tuple(dataclasses.replace(r, stamp=r.stamp - t0) if r.moving else r for r in regions)


def schedules(run: RecordedRun) -> tuple[Callable[[int], np.ndarray], Callable[[int], tuple[Region, ...] | None]]:
    """The bag's target and region timelines as the driver's schedules (regions: None when unchanged)."""
    t0 = float(run.times[0]) if run.times is not None and len(run.times) else 0.0

    def target(k: int) -> np.ndarray:
        return run.targets[k]

    def regions(k: int) -> tuple[Region, ...] | None:
        if k > 0 and run.regions[k] == run.regions[k - 1]:
            return None
        return restamped(run.regions[k], t0)

    return target, regions


class ScheduledController(NmpcController):
    """NmpcController whose run-time settings follow a per-sample schedule (applied before each step)."""

    def __init__(self, settings: ControllerSettings, schedule: Callable[[int], dict[str, Any]]) -> None:
        super().__init__(settings)
        self.schedule = schedule
        self.samples = 0

    def step(self, *args: Any, **kwargs: Any) -> Any:
        changes = {k: v for k, v in self.schedule(self.samples).items() if getattr(self.settings, k) != v}
        if changes:
            self.update_settings(**changes)
        self.samples += 1
        return super().step(*args, **kwargs)


def replay_closed_loop(run: RecordedRun, settings: ControllerSettings, plant: str | Plant | PlantChoice = "euler",
                       overrides: dict[str, Any] | None = None, label: str = "counterfactual") -> Counterfactual:
    """Drive the recorded run's timeline again from its first state under `settings` + `overrides`.

    `plant`: a core plant name (closed_loop.make_plant), a Plant, or the recording's (`recorded_plant`).

    The run-time settings the bag recorded per sample (RecordedRun.parameters) are replayed as they
    changed, except the overridden ones, which hold for the whole run.
    """
    overrides = dict(overrides or {})
    recorded = {k: v for k, v in run.parameters.items() if k not in overrides}
    base = settings.replace(**overrides, **{k: float(v[0]) for k, v in recorded.items()})

    def schedule(k: int) -> dict[str, Any]:
        return {name: float(values[min(k, len(values) - 1)]) for name, values in recorded.items()}

    controller = ScheduledController(base, schedule)
    if isinstance(plant, PlantChoice):
        plant = plant.build(base)
    target, regions = schedules(run)
    result = run_closed_loop(controller, run.x[0], target, len(run.x), plant, regions)
    reference = run.states_with_final
    count = min(len(reference), len(result.x))
    error = float(np.max(np.abs(result.x[:count] - reference[:count])))
    return Counterfactual(label, overrides, result, loop_metrics(result, base), error)


def loop_metrics(run: ClosedLoopRun, settings: ControllerSettings) -> dict[str, Any]:
    """COMPARED metrics of a driven run (definitions: core/loop/metrics.py), the target being the last one."""
    model = make_model(settings.model)
    y = outputs(model, run.x, run.u)
    target = run.targets[-1]
    out: dict[str, Any] = dict.fromkeys(COMPARED)
    if np.all(np.isfinite(target)):
        out.update({k: v for k, v in tracking(y, target, run.sample_time).items() if k in COMPARED})
    # the driver's sample k is at k Ts: a moving region counts where it was then, not at its last update
    regions_then = [tuple(r.at(k * run.sample_time) for r in run.regions[min(k, len(run.regions) - 1)])
                    for k in range(len(run.x))] if run.regions else []
    out["max_penetration"] = penetration(settings, model, run.x, run.u, regions_then, y)["max_penetration"]
    if model.name == "van_der_pol":  # the paper's energy-rate measure
        out["max_abs_x1x2"] = max_abs_product(run.x)
    stats = time_stats(run.solve_time * 1e3)
    out["solve_ms_median"], out["solve_ms_max"] = stats["median"], stats["max"]
    out["fallbacks"] = sum(StepStatus(s).is_fallback for s in run.status)
    out["certificate_violations"] = sum(bool(c["violated"]) for c in run.certificate)
    return out


def recorded_metrics(run: RecordedRun, settings: ControllerSettings) -> dict[str, Any]:
    """The same COMPARED metrics of the recording (bag/analysis.run_metrics)."""
    m = run_metrics(run, settings)
    out = {k: m.get(k) for k in COMPARED}
    if settings.model != "van_der_pol":
        out["max_abs_x1x2"] = None
    out["solve_ms_median"], out["solve_ms_max"] = m["solve_ms"]["median"], m["solve_ms"]["max"]
    return out


def metrics_table(rows: Sequence[tuple[str, dict[str, Any]]]) -> str:
    """A markdown table: one row per (label, metrics), the COMPARED columns."""
    def cell(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return "nan" if math.isnan(v) else f"{v:.4g}"
        return str(v)

    lines = ["| run | " + " | ".join(COMPARED) + " |", "|---" * (len(COMPARED) + 1) + "|"]
    lines += [f"| {label} | " + " | ".join(cell(m.get(k)) for k in COMPARED) + " |" for label, m in rows]
    return "\n".join(lines)
