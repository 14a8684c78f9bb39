"""The plant-model mismatch, measured online, and the margin it adds to the obstacles.

Every sample's plan starts from x(0), the state predicted for the moment its command acts
(core/sample/latency.py), and holds u(0) from then. The next sample measures the plant at its own time t
and compares it with the state the plan predicts for that same instant, flow(x(0), u(0), t - start):
e = |x_measured - that| in the obstacle plane (the two `plane` state
coordinates; with 'output'-frame regions also the two `output_plane` outputs, the larger of both).
The margin is `mismatch_gain` times the largest e of the last `mismatch_window` samples, at most
`max_mismatch_margin`, added to `region_margin`: the plan avoids every obstacle inflated by it.

The bound (docs/design.md, 'Mismatch margin'): if the plant's one-step deviation from the prediction
stays within the window's largest e, a planned x(1) that clears the obstacle inflated by that much
in every direction puts the real x(1) outside the obstacle. Inflation is exact for circles and
polygons (edges moved out); for an ellipse the semi-axes grow by the margin, which keeps at least
b / a of it in every direction (semi-axes b <= a; core/problem/shapes.py Ellipse.inflated), so gain a / b
covers an ellipse and gain 1 a round one. Between the samples the deviation grows from 0 to about e, so the
same margin covers the sub-step states as far as the deviation grows monotonically; the keep-in sets
(`keep_in`) are constraints of the configured problem and are not tightened.

The margin grows at once to MARGIN_HEADROOM times its target and shrinks only when the target falls
below half of it (a target below the penetration tolerance 1e-3 is 0: a model that predicts the plant
that well changes nothing): each change re-packs the regions and restarts the stability certificate's check
(the planned problem changed), so it changes a few times, not every sample.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..config.settings import ControllerSettings
from ..nlp.search import VIOLATION_TOLERANCE
from ..problem.models import Model

#: a changed margin is set to this multiple of its target (room for the next slightly larger error)
MARGIN_HEADROOM = 1.25
#: the margin shrinks only when its target falls below this fraction of it
SHRINK_BELOW = 0.5
#: a measurement counts only if it comes at most (1 + this) samples after the plan's start (later: the
#: plant may have had another command meanwhile, e.g. the late cover's)
TIME_SLACK = 0.5


@dataclass
class Expectation:
    """The plan applied now, to check at the next measurement: it starts from x [n], the state predicted
    for `start` (s; None offline), when its first input u [m] acts; offline the next measurement comes
    `duration` s after the start."""

    x: np.ndarray
    u: np.ndarray
    start: float | None
    duration: float
    #: the measured state [n], its time (s) and the command [m] in force then: `acts_at` re-anchors from it
    origin: tuple[np.ndarray, float | None, np.ndarray | None] | None = None


@dataclass
class MismatchMargin:
    """Carries the one-step errors (plane units) of the last samples and the margin they give."""

    errors: deque = field(default_factory=lambda: deque(maxlen=1))
    expected: Expectation | None = None
    margin: float = 0.0
    last_error: float = math.nan

    def measure(self, x: np.ndarray, time: float | None, advance: Callable[[np.ndarray, np.ndarray, float], np.ndarray],
                model: Model, settings: ControllerSettings, outputs_too: bool) -> None:
        """Compare the measured state x [n] at `time` with the state the last plan predicts for that instant
        (`advance(x, u, dt)`: the model's flow), then drop the expectation."""
        expected, self.expected = self.expected, None
        self.last_error = math.nan
        if expected is None:
            return
        dt = expected.duration if time is None or expected.start is None else time - expected.start
        if not 0.0 <= dt <= (1.0 + TIME_SLACK) * settings.sample_time:
            return  # a measurement from before the command acted, or after a missed sample
        predicted = advance(expected.x, expected.u, dt)
        plane = list(settings.plane)
        error = float(np.linalg.norm(x[plane] - predicted[plane]))
        if outputs_too:
            out = list(settings.output_plane)
            y = np.asarray(model.output(x, expected.u), float).ravel()
            y_pred = np.asarray(model.output(predicted, expected.u), float).ravel()
            error = max(error, float(np.linalg.norm(y[out] - y_pred[out])))
        if math.isfinite(error):
            if self.errors.maxlen != settings.mismatch_window:
                self.errors = deque(self.errors, maxlen=settings.mismatch_window)
            self.errors.append(error)
            self.last_error = error

    def expect(self, x_start: np.ndarray, u: np.ndarray, start: float | None, duration: float,
               origin: tuple[np.ndarray, float | None, np.ndarray | None] | None = None) -> None:
        """The plan applied now starts from x_start [n] at `start` (s) under input u [m]; offline the next
        measurement comes `duration` s later. `origin`: see Expectation."""
        if np.all(np.isfinite(x_start)):
            self.expected = Expectation(np.array(x_start, float), np.array(u, float), start, duration, origin)

    def acts_at(self, at: float, advance: Callable[[np.ndarray, np.ndarray, float], np.ndarray]) -> None:
        """The expected plan's command really acts from `at` (s): its start state is the measured one advanced
        under the command in force until then (nothing known of the measurement's time: unchanged)."""
        expected = self.expected
        if expected is None or expected.origin is None:
            return
        measured, measured_at, before = expected.origin
        if measured_at is None or not at >= measured_at:
            return
        x = advance(measured, before, at - measured_at) if before is not None else np.array(measured, float)
        if np.all(np.isfinite(x)):
            expected.x, expected.start = x, at

    def update(self, settings: ControllerSettings) -> bool:
        """Recompute the margin (plane units) from the window; True if it changed."""
        target = 0.0
        if settings.mismatch_gain > 0 and self.errors:
            target = min(settings.mismatch_gain * max(self.errors), settings.max_mismatch_margin)
        if target < VIOLATION_TOLERANCE:  # below what counts as penetration: not worth a new problem
            target = 0.0
        if target > self.margin or target < SHRINK_BELOW * self.margin:
            new = min(MARGIN_HEADROOM * target, settings.max_mismatch_margin)
            changed, self.margin = new != self.margin, new
            return changed
        return False
