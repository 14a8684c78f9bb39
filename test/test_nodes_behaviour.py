"""The controller node through real DDS: targets, obstacles, parameters, stale state, garbage,
namespaces, process hygiene. Each test starts real node processes in an isolated domain."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rosgraph import CONFIG
from std_msgs.msg import Float64MultiArray
from test_readme import reference_diagnostic_keys
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.loop.closed_loop import DiscretePlant, run_closed_loop
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon, rotated_box
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.ros.markers import delete_marker, ellipse_marker, regions_to_markers
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS

pytestmark = pytest.mark.dds

PARAMS = ["--ros-args", "--params-file", str(CONFIG)]


class Listener:
    """Probe subscriptions: states, commands and the controller's diagnostics (as dicts)."""

    def __init__(self, probe, ns: str = "") -> None:
        self.probe = probe
        self.states: list[list[float]] = []
        self.commands: list[list[float]] = []
        self.diags: list[dict] = []
        self.predictions: list[list[tuple[float, float]]] = []
        node = probe.node
        node.create_subscription(Float64MultiArray, f"{ns}/state", lambda m: self.states.append(list(m.data)),
                                 STREAM_QOS)
        node.create_subscription(Float64MultiArray, f"{ns}/command", lambda m: self.commands.append(list(m.data)),
                                 STREAM_QOS)
        node.create_subscription(Path, f"{ns}/controller/prediction", self._on_path, STREAM_QOS)
        node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self._on_diag(m, ns), STREAM_QOS)
        self.target = node.create_publisher(Float64MultiArray, f"{ns}/target", LATCHED_QOS)
        self.obstacles = node.create_publisher(MarkerArray, f"{ns}/obstacles", LATCHED_QOS)
        self.state_pub = node.create_publisher(Float64MultiArray, f"{ns}/state", STREAM_QOS)

    def _on_path(self, msg: Path) -> None:
        self.predictions.append([(p.pose.position.x, p.pose.position.y) for p in msg.poses])

    def _on_diag(self, msg: DiagnosticArray, ns: str) -> None:
        for status in msg.status:
            if status.name.startswith(f"{ns}/controller"):
                values = {kv.key: kv.value for kv in status.values}
                values["level"] = int.from_bytes(status.level, "little") if isinstance(status.level, bytes) \
                    else int(status.level)
                values["message"] = status.message
                self.diags.append(values)

    def publish_target(self, *y: float) -> None:
        self.target.publish(Float64MultiArray(data=[float(v) for v in y]))

    def spin_until(self, done, timeout: float) -> bool:
        return self.probe.spin_until(done, timeout)


def start_pair(start, *extra: str, lockstep: bool = True, ns: str | None = None, subscribers: int = 2):
    remap = ["-r", f"__ns:={ns}"] if ns else []
    mode = ["-p", f"lockstep:={str(lockstep).lower()}"]
    ctrl = start("controller", *PARAMS, *mode, *remap, *extra)
    plant_extra = ["-p", "integration:=euler", "-p", f"wait_for_subscribers:={subscribers}"] if lockstep else []
    plant = start("plant", *PARAMS, *mode, *remap, *plant_extra)
    return ctrl, plant


@pytest.mark.slow
def test_shipped_config_closes_the_paper_loop_in_real_time_once_a_target_arrives(ros_graph):
    _, _, start, probe = ros_graph
    listen = Listener(probe())
    ctrl, plant = start_pair(start, lockstep=False)
    # no target yet: the controller commands the safe behaviour, no solve
    assert listen.spin_until(lambda: len(listen.diags) >= 2, 30), ctrl.output()
    assert all("solve_time_ms" not in d for d in listen.diags)
    listen.publish_target(5.0)
    solved = lambda: [d for d in listen.diags if "solve_time_ms" in d]  # noqa: E731
    settled = lambda: len(solved()) > 5 and abs(json.loads(solved()[-1]["state"])[0] - 5.0) < 0.05  # noqa: E731
    assert listen.spin_until(settled, 60), (ctrl.output(), plant.output())
    samples = np.array([json.loads(d["state"]) for d in solved()])
    assert np.max(np.abs(samples[:, 0] * samples[:, 1])) <= 2.05
    assert {d["status"] for d in solved()} == {"ok"}
    assert solved()[-1]["mu"] == "1e+08"
    assert reference_diagnostic_keys() <= set(solved()[-1]), reference_diagnostic_keys() - set(solved()[-1])
    assert ctrl.stop(signal.SIGINT) == 0 and plant.stop(signal.SIGTERM) == 0
    assert "controller ready" in ctrl.output() and "plant ready" in plant.output()


@pytest.mark.slow
def test_target_change_and_an_obstacle_mid_run_through_topics(ros_graph):
    """The probe is the plant (the paper's Euler map), so it can hold the loop while a message travels."""
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    listen.publish_target(5.0)
    ctrl = start("controller", *PARAMS, "-p", "lockstep:=true")
    plant = DiscretePlant(make_model("van_der_pol"), 0.5)
    x = [-5.0, 0.0]
    states = [x]

    def drive(steps: int) -> dict:
        nonlocal x
        for _ in range(steps):
            u, diag = lockstep_command(listen, x)
            x = plant.advance(np.array(x), np.array(u), 0.5).tolist()
            states.append(x)
        return diag

    drive(40)
    assert abs(x[0] - 5.0) < 0.05
    listen.publish_target(-3.0)  # a new target, mid-run
    assert listen.spin_until(lambda: "[-3.0]" in ctrl.output(), 10)
    drive(1)
    # an ellipse on the path the loop is about to take, six samples ahead (beyond the horizon, so
    # the dynamics leave room to go around; the offline loop from here predicts that path)
    free_path = run_closed_loop(NmpcController(ControllerSettings()), x, [-3.0], 6, "euler").x
    blocker = Ellipse(center=tuple(free_path[6]), semi_axes=(0.4, 0.2))
    listen.obstacles.publish(MarkerArray(markers=[ellipse_marker(blocker, marker_id=7, ns="test")]))
    assert listen.spin_until(lambda: "1 obstacle region(s) active" in ctrl.output(), 10) or True
    k_obstacle = len(states)
    diag = drive(1)
    assert diag["regions"] == "1", diag
    drive(24)
    depth = max(blocker.depth(s) for s in states[k_obstacle:])
    assert depth <= 0.01, depth  # never inside beyond 1 % of the normalised radius
    listen.obstacles.publish(MarkerArray(markers=[delete_marker("test", 7)]))
    assert listen.spin_until(lambda: False, 0.5) or True
    diag = drive(40)
    assert diag["regions"] == "0"
    assert abs(x[0] + 3.0) < 0.05 and abs(x[1]) < 0.05
    assert {d["status"] for d in listen.diags if "status" in d} == {"ok"}
    assert ctrl.stop() == 0


def lockstep_command(listen: Listener, x: list[float], timeout: float = 20.0) -> tuple[list[float], dict]:
    """Act as the plant: publish x, wait for the controller's command and its diagnostics."""
    n_cmd, n_diag = len(listen.commands), len(listen.diags)
    answered = lambda: len(listen.commands) > n_cmd and len(listen.diags) > n_diag  # noqa: E731
    for _ in range(int(timeout)):
        # re-sent while discovery completes; a repeated state is solved again (same answer)
        listen.state_pub.publish(Float64MultiArray(data=x))
        if listen.spin_until(answered, 1.0):
            return listen.commands[-1], listen.diags[-1]
    raise AssertionError(f"no answer to state {x}")


def controller_with_probe(ros_graph, target: float, *args: str):
    """A controller alone, the probe acting as its plant: (probe, listener, process), once it listens."""
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    listen.publish_target(target)
    ctrl = start("controller", *PARAMS, *args)
    assert listen.spin_until(lambda: p.node.count_subscribers("state") >= 1, 30), ctrl.output()
    return p, listen, ctrl


def test_param_set_of_mu_and_kappa_takes_effect_at_the_next_sample_and_bad_values_are_refused(ros_graph):
    p, listen, ctrl = controller_with_probe(ros_graph, 5.0, "-p", "lockstep:=true", "-p", "kappa:=5000.0")
    u_first, diag = lockstep_command(listen, [-5.0, 0.0])
    assert diag["kappa"] == "5000" and diag["mu"] == "1e+08"  # -p overrides the params file
    client = AsyncParameterClient(p.node, "controller")
    assert client.wait_for_services(10)
    described = client.describe_parameters(["mu", "horizon", "max_iterations"])
    assert listen.spin_until(described.done, 10)
    mu, horizon, budget = described.result().descriptors  # as declared in core/config/settings.py
    assert not mu.read_only and mu.floating_point_range[0].from_value == 0.0
    assert horizon.read_only and budget.read_only and horizon.integer_range[0].to_value == 2000

    def set_params(*params: Parameter):
        future = client.set_parameters(list(params))
        assert listen.spin_until(future.done, 10)
        return future.result().results

    results = set_params(Parameter("mu", value=0.0), Parameter("kappa", value=1e4))
    assert all(r.successful for r in results)
    u_ref = NmpcController(ControllerSettings(mu=0.0)).step([-5.0, 0.0], [5.0]).u
    u_next, diag = lockstep_command(listen, [-5.0, 0.0])
    assert diag["mu"] == "0" and diag["kappa"] == "10000"
    assert abs(u_next[0] - u_first[0]) > 1.0  # mu = 0 changes the first command of the paper run
    assert u_next[0] == pytest.approx(u_ref[0], abs=1e-3)
    for bad in (Parameter("mu", value=-1.0), Parameter("kappa", value=math.nan), Parameter("mu", value=math.nan),
                Parameter("state_weights", value=[1.0])):
        (result,) = set_params(bad)
        assert not result.successful and result.reason, bad.name
    (result,) = set_params(Parameter("horizon", value=10))
    assert not result.successful and "read-only" in result.reason.lower()
    # the node's own parameters are validated through the same declarations; a bad batch changes nothing
    for bad in (Parameter("stale_behavior", value="panic"), Parameter("target", value=[1.0, 2.0]),
                Parameter("safe_input", value=[0.0, 0.0])):
        (result,) = set_params(bad)
        assert not result.successful and bad.name in result.reason, (bad.name, result.reason)
    batch = client.set_parameters_atomically([Parameter("mu", value=5.0), Parameter("stale_behavior", value="panic")])
    assert listen.spin_until(batch.done, 10)
    assert not batch.result().result.successful  # all or nothing: mu stays 0 (checked below)
    _, diag = lockstep_command(listen, [-5.0, 0.0])
    assert diag["mu"] == "0" and diag["kappa"] == "10000"


def test_certificate_violations_warn_with_the_margin_then_error_and_go_on_the_certificate_topic(ros_graph):
    """A plant that is pushed away from y_t every sample breaks the nominal decrease again and again."""
    p, listen, ctrl = controller_with_probe(ros_graph, 5.0, "-p", "lockstep:=true", "-p", "mu:=0.0")
    certificates: list[Float64MultiArray] = []
    p.node.create_subscription(Float64MultiArray, "controller/certificate", certificates.append, STREAM_QOS)
    plant = DiscretePlant(make_model("van_der_pol"), 0.5)
    x = [4.0, 0.0]
    diags = []
    for _ in range(8):
        u, diag = lockstep_command(listen, x)
        diags.append(diag)
        x = (plant.advance(np.array(x), np.array(u), 0.5) - [0.6, 0.0]).tolist()
    violated = [d for d in diags if d["certificate_verdict"] == "violated"]
    assert violated, [d["certificate"] for d in diags]
    first = violated[0]
    assert first["level"] == 1 and "certificate violated by" in first["message"]
    assert float(first["certificate_margin"]) < 0
    assert float(first["decrease"]) > float(first["decrease_bound"])
    assert any(d["level"] == 2 for d in diags)  # three in a row: ERROR
    assert int(diags[-1]["certificate_violations"]) == len(violated)
    assert listen.spin_until(lambda: len(certificates) >= 8, 5)
    layout = certificates[-1].layout.dim[0].label.split(",")
    last = dict(zip(layout, certificates[-1].data))
    assert last["certificate_violations"] == len(violated) and last["value_function"] == \
        float(diags[-1]["value_function"])
    assert ctrl.stop() == 0


@pytest.mark.slow
def test_stale_state_triggers_the_safe_behaviour_and_an_error_then_control_resumes(ros_graph):
    p, listen, ctrl = controller_with_probe(ros_graph, 0.5, "-p", "state_timeout:=0.6", "-p", "sample_time:=0.2")

    def feed(seconds: float) -> None:
        end = p.node.get_clock().now().nanoseconds + seconds * 1e9
        while p.node.get_clock().now().nanoseconds < end:
            listen.state_pub.publish(Float64MultiArray(data=[0.5, 0.0]))
            p.spin_for(0.05)

    def solved() -> bool:  # discovery done both ways: states reach it, its diagnostics reach us
        feed(0.2)
        return bool(listen.diags) and listen.diags[-1].get("status") == "ok"

    assert p.spin_until(solved, 30), ctrl.output()
    feed(1.0)
    assert listen.diags and listen.diags[-1].get("status") == "ok"
    u_a = json.loads(listen.diags[-1]["command"])
    n_diag, n_cmd = len(listen.diags), len(listen.commands)
    p.spin_for(1.6)  # the plant "stops": no state for longer than the timeout
    after = listen.diags[n_diag:]
    errors = [d for d in after if d["level"] == 2]
    assert errors and "stale" in errors[0]["message"]
    assert len(listen.commands) - n_cmd >= 5  # a command every sample, still
    assert json.loads(errors[-1]["command"])[0] == pytest.approx(listen.commands[-1][0])
    assert abs(listen.commands[-1][0] - 0.5) < abs(u_a[0] - 0.5) + 0.6  # hold_steady: u_a of the last plan
    n_diag = len(listen.diags)
    feed(1.0)
    assert listen.diags[-1]["level"] == 0 and listen.diags[-1]["status"] == "ok"
    assert int(listen.diags[-1]["stale"]) >= 2
    assert ctrl.stop() == 0


@pytest.mark.slow
def test_garbage_on_every_input_never_stops_the_controller(ros_graph):
    p, listen, ctrl = controller_with_probe(ros_graph, 1.0, "-p", "sample_time:=0.2", "-p", "state_timeout:=5.0")
    good = Float64MultiArray(data=[0.5, 0.0])
    garbage_vectors = [[math.nan, 0.0], [1.0], [], [0.0, 0.0, 0.0], [math.inf, 1.0]]
    bad_markers = []
    for i, (mtype, sx) in enumerate([(Marker.CYLINDER, -1.0), (Marker.SPHERE, math.nan), (42, 1.0),
                                     (Marker.LINE_STRIP, 1.0), (Marker.CUBE, 0.0)]):
        m = Marker(type=mtype, id=i, ns="junk")
        m.scale.x = m.scale.y = sx
        bad_markers.append(m)
    flood = MarkerArray(markers=[Marker(type=Marker.CYLINDER, id=i) for i in range(10_000)])

    def loop_closed() -> bool:  # discovery done both ways: our state reaches it, its command reaches us
        listen.state_pub.publish(good)
        p.spin_for(0.1)
        return bool(listen.commands)

    assert listen.spin_until(loop_closed, 30), ctrl.output()
    n_cmd = len(listen.commands)
    for k in range(10):
        listen.state_pub.publish(good)
        listen.state_pub.publish(Float64MultiArray(data=garbage_vectors[k % 5]))
        listen.target.publish(Float64MultiArray(data=garbage_vectors[(k + 1) % 5]))
        listen.obstacles.publish(MarkerArray(markers=bad_markers))
        if k == 5:
            listen.obstacles.publish(flood)
        p.spin_for(0.2)
    listen.state_pub.publish(good)
    p.spin_for(1.0)
    assert ctrl.alive(), ctrl.output()
    assert len(listen.commands) - n_cmd >= 8  # about one per 0.2 s sample over ~3 s
    last = listen.diags[-1]
    assert int(last["rejected_inputs"]) >= 30
    # samples after the last good state coast on the plan; the last solved sample is a clean solve
    solved = [d for d in listen.diags if d.get("solver_status") not in (None, "no_new_state")]
    assert solved[-1]["status"] == "ok" and last["regions"] == "0"
    assert json.loads(solved[-1]["state"]) == [0.5, 0.0]  # the last good state, never a garbage one
    assert "rejected" in ctrl.output()
    assert ctrl.stop() == 0


@pytest.mark.slow
def test_two_pairs_in_namespaces_run_side_by_side_without_crosstalk(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    one, two = Listener(p, "/robot1"), Listener(p, "/robot2")
    one.publish_target(5.0)
    two.publish_target(-3.0)
    procs = [*start_pair(start, "-p", "mu:=0.0", ns="/robot1"), *start_pair(start, "-p", "mu:=0.0", ns="/robot2")]
    assert p.spin_until(lambda: len(one.states) >= 40 and len(two.states) >= 40, 90), [x.output() for x in procs]
    assert abs(one.states[-1][0] - 5.0) < 0.05 and abs(two.states[-1][0] + 3.0) < 0.05
    assert all(d["y_a"] != "[-3.0]" for d in one.diags if "y_a" in d)
    assert all(proc.stop() == 0 for proc in procs)


@pytest.mark.parametrize("command", ["controller", "plant"])
def test_help_and_bad_configuration_exit_codes(command, ros_graph):
    _, env, _, _ = ros_graph
    res = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", command, "--help"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0 and "ros-args" in res.stdout
    # controller: out of the declared ROS range, the wrong ROS type (an integer for a double), refused by
    # the core declaration (a node setting) -- each one line naming the parameter
    bads = ("horizon:=0", "mu:=0", "stale_behavior:=panic", "safe_input:=[9.0]") if command == "controller" \
        else ("initial_state:=[1.0]",)
    for bad in bads:
        res = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", command, *PARAMS, "-p", bad], env=env,
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and "configuration error" in res.stderr and "Traceback" not in res.stderr, bad
        assert bad.split(":=")[0] in res.stderr.strip().splitlines()[-1], res.stderr


@pytest.mark.slow
def test_mobile_robot_reaches_its_goal_among_obstacles_published_as_markers(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    config = str(CONFIG.parent / "mobile_robot.yaml")
    regions = [Ellipse((-3.0, -2.5), (1.2, 1.2), frame="output"), Ellipse((3.0, 2.0), (1.0, 1.5), 0.5, "output"),
               rotated_box((0.0, 0.0), (2.0, 1.0), 0.6, "output"),
               Polygon(((4.5, 4.5), (6.5, 4.5), (5.5, 6.0)), "output")]
    listen.obstacles.publish(regions_to_markers(regions))
    listen.publish_target(8.0, 6.0)
    args = ["--ros-args", "--params-file", config, "-p", "lockstep:=true"]
    ctrl = start("controller", *args, "-p", "max_solve_time:=2.0")
    plant = start("plant", *args, "-p", "wait_for_subscribers:=2")
    assert p.spin_until(lambda: len(listen.states) >= 121, 120), (ctrl.output(), plant.output())
    xs = np.array(listen.states[:121])
    assert np.hypot(xs[-1, 0] - 8.0, xs[-1, 1] - 6.0) < 0.05
    assert max(max(r.depth(x[:2]) for r in regions) for x in xs) <= 0.01
    assert listen.diags[-1]["regions"] == "4"
    # the straight line from start to goal crosses the box: the obstacles changed the path
    assert rotated_box((0.0, 0.0), (2.0, 1.0), 0.6).depth((0.0, 0.0)) > 0
    assert plant.stop() == 0 and ctrl.stop() == 0
