"""The timing of a real-time loop read back from its bag, and a plant that replays it.

A real-time plant node (nodes/plant.py) advances in steps of its own period (1 / `publish_rate`
s) under the command it holds when each step is due, and publishes the state after each step. The
controller solves on its timer on the latest state and its command is used from the plant step
it reaches. So a sample does not last exactly `sample_time`: it lasts a whole number of plant
steps (the first one fewer or more, while the plant held x0 until the first command), and a
command that reaches the plant after its next step is due leaves that step under the previous
command. Both are in the bag: the recorded states, one per plant step, hold the state each sample
solved on. `recorded_timing` reads them (and checks that the recorded commands applied that way
reproduce every solved state); `TimedPlant` replays a loop with that timing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bag.analysis import RecordedRun
from ..bag.mcap_io import Bag
from ..core.loop.closed_loop import Plant

#: m.s.: the recorded commands applied with the timing must reproduce the solved states this closely
TIMING_TOLERANCE = 1e-6


@dataclass
class RecordedTiming:
    """Plant steps of `period` s: `steps[k]` between the state sample k solved on and the next one (the
    last: to the recorded final state, or sample_time's worth); `late[k]` of them, at their start,
    still under the previous command (its own arrived late)."""

    period: float
    steps: list[int]
    late: list[int]

    def describe(self) -> str:
        late = sum(1 for d in self.late if d)
        between = self.steps[:-1] or self.steps  # the last: to the final state
        return (f"the recorded timing: plant steps of {self.period * 1e3:g} ms, {min(between)} to "
                f"{max(between)} per sample, {late} of {len(self.late)} commands used a step late")


def _state_messages(bag: Bag) -> list[np.ndarray]:
    """The recorded plant states (the `state` topic, namespaced or not), in order."""
    name = next((t for t in sorted(bag.topics) if t == "/state" or t.endswith("/state")), None)
    return [np.asarray(msg.data, float) for _, msg in bag.topics.get(name, [])] if name else []


def recorded_timing(bag: Bag, run: RecordedRun, plant: Plant, period: float, sample_time: float
                    ) -> tuple[RecordedTiming | None, str]:
    """The timing of `run` in `bag` (`plant`: the continuous plant, `period`: its step, s) and one line
    on it; (None, why) when the recorded states do not tell it (no array states, noise, another plant)."""
    states = _state_messages(bag)
    found: list[int] = []
    for k, x in enumerate(run.x):
        start = found[-1] if found else 0
        i = next((i for i in range(start, len(states)) if np.array_equal(states[i], x)), None)
        if i is None:
            return None, f"sample {k}'s state is not among the recorded states"
        while k == 0 and i + 1 < len(states) and np.array_equal(states[i + 1], x):
            i += 1  # held x0: the plant moves from the last one
        found.append(i)
    final = None
    if run.final_state is not None:
        final = next((i for i in range(found[-1] + 1, len(states)) if np.array_equal(states[i], run.final_state)),
                     None)
    steps = list(np.diff(found)) + [final - found[-1] if final is not None else max(1, round(sample_time / period))]
    late = []
    for k, i in enumerate(found):
        previous = run.u[k - 1] if k else np.zeros_like(run.u[0])
        d = 0
        while d < steps[k] and i + d + 1 < len(states):  # a step under the previous command fits better
            new = plant.advance(states[i + d], run.u[k], period)
            old = plant.advance(states[i + d], previous, period)
            if np.max(np.abs(new - states[i + d + 1])) <= np.max(np.abs(old - states[i + d + 1])):
                break
            d += 1
        late.append(d)
    timing = RecordedTiming(period, [int(n) for n in steps], late)
    replayed = TimedPlant(plant, timing)
    x, error = run.x[0], 0.0
    for k, u in enumerate(run.u):
        x = replayed.advance(x, u, sample_time)
        reference = run.x[k + 1] if k + 1 < len(run.x) else run.final_state
        if reference is not None:
            error = max(error, float(np.max(np.abs(x - reference))))
    if not error <= TIMING_TOLERANCE:
        return None, (f"the recorded commands with the plant's {period * 1e3:g} ms steps reproduce the recorded "
                      f"states only to {error:.3g}")
    return timing, timing.describe()


class TimedPlant:
    """`plant` advanced as the recording's real-time plant was: sample k lasts `steps[k]` plant steps, the
    first `late[k]` of them under the previous command (the held input before the first: zeros)."""

    def __init__(self, plant: Plant, timing: RecordedTiming) -> None:
        self.plant, self.timing = plant, timing
        self.sample = 0
        self.previous: np.ndarray | None = None

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """State [n] after sample `self.sample` from x [n] under u [m] (dt, the nominal sample time, unused)."""
        t = self.timing
        k = min(self.sample, len(t.steps) - 1)
        steps, late = t.steps[k], min(t.late[k], t.steps[k])
        previous = np.zeros_like(u) if self.previous is None else self.previous
        if late:
            x = self.plant.advance(x, previous, late * t.period)
        if steps > late:
            x = self.plant.advance(x, u, (steps - late) * t.period)
        self.previous = np.asarray(u, float)
        self.sample += 1
        return x
