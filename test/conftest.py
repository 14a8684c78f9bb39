"""Shared fixtures: the paper's four closed-loop runs are computed once per session."""

from __future__ import annotations

import functools
import itertools
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # test helpers (rosgraph)

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.loop.closed_loop import ClosedLoopRun, run_closed_loop
from nmpc_avoid_ros.core.sample.controller import NmpcController

PAPER_X0 = [-5.0, 0.0]
PAPER_TARGET = [5.0]
PAPER_STEPS = 50


def count_solves(controller: NmpcController, first: str) -> dict[str, int]:
    """Count the solver calls of one of the controller's NLPs (`first`: "regular" or the fast path's
    "reference") and of each ellipse tier ("tier<k>", k its capacity); the dict fills as they run."""
    nlps = [(first, controller.nlp if first == "regular" else controller.cold_nlp)]
    nlps += [(f"tier{k}", nlp) for k, nlp in controller.tiered.tiers]
    calls = {}
    for name, nlp in nlps:
        calls[name] = 0
        original = nlp.solve

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)

        nlp.solve = counted
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


_DOMAIN_BASE = 10 + os.getpid() % 40  # distinct from other concurrent test sessions on this host
_domain_counter = itertools.count()


@pytest.fixture
def ros_graph(tmp_path):
    """(domain_id, env, start, probe_factory): isolated DDS domain; every started node is stopped."""
    from rosgraph import NodeProcess, Probe, ros_env

    domain = _DOMAIN_BASE + 2 * (next(_domain_counter) % 25)
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
