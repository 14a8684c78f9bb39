"""Moving obstacles through real DDS: the obstacles node, controller, plant and recorder with a
walker crossing (clearance by analyze on the bag), and bad moving markers refused or reset with a
reason in diagnostics while the controller keeps its last good regions."""

from __future__ import annotations

import math
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph import ROOT
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.bag.analysis import load_run
from nmpc_avoid_ros.core.regions import Ellipse
from nmpc_avoid_ros.core.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.ros.conversions import seconds_to_time
from nmpc_avoid_ros.ros.markers import region_marker
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS
from nmpc_avoid_ros.tools.scene_demo import run_scene_demo

ROBOT = ROOT / "config" / "mobile_robot.yaml"
WALKER = (ROOT / "config" / "scenes" / "crossing_walker.yaml").read_text()


def test_walker_crossing_through_dds_keeps_clearance_in_the_recorded_bag(ros_graph, tmp_path, monkeypatch):
    """obstacles node + controller + real-time plant + recorder; analyze on the bag: clearance >= -1e-3."""
    domain, env, _, _ = ros_graph
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR", "PYTHONPATH"):
        monkeypatch.setenv(key, env[key])
    scene = tmp_path / "walker.yaml"
    scene.write_text(WALKER.replace("steps: 80", "steps: 48"))  # the crossing is over by 10 s
    report = run_scene_demo(scene, tmp_path / "out", predict=True, timeout=240.0)
    (metrics,) = report["bags"]
    assert metrics["samples"] >= 48 and metrics["finished"]
    assert metrics["min_clearance_obstacles"] >= -1e-3, metrics
    settings = ControllerSettings.from_params(load_params_file(tmp_path / "out" / "params.yaml").section("controller"))
    run = load_run(tmp_path / "out" / "scene.mcap", settings=settings)
    # the controller saw the walker moving (explicit velocity) and the robot came close to it
    assert all(r.moving and r.velocity == pytest.approx((0.0, 0.5)) for regions in run.regions[5:] for r in regions)
    assert metrics["min_clearance_obstacles"] < 1.0
    assert (tmp_path / "out" / "phase_portrait.png").stat().st_size > 10_000


def test_bad_moving_markers_are_refused_or_reset_with_a_reason_and_the_last_good_regions_stay(ros_graph):
    _, _, start, probe_factory = ros_graph
    ctrl = start("controller", "--ros-args", "--params-file", str(ROBOT), "-p", "target:=[8.0, 0.0]",
                 "-p", "max_obstacle_speed:=2.0", "-p", "state_timeout:=30.0")
    probe = probe_factory()
    node = probe.node
    diags: list[dict] = []

    def on_diag(msg: DiagnosticArray) -> None:
        diags.extend({kv.key: kv.value for kv in s.values} for s in msg.status if "controller" in s.name)

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, STREAM_QOS)
    obstacles = node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
    states = node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    assert probe.spin_until(lambda: node.count_subscribers("state") >= 1 and node.count_subscribers("obstacles") >= 1,
                            120.0), ctrl.output()[-3000:]

    def now() -> float:
        return node.get_clock().now().nanoseconds * 1e-9

    def send(center, stamp: float | None = None, text: str | None = None) -> None:
        marker = region_marker(Ellipse(center, (0.5, 0.5), 0.0, "output"), 1, "tracker")
        marker.header.stamp = seconds_to_time(now() if stamp is None else stamp)
        if text is not None:
            marker.text = text
        obstacles.publish(MarkerArray(markers=[marker]))

    def settle(seconds: float) -> dict:
        """Feed states for a while; the controller's last solved diagnostic."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            states.publish(Float64MultiArray(data=[-8.0, 0.0, 0.0, 0.0]))
            probe.spin_for(0.1)
        solved = [d for d in diags if "solve_time_ms" in d]
        assert solved, ctrl.output()[-3000:]
        return solved[-1]

    send((3.0, -2.0), text="velocity=0.0,0.5")  # the good moving region
    good = settle(2.0)
    assert (good["regions"], good["moving_regions"]) == ("1", "1")
    cases = [
        (dict(text="velocity=nan,0.5"), "refused", "NaN or infinite"),
        (dict(text="velocity=inf,0"), "refused", "NaN or infinite"),
        (dict(text="velocity=2.5,0"), "refused", "exceeds max_obstacle_speed"),
        (dict(stamp=now() + 60.0, text="velocity=0.0,0.5"), "refused", "ahead of its receipt"),
        (dict(stamp=now() - 60.0, text="velocity=0.0,0.5"), "refused", "behind its receipt"),
    ]
    rejected, samples = int(good["rejected_inputs"]), int(good["samples"])
    for kwargs, verdict, reason in cases:
        send((9.0, 9.0), **kwargs)
        last = settle(0.8)
        assert last["last_obstacle_issue"].startswith(f"{verdict} tracker/1") and reason in last["last_obstacle_issue"]
        assert int(last["rejected_inputs"]) == rejected + 1
        rejected += 1
        # the last good region stays in force and the controller keeps solving
        assert (last["regions"], last["moving_regions"]) == ("1", "1"), last
        assert int(last["samples"]) > samples and math.isfinite(float(last["solve_time_ms"]))
        samples = int(last["samples"])
    # estimated motion: a stamped marker without velocity that jumps across the map is reset
    t0 = now()
    send((0.0, -3.0), stamp=t0)
    send((0.0, -2.9), stamp=t0 + 0.2)
    moving = settle(0.8)
    assert moving["moving_regions"] == "1"
    send((40.0, 40.0), stamp=t0 + 0.4)
    jumped = settle(0.8)
    assert jumped["last_obstacle_issue"].startswith("reset tracker/1") and "jumped" in jumped["last_obstacle_issue"]
    assert int(jumped["obstacle_resets"]) >= 1
    assert (jumped["regions"], jumped["moving_regions"]) == ("1", "0")
    assert ctrl.alive() and math.isfinite(float(jumped["solve_time_ms"]))
