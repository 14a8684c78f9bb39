"""A process ends cleanly while a thread is still in CasADi's native code (core/nlp/native_threads.py).

CasADi releases the interpreter lock in its long calls; a daemon thread inside one when the interpreter finalised
crashed the process (exit 134 or 139 after a clean stop; a first start's feedback law of the 40-sample passage NLP
takes ~14 s). The node's exit now waits NATIVE_EXIT_WAIT for such threads, then leaves without finalising.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest
from rosgraph import ROOT

from nmpc_avoid_ros.nodes.runner import NATIVE_EXIT_WAIT

LEAVING = """
import atexit, pathlib, sys, time
import casadi as ca
from nmpc_avoid_ros.core.nlp.native_threads import leave, scratch, start_native, wait_native

def symbolic():  # native work: the Hessian of a long sum, seconds of CasADi with the interpreter lock released
    x = ca.SX.sym("x", 400)
    for _ in range(100000):  # minutes: the process must not wait for it
        ca.hessian(ca.sum1(ca.sin(x) * ca.cos(x[::-1]) ** 2), x)

atexit.register(lambda: pathlib.Path(sys.argv[1]).write_text("exit handlers ran"))
build = pathlib.Path(sys.argv[2])
build.mkdir()
(build / "half.c").write_text("int half;")
start_native(symbolic, name="symbolic")
time.sleep(0.2)
print(wait_native(0.1), flush=True)
with scratch(build):  # a compile's temporary folder, being written when the process ends
    leave(3)
"""


def test_leave_runs_the_exit_handlers_removes_the_scratch_and_ends_with_the_code_while_a_native_thread_runs(tmp_path):
    marker = tmp_path / "atexit.txt"
    begin = time.monotonic()
    build = tmp_path / "tmpbuild"
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(LEAVING), str(marker), str(build)],
                          capture_output=True, text=True, timeout=60, cwd=ROOT)
    elapsed = time.monotonic() - begin
    assert done.returncode == 3, done.stderr
    assert done.stdout.strip() == "['symbolic']"  # still running when the process ended
    assert marker.read_text() == "exit handlers ran" and not build.exists()
    assert elapsed < 10.0, elapsed  # well before the symbolic work would have ended


@pytest.mark.dds
@pytest.mark.slow
def test_a_controller_stopped_while_its_passage_law_is_built_exits_0_within_the_wait(ros_graph, tmp_path):
    """The robot's live config with a 40-sample passage NLP, on an empty cache: that NLP's feedback law is built by a
    thread for ~14 s after the controller is active; SIGINT then (a user's Ctrl-C) ends the process with 0."""
    _, _, start, _ = ros_graph
    config = (ROOT / "config" / "mobile_robot_live.yaml").read_text()
    assert config.count("    horizon: 20\n") == 1 and "escape_horizon" not in config
    params = tmp_path / "robot40.yaml"
    params.write_text(config.replace("    horizon: 20\n", "    horizon: 20\n    escape_horizon: 40\n"))
    ctrl = start("controller", "--ros-args", "--params-file", str(params), "-p", f"cache_dir:={tmp_path / 'cache'}")
    deadline = time.monotonic() + 90
    while "controller active" not in ctrl.output() and time.monotonic() < deadline:
        assert ctrl.alive(), ctrl.output()
        time.sleep(0.1)
    assert "controller active" in ctrl.output()
    begin = time.monotonic()
    assert ctrl.stop(signal.SIGINT) == 0, ctrl.output()[-3000:]
    elapsed = time.monotonic() - begin
    leaving = [line for line in ctrl.output().splitlines() if line.startswith("controller: leaving without")]
    assert len(leaving) == 1 and "feedback-laws" in leaving[0], ctrl.output()[-3000:]
    assert elapsed < NATIVE_EXIT_WAIT + 3.0, elapsed
