"""Runs read back from bags: the controller's samples, the regions over time, metrics.

The controller publishes one diagnostic per solved sample carrying the state it solved on, the
command, y_a and the solve time (all as exact float reprs), so a bag holds everything needed to
re-plot, score and re-solve a run without a ROS graph.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.loop.alarm import ALARM_DEPTH
from ..core.loop.intersample import clearance_between_samples
from ..core.loop.metrics import max_abs_product, outputs, penetration, region_values, time_stats, tracking
from ..core.problem.models import make_model
from ..core.problem.regions import Region
from ..core.sample.status import StepStatus
from .mcap_io import Bag, BagError, load_bag


@dataclass
class RecordedRun:
    """The solved samples of one controller in a bag.

    Attributes: t [K] s since the first sample (times - times[0]); x [K, n] states solved on; u [K, m] commands;
    y_a [K, p]; targets [K, p] (in force at each sample); regions [K] (tuples of core regions in
    force at each sample, moving ones with their velocity and stamp); solve_ms [K]; status [K];
    last diagnostic counters; final state [n] (the state after the last sample, if recorded);
    times [K]: clock time (s, the clock of the marker stamps) at which each state was valid, so
    that a moving region is evaluated where it was then (`regions_at`).
    """

    path: Path
    finished: bool
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    y_a: np.ndarray
    targets: np.ndarray
    regions: list[tuple[Region, ...]]
    solve_ms: np.ndarray
    status: list[str]
    counters: dict[str, int] = field(default_factory=dict)
    final_state: np.ndarray | None = None
    sample_time: float = math.nan
    times: np.ndarray | None = None
    #: the controller's stability certificate per sample (CERTIFICATE_KEYS -> [K], nan where the
    #: diagnostics lack it) and `violated` [K] bool; empty for bags of controllers without it
    certificate: dict[str, np.ndarray] = field(default_factory=dict)
    #: the run-time settings the diagnostics report per sample (RECORDED_PARAMETERS -> [K])
    parameters: dict[str, np.ndarray] = field(default_factory=dict)
    #: the plan's cost terms per sample (COST_KEYS -> [K], 6 significant digits as the diagnostics carry them)
    costs: dict[str, np.ndarray] = field(default_factory=dict)
    #: the honest status's depths per sample (core/loop/alarm.py: state_depth, plan_depth -> [K]); empty for
    #: bags of controllers without it
    depths: dict[str, np.ndarray] = field(default_factory=dict)
    #: the fully qualified name of the controller whose samples these are (its diagnostics' hardware_id)
    controller_node: str | None = None

    @property
    def states_with_final(self) -> np.ndarray:
        return self.x if self.final_state is None else np.vstack([self.x, self.final_state])

    def regions_at(self, k: int, sample_time: float | None = None) -> tuple[Region, ...]:
        """The regions of sample k (k = K: the final state, one sample time later), moving ones moved to its time."""
        regions = self.regions[min(k, len(self.regions) - 1)]
        if self.times is None or not any(r.moving for r in regions):
            return regions
        ts = self.sample_time if sample_time is None else sample_time
        t = self.times[k] if k < len(self.times) else self.times[-1] + (k - len(self.times) + 1) * ts
        return tuple(r.at(t) if r.moving else r for r in regions)


#: the cost terms of the applied plan in the controller's diagnostics
COST_KEYS = ("offset_cost", "avoidance_cost", "tracking_cost")
#: run-time settings whose value in force the controller's diagnostics carry at every sample
RECORDED_PARAMETERS = ("mu", "kappa")
#: diagnostic keys of the certificate (nodes/controller.py)
CERTIFICATE_KEYS = ("value_function", "decrease", "decrease_bound", "certificate_margin")


def _certificate(samples: list[dict[str, str]]) -> dict[str, np.ndarray]:
    if not any("value_function" in v for v in samples):
        return {}
    out = {key: np.array([float(v.get(key, "nan")) for v in samples]) for key in CERTIFICATE_KEYS}
    out["violated"] = np.array([v.get("certificate", "").startswith("violated") for v in samples])
    return out


def _topic(bag: Bag, suffix: str) -> str | None:
    """The bag's topic named `suffix` (relative names may carry a namespace): /state, /robot1/state."""
    for name in sorted(bag.topics):
        if name == f"/{suffix}" or name.endswith(f"/{suffix}"):
            return name
    return None


def _statuses(path: str | Path, samples: list[tuple[int, dict[str, str]]]) -> list[StepStatus]:
    """The samples' statuses; BagError naming the first one that is no `StepStatus`."""
    try:
        return [StepStatus(v["status"]) for _, v in samples]
    except ValueError as exc:
        raise BagError(f"{path}: a controller sample has an unknown status ({exc}; known: "
                       f"{', '.join(StepStatus)})") from None


def _float_list(text: str) -> list[float]:
    """A diagnostic's list of floats; Python's repr writes NaN (a sample without a plan) as nan."""
    return json.loads(text.replace("nan", "NaN").replace("inf", "Infinity"))


def controller_samples(bag: Bag) -> tuple[list[tuple[int, dict[str, str]]], str | None]:
    """The solved samples in the bag's /diagnostics ([(log time ns, {key: value})]) and the name of the
    controller that reported the first one (None: no sample, or no name)."""
    samples: list[tuple[int, dict[str, str]]] = []
    name = None
    for stamp, msg in bag.topics.get("/diagnostics", []):
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if "solve_time_ms" in values and "state" in values:
                samples.append((stamp, values))
                name = name or status.hardware_id or None
    return samples, name


def load_run(path: str | Path, progress: bool = False, settings: ControllerSettings | None = None,
             bag: Bag | None = None) -> RecordedRun:
    """Read a bag into a RecordedRun; BagError if it holds no solved controller sample.

    `settings`: the controller's, for the obstacle speed and stamp limits its region store applied.
    `bag`: the bag at `path` already read (load_bag), so it is not read twice.
    """
    from ..ros.markers import RegionStore  # duck-typed on decoded messages

    bag = bag if bag is not None else load_bag(path, progress_every=20000 if progress else 0)
    samples, controller_node = controller_samples(bag)
    if not samples:
        raise BagError(f"{path}: no controller samples (no /diagnostics with solve results); "
                       f"topics: {', '.join(sorted(bag.topics)) or 'none'}")
    events: list[tuple[int, int, str, Any]] = []
    for order, suffix in enumerate(("target", "obstacles")):
        name = _topic(bag, suffix)
        for stamp, msg in bag.topics.get(name, []) if name else []:
            events.append((stamp, order, suffix, msg))
    events.sort(key=lambda e: (e[0], e[1]))
    limits = settings or ControllerSettings()
    store = RegionStore(max_markers_per_message=10**6, max_speed=limits.max_obstacle_speed,
                        max_stamp_skew=limits.max_obstacle_stamp_skew)
    target: list[float] | None = None
    targets, regions = [], []
    cursor = 0
    for stamp, _ in samples:
        while cursor < len(events) and events[cursor][0] <= stamp:
            _, _, kind, msg = events[cursor]
            if kind == "target":
                target = [float(v) for v in msg.data]
            else:
                store.apply(msg, events[cursor][0] * 1e-9)
            cursor += 1
        targets.append(target if target is not None else [math.nan])
        regions.append(store.active(stamp * 1e-9))
    state_topic = _topic(bag, "state")
    final_state = None
    if state_topic and bag.topics.get(state_topic):
        # the state after the last sample: the next different state message after the one solved on
        # (log times cannot order them: the plant may answer a command before its diagnostic lands)
        recorded = [np.array([float(v) for v in msg.data]) for _, msg in bag.topics[state_topic]]
        last = np.array(json.loads(samples[-1][1]["state"]))
        hits = [i for i, x in enumerate(recorded) if x.shape == last.shape and np.array_equal(x, last)]
        later = [x for x in recorded[hits[-1] + 1:] if not np.array_equal(x, last)] if hits else []
        final_state = later[0] if later else None
    # the controller's own time of each state; older bags: the diagnostic's log time
    times = np.array([float(v["state_time"]) if "state_time" in v else stamp * 1e-9 for stamp, v in samples])
    # t from the states' times: a diagnostic is logged a solve after its state and, in lockstep on
    # simulated time, may already carry the next /clock tick (t went 0, 0.25, 0.75, 1.0, ...)
    t = times - times[0]
    width = max(len(v) for v in targets)
    return RecordedRun(
        path=Path(path), finished=bag.finished, t=t,
        x=np.array([json.loads(v["state"]) for _, v in samples]),
        u=np.array([json.loads(v["command"]) for _, v in samples]),
        y_a=np.array([_float_list(v["y_a"]) for _, v in samples]),
        targets=np.array([v + [math.nan] * (width - len(v)) for v in targets]),
        regions=regions,
        solve_ms=np.array([float(v["solve_time_ms"]) for _, v in samples]),
        status=_statuses(path, samples),
        counters={k: int(samples[-1][1][k]) for k in ("fallbacks", "rejected_inputs", "deadline_overruns", "stale",
                                                       "samples", "certificate_violations") if k in samples[-1][1]},
        final_state=final_state,
        sample_time=float(np.median(np.diff(t))) if len(t) > 1 else math.nan,
        times=times,
        certificate=_certificate([v for _, v in samples]),
        parameters={key: np.array([float(v[key]) for _, v in samples]) for key in RECORDED_PARAMETERS
                    if all(key in v for _, v in samples)},
        costs={key: np.array([float(v.get(key, "nan")) for _, v in samples]) for key in COST_KEYS},
        depths={key: np.array([float(v[key]) for _, v in samples]) for key in ("state_depth", "plan_depth")
                if all(key in v for _, v in samples)},
        controller_node=controller_node,
    )


def run_metrics(run: RecordedRun, settings: ControllerSettings) -> dict[str, Any]:
    """Settling, overshoot, final error, penetration/clearance, solve-time statistics, counters
    (definitions: core/loop/metrics.py)."""
    model = make_model(settings.model)
    xs = run.states_with_final
    y = outputs(model, xs, run.u)
    target = run.targets[-1]
    metrics: dict[str, Any] = {"bag": str(run.path), "finished": run.finished, "samples": len(run.x),
                               "target": target.tolist()}
    if np.all(np.isfinite(target)):
        metrics.update(tracking(y, target, settings.sample_time))
    # moving regions where they were at each state's time (the final state one sample later)
    pen = penetration(settings, model, xs, run.u, [run.regions_at(k, settings.sample_time) for k in range(len(xs))], y)
    for key in ("max_penetration", "min_clearance", "max_penetration_keep_in", "max_penetration_obstacles",
                "min_clearance_obstacles"):
        metrics[key] = pen[key]
    # the continuous motion under each recorded command, 10 points per sample (core/loop/intersample.py)
    between = clearance_between_samples(settings, model, xs, run.u, run.regions, run.times)
    metrics["between_samples"] = {key: between[key] for key in ("max_penetration", "min_clearance",
                                                                 "min_clearance_obstacles")}
    # samples the controller itself reported inside a region or planning to enter one (WARN)
    metrics["alarm_samples"] = (int(np.sum((run.depths["state_depth"] > ALARM_DEPTH)
                                           | (run.depths["plan_depth"] > ALARM_DEPTH))) if run.depths else None)
    if model.n >= 2:
        metrics["max_abs_x1x2"] = max_abs_product(xs)
    metrics["solve_ms"] = time_stats(run.solve_ms)
    metrics["deadline_overruns"] = int(np.sum(run.solve_ms > settings.sample_time * 1e3))
    metrics["fallbacks"] = sum(StepStatus(s).is_fallback for s in run.status)
    metrics["rejected_inputs"] = run.counters.get("rejected_inputs", 0)
    metrics["stale_samples"] = run.counters.get("stale", 0)
    cert = run.certificate
    # None: the bag's controller did not report the certificate
    metrics["certificate_violations"] = int(np.sum(cert["violated"])) if cert else None
    metrics["certificate_checked"] = int(np.sum(np.isfinite(cert["decrease"]))) if cert else None
    return metrics


def union_regions(runs: Sequence[RecordedRun]) -> list[Region]:
    """Every distinct static region that was in force at some sample of some run (for drawing;
    moving ones are drawn as snapshots, see `moving_snapshots`)."""
    seen: list[Region] = []
    for run in runs:
        for regions in run.regions:
            for r in regions:
                if not r.moving and r not in seen:
                    seen.append(r)
    return seen


def moving_snapshots(run: RecordedRun, settings: ControllerSettings, count: int = 5
                     ) -> list[tuple[float, np.ndarray, tuple[Region, ...]]]:
    """(t s since the first sample, state [n], moving regions there) at `count` evenly spread samples
    and at the closest approach to a moving region (with the samples 4 before and after it)."""
    states = run.states_with_final
    ts = settings.sample_time
    moving = [tuple(r for r in run.regions_at(k, ts) if r.moving) for k in range(len(states))]
    y = outputs(make_model(settings.model), states, run.u)
    worst = region_values(settings, states, y, moving)
    picks = {int(round(i)) for i in np.linspace(0, len(states) - 1, count)}
    if np.any(np.isfinite(worst)):
        closest = int(np.argmax(worst))
        picks |= {k for k in (closest - 4, closest, closest + 4) if 0 <= k < len(states)}
    out = []
    for k in sorted(picks):
        if moving[k]:
            t = run.t[k] if k < len(run.t) else run.t[-1] + ts
            out.append((float(t), states[k], moving[k]))
    return out
