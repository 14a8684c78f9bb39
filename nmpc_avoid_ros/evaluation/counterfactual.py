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
from ..core.problem.models import Model, make_model, parse_model_parameters
from ..core.problem.regions import Region
from ..core.sample.controller import NmpcController
from ..core.sample.status import StepStatus
from .recorded_latency import RecordedLatency
from .recorded_timing import RecordedTiming, TimedPlant, recorded_timing

#: m.s.: an unchanged replay reproduces the recorded states this closely, or says where and why not (measured:
#: see docs/usage.md, 'replay'; the plant's timing alone reproduces them to TIMING_TOLERANCE)
REPLAY_BOUND = 1e-6
#: m.s.: a replay state this far from the recorded one has begun to part from it (the timing alone: <= 3e-9)
DRIFT = 1e-8
#: the metrics compared side by side (and tabulated by a sweep), in this order
COMPARED = ("settling_step", "final_error", "max_penetration", "max_abs_x1x2", "solve_ms_median", "solve_ms_max",
            "fallbacks", "certificate_violations")


@dataclass
class PlantChoice:
    """The plant a replay drives: the plant node's `integration` (PLANT_INTEGRATIONS) of `model`, and why.

    `step`: s the plant advances per command when that is its own lockstep sample time rather than
    the controller's (None: the controller's). `timing`: a real-time plant's periods and command arrivals
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
    #: the recorded plant ran in real time (its timer), not in lockstep
    real_time: bool = False
    #: the recorded timing in one line (`timing` set), or why it could not be recovered (None: not asked)
    timing_note: str | None = None
    #: the plant's model_parameters ('name=value'), as recorded (else the controller's)
    model_parameters: tuple[str, ...] = ()

    def make_model(self) -> Model:
        return make_model(self.model, parse_model_parameters(self.model_parameters))

    def build(self, settings: ControllerSettings) -> Plant:
        """The core plant (ConfigError when its model does not fit the controller's state and input)."""
        model, ctrl = self.make_model(), settings.build_model()
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
    choice.real_time = real_time
    if run is not None and real_time and choice.integration == "continuous":
        with_timing(choice, bag, setup, run, settings)
    return choice


def with_timing(choice: PlantChoice, bag: Bag, setup: RecordedSetup, run: RecordedRun,
                settings: ControllerSettings) -> None:
    """Give `choice` the real-time plant's recorded periods and command arrivals, or a note why not. The
    plant's step is 1 / its publish_rate (without its parameters: the median gap of the recorded
    states' log times, rounded to a whole rate in Hz; the check against the states catches a wrong one)."""
    rate = (setup.plant or {}).get("publish_rate")
    if not isinstance(rate, int | float) or not rate > 0:
        name = next((t for t in sorted(bag.topics) if t == "/state" or t.endswith("/state")), None)
        times = np.array([t for t, _ in bag.topics.get(name, [])] if name else [], float)
        rate = round(1e9 / float(np.median(np.diff(times)))) if len(times) > 2 else 0
    if not rate:
        choice.timing_note = "too few recorded states to tell the plant's period"
        return
    noise = (setup.plant or {}).get("process_noise_std") or 0.0
    if noise:
        choice.timing_note = (f"the plant added process noise (std {noise:g}) to every step: the recorded states "
                              "follow from no command timing")
        return
    plant = integration_plant("continuous", choice.make_model(), settings.sample_time)
    held = bool((setup.plant or {}).get("hold_until_command", True))
    timing, line = recorded_timing(bag, run, plant, 1.0 / rate, settings.sample_time, held)
    choice.timing = timing
    choice.timing_note = line


def _plant_choice(bag: Bag, setup: RecordedSetup, settings: ControllerSettings, flag: str | None) -> PlantChoice:
    choice = _plant_integration(bag, setup, settings, flag)
    recorded = (setup.plant or {}).get("model_parameters")
    choice.model_parameters = tuple(recorded or (() if setup.plant else settings.model_parameters))
    return choice


def _plant_integration(bag: Bag, setup: RecordedSetup, settings: ControllerSettings, flag: str | None) -> PlantChoice:
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
    #: the first state beyond REPLAY_BOUND and the sample before it, recorded and replayed (None: none beyond)
    first_beyond: dict[str, Any] | None = None

    def verdict(self) -> str:
        """One line: within the bound, or where the replay left it and what that sample did in both runs."""
        if self.first_beyond is None:
            return f"max |x - x_recorded| {self.max_state_error:.3g} (within the bound {REPLAY_BOUND:g})"
        f = self.first_beyond
        solve = (f"; solve {f['recorded_solve_ms']:.3g} ms recorded, {f['replayed_solve_ms']:.3g} ms replayed"
                 if f["recorded_solve_ms"] is not None and f["replayed_solve_ms"] is not None else "")
        command = (f"; its command differs by {f['command_difference']:.3g}" if f["command_difference"] is not None
                   else "")
        drift = ("" if f["drift_sample"] == f["sample"] else
                 f"; it began to part ({f['drift']:.3g}) after sample {f['drift_sample']}, "
                 f"{f['drift_recorded_status']} recorded, {f['drift_replayed_status']} replayed")
        inexact = {f["drift_recorded_status"], f["recorded_status"]} & {"truncated", "unconverged"}
        why = (" (a solve cut by its wall-clock budget (truncated) or stopped short (unconverged) is not repeated "
               "exactly offline)" if inexact else " (the replay's timing or latency is not the recording's)")
        return (f"max |x - x_recorded| {self.max_state_error:.3g}, beyond the bound {REPLAY_BOUND:g} from state "
                f"{f['state']} ({f['deviation']:.3g}): sample {f['sample']} {f['recorded_status']} recorded, "
                f"{f['replayed_status']} replayed{command}{solve}{drift}{why}")


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
    """NmpcController whose run-time settings follow a per-sample schedule (applied before each step) and, with
    `latency` (evaluation/recorded_latency.py), stepped as the recording's node stepped it: with the latency
    each sample predicted, at the recorded state times, told when each command left (`command_sent`); the
    command in force is the controller's own last one (the replay's previously applied command)."""

    def __init__(self, settings: ControllerSettings, schedule: Callable[[int], dict[str, Any]],
                 latency: RecordedLatency | None = None) -> None:
        super().__init__(settings)
        self.schedule = schedule
        self.recorded = latency
        self.samples = 0

    def step(self, x: Any, y_t: Any, regions: Any = None, time: float | None = None, **kwargs: Any) -> Any:
        k = self.samples
        changes = {name: v for name, v in self.schedule(k).items() if getattr(self.settings, name) != v}
        if changes:
            self.update_settings(**changes)
        self.samples += 1
        rec = self.recorded
        if rec is None or k >= len(rec.latency):
            return super().step(x, y_t, regions, time, **kwargs)
        if rec.times is not None:
            time = rec.times[k]
        kwargs.setdefault("latency", rec.latency[k])
        result = super().step(x, y_t, regions, time, **kwargs)
        if rec.sent is not None:
            self.command_sent(rec.sent[k])
        return result


def replay_closed_loop(run: RecordedRun, settings: ControllerSettings, plant: str | Plant | PlantChoice = "euler",
                       overrides: dict[str, Any] | None = None, label: str = "counterfactual",
                       latency: RecordedLatency | None = None) -> Counterfactual:
    """Drive the recorded run's timeline again from its first state under `settings` + `overrides`.

    `plant`: a core plant name (closed_loop.make_plant), a Plant, or the recording's (`recorded_plant`).
    `latency`: the recorded samples' latency and times (evaluation/recorded_latency.py; None: none, sample k
    at k Ts).

    The run-time settings the bag recorded per sample (RecordedRun.parameters) are replayed as they
    changed, except the overridden ones, which hold for the whole run.
    """
    overrides = dict(overrides or {})
    recorded = {k: v for k, v in run.parameters.items() if k not in overrides}
    base = settings.replace(**overrides, **{k: float(v[0]) for k, v in recorded.items()})

    def schedule(k: int) -> dict[str, Any]:
        return {name: float(values[min(k, len(values) - 1)]) for name, values in recorded.items()}

    controller = ScheduledController(base, schedule, latency)
    if isinstance(plant, PlantChoice):
        plant = plant.build(base)
    target, regions = schedules(run)
    result = run_closed_loop(controller, run.x[0], target, len(run.x), plant, regions)
    reference = run.states_with_final
    count = min(len(reference), len(result.x))
    deviation = np.max(np.abs(result.x[:count] - reference[:count]), axis=1)
    error = float(np.max(deviation))
    beyond = np.flatnonzero(deviation > REPLAY_BOUND)
    first = None
    if beyond.size:
        k = int(beyond[0])  # the state after sample k - 1: that sample's solve or timing differs
        j = max(k - 1, 0)
        drift = int(np.flatnonzero(deviation > DRIFT)[0])  # where the replay began to part from the recording
        first = {"state": k, "deviation": float(deviation[k]), "sample": j,
                 "drift_sample": max(drift - 1, 0), "drift": float(deviation[drift]),
                 "drift_recorded_status": str(run.status[max(drift - 1, 0)]),
                 "drift_replayed_status": str(result.status[max(drift - 1, 0)]),
                 "recorded_status": str(run.status[j]) if j < len(run.status) else None,
                 "replayed_status": str(result.status[j]) if j < len(result.status) else None,
                 "recorded_solve_ms": float(run.solve_ms[j]) if j < len(run.solve_ms) else None,
                 "replayed_solve_ms": float(result.solve_time[j] * 1e3) if j < len(result.solve_time) else None,
                 "command_difference": (float(np.max(np.abs(result.u[j] - run.u[j])))
                                        if j < min(len(result.u), len(run.u)) else None)}
    return Counterfactual(label, overrides, result, loop_metrics(result, base), error, first)


def loop_metrics(run: ClosedLoopRun, settings: ControllerSettings) -> dict[str, Any]:
    """COMPARED metrics of a driven run (definitions: core/loop/metrics.py), the target being the last one."""
    model = settings.build_model()
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
