"""Shared fixtures: the paper's four closed-loop runs are computed once per session."""

from __future__ import annotations

import functools
import itertools
import os
import sys
from collections.abc import Iterable
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # test helpers (rosgraph)

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.loop.closed_loop import ClosedLoopRun, run_closed_loop
from nmpc_avoid_ros.core.nlp.search import SearchReport
from nmpc_avoid_ros.core.sample.controller import NmpcController

PAPER_X0 = [-5.0, 0.0]
PAPER_TARGET = [5.0]
PAPER_STEPS = 50


def solver_calls(controller: NmpcController, searches: Iterable[SearchReport]) -> dict[str, int]:
    """The solver calls the samples' search reports show, per NLP: 'tier<k>' (the ellipse tier of capacity k,
    Tried.tier), 'reference' (the fast path's cold-start reference: its start's label), 'passage' (the
    passage mode's NLP) and 'regular' (the regular NLP); starts skipped for the budget or refused as
    non-finite guesses made no call (Tried.solver_called)."""
    calls = {"regular": 0, "reference": 0, "passage": 0, **{f"tier{k}": 0 for k, _ in controller.tiered.tiers}}
    for report in searches:
        for t in report.tried:
            if not t.solver_called:
                continue
            if t.tier is not None:
                calls[f"tier{t.tier}"] += 1
            elif t.label == "reference":
                calls["reference"] += 1
            else:
                calls["passage" if t.phase in ("passage", "passage_try") else "regular"] += 1
    return calls


@functools.cache
def paper_run(mu: float, plant: str) -> ClosedLoopRun:
    """The paper scenario (x0 = [-5, 0], y_t = 5, 50 steps) with the given mu and plant."""
    controller = NmpcController(ControllerSettings(mu=mu))
    return run_closed_loop(controller, PAPER_X0, PAPER_TARGET, PAPER_STEPS, plant)


@pytest.fixture
def paper():
    return paper_run


@functools.cache
def shipped_paper_run(mu: float, plant: str) -> ClosedLoopRun:
    """The paper scenario with the shipped config/van_der_pol.yaml controller (the real-time path) and
    the given mu: the offline loop `simulate`, the demo and the nodes run with that file."""
    params = load_params_file(default_config_path()).section("controller")
    controller = NmpcController(ControllerSettings.from_params(params).replace(mu=mu))
    return run_closed_loop(controller, PAPER_X0, PAPER_TARGET, PAPER_STEPS, plant)


@pytest.fixture
def shipped_paper():
    return shipped_paper_run


# each pytest-xdist worker its own block of 25 domains, the session's blocks apart from another session's on
# this host (by the session's pid: the workers' parent); ids stay below 160 (test_lifecycle_qos takes 200)
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
_SESSION = os.getppid() if _WORKER else os.getpid()
_DOMAIN_BASE = 10 + 50 * (_SESSION % 3) + 25 * (int(_WORKER[2:]) % 2 if _WORKER[2:].isdigit() else 0)
_domain_counter = itertools.count()


@pytest.fixture
def ros_graph(tmp_path):
    """(domain_id, env, start, probe_factory): isolated DDS domain; every started node is stopped."""
    from rosgraph import NodeProcess, Probe, ros_env

    domain = _DOMAIN_BASE + next(_domain_counter) % 25
    log_dir = tmp_path / "ros_logs"
    log_dir.mkdir()
    env = ros_env(domain, log_dir)
    started: list[NodeProcess] = []
    probes: list[Probe] = []

    def start(command: str, *args: str) -> NodeProcess:
        proc = NodeProcess(command, list(args), env, log_dir)
        started.append(proc)
        return proc

    def probe(name: str = "probe") -> Probe:
        p = Probe(domain, name)
        probes.append(p)
        return p

    yield domain, env, start, probe
    for p in probes:
        p.close()
    for proc in started:
        if proc.alive():
            proc.stop()
