"""When the controller's command leaves, and how far the plan predicts the measured state for it.

The node's part of latency compensation (core/sample/latency.py does the prediction): a sample starts
when the timer fires on a state that is already `state_age` s old. With `command_latency` > 0 the
command is held back until that long after the timer's tick (not the callback's start, which a busy
executor delays: a sample started 17 ms late held the previous command 17 ms longer than its plan
assumed, and the plant left the box by 4e-3), so commands leave one sample apart and the instant the
plan was predicted for is the instant the command leaves; a solve that takes longer publishes at once
and is counted (`late_commands`). With 0 the command leaves at once and the prediction uses the median of the last
LATENCY_WINDOW samples' start-to-publish times. A sample answered by its prepared plan (core/sample/feedback.py)
is held like any other (every plan assumes the last command in force until the hold); with command_latency 0 it
leaves at once, predicted from the median of the last such samples' times, kept apart. Lockstep never predicts:
its plant waits for the command.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

#: samples over which the expected start-to-publish time is the median (command_latency 0)
LATENCY_WINDOW = 20
#: s a command may leave after command_latency before it counts as late (the sleep's own wake-up delay)
LATE_COMMAND_SLACK = 2e-3
#: s of the hold spent spinning instead of sleeping (at most this much CPU per sample)
SPIN = 3e-3


class CommandTiming:
    """Start-to-publish times of the last samples and the hold of the next command."""

    def __init__(self) -> None:
        self.latencies: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self.answered: deque[float] = deque(maxlen=LATENCY_WINDOW)  # the samples a prepared plan answered
        self.late_commands = 0

    def expected(self, answered: bool = False) -> float:
        """s from a sample's start to its command's publication without a hold: the median of the last samples'
        (`answered`: of those a prepared plan answered; 0: none yet)."""
        window = self.answered if answered else self.latencies
        return float(np.median(window)) if window else 0.0

    def predicted(self, state_age: float, hold: float, answered: bool = False) -> float:
        """s from the state's measurement to the command's departure, as the next step should predict it."""
        return state_age + (hold if hold > 0 else self.expected(answered))

    def hold_until(self, started: float, hold: float) -> float:
        """Wait until `hold` s after `started` (time.perf_counter s); at once if that has passed. Sleeps, then
        spins the last SPIN s: a sleep alone wakes up to several ms late under the interpreter's other threads.
        Returns the seconds waited."""
        begin = time.perf_counter()
        end = started + hold
        if hold <= 0 or begin >= end:
            return 0.0
        if end - begin > SPIN:
            time.sleep(end - begin - SPIN)
        while time.perf_counter() < end:
            pass
        return time.perf_counter() - begin

    @staticmethod
    def hold_after_tick(command_latency: float, since_tick: float) -> float:
        """The hold (s from now) that makes the command leave `command_latency` s after the timer's tick,
        `since_tick` s ago; 0 when that has passed (the command leaves at once, late) or nothing is held."""
        return max(command_latency - since_tick, 0.0) if command_latency > 0 else 0.0

    def record(self, latency: float, waited: float, hold: float, command_latency: float = 0.0,
               answered: bool = False) -> None:
        """A command left `latency` s after its sample started, `waited` s of it held back, for a hold of `hold`
        s of a `command_latency` (late when it left after the hold, or had nothing left to hold); `answered`: a
        prepared plan answered it (its time is kept apart: with no hold it leaves at once)."""
        (self.answered if answered else self.latencies).append(latency - waited)
        if command_latency > 0 and (hold <= 0 or latency > hold + LATE_COMMAND_SLACK):
            self.late_commands += 1
