"""A first start that says what it does (issue 32 item 7), through real DDS.

The controller with an empty solver cache (NMPC_AVOID_ROS_CACHE in a temp dir) compiles its
generated code before it serves: it logs that once, with the expected time and the cache folder
(core/nlp/codegen.py, passed to the ROS log by nodes/runner.py). The node is in the graph from the
start (created before the build), so a `send` started at the same time sees it, says on stderr that
it waits for a starting controller and delivers once the controller subscribes, instead of failing
with "is it running?" after its --timeout.

config/van_der_pol_fast.yaml (the stage-wise SQP) with a longer RK4 horizon: a compile of a few
seconds, longer than send's --timeout here, shorter than the live configs' minute or more.
"""

from __future__ import annotations

import re
import time

import pytest
from rosgraph import ROOT, NodeProcess

pytestmark = [pytest.mark.dds, pytest.mark.slow]

CONFIG = ROOT / "config" / "van_der_pol_fast.yaml"
BIGGER = ["-p", "horizon:=40", "-p", "discretization:=rk4"]
#: send's --timeout here: far below the compile, so only the wait for a starting node can deliver
SEND_TIMEOUT = 1.0


def test_a_first_start_logs_its_compile_and_send_waits_for_it(ros_graph, tmp_path):
    _, env, start, _ = ros_graph
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
        built = re.search(r"solver built in ([0-9.]+) s", out)
        print(f"first start: solver built in {built.group(1) if built else '?'} s; send exited {code} after "
              f"{waited:.1f} s (its --timeout {SEND_TIMEOUT:g} s)")
        assert code == 0, (sent, out[-3000:])
        compiling = [line for line in out.splitlines() if "compiling the solver's generated code" in line]
        assert len(compiling) == 1, out[-3000:]  # once, though the config compiles more than one NLP
        assert "s per NLP" in compiling[0] and str(cache) in compiling[0], compiling
        print(compiling[0], *[line for line in sent.splitlines() if "starting" in line], sep="\n")
        assert "generated and compiled" in out, out[-3000:]
        assert float(built.group(1)) > SEND_TIMEOUT  # the compile outlasted send's own timeout ...
        assert "/controller is up but has no subscription on /target yet" in sent, sent  # ... and send waited
        assert "acknowledged by /controller" in sent, sent
        assert "target y_t = [5.0]" in ctrl.output(), ctrl.output()[-3000:]
        assert list(cache.glob("nmpc_*.so")), list(cache.iterdir())
    finally:
        assert ctrl.stop() == 0
