"""A car-like robot's cold guess: its own model driven towards the goal by a simple steering law.

Why: a model that cannot turn on the spot (the kinematic bicycle) starts cold from a plan resting where it stands,
and the solver then turns the heading, builds the speed and moves y_a all at once: FATROP took 116 iterations (68
ms) on the bench's first sample among 4 ellipses (BENCHMARKS.md, 'The car-like robot among 4 ellipses'). Driven by
the model itself, the guess meets the dynamics exactly and already heads for the goal: 15 iterations, 14 ms, and a
cheaper plan (cost 2333 against the resting plan's 2404). The guess ignores the regions: the solver moves it
around them (a penetrating start is a slack to it, not a failure).
"""

from __future__ import annotations

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
    input_rate_max of the one before (from rest: the guess meets the rate rows of a start from rest too).

    One stage of the pursuit is one CasADi Function (`_stage`), built here: the Python loop of numpy and two CasADi
    calls a stage took 2.4 ms of the car's 20-stage cold guess; it calls one Function a stage."""

    def __init__(self, model: Model, settings: ControllerSettings, horizon: int) -> None:
        planar = model.planar
        assert planar is not None and planar.yaw is not None and planar.from_command is not None
        self._planar, self.horizon, dt = planar, horizon, settings.sample_time
        step = model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)
        lo, hi = np.asarray(settings.input_min, float), np.asarray(settings.input_max, float)
        top_speed = max(float(planar.command(ca.DM.zeros(model.n), hi)[0]), 0.0)
        #: the largest change of each input over a sample (input_rate_max; inf: none), from rest at the first
        rate_step = np.asarray(settings.input_rate_max, float) * settings.sample_time \
            if settings.input_rate_max else np.full(model.m, np.inf)
        self._rest_input = np.clip(np.zeros(model.m), lo, hi)
        # one stage: the state, the point pursued, the way left beyond it (m), the stages left including this one,
        # the input before, and whether the stage is the last (a zero command) -> (its input, the next state)
        state, point = ca.SX.sym("x", model.n), ca.SX.sym("point", 2)
        beyond, stages_left, previous, last = ca.SX.sym("beyond"), ca.SX.sym("stages_left"), \
            ca.SX.sym("previous", model.m), ca.SX.sym("last")
        offset = point - ca.vertcat(state[planar.x], state[planar.y])
        bearing = ca.atan2(offset[1], offset[0]) - state[planar.yaw]
        error = ca.atan2(ca.sin(bearing), ca.cos(bearing))  # in (-pi, pi]
        pace = PACE * (ca.norm_2(offset) + beyond) / (dt * stages_left)
        command = ca.if_else(last, ca.DM.zeros(2), ca.vertcat(
            ca.fmin(top_speed, pace) * ca.fmax(ca.cos(error), MIN_SPEED_SHARE), HEADING_GAIN * error))
        u = ca.fmin(ca.fmax(planar.from_command(state, command), lo), hi)
        u = ca.fmin(ca.fmax(u, previous - rate_step), previous + rate_step)  # input_rate_max
        self._stage = ca.Function("rollout_stage", [state, point, beyond, stages_left, previous, last],
                                  [u, step(state, u)])

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
            beyond = sum(float(np.linalg.norm(b - a)) for a, b in zip(points, points[1:]))
            u, state = self._stage(state, points[0], beyond, N - k, previous, float(k == N - 1))
            previous, state = np.asarray(u, float).ravel(), np.asarray(state, float).ravel()
            states.append(state)
            inputs.append(previous)
        return np.array(states), np.array(inputs)
