"""`analyze`'s metrics of one bag: the recorded plant states (the truth) beside the samples and the re-simulation.

Three views of the same run's clearance, named for what they look at (`clearance` in metrics.json):

* `recorded_states`: every plant state the bag recorded while the controller drove it, at the plant's
  own rate (bag/recorded_states.py), against the regions in force when it was recorded, moving ones
  where they were then; the keep-in expressions at each; this is what the plant did;
* `at_samples`: the states the controller solved on (one per sample);
* `resimulated_between_samples`: the model integrated from each sample's state under its command,
  10 points per sample (core/loop/intersample.py): ideal command timing, no latency, no noise.

g is the controller's measure (keep-in: the expression's value, e.g. |x1 x2| - 2; a region: 1 -
normalised r^2 for an ellipse); `min_obstacle_distance` is the Euclidean clearance in the plane's
units (bag/distance.py; metres for a robot); with a footprint (settings.body_radius > 0) each view also
has `min_body_distance`, that distance less the body's radius: the clearance of the body, not of its
centre (exact for a disc, conservative for a polygon approximated by its circumscribed disc). The state
box is checked on the recorded states, the input box on the recorded commands (`command`, or `cmd_vel`
on the robot interface).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.loop.metrics import keep_in_values, max_abs_product, outputs, penetration, region_values
from ..core.problem.models import Model
from .analysis import RecordedRun, run_metrics
from .distance import nearest_region_distance, plane_units
from .mcap_io import Bag, BagError
from .recorded_states import RecordedStates, recorded_commands, recorded_states
from .timeline import regions_at

#: run_metrics' keys about the states the samples solved on
AT_SAMPLES = ("max_penetration", "min_clearance", "max_penetration_keep_in", "max_penetration_obstacles",
              "min_clearance_obstacles", "min_obstacle_distance", "max_abs_x1x2")


def box_excursion(values: np.ndarray, low: Sequence[float], high: Sequence[float], names: Sequence[str],
                  times: np.ndarray | None = None) -> dict[str, Any]:
    """How far values [J, d] went beyond the box [low, high]: max_excursion (>= 0, the coordinate's units),
    which coordinate and when (s; None inside), how many rows were outside, and the excursion per coordinate."""
    values = np.atleast_2d(np.asarray(values, float))
    beyond = np.maximum(values - np.asarray(high, float), np.asarray(low, float) - values)  # > 0 outside
    per = np.maximum(np.max(beyond, axis=0), 0.0)
    j, i = np.unravel_index(int(np.argmax(beyond)), beyond.shape)
    worst = float(max(0.0, beyond[j, i]))
    return {"max_excursion": worst, "coordinate": names[i] if worst > 0 else None,
            "time": float(times[j]) if worst > 0 and times is not None else None,
            "outside": int(np.sum(np.any(beyond > 0, axis=1))),
            "per_coordinate": {name: float(v) for name, v in zip(names, per)}}


def _distances(settings: ControllerSettings, x: np.ndarray, y: np.ndarray, regions: list) -> np.ndarray:
    return nearest_region_distance(settings.plane, settings.output_plane, x, y, regions)


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def states_metrics(bag: Bag, run: RecordedRun, settings: ControllerSettings, model: Model,
                   states: RecordedStates) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """The `recorded_states` entry (module doc), and per recorded state its largest g and its distance."""
    u = np.asarray(run.u, float)[states.sample]
    y = outputs(model, states.x, u)
    in_force = regions_at(bag, settings, run.interface, states.log_ns, run.controller_node)
    regions = [tuple(r.at(t) if r.moving else r for r in rs) for rs, t in zip(in_force, states.t)]
    since = states.t - (run.times[0] if run.times is not None else 0.0)
    pen = penetration(settings, model, states.x, u, regions, y)
    keep = keep_in_values(settings, model, states.x, u)
    distance = _distances(settings, states.x, y, regions)
    worst_g = np.max(keep, axis=1) if keep.size else np.full(len(states.x), -math.inf)
    worst_g = np.maximum(worst_g, region_values(settings, states.x, y, regions))
    entry: dict[str, Any] = {"topic": states.topic, "states": len(states.x), "rate_hz": states.rate_hz,
                             "skipped_messages": states.skipped, "span": states.notes, **pen,
                             "min_obstacle_distance": _finite_or_none(float(np.min(distance)))}
    # the keep-in expressions (penalised) and the hard constraints of Z, on what the plant did
    hard = keep_in_values(settings, model, states.x, u, settings.constraints)
    for key, values, texts in (("keep_in", keep, settings.keep_in), ("constraints", hard, settings.constraints)):
        entry[key] = [{"expression": text, "max_g": float(np.max(values[:, i])),
                       "time": float(since[int(np.argmax(values[:, i]))]),
                       "states_outside": int(np.sum(values[:, i] > 0))}
                      for i, text in enumerate(texts)]
    if model.name == "van_der_pol":  # the paper's energy-rate measure
        entry["max_abs_x1x2"] = max_abs_product(states.x)
    return entry, worst_g, distance


def _units(run: RecordedRun, settings: ControllerSettings, model: Model) -> dict[str, str]:
    frames = sorted({r.frame for regions in run.regions for r in regions})
    units = {f"obstacle_distance_{frame}": plane_units(model, frame, settings.plane if frame == "state"
                                                        else settings.output_plane) for frame in frames}
    return {"g": "keep-in: the expression's value; region: 1 - normalised r^2 (ellipse), depth (polygon)", **units}


def bag_metrics(bag: Bag, run: RecordedRun, settings: ControllerSettings) -> dict[str, Any]:
    """metrics.json's entry for one bag: run_metrics with its sample-based clearance moved under
    `clearance.at_samples` and the re-simulation under `clearance.resimulated_between_samples`, beside
    `clearance.recorded_states`; per segment the recorded states' clearance; the state and input boxes."""
    model = settings.build_model()
    if run.x.shape[1] != model.n or run.u.shape[1] != model.m:
        raise BagError(f"{run.path}: the samples have {run.x.shape[1]} states and {run.u.shape[1]} inputs, the "
                       f"settings' model {model.name} {model.n} and {model.m}: give the run's params file (--config)")
    metrics = run_metrics(run, settings)
    at_samples = {key: metrics.pop(key) for key in AT_SAMPLES if key in metrics}
    between = metrics.pop("between_samples")
    states = recorded_states(bag, run, model, settings.sample_time)
    truth = None
    if states is not None:
        truth, worst_g, distance = states_metrics(bag, run, settings, model, states)
        for seg in metrics["segments"]:
            inside = (states.sample >= seg["start_step"]) & (states.sample < seg["end_step"])
            seg["recorded_states"] = int(np.sum(inside))
            seg["max_penetration"] = float(max(0.0, np.max(worst_g[inside]))) if np.any(inside) else None
            seg["min_obstacle_distance"] = _finite_or_none(float(np.min(distance[inside]))) if np.any(inside) \
                else None
    metrics["clearance"] = {"units": _units(run, settings, model), "recorded_states": truth, "at_samples": at_samples,
                            "resimulated_between_samples": between}
    body = settings.body_radius
    if body > 0:  # a robot with a body (footprint): its clearance is the reference point's less the body's radius
        metrics["clearance"]["body_radius"] = body
        for view in (truth, at_samples, between):
            if view is not None and view.get("min_obstacle_distance") is not None:
                view["min_body_distance"] = view["min_obstacle_distance"] - body
    metrics["state_box"] = None if states is None else {
        "source": states.topic, "states": len(states.x),
        **box_excursion(states.x, settings.state_min, settings.state_max, model.state_names,
                        states.t - (run.times[0] if run.times is not None else 0.0))}
    source, commands = recorded_commands(bag, run, model.m)
    metrics["input_box"] = {"source": source, "commands": len(commands),
                            **box_excursion(commands, settings.input_min, settings.input_max, model.input_names)}
    return metrics
