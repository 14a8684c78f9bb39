"""A first start that says what it does (issue 32 item 7), through real DDS.

The controller with an empty solver cache (NMPC_AVOID_ROS_CACHE in a temp dir) compiles its
generated code before it serves: it logs that once, with the expected time and the cache folder
(core/nlp/codegen.py, passed to the ROS log by nodes/runner.py). The node is in the graph from the
start (created before the build), so a `send` started at the same time sees it, says on stderr that
it waits for a starting controller and delivers once the controller subscribes, instead of failing
with "is it running?" after its --timeout.

config/van_der_pol_fast.yaml (the stage-wise SQP) with a longer RK4 horizon: a compile of a few
seconds, longer than send's --timeout here, shorter than the live configs' minute or more.

A first start in seconds (issue 31 item 4): with codegen_background the live config's controller on an
empty cache commands within FIRST_COMMAND_BOUND of its start, with interpreted solvers, while its 6
libraries compile in a background process; the compiled solvers are swapped in between samples
(core/nlp/background.py) and the loop goes on. The test prints the time to the first command and to
the last swap.
"""

from __future__ import annotations

import time

import pytest
from rosgraph import ROOT, NodeProcess
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.nodes.controller_io import COMMAND_QOS

# a start within seconds of real time (send's 1 s, the first command's bound): alone on the machine
pytestmark = [pytest.mark.dds, pytest.mark.slow, pytest.mark.serial]

CONFIG = ROOT / "config" / "van_der_pol_fast.yaml"
BIGGER = ["-p", "horizon:=40", "-p", "discretization:=rk4"]
#: send's --timeout here: far below the compile, so only the wait for a starting node can deliver
SEND_TIMEOUT = 1.0
LIVE = ROOT / "config" / "van_der_pol_live.yaml"
#: interpreted solvers while the libraries compile (the setting's default is to wait for the compile)
BACKGROUND = ["-p", "codegen_background:=true"]
#: s from the controller's process start to its first command on an empty cache. The issue's goal is 10 s:
#: 7.4 s measured on an idle 2-core VM (Python, rclpy, the interpreted build, the first sample), 13 s with
#: a test suite running beside it at nice 10; before the background compile: 98 s (the compile of 6 NLPs)
FIRST_COMMAND_BOUND = 25.0
#: s for the first of the live config's 6 libraries to compile in the background (~15 s on 2 cores; all: ~80 s)
COMPILE_LIMIT = 400.0


def build_seconds(probe, heard: list[dict[str, str]]) -> float | None:
    """The controller's solver build time, s, from its /diagnostics (solver_build_s; up to 10 s for one to arrive)."""
    probe.spin_until(lambda: any("solver_build_s" in d for d in heard), 10.0)
    return next((float(d["solver_build_s"]) for d in heard if "solver_build_s" in d), None)


def test_a_first_start_logs_its_compile_and_send_waits_for_it(ros_graph, tmp_path):
    _, env, start, probe_factory = ros_graph
    probe = probe_factory()
    heard = probe.diagnostics_of()
    cache = tmp_path / "solver_cache"
    cold = {**env, "NMPC_AVOID_ROS_CACHE": str(cache)}
    log_dir = tmp_path / "ros_logs"
    ctrl = NodeProcess("controller", ["--ros-args", "--params-file", str(CONFIG), *BIGGER], cold, log_dir)
    try:
        started = time.monotonic()
        send = start("send", "target", "5", "--timeout", str(SEND_TIMEOUT))
        code = send.proc.wait(300)
        waited = time.monotonic() - started
        out, sent = ctrl.output(), send.output()
        built = build_seconds(probe, heard)
        print(f"first start: solver built in {built} s; send exited {code} after "
              f"{waited:.1f} s (its --timeout {SEND_TIMEOUT:g} s)")
        assert code == 0, (sent, out[-3000:])
        compiling = [line for line in out.splitlines() if "compiling the solver's generated code" in line]
        assert len(compiling) == 1, out[-3000:]  # once, though the config compiles more than one NLP
        assert "s per NLP" in compiling[0] and str(cache) in compiling[0], compiling
        print(compiling[0], *[line for line in sent.splitlines() if "starting" in line], sep="\n")
        assert "generated and compiled" in out, out[-3000:]
        assert built is not None and built > SEND_TIMEOUT  # the compile outlasted send's own timeout ...
        assert "/controller is up but has no subscription on /target yet" in sent, sent  # ... and send waited
        assert "acknowledged by /controller" in sent, sent
        assert "target y_t = [5.0]" in ctrl.output(), ctrl.output()[-3000:]
        assert list(cache.glob("nmpc_*.so")), list(cache.iterdir())
    finally:
        assert ctrl.stop() == 0


def test_a_first_start_on_an_empty_cache_commands_within_seconds_and_swaps_in_the_compiled_solvers(ros_graph,
                                                                                                    tmp_path):
    _, env, start, probe_factory = ros_graph
    cache = tmp_path / "solver_cache"
    cold = {**env, "NMPC_AVOID_ROS_CACHE": str(cache)}
    probe = probe_factory()
    heard = probe.diagnostics_of()
    commands: list[float] = []
    probe.node.create_subscription(Float64MultiArray, "command", lambda m: commands.append(time.monotonic()),
                                   COMMAND_QOS)
    start("plant", "--ros-args", "--params-file", str(LIVE))
    started = time.monotonic()
    ctrl = NodeProcess("controller", ["--ros-args", "--params-file", str(LIVE), *BACKGROUND, "-p", "target:=[5.0]"],
                       cold, tmp_path / "ros_logs")
    try:
        assert probe.spin_until(lambda: bool(commands), 120.0), ctrl.output()[-3000:]
        first = commands[0] - started
        built = build_seconds(probe, heard)
        print(f"first start on an empty cache: solver built in {built} s, first command "
              f"{first:.2f} s after the controller's start")
        assert first < FIRST_COMMAND_BOUND, ctrl.output()[-3000:]
        out = ctrl.output()
        assert "compiling the solver's generated code in the background" in out, out[-3000:]
        # the first swap between samples, and the loop goes on (all six: test_first_start.py, offline; waiting for
        # them here took 80 s of make test): stopped then, mid-compile, the controller leaves no job or build behind
        assert probe.spin_until(lambda: "compiled solver(s) swapped in" in ctrl.output(), COMPILE_LIMIT), \
            ctrl.output()[-3000:]
        print(f"first compiled solver swapped in {time.monotonic() - started:.1f} s after the start")
        heard = len(commands)
        assert probe.spin_until(lambda: len(commands) >= heard + 4, 10.0), ctrl.output()[-3000:]  # the loop goes on
        assert list(cache.glob("nmpc_*.so")), list(cache.iterdir())
        assert "failed" not in ctrl.output(), ctrl.output()[-3000:]
    finally:
        assert ctrl.stop() == 0
    # the compiled solvers and the feedback laws' saved derivatives stay; nothing else (a half-written save neither)
    leftovers = lambda: [p for p in cache.iterdir() if p.suffix not in (".so", ".casadi")]  # noqa: E731
    deadline = time.monotonic() + 10.0  # the compile process ends on its parent's end and removes its folder
    while leftovers() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not leftovers(), list(cache.iterdir())  # no job or build left
