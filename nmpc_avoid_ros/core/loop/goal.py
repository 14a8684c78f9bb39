"""The end of the way as a robot user expects it: a goal reached stops the commands, a goal nobody can reach is said.

`GoalWatch.observe` looks at one sample (the measured state, the goal y_t, the controller's result) and returns a
`GoalVerdict`; the node (nodes/controller_goal.py) publishes the zero command while the verdict `holds`, latches
`~/goal_reached` and adds the verdict to its diagnostics. Offline loops may use it the same way.

* Reached: the output h(x) within `tolerance` of y_t (Euclidean, output units) with the state at rest under the zero
  input (|f(x, 0)|_inf <= `rest_speed`: a unicycle always is, a double integrator once its speed is that low).
  Then the command is zero, not the plan's last 1e-4 m/s creep. It holds until the output leaves y_t by
  `tolerance` + `hysteresis`, or a different goal arrives.
* Unreachable: y_t lies inside an obstacle region (as the plan avoids it: inflated by region_margin and the
  mismatch margin; the steady state of y_t for a region in the state frame), or out of reach of the steady states
  in lambda Z (the controller tracks its projection, core/nlp/projection.py). The plan then comes to rest at y_a:
  `stop` says where. Once y_a has settled (moved less than SETTLED_MOVE in SETTLED_SAMPLES samples) and the output is
  within `tolerance` of it at rest, the command is zero there too (held as a reached goal, by the same hysteresis:
  until the output is further than `tolerance` + `hysteresis` from y_a, e.g. when a moving region frees the way).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..problem.models import Model
from ..problem.regions import Region, RegionError
from ..sample.step_result import StepResult
from ..sample.warm_start import steady_of

#: y_a has settled when it moved less than this (output units, inf-norm) over each of SETTLED_SAMPLES samples
SETTLED_MOVE = 1e-3
SETTLED_SAMPLES = 5
#: a goal this close (inf-norm) to the last one is the same goal (a goal sent again does not resume)
SAME_GOAL = 1e-9


@dataclass
class GoalVerdict:
    """One sample's verdict.

    reached: the goal is reached (held, see the module); holds: the command is zero now (reached, or settled at
    the stop point of an unreachable goal); changed: `reached` differs from the last verdict's; distance: |h(x) -
    y_t| (output units); unreachable: why y_t cannot be reached ('' if it can); stop: where the plan comes to rest
    instead (y_a [p]) when unreachable, else None.
    """

    reached: bool = False
    holds: bool = False
    changed: bool = False
    distance: float = float("nan")
    unreachable: str = ""
    stop: np.ndarray | None = None

    def values(self) -> dict[str, str]:
        """The verdict as diagnostics values (strings)."""
        return {"goal_reached": str(self.reached).lower(), "goal_distance": f"{self.distance:.4g}",
                "goal_unreachable": str(bool(self.unreachable)).lower(), "goal_unreachable_reason": self.unreachable,
                "goal_stop": "" if self.stop is None else str(np.round(self.stop, 4).tolist())}

    def note(self) -> str:
        """For the diagnostics message: '' when there is nothing to say."""
        if self.reached:
            return f"goal reached ({self.distance:.3g} from it): zero command"
        if self.unreachable:
            where = "" if self.stop is None else f"; stopping at {np.round(self.stop, 3).tolist()}"
            return f"goal unreachable: {self.unreachable}{where}" + (": zero command" if self.holds else "")
        return ""


class GoalWatch:
    """Goal reached / unreachable for one model; `observe` once per sample."""

    def __init__(self, model: Model) -> None:
        self.model = model
        self.reset()

    def reset(self) -> None:
        """Forget the goal and the verdict (a reactivated node starts over)."""
        self.goal: np.ndarray | None = None
        self.last = GoalVerdict()
        self._y_a: np.ndarray | None = None
        self._settled = 0

    def output(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.output(x, np.zeros(self.model.m)), float).ravel()

    def at_rest(self, x: np.ndarray, rest_speed: float) -> bool:
        """|f(x, 0)|_inf <= rest_speed: the zero command leaves the state (nearly) where it is."""
        return bool(np.max(np.abs(np.asarray(self.model.dynamics(x, np.zeros(self.model.m)), float))) <= rest_speed)

    def observe(self, x: Sequence[float], y_t: Sequence[float], result: StepResult | None,
                regions: Sequence[Region], plane: Sequence[int], output_plane: Sequence[int], *, tolerance: float,
                hysteresis: float, rest_speed: float, time: float | None = None) -> GoalVerdict:
        """The verdict for the measured state x [n], the goal y_t [p] and this sample's `result` (None: no solve;
        y_a is then not observed), `regions` as planned around (inflated), in their `plane` (state indices) or
        `output_plane` (output indices), at `time` (s, the regions' clock). `tolerance` <= 0: never reached."""
        x, y_t = np.asarray(x, float).ravel(), np.asarray(y_t, float).ravel()
        was_reached = self.last.reached  # `changed` also tells a reached goal's end by a new goal
        if self.goal is None or np.max(np.abs(y_t - self.goal)) > SAME_GOAL:  # a new goal: start over
            self.reset()
            self.goal = y_t.copy()
        before = self.last
        distance = float(np.linalg.norm(self.model.output_error(self.output(x), y_t)))  # an angle: the short way
        rest = self.at_rest(x, rest_speed)
        enabled = tolerance > 0
        reached = enabled and (distance <= tolerance + hysteresis if before.reached else distance <= tolerance and rest)
        unreachable, stop = "", None
        if result is not None:
            y_a = np.asarray(result.y_a, float).ravel()
            moved = np.inf if self._y_a is None else float(np.max(np.abs(y_a - self._y_a)))
            self._settled = self._settled + 1 if moved < SETTLED_MOVE else 0
            self._y_a = y_a.copy()
            unreachable = self.why_unreachable(x, y_t, result, regions, plane, output_plane, time, tolerance)
        if unreachable and not reached:
            stop = self._y_a
        holds = reached
        if stop is not None and enabled:  # held by the hysteresis once it holds (y_a moving away ends it)
            off = float(np.linalg.norm(self.output(x) - stop))
            holds = off <= tolerance + hysteresis if before.holds else \
                self._settled >= SETTLED_SAMPLES and off <= tolerance and rest
        self.last = GoalVerdict(reached, holds, reached != was_reached, distance, unreachable, stop)
        return self.last

    def why_unreachable(self, x: np.ndarray, y_t: np.ndarray, result: StepResult, regions: Sequence[Region],
                        plane: Sequence[int], output_plane: Sequence[int], time: float | None,
                        tolerance: float) -> str:
        """'' where y_t can be reached; else why: inside a region, or out of reach (tracking its projection)."""
        x_s = steady_of(self.model, y_t, x)[0]
        for region in regions:
            try:
                region = region.at(time) if time is not None and region.moving else region
            except RegionError:
                continue
            point = x_s[list(plane)] if region.frame == "state" else y_t[list(output_plane)]
            if region.depth(point) > 0:
                return "inside an obstacle region"
        tracked = result.target
        if tracked is not None and float(np.linalg.norm(np.asarray(tracked, float) - y_t)) > max(tolerance, 1e-6):
            return f"out of reach: tracking its nearest reachable output {np.round(tracked, 3).tolist()}"
        return ""
