"""A car-like robot's cold guess: its own model driven towards the goal by a simple steering law.

Why: a model that cannot turn on the spot (the kinematic bicycle) starts cold from a plan resting where it stands,
and the solver then turns the heading, builds the speed and moves y_a all at once: FATROP took 116 iterations (68
ms) on the bench's first sample among 4 ellipses (BENCHMARKS.md, 'The car-like robot among 4 ellipses'). Driven by
the model itself, the guess meets the dynamics exactly and already heads for the goal: 15 iterations, 14 ms, and a
cheaper plan (cost 2333 against the resting plan's 2404). The guess ignores the regions: the solver moves it
around them (a penetrating start is a slack to it, not a failure).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..problem.models import Model

#: rad/s of yaw rate per rad of heading error
HEADING_GAIN = 2.0
#: the speed's share kept while the heading error is large (cos(error) below it): the car turns while it moves
MIN_SPEED_SHARE = 0.3
#: how much faster than the even pace to the goal over the horizon the guess drives (capped by the input box)
PACE = 1.5
#: m from a waypoint at which the pursuit turns to the next
VIA_REACH = 0.5


class Rollout:
    """x [n], the goal's position [2] -> (x(1..N) [N, n], u(0..N-1) [N, m]) of a planar model with a heading and a
    velocity-command map (PlanarMap.command, from_command): pursuit of the goal's position, at rest in the last
    stage (u(N-1) the input of a zero command, so that x(N) can be a steady state), each input within
    input_rate_max of the one before (from rest: the guess meets the rate rows of a start from rest too)."""

    def __init__(self, model: Model, settings: ControllerSettings, horizon: int) -> None:
        planar = model.planar
        assert planar is not None and planar.yaw is not None and planar.from_command is not None
        self._planar, self.horizon, self._dt = planar, horizon, settings.sample_time
        self._step = model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)
        self._input_lo = np.asarray(settings.input_min, float)
        self._input_hi = np.asarray(settings.input_max, float)
        speed = planar.command(ca.DM.zeros(model.n), self._input_hi)
        self._top_speed = max(float(speed[0]), 0.0)
        #: the largest change of each input over a sample (input_rate_max; inf: none), from rest at the first
        self._rate_step = np.asarray(settings.input_rate_max, float) * settings.sample_time \
            if settings.input_rate_max else np.full(model.m, np.inf)
        self._rest_input = np.clip(np.zeros(model.m), self._input_lo, self._input_hi)

    def __call__(self, x: np.ndarray, goal: np.ndarray, via: Sequence[np.ndarray] = ()
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Pursuit of each of the positions `via` [2] in turn (the next once within VIA_REACH), then of `goal` [2]."""
        planar, N = self._planar, self.horizon
        states, inputs = [], []
        state, previous = np.asarray(x, float), self._rest_input
        points = [np.asarray(p, float) for p in via] + [np.asarray(goal, float)]
        for k in range(N):
            while len(points) > 1 and np.linalg.norm(points[0] - state[[planar.x, planar.y]]) < VIA_REACH:
                points.pop(0)
            offset = points[0] - state[[planar.x, planar.y]]
            error = math.remainder(math.atan2(offset[1], offset[0]) - state[planar.yaw], math.tau)
            left = float(np.linalg.norm(offset)) + sum(float(np.linalg.norm(b - a)) for a, b in zip(points, points[1:]))
            pace = PACE * left / (self._dt * (N - k))
            command = [min(self._top_speed, pace) * max(math.cos(error), MIN_SPEED_SHARE), HEADING_GAIN * error]
            if k == N - 1:
                command = [0.0, 0.0]
            u = np.clip(np.asarray(planar.from_command(state, command), float).ravel(), self._input_lo,
                        self._input_hi)
            u = previous = np.clip(u, previous - self._rate_step, previous + self._rate_step)  # input_rate_max
            state = np.asarray(self._step(state, u), float).ravel()
            states.append(state)
            inputs.append(u)
        return np.array(states), np.array(inputs)
