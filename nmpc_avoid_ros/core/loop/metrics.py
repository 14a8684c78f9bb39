"""Closed-loop metrics: the one definition of settling, final error, penetration and clearance.

Every consumer computes its figures here: `analyze` (runs read back from bags, bag/analysis.py),
`simulate`, `bench` and `campaign` (nmpc_avoid_ros/evaluation/). The module needs numpy, CasADi
and the core regions only, so the bag layer and everything above it can use it.

Conventions (K samples; x [K+1, n] the states the samples solved on plus the state after the
last one, u [K, m] the commands):

* the output of state k is h(x(k), u(k)); the final state uses the last command u(K-1);
* `regions[k]` is the region set in force at sample k; it applies to x(k); the final state
  x(K) is measured against the last set (a list shorter than x repeats its last entry); moving
  regions must be given where they are at each state's time (`Region.at`);
* penetration is the largest g over the states (keep-in expression: its value, > 0 outside the
  keep-in set, e.g. |x1 x2| - 2; region: `Region.depth`, for an ellipse 1 - normalised r^2),
  0 if no state is ever inside; clearance is -max g (None when there is no region at all);
* settled: |y - y_t| (Euclidean) below SETTLING_TOLERANCE from some sample on, for good;
* overshoot: the largest excursion beyond y_t in the direction of the step s = y_t - y(0), as a
  fraction of |s|; left out (None, with the reason) when |s| < SETTLING_TOLERANCE (`overshoot`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..problem.expressions import parse_keep_in
from ..problem.models import Model
from ..problem.regions import Ellipse, Region, ellipse_g

#: settled: |y - y_t| below this from some sample on, for good (the paper scenario's criterion)
SETTLING_TOLERANCE = 0.05


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


def padded_inputs(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """u [K, m] extended to one row per state of x [K or K+1, n] by repeating its last row."""
    u = np.atleast_2d(np.asarray(u, float))
    return np.vstack([u, u[-1:]]) if len(x) > len(u) else u


def outputs(model: Model, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """y [len(x), p] = h(x(k), u(k)) with the last command held for the final state."""
    us = padded_inputs(x, u)
    return np.array([np.asarray(model.output(xk, uk)).ravel() for xk, uk in zip(x, us)])


def overshoot(y: np.ndarray, target: Sequence[float], min_step: float = SETTLING_TOLERANCE
              ) -> tuple[float | None, str | None]:
    """Overshoot of the outputs y [K+1, p] (output units) against the step from y(0) to the target y_t [p].

    With the step s = y_t - y(0) (Euclidean size |s|), the overshoot is the largest excursion beyond
    the target in the direction of the step, divided by |s|: max(0, max_k (y(k) - y_t) . s / |s|^2)
    (dimensionless; 0.1 = 10 % of the step). Below `min_step` (default: the settling tolerance, in
    output units) the run starts settled and that fraction means nothing (a bag that began at its
    target gave 7e6): (None, the reason). Otherwise (value, None).
    """
    y, target = np.atleast_2d(np.asarray(y, float)), np.asarray(target, float)
    step = target - y[0]
    size = float(np.linalg.norm(step))
    if not size >= min_step:
        return None, (f"step |y_t - y(0)| = {size:.3g} is below {min_step:g} (the settling tolerance): the run starts "
                      "settled, so there is no step to overshoot")
    beyond = (y - target) @ step / size
    return float(max(0.0, np.max(beyond)) / size), None


def tracking(y: np.ndarray, target: Sequence[float], sample_time: float,
             tolerance: float = SETTLING_TOLERANCE) -> dict[str, Any]:
    """Settling step and time (s), final error |y_K - y_t| and overshoot (`overshoot`) of y [K+1, p].

    `overshoot` is None when the step is below `tolerance`; `overshoot_note` then says why (else None).
    """
    target = np.asarray(target, float)
    err = np.linalg.norm(y - target, axis=1)
    step = settling_step(err, 0.0, tolerance)
    over, note = overshoot(y, target, tolerance)
    return {"settling_step": step, "settling_time": None if step is None else float(step * sample_time),
            "final_error": float(err[-1]), "overshoot": over, "overshoot_note": note}


def region_depth(region: Region, points: np.ndarray) -> np.ndarray:
    """g of a region at points [2, K] (> 0 inside) [K]; ellipses vectorised, others point by point."""
    points = np.asarray(points, float)
    if isinstance(region, Ellipse):
        return np.asarray(ellipse_g(points, region.slot_values()), float)
    return np.array([region.depth(pt) for pt in points.T])


def keep_in_function(settings: ControllerSettings, model: Model,
                     expressions: Sequence[str] | None = None) -> ca.Function | None:
    """(x [n], u [m]) -> g of each keep-in expression [q] (> 0: outside the keep-in set), parsed once; None without
    any. `expressions`: other inequalities of the same form instead (e.g. settings.constraints, the hard ones)."""
    xsym, usym = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m)
    table = model.symbol_table(xsym, usym)
    keep = [parse_keep_in(text, table).g for text in (settings.keep_in if expressions is None else expressions)]
    return ca.Function("keep_in", [xsym, usym], [ca.vertcat(*keep)]) if keep else None


def keep_in_values(settings: ControllerSettings, model: Model, x: np.ndarray, u: np.ndarray,
                   expressions: Sequence[str] | None = None) -> np.ndarray:
    """g of each keep-in expression at each state [len(x), q] (> 0: outside the keep-in set);
    `expressions`: as in keep_in_function."""
    fn = keep_in_function(settings, model, expressions)
    if fn is None:
        return np.zeros((len(x), 0))
    q = fn.size1_out(0)
    return np.asarray(fn.map(len(x))(np.asarray(x, float).T, padded_inputs(x, u).T), float).T.reshape(len(x), q)


def region_values(settings: ControllerSettings, x: np.ndarray, y: np.ndarray,
                  regions: Sequence[Sequence[Region]]) -> np.ndarray:
    """Largest region g at each state [len(x)] (-inf where no region is in force); see the conventions."""
    worst = np.full(len(x), -math.inf)
    if not len(regions):
        return worst
    for k in range(len(x)):
        for region in regions[min(k, len(regions) - 1)]:
            plane, source = (settings.plane, x[k]) if region.frame == "state" else (settings.output_plane, y[k])
            worst[k] = max(worst[k], float(region.depth((source[plane[0]], source[plane[1]]))))
    return worst


def penetration(settings: ControllerSettings, model: Model, x: np.ndarray, u: np.ndarray,
                regions: Sequence[Sequence[Region]], y: np.ndarray | None = None) -> dict[str, Any]:
    """Penetration of the keep-in set and of the regions, and the clearance, over x [K+1, n].

    Returns max_penetration (both), max_penetration_keep_in, max_penetration_obstacles (>= 0),
    min_clearance (-max g over both, None if there is neither a keep-in expression nor a region)
    and min_clearance_obstacles (-max g over the regions alone, None without regions).
    """
    y = outputs(model, x, u) if y is None else y
    keep = keep_in_values(settings, model, x, u)
    keep_worst = float(np.max(keep)) if keep.size else -math.inf
    region_worst = float(np.max(region_values(settings, x, y, regions)))
    worst = max(keep_worst, region_worst)
    return {"max_penetration": max(0.0, worst), "max_penetration_keep_in": max(0.0, keep_worst),
            "max_penetration_obstacles": max(0.0, region_worst),
            "min_clearance": -worst if math.isfinite(worst) else None,
            "min_clearance_obstacles": -region_worst if math.isfinite(region_worst) else None}


def time_stats(values: np.ndarray, percentiles: Sequence[int] = (99,)) -> dict[str, float]:
    """median, p<q> for each q, and max of a series (units kept; e.g. solve times in ms)."""
    values = np.asarray(values, float)
    return {"median": float(np.median(values)), **{f"p{q}": float(np.percentile(values, q)) for q in percentiles},
            "max": float(np.max(values))}
