"""The managed controller through real DDS: its lifecycle driven by a lifecycle_msgs client, and
latched inputs that accept volatile publishers (`ros2 topic pub`), transient-local ones and a
controller that joins late."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.qos import QoSPresetProfiles
from std_msgs.msg import Float64MultiArray
from test_nodes_behaviour import PARAMS, Listener, lockstep_command

from nmpc_avoid_ros.core.loop.closed_loop import DiscretePlant
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS

pytestmark = pytest.mark.dds


class LifecycleClient:
    """The standard lifecycle services of one node, called from the probe."""

    def __init__(self, probe, node: str = "controller") -> None:
        self.probe = probe
        self.change = probe.node.create_client(ChangeState, f"/{node}/change_state")
        self.get = probe.node.create_client(GetState, f"/{node}/get_state")

    def _call(self, client, request):
        assert self.probe.spin_until(client.service_is_ready, 30), client.srv_name
        future = client.call_async(request)
        assert self.probe.spin_until(future.done, 60), client.srv_name
        return future.result()

    def state(self) -> int:
        return self._call(self.get, GetState.Request()).current_state.id

    def transition(self, transition_id: int) -> bool:
        return self._call(self.change, ChangeState.Request(transition=Transition(id=transition_id))).success


@pytest.mark.slow
def test_lifecycle_sequence_through_the_lifecycle_services(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    listen.publish_target(1.0)
    ctrl = start("controller", *PARAMS, "-p", "autostart:=false", "-p", "sample_time:=0.2",
                 "-p", "deactivate_command:=zero")
    life = LifecycleClient(p)
    assert life.state() == State.PRIMARY_STATE_UNCONFIGURED
    assert "controller ready" not in ctrl.output()  # nothing built before configure

    def feed(seconds: float) -> None:  # the probe as a plant resting at x = [0.5, 0]
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            listen.state_pub.publish(Float64MultiArray(data=[0.5, 0.0]))
            p.spin_for(0.05)

    assert life.transition(Transition.TRANSITION_CONFIGURE)
    assert life.state() == State.PRIMARY_STATE_INACTIVE
    assert ctrl.output().count("solver built") == 1  # the build happens in configure
    feed(1.0)
    assert listen.commands == [] and listen.diags == []  # inactive: no sample, no command

    def active_phase() -> None:
        assert life.transition(Transition.TRANSITION_ACTIVATE)
        assert life.state() == State.PRIMARY_STATE_ACTIVE
        n, n_start = len(listen.diags), len(listen.commands)
        end = time.monotonic() + 30
        while time.monotonic() < end and len([d for d in listen.diags[n:] if d.get("status") == "ok"]) < 5:
            feed(0.2)
        solved = [d for d in listen.diags[n:] if d.get("status") == "ok"]
        assert len(solved) >= 5, ctrl.output()
        assert json.loads(solved[-1]["y_a"])[0] > 0.55  # heading for the target 1.0
        n_cmd = len(listen.commands)
        assert life.transition(Transition.TRANSITION_DEACTIVATE)
        feed(1.5)  # states keep coming: an inactive controller must not answer them
        after = listen.commands[n_cmd:]
        # commands of samples before the request may still arrive; the zero command is the last,
        # once: nothing follows it
        assert after and after[-1] == [0.0] and after.count([0.0]) == 1, after
        assert all(c != [0.0] for c in listen.commands[n_start:n_cmd])
        assert life.state() == State.PRIMARY_STATE_INACTIVE

    active_phase()
    active_phase()  # re-activation works and reuses the configured solver
    assert ctrl.output().count("solver built") == 1
    assert p.node.count_publishers("/command") == 1
    assert life.transition(Transition.TRANSITION_CLEANUP)
    assert life.state() == State.PRIMARY_STATE_UNCONFIGURED
    assert p.spin_until(lambda: p.node.count_publishers("/command") == 0
                        and p.node.count_subscribers("/target") == 0, 10)  # released
    assert life.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
    assert life.state() == State.PRIMARY_STATE_FINALIZED
    assert ctrl.alive() and ctrl.stop() == 0


def test_volatile_and_transient_local_publishers_and_a_late_joining_controller(ros_graph):
    """Late joiner: a latched target published before the controller starts reaches it. Then a
    volatile publisher (what `ros2 topic pub` creates, no QoS flags) and a transient-local one
    each move the loop to their target; each sample is applied once (both readers see a
    transient-local sample)."""
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    listen.publish_target(1.0)  # latched, before the controller exists
    ctrl = start("controller", *PARAMS, "-p", "lockstep:=true")
    plant = DiscretePlant(make_model("van_der_pol"), 0.5)
    x = np.array([0.0, 0.0])

    def drive_to(goal: float, steps: int = 30) -> None:
        nonlocal x
        for _ in range(steps):
            u, _ = lockstep_command(listen, x.tolist())
            x = plant.advance(x, np.array(u), 0.5)
        assert abs(x[0] - goal) < 0.05, (goal, x, ctrl.output()[-2000:])

    def wait_until_applied(goal: float, timeout: float = 10.0) -> list[float]:
        """The targets the controller has applied (diagnostics `target_applied`), once `goal` is the last;
        each state sent to ask is the current one again (solved again, the plant does not move)."""
        end = time.monotonic() + timeout
        while True:
            _, diag = lockstep_command(listen, x.tolist())
            applied = [value for (value,) in json.loads(diag["target_applied"])]
            if applied and applied[-1] == goal or time.monotonic() > end:
                assert applied and applied[-1] == goal, (applied, ctrl.output()[-2000:])
                return applied

    drive_to(1.0)
    volatile = p.node.create_publisher(Float64MultiArray, "target", QoSPresetProfiles.DEFAULT.value)
    # as `ros2 topic pub --once` does: wait for a matching subscription, publish once
    assert p.spin_until(lambda: volatile.get_subscription_count() >= 1, 20)
    volatile.publish(Float64MultiArray(data=[-3.0]))
    wait_until_applied(-3.0)
    drive_to(-3.0, 40)
    latched = p.node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    assert p.spin_until(lambda: latched.get_subscription_count() >= 2, 20)  # both readers match it
    latched.publish(Float64MultiArray(data=[2.0]))
    wait_until_applied(2.0)
    drive_to(2.0, 40)
    burst = [2.1, 2.2, 2.3, 2.4, 2.5]  # back to back: each applied once, in order (both readers queue them)
    for value in burst:
        latched.publish(Float64MultiArray(data=[value]))
    wait_until_applied(2.5)
    p.spin_for(0.5)
    applied = wait_until_applied(2.5)
    # every target applied once, in order: the latched one before the controller existed, the volatile one,
    # the transient-local one and its burst (the controller's record, not its log: nodes/controller_inputs.py)
    assert applied == [1.0, -3.0, 2.0, *burst], applied
    assert "incompatible QoS" not in ctrl.output()
    assert ctrl.stop() == 0


def test_parameters_set_while_unconfigured_are_checked_then_applied_at_configure(tmp_path, monkeypatch):
    """In process, no graph needed: an unconfigured controller refuses bad values with the reason,
    keeps good ones, builds nothing, and configure uses them."""
    import rclpy
    from rclpy.parameter import Parameter

    from nmpc_avoid_ros.nodes.controller import SUCCESS, ControllerNode

    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(args=["controller", *PARAMS, "-p", "autostart:=false"], context=context, domain_id=200)
    node = ControllerNode(context=context)
    try:
        assert node.controller is None  # nothing built
        (bad,) = node.set_parameters([Parameter("mu", value=-1.0)])
        assert not bad.successful and "mu" in bad.reason
        (bad,) = node.set_parameters([Parameter("deactivate_command", value="nope")])
        assert not bad.successful
        assert all(r.successful for r in node.set_parameters([Parameter("mu", value=5.0),
                                                                Parameter("deactivate_command", value="hold_steady")]))
        assert node.trigger_configure() == SUCCESS
        assert node.controller.settings.mu == 5.0 and node.options.deactivate_command == "hold_steady"
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
