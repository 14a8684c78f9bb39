"""The latency each recorded sample predicted over, read back from its diagnostics, for a closed-loop replay.

A real-time controller with latency compensation (core/sample/latency.py, nodes/command_timing.py) plans
from its measured state predicted `latency + input_delay` s ahead under the command in force; its
diagnostics say over how long (`predicted_delay_ms`, to 10 us), from which state (`state`, measured)
to which (`planned_state`), when the state arrived (`state_time`), how old it was when the sample started
(`state_age_ms`) and when the command left (`step_latency_ms` after the start: `command_sent`). Stepping
the re-run controller with the same latency, at the same times, makes an unchanged replay plan from the
same state. The 10 us rounding of `predicted_delay_ms` alone would move that state by ~1e-5, so the delay
is refined to the one that carries `state` to `planned_state` under the previous sample's command
(the model's own flow, Gauss-Newton on the one scalar).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..bag.analysis import RecordedRun, controller_samples
from ..bag.mcap_io import Bag
from ..core.config.settings import ControllerSettings
from ..core.sample.latency import LatencyPrediction

#: m.s.: a refined delay is taken when it carries the measured state to `planned_state` this closely
REFINE_TOLERANCE = 1e-10
#: s: the refinement searches this far around predicted_delay_ms (printed to 10 us)
REFINE_WINDOW = 5e-5


@dataclass
class RecordedLatency:
    """Per recorded sample k: `latency[k]` s to pass to NmpcController.step (its predicted delay minus
    input_delay), `times[k]` the sample's state time (s since the first sample's), `sent[k]` when its command
    left (same clock; None: the recording did not compensate, nothing to tell the controller); `line`: what
    was used, or why none."""

    latency: list[float]
    times: list[float] | None
    sent: list[float] | None
    line: str


def _vector(values: dict[str, str], key: str) -> np.ndarray | None:
    try:
        return np.asarray(json.loads(values[key].replace("nan", "NaN")), float)
    except (KeyError, ValueError, TypeError):
        return None


def _refine(flow: Callable[[float], np.ndarray], planned: np.ndarray, delay: float) -> float | None:
    """The delay d near `delay` (s) with flow(d) = planned (Gauss-Newton, derivative by central differences),
    or None when none within REFINE_WINDOW reproduces `planned` to REFINE_TOLERANCE."""
    d, h = delay, 1e-7
    for _ in range(8):
        r = flow(d) - planned
        if float(np.max(np.abs(r))) <= REFINE_TOLERANCE * 1e-3:
            break
        slope = (flow(d + h) - flow(d - h)) / (2 * h)
        norm = float(slope @ slope)
        if not norm > 0:
            break
        d = min(max(d - float(slope @ r) / norm, delay - REFINE_WINDOW, 0.0), delay + REFINE_WINDOW)
    return d if float(np.max(np.abs(flow(d) - planned))) <= REFINE_TOLERANCE else None


def recorded_latency(bag: Bag, run: RecordedRun, settings: ControllerSettings) -> RecordedLatency:
    """The latency of each of `run`'s samples in `bag` (`settings`: its controller's model, flow, input_delay)."""
    samples = [v for _, v in controller_samples(bag)[0]][:len(run.x)]
    K = len(run.x)
    t0 = float(run.times[0]) if run.times is not None and len(run.times) else 0.0
    times = [float(t) - t0 for t in run.times] if run.times is not None and len(run.times) == K else None
    if not samples or not any("predicted_delay_ms" in v for v in samples):
        return RecordedLatency([0.0] * K, times, None,
                               "none: the bag's diagnostics carry no predicted_delay_ms (recorded before latency "
                               "compensation: the controller planned from the measured state, as the replay does)")
    missing = sum("predicted_delay_ms" not in v for v in samples)
    delays = [float(v.get("predicted_delay_ms", "0")) * 1e-3 for v in samples]
    prediction = LatencyPrediction(settings.build_model(), settings)
    refined = 0
    for k in range(1, K):
        x, planned = _vector(samples[k], "state"), _vector(samples[k], "planned_state")
        if x is None or planned is None or delays[k] <= 0.0 or x.shape != planned.shape:
            continue
        d = _refine(lambda d, x=x, u=run.u[k - 1]: prediction.advance(x, u, d), planned, delays[k])
        if d is not None:
            delays[k], refined = d, refined + 1
    latency = [max(0.0, d - settings.input_delay) if d > 0 else 0.0 for d in delays]
    compensated = any(d > 0 for d in latency)
    sent = None
    if compensated and times is not None and all("state_age_ms" in v and "step_latency_ms" in v for v in samples):
        sent = [t + (float(v["state_age_ms"]) + float(v["step_latency_ms"])) * 1e-3 for t, v in zip(times, samples,
                                                                                                  strict=True)]
    predicted = [d for d in delays if d > 0]
    line = (f"each sample stepped with the latency it predicted (predicted_delay_ms - input_delay "
            f"{settings.input_delay * 1e3:g} ms): {min(latency) * 1e3:.4g} to {max(latency) * 1e3:.4g} ms, "
            f"{refined} of {len(predicted)} refined against planned_state"
            if compensated else f"none: the recorded samples predicted no latency beyond input_delay "
                                f"{settings.input_delay * 1e3:g} ms (compensation off)")
    if compensated and refined < len(predicted):
        line += (" (the others' planned_state does not follow from their state under the previous sample's "
                 "command, e.g. a late cover in force: their latency as printed, to 10 us)")
    if missing:
        line += f"; {missing} sample(s) without predicted_delay_ms stepped without latency"
    if compensated and sent is None:
        line += "; no state_age_ms / step_latency_ms: the controller is not told when each command left"
    return RecordedLatency(latency, times, sent, line)
