"""A run cut where its target changed: each target the controller accepted is scored on the samples it held.

Segment i runs from the first sample at which target i was in force to the sample before the next
change; its outputs are those of its samples plus the state after its last one (the next segment's
first state, or the run's final state). Settling, final error and overshoot are core/loop/metrics.py
`tracking` of those outputs against the segment's target: the settling step and time count from the
segment's start (the target change), the overshoot is against the step from the output there. A
target sent again unchanged does not start a segment (the controller's target did not change).
Samples solved before any target was recorded (a bag that missed it) form a segment without target.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.loop.metrics import tracking


@dataclass
class Segment:
    """Samples start..end-1 of a run under one target [p] (None: no target recorded for them)."""

    start: int
    end: int
    target: np.ndarray | None


def split(targets: np.ndarray) -> list[Segment]:
    """The runs of equal consecutive rows of `targets` [K, p] (nan rows: no target)."""
    out: list[Segment] = []
    for k, row in enumerate(np.asarray(targets, float)):
        value = row if np.all(np.isfinite(row)) else None
        same = out and ((value is None and out[-1].target is None) or
                        (value is not None and out[-1].target is not None and np.array_equal(value, out[-1].target)))
        if same:
            out[-1].end = k + 1
        else:
            out.append(Segment(k, k + 1, None if value is None else value.copy()))
    return out


def segment_metrics(y: np.ndarray, targets: np.ndarray, t: np.ndarray, sample_time: float) -> list[dict[str, Any]]:
    """One entry per segment (module doc) of the outputs y [K or K+1, p] at the sample times t [K] (s since the
    first sample): index, target, start_step, end_step (exclusive), start_time (s), samples, then
    `tracking`'s settling_step / settling_time (from the segment's start), final_error, overshoot,
    overshoot_note, and settled_at_step (the run's sample index; None when it did not settle)."""
    entries = []
    for i, seg in enumerate(split(targets)):
        entry: dict[str, Any] = {"index": i, "target": None if seg.target is None else seg.target.tolist(),
                                 "start_step": seg.start, "end_step": seg.end, "start_time": float(t[seg.start]),
                                 "samples": seg.end - seg.start}
        ys = y[seg.start:min(seg.end + 1, len(y))]
        if seg.target is None:
            entry.update({"settling_step": None, "settling_time": None, "final_error": None, "overshoot": None,
                          "overshoot_note": "no target recorded for these samples", "settled_at_step": None})
        else:
            quality = tracking(ys, seg.target, sample_time)
            entry.update(quality)
            step = quality["settling_step"]
            entry["settled_at_step"] = None if step is None else seg.start + step
        entries.append(entry)
    return entries
