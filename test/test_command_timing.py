"""When the command leaves (nodes/command_timing.py): counted from the timer's tick, late ones counted."""

from __future__ import annotations

import time

import pytest

from nmpc_avoid_ros.nodes.command_timing import LATE_COMMAND_SLACK, CommandTiming


def test_the_hold_counts_from_the_tick_and_is_gone_once_the_tick_is_that_old() -> None:
    assert CommandTiming.hold_after_tick(0.06, 0.017) == pytest.approx(0.043)  # a callback run 17 ms late
    assert CommandTiming.hold_after_tick(0.06, 0.08) == 0.0  # later than the hold: at once
    assert CommandTiming.hold_after_tick(0.0, 0.01) == 0.0  # no hold configured


def test_the_hold_waits_until_its_instant_and_returns_what_it_waited() -> None:
    timing = CommandTiming()
    started = time.perf_counter()
    waited = timing.hold_until(started, 0.02)
    assert time.perf_counter() - started >= 0.02 and 0.0 < waited <= 0.02 + 0.01
    assert timing.hold_until(started, 0.001) == 0.0  # already past


def test_the_prediction_uses_the_hold_or_the_median_unheld_latency_and_counts_late_commands() -> None:
    timing = CommandTiming()
    assert timing.predicted(0.03, 0.0) == pytest.approx(0.03)  # nothing measured yet
    for latency, waited in ((0.0605, 0.0525), (0.0606, 0.0526), (0.0604, 0.0524)):  # 8 ms of work each
        timing.record(latency, waited, hold=0.06, command_latency=0.06)
    assert timing.expected() == pytest.approx(0.008)  # the work, not the hold
    assert timing.predicted(0.03, 0.05) == pytest.approx(0.08)
    assert timing.predicted(0.03, 0.0) == pytest.approx(0.038)
    assert timing.late_commands == 0
    timing.record(0.06 + 2 * LATE_COMMAND_SLACK, 0.0, hold=0.06, command_latency=0.06)  # the solve took longer
    timing.record(0.01, 0.0, hold=0.0, command_latency=0.06)  # the tick was older than the hold
    assert timing.late_commands == 2
