"""Controller and plant as separate processes through real DDS topics, in lockstep."""

from __future__ import annotations

import numpy as np
import pytest
from rosgraph import CONFIG
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS

pytestmark = pytest.mark.dds

STEPS = 50


def run_lockstep(ros_graph, mu: float, extra: tuple[str, ...] = ()) -> np.ndarray:
    """Start plant + controller in lockstep, publish y_t = 5, collect x(0..STEPS)."""
    _domain, _env, start, probe = ros_graph
    p = probe()
    states: list[list[float]] = []
    p.node.create_subscription(Float64MultiArray, "state", lambda m: states.append(list(m.data)), STREAM_QOS)
    target = p.node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    target.publish(Float64MultiArray(data=[5.0]))
    common = ["--ros-args", "--params-file", str(CONFIG), "-p", "lockstep:=true"]
    ctrl = start("controller", *common, "-p", f"mu:={mu}", *extra)
    plant = start("plant", *common, "-p", "integration:=euler", "-p", "wait_for_subscribers:=2")
    assert p.spin_until(lambda: len(states) >= STEPS + 1, timeout=90), (len(states), ctrl.output(), plant.output())
    assert plant.stop() == 0 and ctrl.stop() == 0, ctrl.output()
    return np.array(states[: STEPS + 1])


@pytest.mark.parametrize("mu", [0.0, 1e8])
def test_lockstep_through_dds_reproduces_the_offline_loop(ros_graph, shipped_paper, mu):
    states = run_lockstep(ros_graph, mu)
    offline = shipped_paper(mu, "euler")
    np.testing.assert_allclose(states, offline.x, atol=1e-6, rtol=0)
