"""The plant-model mismatch, measured online, and the margin it adds to the obstacles.

Every sample predicts x(1), where the plant will be one sample later under the command it applies.
The next sample measures it: e = |x_measured - x(1)| in the obstacle plane (the two `plane` state
coordinates; with 'output'-frame regions also the two `output_plane` outputs, the larger of both).
The margin is `mismatch_gain` times the largest e of the last `mismatch_window` samples, at most
`max_mismatch_margin`, added to `region_margin`: the plan avoids every obstacle inflated by it.

The bound (docs/design.md, 'Mismatch margin'): if the plant's one-step deviation from the prediction
stays within the window's largest e, a planned x(1) that clears the obstacle inflated by that much
in every direction puts the real x(1) outside the obstacle. Inflation is exact for circles and
polygons (edges moved out); for an ellipse the semi-axes grow by the margin, which keeps at least
0.41 of it in every direction (needle-thin), so gain 1 / 0.41 = 2.5 covers any ellipse and gain 1 a
round one. Between the samples the deviation grows from 0 to about e, so the same margin covers the
sub-step states as far as the deviation grows monotonically; the keep-in sets (`keep_in`) are
constraints of the configured problem and are not tightened.

The margin grows at once to MARGIN_HEADROOM times its target and shrinks only when the target falls
below half of it (a target below the penetration tolerance 1e-3 is 0: a model that predicts the plant
that well changes nothing): each change re-packs the regions and restarts the stability certificate's check
(the planned problem changed), so it changes a few times, not every sample.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..config.settings import ControllerSettings
from ..nlp.search import VIOLATION_TOLERANCE
from ..problem.models import Model

#: a changed margin is set to this multiple of its target (room for the next slightly larger error)
MARGIN_HEADROOM = 1.25
#: the margin shrinks only when its target falls below this fraction of it
SHRINK_BELOW = 0.5
#: a measurement counts only if it comes one sample after its prediction, within this share of Ts
TIME_SLACK = 0.5


@dataclass
class Expectation:
    """The prediction to check at the next sample: x(1) [n], the input applied over it [m], the
    time (s, None offline: consecutive samples assumed) at which x(1) is due."""

    x: np.ndarray
    u: np.ndarray
    due: float | None


@dataclass
class MismatchMargin:
    """Carries the one-step errors (plane units) of the last samples and the margin they give."""

    errors: deque = field(default_factory=lambda: deque(maxlen=1))
    expected: Expectation | None = None
    margin: float = 0.0
    last_error: float = math.nan

    def measure(self, x: np.ndarray, time: float | None, model: Model, settings: ControllerSettings,
                outputs_too: bool) -> None:
        """Compare the measured state x [n] at `time` with the expectation (then drop it)."""
        expected, self.expected = self.expected, None
        self.last_error = math.nan
        if expected is None:
            return
        if time is not None and expected.due is not None and \
                abs(time - expected.due) > TIME_SLACK * settings.sample_time:
            return  # not the sample the prediction was for (a missed or late one)
        plane = list(settings.plane)
        error = float(np.linalg.norm(x[plane] - expected.x[plane]))
        if outputs_too:
            out = list(settings.output_plane)
            y = np.asarray(model.output(x, expected.u), float).ravel()
            y_pred = np.asarray(model.output(expected.x, expected.u), float).ravel()
            error = max(error, float(np.linalg.norm(y[out] - y_pred[out])))
        if math.isfinite(error):
            if self.errors.maxlen != settings.mismatch_window:
                self.errors = deque(self.errors, maxlen=settings.mismatch_window)
            self.errors.append(error)
            self.last_error = error

    def expect(self, x_next: np.ndarray, u: np.ndarray, time: float | None, sample_time: float) -> None:
        """The plan applied now predicts x_next [n] one sample after `time` under input u [m]."""
        if np.all(np.isfinite(x_next)):
            self.expected = Expectation(np.array(x_next, float), np.array(u, float),
                                        None if time is None else time + sample_time)

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
