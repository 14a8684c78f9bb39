"""Shared fixtures: the paper's four closed-loop runs are computed once per session."""

from __future__ import annotations

import functools

import pytest

from nmpc_avoid_ros.core.closed_loop import ClosedLoopRun, run_closed_loop
from nmpc_avoid_ros.core.controller import NmpcController
from nmpc_avoid_ros.core.settings import ControllerSettings

PAPER_X0 = [-5.0, 0.0]
PAPER_TARGET = [5.0]
PAPER_STEPS = 50


@functools.cache
def paper_run(mu: float, plant: str) -> ClosedLoopRun:
    """The paper scenario (x0 = [-5, 0], y_t = 5, 50 steps) with the given mu and plant."""
    controller = NmpcController(ControllerSettings(mu=mu))
    return run_closed_loop(controller, PAPER_X0, PAPER_TARGET, PAPER_STEPS, plant)


@pytest.fixture
def paper():
    return paper_run
