"""The data of the HTML report: per bag, everything needed to draw sample k without the bag.

`report_data(run, ...)` turns a RecordedRun (plus the bag's ~/prediction messages) into plain JSON:

    label, plane [2], state_names, input_names, sample_time s
    t [K] s (k Ts), x [K(+1), n], u [K, m], y_a [K, p], x_a [K, 2] (plane coordinates, null
    without a closed-form steady state), target [K, p], solve_ms [K], status [K]
    costs {offset, avoidance, tracking} [K], certificate {value_function, decrease, decrease_bound,
    violated} [K] (empty without it)
    prediction [K]: the plan's x(0..N) in the plane [N+1, 2], or null (no plan published then)
    regions: table of distinct regions {kind: ellipse|polygon, frame, center, semi_axes, yaw,
    vertices, velocity, stamp}; active [K]: indices into the table; times [K]: the controller's
    clock of each sample since the first (moving regions sit at c + v (t - stamp), stamps on the same
    clock)
    keep_in: {x [2], y [2], nx, ny, mask}: '1' where a keep-in expression is violated on a grid of
    the plane (other states and inputs 0), row-major from the lower left; null without keep-in
    metrics: bag/analysis.run_metrics

Floats are rounded to 7 significant digits: the report is for the eye, the bag keeps the exact values.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.loop.metrics import keep_in_values
from ..core.problem.regions import Ellipse, Region
from .analysis import RecordedRun, run_metrics
from .mcap_io import Bag

#: keep-in grid resolution (columns, rows)
GRID = (160, 80)
#: how many prediction messages ahead of the last matched one a sample's plan is looked for
PREDICTION_WINDOW = 4


def rounded(value: Any) -> Any:
    """Nested lists of floats with 7 significant digits (nan and inf -> None, so the JSON is strict)."""
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(v) for v in value]
    if isinstance(value, float):
        return float(f"{value:.7g}") if math.isfinite(value) else None
    return value


def predictions(bag: Bag, run: RecordedRun, plane: tuple[int, int]) -> list[list | None]:
    """The plan published with each sample: the ~/prediction Path whose first pose is the sample's state."""
    topic = next((name for name in sorted(bag.topics) if name.endswith("/prediction")), None)
    paths = [np.array([[p.pose.position.x, p.pose.position.y] for p in msg.poses]) for _, msg in
             bag.topics.get(topic, [])] if topic else []
    out: list[list | None] = []
    cursor = 0
    for x in run.x:
        first = np.array([x[plane[0]], x[plane[1]]])
        match = next((i for i in range(cursor, min(cursor + PREDICTION_WINDOW, len(paths)))
                      if len(paths[i]) and np.array_equal(paths[i][0], first)), None)
        if match is None:  # a sample without a solve (coasting on the plan): nothing was published
            out.append(None)
            continue
        out.append(paths[match].tolist())
        cursor = match + 1
    return out


def region_entry(region: Region, t0: float) -> dict[str, Any]:
    """A region as JSON, its stamp in seconds since t0 (absolute clock times do not survive the rounding)."""
    common = {"frame": region.frame, "velocity": list(region.velocity), "stamp": region.stamp - t0}
    if isinstance(region, Ellipse):
        return {"kind": "ellipse", "center": list(region.center), "semi_axes": list(region.semi_axes),
                "yaw": region.yaw, **common}
    return {"kind": "polygon", "vertices": [list(v) for v in region.vertices], **common}


def keep_in_grid(settings: ControllerSettings, box: tuple[tuple[float, float], tuple[float, float]]
                 ) -> dict[str, Any] | None:
    """Where the keep-in expressions are violated on a grid of the plane (see the module doc)."""
    if not settings.keep_in:
        return None
    model = settings.build_model()
    (x_lo, x_hi), (y_lo, y_hi) = box
    nx, ny = GRID
    gx, gy = np.meshgrid(np.linspace(x_lo, x_hi, nx), np.linspace(y_lo, y_hi, ny))
    states = np.zeros((nx * ny, model.n))
    states[:, settings.plane[0]], states[:, settings.plane[1]] = gx.ravel(), gy.ravel()
    g = keep_in_values(settings, model, states, np.zeros((nx * ny, model.m)))
    mask = np.any(g > 0, axis=1)
    return {"x": [x_lo, x_hi], "y": [y_lo, y_hi], "nx": nx, "ny": ny, "mask": "".join("1" if v else "0" for v in mask)}


def plane_box(settings: ControllerSettings, states: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """The plane's state bounds, or the data's extent (with a margin) where a bound is infinite."""
    box = []
    for axis in settings.plane:
        lo, hi = settings.state_min[axis], settings.state_max[axis]
        data = states[:, axis]
        span = max(float(np.ptp(data)), 1.0)
        lo = lo if math.isfinite(lo) else float(np.min(data)) - 0.1 * span
        hi = hi if math.isfinite(hi) else float(np.max(data)) + 0.1 * span
        box.append((float(lo), float(hi)))
    return box[0], box[1]


def report_data(run: RecordedRun, bag: Bag, settings: ControllerSettings, label: str) -> dict[str, Any]:
    """The JSON of one bag for the report page (layout: module doc)."""
    model = settings.build_model()
    plane = tuple(settings.plane)
    xs = run.states_with_final
    x_a = None
    if model.steady_state is not None:
        x_a = [None if not np.all(np.isfinite(y)) else
               np.asarray(model.steady_state(y)[0], float).ravel()[list(plane)].tolist() for y in run.y_a]
    table: list[Region] = []
    active = []
    for regions in run.regions:
        indices = []
        for region in regions:
            if region not in table:
                table.append(region)
            indices.append(table.index(region))
        active.append(indices)
    cert = run.certificate
    times = run.times if run.times is not None else np.arange(len(run.x)) * settings.sample_time
    t0 = float(times[0])
    data = {
        "label": label, "plane": list(plane), "state_names": list(model.state_names),
        "input_names": list(model.input_names), "sample_time": settings.sample_time,
        "t": np.arange(len(run.x)) * settings.sample_time, "x": xs, "u": run.u, "y_a": run.y_a, "x_a": x_a,
        "target": run.targets, "solve_ms": run.solve_ms, "status": list(run.status),
        "costs": {k.removesuffix("_cost"): v for k, v in run.costs.items()},
        "certificate": {k: cert[k] for k in ("value_function", "decrease", "decrease_bound")} if cert else {},
        "violated": [bool(v) for v in cert["violated"]] if cert else [],
        "prediction": predictions(bag, run, plane),
        "regions": [region_entry(r, t0) for r in table], "active": active,
        "times": np.asarray(times, float) - t0,
        "horizon": settings.horizon,
        "keep_in": keep_in_grid(settings, plane_box(settings, xs)),
        "box": plane_box(settings, xs),
        "metrics": run_metrics(run, settings),
    }
    return rounded(data)
