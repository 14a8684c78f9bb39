"""An honest status: is the measured state inside a region, does the applied plan predict entering one?

A sample can be `ok` for the solver (converged, feasible) while the state it measured lies inside an
obstacle, or while its plan trades penetration against the offset cost (a finite mu). The node reports
either as a WARN (nodes/controller.py) with the depth, and `analyze` counts such samples from the
recorded diagnostics (`state_depth`, `plan_depth`).

Depths are the region functions g of the regions as given (not inflated by region_margin) and of the
keep-in expressions: > 0 inside, for an ellipse 1 - normalised r^2 (core/loop/metrics.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..problem.expressions import parse_keep_in
from ..sample.controller import NmpcController
from ..sample.step_result import StepResult
from .metrics import padded_inputs, region_values

#: a depth beyond this is reported (issue 22: "inside a region beyond 1e-3")
ALARM_DEPTH = 1e-3


@dataclass(frozen=True)
class AvoidanceAlarm:
    """state_depth: largest g at the measured state x(0); plan_depth: largest g over the plan's x(1..N);
    both -inf when nothing is in force. message: '' when neither exceeds ALARM_DEPTH."""

    state_depth: float
    plan_depth: float
    message: str


class AvoidanceCheck:
    """Built once per controller (the keep-in function is compiled here, not per sample)."""

    def __init__(self, controller: NmpcController) -> None:
        self.controller = controller
        model, settings = controller.model, controller.settings
        x, u = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m)
        table = model.symbol_table(x, u)
        keep = [parse_keep_in(text, table).g for text in settings.keep_in]
        self._keep_in = ca.Function("keep_in_alarm", [x, u], [ca.vertcat(*keep)]) if keep else None

    def depths(self, states: np.ndarray, inputs: np.ndarray, time: float | None) -> np.ndarray:
        """Largest g at each state [len(states)]: keep-in (when mu > 0 enforces it) and the regions, moving
        ones where they are at t = time + k Ts."""
        c = self.controller
        s, model = c.settings, c.model
        us = padded_inputs(states, inputs)
        worst = np.full(len(states), -math.inf)
        if self._keep_in is not None and np.any(c.keep_in_active):
            values = np.asarray(self._keep_in.map(len(states))(states.T, us.T), float).T
            worst = np.max(values[:, np.asarray(c.keep_in_active, bool)], axis=1)
        regions = c.regions
        if regions:
            y = np.array([np.asarray(model.output(xk, uk)).ravel() for xk, uk in zip(states, us)])
            per_state = [tuple(r.at(time + k * s.sample_time) if r.moving and time is not None else r
                               for r in regions) for k in range(len(states))]
            worst = np.maximum(worst, region_values(s, states, y, per_state))
        return worst

    def check(self, result: StepResult, time: float | None = None) -> AvoidanceAlarm:
        """The alarm of one sample's result (its measured state and its plan) at `time` (s, as stepped)."""
        if result.states.shape[0] == 0 or not np.all(np.isfinite(result.states)):
            return AvoidanceAlarm(-math.inf, -math.inf, "")
        depth = self.depths(result.states, result.inputs, time)
        state_depth = float(depth[0])
        plan_depth = float(np.max(depth[1:])) if len(depth) > 1 else -math.inf
        notes = []
        if state_depth > ALARM_DEPTH:
            notes.append(f"state inside a region by {state_depth:.3g}")
        if plan_depth > ALARM_DEPTH:
            notes.append(f"plan enters a region by {plan_depth:.3g} at stage {int(np.argmax(depth[1:])) + 1}")
        return AvoidanceAlarm(state_depth, plan_depth, "; ".join(notes))
