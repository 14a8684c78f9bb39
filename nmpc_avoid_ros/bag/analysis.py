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
from ..core.loop.intersample import dense_run
from ..core.loop.metrics import max_abs_product, outputs, penetration, region_values, time_stats
from ..core.problem.regions import Region
from ..core.sample.status import StepStatus
from .distance import nearest_region_distance
from .mcap_io import Bag, BagError, load_bag
from .node_parameters import node_parameters
from .segments import segment_metrics
from .timeline import Interface, TargetEvent, controller_interface, regions_at, target_events, targets_at, topic_named


@dataclass
class RecordedRun:
    """The solved samples of one controller in a bag.

    Attributes: t [K] s since the first sample (times - times[0]); x [K, n] states solved on; u [K, m] commands;
    y_a [K, p]; targets [K, p] (the accepted target in force at each sample, nan before any); regions [K]
    (tuples of core regions in force at each sample, moving ones with their velocity and stamp); solve_ms [K];
    status [K]; last diagnostic counters; final state [n] (the state after the last sample, if recorded);
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
    #: log time (ns, the recorder's clock) of each sample's diagnostic [K]
    log_times_ns: np.ndarray | None = None
    #: every target message, accepted or refused as the controller would (bag/timeline.py)
    target_events: list[TargetEvent] = field(default_factory=list)
    #: the controller's interface (array or robot) and where that was read
    interface: Interface = field(default_factory=Interface)
    #: s each sample's command acted after its state (diagnostics `predicted_delay_ms`: a latency-compensated
    #: controller); None: at once (older bags)
    delays: np.ndarray | None = None
    #: the two phases per sample (core/sample/feedback.py; diagnostics `feedback`, `feedback_ms`, `preparation_ms`):
    #: what became of the prepared plan ('' none), ms to the command where it answered, ms of its preparation;
    #: empty for bags of controllers without them
    phases: dict[str, np.ndarray] = field(default_factory=dict)

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
    out["violated"] = np.array([_violated(v) for v in samples])
    return out


def _violated(values: dict[str, str]) -> bool:
    """The certificate's verdict of one sample: `certificate_verdict`; bags from before it carry only the
    rendered `certificate` line, whose first word is the verdict."""
    if "certificate_verdict" in values:
        return values["certificate_verdict"] == "violated"
    return values.get("certificate", "").split(";")[0] == "violated"


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

    `settings`: the controller's, for its model and for the obstacle capacities, speed and stamp
    limits its region store applied (default: ControllerSettings()). `bag`: the bag at `path` already
    read (load_bag), so it is not read twice. The targets are those the controller accepted: each sample's
    own `target` value where recorded, else by log time (bag/timeline.py; p from the samples' y_a); the
    interface comes from the controller's recorded parameters (else inferred from the topics).
    """
    bag = bag if bag is not None else load_bag(path, progress_every=20000 if progress else 0)
    samples, controller_node = controller_samples(bag)
    if not samples:
        raise BagError(f"{path}: no controller samples (no /diagnostics with solve results); "
                       f"topics: {', '.join(sorted(bag.topics)) or 'none'}")
    settings = settings or ControllerSettings()
    y_a = [_float_list(v["y_a"]) for _, v in samples]
    p = len(y_a[0]) or settings.build_model().p
    interface = controller_interface(bag, node_parameters(bag)[0].get(controller_node or ""))
    # a model with an angle output (unicycle_pose) takes the goal's heading too (nodes/controller_io.py)
    events = target_events(bag, p, interface, controller_node, bool(settings.build_model().angle_outputs))
    stamps = [stamp for stamp, _ in samples]
    targets = targets_at(events, stamps, p)
    # the controller names the y_t each sample solved for: the recorder's log times cannot order a target
    # from `send` against the first diagnostic that used it (two publishers); older bags: the log times
    said = [_float_list(v["target"]) if v.get("target") else None for _, v in samples]
    for k, value in enumerate(said):
        if value is not None and len(value) == p:
            targets[k] = value
    regions = regions_at(bag, settings, interface, stamps, controller_node)
    state_topic = topic_named(bag, "state", controller_node)
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
    return RecordedRun(
        path=Path(path), finished=bag.finished, t=t,
        x=np.array([json.loads(v["state"]) for _, v in samples]),
        u=np.array([json.loads(v["command"]) for _, v in samples]),
        y_a=np.array(y_a),
        targets=targets,
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
        log_times_ns=np.array(stamps, dtype=np.int64),
        target_events=events,
        interface=interface,
        delays=(np.array([float(v["predicted_delay_ms"]) * 1e-3 for _, v in samples])
                if all("predicted_delay_ms" in v for _, v in samples) else None),
        phases=({"feedback": np.array([v["feedback"] for _, v in samples]),
                 "feedback_ms": np.array([float(v["feedback_ms"]) for _, v in samples]),
                 "preparation_ms": np.array([float(v["preparation_ms"]) for _, v in samples])}
                if all("feedback_ms" in v for _, v in samples) else {}),
    )


def run_metrics(run: RecordedRun, settings: ControllerSettings) -> dict[str, Any]:
    """Tracking per target (segments), penetration/clearance at the samples and re-simulated between them,
    solve-time statistics, counters (definitions: core/loop/metrics.py, bag/segments.py).

    The top-level settling_step / settling_time are the sample (and s since the first) from which the
    output stays at the last target; overshoot, overshoot_note and final_error the last segment's (a
    run with one target: its step from the start). The flat penetration and clearance keys are those
    of the states the samples solved on; `between_samples` the model re-simulated from each sample
    under its command, acting when the controller predicted it would (core/loop/intersample.py). The recorded
    plant states, the truth, are
    bag/truth.py's (`analyze` reports them beside these)."""
    model = settings.build_model()
    xs = run.states_with_final
    y = outputs(model, xs, run.u)
    accepted = [e for e in run.target_events if e.accepted]
    target = run.targets[-1]
    metrics: dict[str, Any] = {"bag": str(run.path), "finished": run.finished, "samples": len(run.x),
                               "model": model.name,
                               "target": target.tolist() if np.all(np.isfinite(target)) else None,
                               "targets_accepted": len(accepted),
                               "targets_refused": [{"time_ns": e.time_ns, "topic": e.topic, "reason": e.reason}
                                                   for e in run.target_events if not e.accepted],
                               "settling_step": None, "settling_time": None, "final_error": None,
                               "overshoot": None, "overshoot_note": "no target recorded"}
    segments = segment_metrics(y, run.targets, run.t, settings.sample_time)
    last = segments[-1]
    if last["target"] is not None:
        metrics.update({k: last[k] for k in ("final_error", "overshoot", "overshoot_note")})
        metrics["settling_step"] = last["settled_at_step"]
        metrics["settling_time"] = None if last["settled_at_step"] is None else \
            float(last["settled_at_step"] * settings.sample_time)
    metrics["segments"] = segments
    # moving regions where they were at each state's time (the final state one sample later)
    regions_then = [run.regions_at(k, settings.sample_time) for k in range(len(xs))]
    pen = penetration(settings, model, xs, run.u, regions_then, y)
    for key in ("max_penetration", "min_clearance", "max_penetration_keep_in", "max_penetration_obstacles",
                "min_clearance_obstacles"):
        metrics[key] = pen[key]
    metrics["min_obstacle_distance"] = _min_distance(settings, xs, y, regions_then)
    # the continuous motion under each recorded command, 10 points per sample (core/loop/intersample.py)
    dense, held, dense_regions = dense_run(settings, model, xs, run.u, run.regions, run.times, delays=run.delays)
    between = penetration(settings, model, dense, held, dense_regions)
    metrics["between_samples"] = {key: between[key] for key in ("max_penetration", "min_clearance",
                                                                 "min_clearance_obstacles")}
    metrics["between_samples"]["min_obstacle_distance"] = _min_distance(settings, dense, outputs(model, dense, held),
                                                                        dense_regions)
    # samples the controller itself reported inside a region or planning to enter one (WARN)
    metrics["alarm_samples"] = (int(np.sum((run.depths["state_depth"] > ALARM_DEPTH)
                                           | (run.depths["plan_depth"] > ALARM_DEPTH))) if run.depths else None)
    if model.name == "van_der_pol":  # the paper's energy-rate measure
        metrics["max_abs_x1x2"] = max_abs_product(xs)
    metrics["solve_ms"] = time_stats(run.solve_ms)
    if run.phases:  # answered by the prepared plan: the feedback's own time; the preparations between the samples
        answered, prepared = run.phases["feedback"] == "answered", run.phases["feedback"] != ""
        metrics["feedback"] = {
            "answered": int(np.sum(answered)), "prepared": int(np.sum(prepared)),
            "feedback_ms": time_stats(run.phases["feedback_ms"][answered]) if answered.any() else None,
            "preparation_ms": time_stats(run.phases["preparation_ms"][prepared]) if prepared.any() else None}
    metrics["deadline_overruns"] = int(np.sum(run.solve_ms > settings.sample_time * 1e3))
    metrics["fallbacks"] = sum(StepStatus(s).is_fallback for s in run.status)
    metrics["rejected_inputs"] = run.counters.get("rejected_inputs", 0)
    metrics["stale_samples"] = run.counters.get("stale", 0)
    cert = run.certificate
    # None: the bag's controller did not report the certificate
    metrics["certificate_violations"] = int(np.sum(cert["violated"])) if cert else None
    metrics["certificate_checked"] = int(np.sum(np.isfinite(cert["decrease"]))) if cert else None
    return metrics


def _min_distance(settings: ControllerSettings, x: np.ndarray, y: np.ndarray,
                  regions: Sequence[Sequence[Region]]) -> float | None:
    """The smallest signed Euclidean distance to a region (plane units, bag/distance.py; None without regions)."""
    nearest = float(np.min(nearest_region_distance(settings.plane, settings.output_plane, x, y, regions)))
    return nearest if math.isfinite(nearest) else None


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
    y = outputs(settings.build_model(), states, run.u)
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
