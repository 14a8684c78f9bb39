"""The plant's actuator delay (`input_delay`, nodes/plant.py): a command acts that long after it arrives."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from rosgraph import CONFIG
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.ros.parameters import STREAM_QOS

pytestmark = pytest.mark.dds

DELAY = 0.1
SAMPLE_TIME = 0.5
X0 = [-5.0, 0.0]
COMMANDS = [[2.0], [-3.0], [1.5]]


def test_a_lockstep_plant_acts_on_each_command_its_delay_after_it_arrives(ros_graph):
    """Each step integrates the previous command for DELAY s, then the new one for the rest of the sample."""
    _, _, start, probe = ros_graph
    p = probe()
    states: list[list[float]] = []
    p.node.create_subscription(Float64MultiArray, "state", lambda m: states.append(list(m.data)), STREAM_QOS)
    command = p.node.create_publisher(Float64MultiArray, "command", STREAM_QOS)
    plant = start("plant", "--ros-args", "--params-file", str(CONFIG), "-p", "lockstep:=true",
                  "-p", f"input_delay:={DELAY}", "-p", "integration:=continuous", "-p", f"initial_state:={X0}")
    assert p.spin_until(lambda: len(states) >= 1, 60), plant.output()
    for k, u in enumerate(COMMANDS, start=1):
        command.publish(Float64MultiArray(data=u))
        assert p.spin_until(lambda k=k: len(states) > k, 30), plant.output()
    sim, x, previous = ContinuousPlant(make_model("van_der_pol")), np.array(X0), np.zeros(1)
    expected = [x]
    for u in COMMANDS:
        x = sim.advance(sim.advance(x, previous, DELAY), np.array(u), SAMPLE_TIME - DELAY)
        expected.append(x)
        previous = np.array(u)
    assert np.allclose(states[: len(expected)], expected, atol=1e-9, rtol=0), (states, expected)
    # not the undelayed step: the delay is felt
    assert not np.allclose(states[1], sim.advance(np.array(X0), np.array(COMMANDS[0]), SAMPLE_TIME), atol=1e-3)
    assert plant.stop() == 0


@pytest.mark.parametrize("bad", [["lockstep:=true", "input_delay:=0.5"],  # not below sample_time 0.5
                                 ["lockstep:=true", "integration:=euler", "input_delay:=0.1"]])
def test_a_delay_lockstep_cannot_integrate_is_refused_in_one_line(ros_graph, bad):
    _, env, _, _ = ros_graph
    args = [a for b in bad for a in ("-p", b)]
    res = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", "plant", "--ros-args", "--params-file",
                          str(CONFIG), *args], env=env, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "input_delay" in res.stderr.strip().splitlines()[-1], res.stderr


@pytest.mark.parametrize("lag", [0.0, 0.012, 0.3])
def test_a_real_time_command_acts_from_its_dds_reception_not_from_its_callback(lag):
    """A busy executor runs a command's callback after the middleware received it: the plant acts from the
    reception stamp (a real actuator does not wait for the interpreter), a stamp it cannot trust from now."""
    import time

    from nmpc_avoid_ros.nodes.plant import arrival_instant
    from nmpc_avoid_ros.ros.conversions import DDS_STAMP_SKEW

    before = time.monotonic()
    at = arrival_instant({"received_timestamp": time.time_ns() - round(lag * 1e9)})
    after = time.monotonic()
    assert before - lag - 2e-3 <= at <= after - lag + 2e-3
    for untrusted in ({}, None, {"received_timestamp": 0},
                      {"received_timestamp": time.time_ns() - round((DDS_STAMP_SKEW + 1) * 1e9)},
                      {"received_timestamp": time.time_ns() + 10**9}):
        before = time.monotonic()
        assert before <= arrival_instant(untrusted) <= time.monotonic()
