"""Latency the controller accounts for: the state is old when it is solved on, the command acts later.

A real loop measures x at time t, solves for a few milliseconds, publishes, and the command reaches the
actuator some time after that. Over that delay d the plant keeps moving under the command already in
force. Planning from the measured x applies u(0) to a state the plant has left (measured on the live
van der Pol loop: |x1 x2| 2.026 with 42-45 ms old states, docs/design.md 'Latency'). So each step plans from

    x(0) = flow(x_measured, u_in_force, d),   d = latency + input_delay,

where `latency` is what the caller knows of this sample (the node: the state's age plus its expected
solve-and-publish time) and `input_delay` the plant's configured actuator delay; flow integrates the
model with the configured method and sub-steps (Model.flow). The regions are placed at t + d.

The same flow tells the state a plan expected at a later measurement's own time (core/sample/mismatch.py),
so a late sample is not counted as model error.
"""

from __future__ import annotations

import math

import numpy as np

from ..config.settings import ControllerSettings
from ..errors import InputError
from ..nlp.buffered import Buffered
from ..problem.models import Model


class LatencyPrediction:
    """Predicts a state forward over a delay under a held input (one CasADi Function, built once)."""

    def __init__(self, model: Model, settings: ControllerSettings) -> None:
        # called through Function.buffer(): a plain call's conversions cost more than the RK4 (on the feedback
        # path, core/sample/feedback.py, every microsecond before the command counts)
        self._flow = Buffered(model.flow(settings.discretization, settings.integration_steps))
        #: the longest delay predicted over, s: one sample (an older state is the stale-state logic's matter)
        self.max_delay = settings.sample_time

    def delay(self, latency: float, input_delay: float, command: np.ndarray | None) -> float:
        """The delay to predict over, s: latency + input_delay, at most one sample; 0 without a command in force
        (nothing has moved the plant yet: a plant holds its state until its first command)."""
        if not (math.isfinite(latency) and latency >= 0.0):
            raise InputError(f"latency must be finite seconds >= 0, got {latency}")
        if command is None:
            return 0.0
        return min(latency + input_delay, self.max_delay)

    def shift(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """The state [n] dt s after x [n] under u [m] held, backwards for dt < 0 (the model is smooth: a state a
        few milliseconds earlier on the same arc, e.g. a prepared sample expecting a shorter delay)."""
        return self._flow(x, u, dt)[0].copy() if dt != 0.0 else np.array(x, float)

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """The state [n] dt s after x [n] under the input u [m] held (x itself for dt <= 0)."""
        return self.shift(x, u, dt) if dt > 0.0 else np.array(x, float)
