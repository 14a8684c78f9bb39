"""`send goal X Y [YAW]` (issue 33 item 3) through real DDS: a PoseStamped on `goal_pose` in the
controller's odom frame reaches the robot-interface controller (its verdict `accepted`, its target the
goal's position) and the recorder (the bag's /goal_pose holds every goal, in order), call after call;
to a controller of the array interface it fails at once, naming the interface.

The unicycle (config/unicycle.yaml, robot interface) without a plant: the idle controller publishes
its diagnostics every sample (ERROR: no odometry), which carry `goal_pose_received` / `_verdict` /
`_reason` and `goal_pose_applied` (the targets it took). The recorder's ~/counts say when it wrote each goal.
"""

from __future__ import annotations

import json
import math

import pytest
from rosgraph import CONFIG, ROOT, run_send

from nmpc_avoid_ros.bag.mcap_io import load_bag
from nmpc_avoid_ros.tools.processes import recorder_counts

pytestmark = pytest.mark.dds

UNICYCLE = ROOT / "config" / "unicycle.yaml"
NO_COMPILE = ["-p", "codegen:=false"]
#: goals sent after the first (20 in a row by hand: 20 of 20 reached both; 17 of 20 before send lingered)
REPEATS = 5


def test_send_goal_reaches_the_robot_controller_and_the_recorder_every_time(ros_graph, tmp_path) -> None:
    _, env, start, probe_factory = ros_graph
    bag_path = tmp_path / "goals.mcap"
    recorder = start("recorder", "--ros-args", "-p", f"output:={bag_path}")
    ctrl = start("controller", "--ros-args", "--params-file", str(UNICYCLE), *NO_COMPILE)
    probe = probe_factory()
    diags = probe.diagnostics_of("/controller")
    counts = recorder_counts(probe.node)
    for name, proc in (("recorder", recorder), ("controller", ctrl)):
        assert probe.heard_by(name, 120.0), proc.output()[-3000:]
    # the recorder subscribes to goal_pose once the graph shows the controller's subscription
    assert probe.spin_until(lambda: any(i.node_name == "recorder" for i in
                                        probe.node.get_subscriptions_info_by_topic("/goal_pose")), 30.0), \
        recorder.output()[-3000:]
    assert probe.spin_until(lambda: bool(diags) and "goal_pose_received" in diags[-1], 10.0), ctrl.output()[-3000:]
    assert diags[-1]["goal_pose_verdict"] == "none"

    def send_goal(*args: str) -> str:
        proc, seconds = run_send(env, "goal", *args)
        assert proc.returncode == 0, (args, proc.stdout, proc.stderr, ctrl.output()[-2000:])
        assert "acknowledged by /controller, /recorder; accepted by /controller" in proc.stdout, proc.stdout
        assert not proc.stderr.strip(), proc.stderr  # every reader matched and acknowledged it
        print(f"send goal {' '.join(args)}: {seconds:.1f} s")
        return proc.stdout

    sent = [(3.0, 2.0, 0.0)]
    line = send_goal("3", "2")
    assert "goal [3, 2] yaw 0 on /goal_pose" in line, line
    assert probe.spin_until(lambda: diags[-1]["goal_pose_received"] == "1", 5.0), diags[-1]
    assert (diags[-1]["goal_pose_verdict"], diags[-1]["goal_pose_reason"]) == ("accepted", "")
    assert json.loads(diags[-1]["goal_pose_applied"]) == [[3.0, 2.0]]  # the target it took: the goal's position

    for i in range(REPEATS):  # each call reaches both: the recorder's count of /goal_pose goes up by one
        goal = (3.0 - i, 2.0 + 0.5 * i, 0.4 * i - 0.8)
        send_goal(*(f"{v:g}" for v in goal))
        sent.append(goal)
        assert probe.spin_until(lambda: counts.get("/goal_pose") == len(sent), 5.0), counts
    assert probe.spin_until(lambda: diags[-1]["goal_pose_received"] == str(len(sent)), 5.0), diags[-1]
    assert json.loads(diags[-1]["goal_pose_applied"]) == [[x, y] for x, y, _ in sent]

    # the robot interface subscribes `target` too (an array y_t of p = 2 values)
    proc, _ = run_send(env, "target", "1", "1")
    assert proc.returncode == 0 and "accepted by /controller" in proc.stdout, (proc.stdout, proc.stderr)

    assert recorder.stop() == 0
    assert ctrl.stop() == 0
    goals = [msg for _, msg in load_bag(bag_path).topics["/goal_pose"]]
    assert [(g.pose.position.x, g.pose.position.y) for g in goals] == [(x, y) for x, y, _ in sent]
    for g, (_, _, yaw) in zip(goals, sent):
        assert g.header.frame_id == "odom"  # the controller's odom_frame
        q = g.pose.orientation
        assert math.isclose(2.0 * math.atan2(q.z, q.w), yaw, abs_tol=1e-12), (q, yaw)
        assert g.header.stamp.sec > 0


def test_send_goal_to_an_array_controller_fails_naming_its_interface(ros_graph) -> None:
    _, env, start, probe_factory = ros_graph
    ctrl = start("controller", "--ros-args", "--params-file", str(CONFIG), *NO_COMPILE)
    assert probe_factory().heard_by("controller", 120.0), ctrl.output()[-3000:]
    proc, seconds = run_send(env, "goal", "3", "2", "--timeout", "10")
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert proc.stderr.strip() == (
        "send: /controller has no goal_pose subscription: its interface is 'array', and goal_pose is the robot "
        "interface's input (interface: robot); send it a target instead (send target ...)"), proc.stderr
    assert seconds < 10.0, seconds  # at once, not after --timeout
    print(f"\nsend goal to the array controller: exit 1 after {seconds:.1f} s")
