"""`send` (tools/send.py) through real DDS: the README's sequence reaches the controller and the
recorder, and `send` fails fast and clearly when nothing listens.

The live run is the README's: plant and controller with config/van_der_pol_live.yaml (continuous plant
in real time, RK4 prediction in 8 sub-steps, 3 cm margin), a recorder, then `send target 5`, the
README's ellipse, `send target -3` (past the ellipse), `send delete 1`, `send param mu 0`. The bag
must hold every message sent, and the loop must keep the ellipse clear at the samples and between
them (the recorded commands integrated at 10 points per sample, bag/analysis.py).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph import ROOT, run_send
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.bag.analysis import load_run, run_metrics
from nmpc_avoid_ros.bag.mcap_io import load_bag
from nmpc_avoid_ros.bench.live_truth import command_timing
from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.ros.parameters import STREAM_QOS

pytestmark = pytest.mark.dds

LIVE = ROOT / "config" / "van_der_pol_live.yaml"
#: the issue's bound on penetration, at the samples and between them
BOUND = 1e-3
#: interpreted CasADi functions instead of the ~70 s compile of a fresh machine: the same NLP (solve
#: median 8 ms, max 92 ms offline on the README's scene, within the 0.4 s budget)
NO_COMPILE = ["-p", "codegen:=false"]
#: the interpreted solves take longer than the compiled ones the live config's 60 ms hold is chosen for:
#: the command is held to 150 ms after the sample's start (nodes/command_timing.py), so it still leaves
#: at the instant the plan was predicted for
INTERPRETED_HOLD = ["-p", "command_latency:=0.15"]


def test_send_exits_1_within_its_timeout_when_no_controller_runs(ros_graph, tmp_path) -> None:
    """A recorder subscribes to `target` and `obstacles` too: a reader that is not the controller is not enough."""
    _, env, start, probe_factory = ros_graph
    recorder = start("recorder", "--ros-args", "-p", f"output:={tmp_path / 'bag.mcap'}")
    assert probe_factory().heard_by("recorder", 60.0), recorder.output()[-3000:]
    for args, what in ((["target", "5"], "no subscriber of /controller on /target"),
                       (["obstacle", "ellipse", "--center", "2", "-0.5", "--axes", "0.4", "0.2"],
                        "no subscriber of /controller on /obstacles"),
                       (["param", "mu", "0"], "no parameter service /controller/set_parameters")):
        proc, seconds = run_send(env, *args, "--timeout", "1.5")
        assert proc.returncode == 1, (args, proc.stdout, proc.stderr)
        assert what in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert seconds < 1.5 + 8.0, seconds  # the timeout plus starting Python, rclpy and a DDS participant


def test_send_refuses_bad_arguments_with_exit_2_before_any_dds(ros_graph) -> None:
    _, env, _, _ = ros_graph
    for args in (["target", "nan"], ["obstacle", "ellipse", "--center", "2", "0", "--axes", "0", "1"],
                 ["obstacle", "polygon", "--vertices", "0", "0", "1"], ["delete", "x"]):
        proc, seconds = run_send(env, *args)
        assert proc.returncode == 2, (args, proc.stderr)
        assert "error" in proc.stderr and seconds < 8.0, (args, proc.stderr, seconds)


@pytest.mark.slow
@pytest.mark.serial  # clearance in real time: alone on the machine
def test_the_readme_sequence_through_send_arrives_and_the_live_loop_keeps_the_ellipse_clear(ros_graph,
                                                                                          tmp_path) -> None:
    _, env, start, probe_factory = ros_graph
    bag_path = tmp_path / "readme.mcap"
    recorder = start("recorder", "--ros-args", "-p", f"output:={bag_path}")
    plant = start("plant", "--ros-args", "--params-file", str(LIVE))
    ctrl = start("controller", "--ros-args", "--params-file", str(LIVE), *NO_COMPILE, *INTERPRETED_HOLD)
    probe = probe_factory()
    states: list[list[float]] = []
    diags: list[dict[str, str]] = []
    probe.node.create_subscription(Float64MultiArray, "state", lambda m: states.append(list(m.data)), STREAM_QOS)
    probe.node.create_subscription(
        DiagnosticArray, "/diagnostics",
        lambda m: diags.extend({"message": s.message, **{kv.key: kv.value for kv in s.values}} for s in m.status
                               if "controller" in s.name),
        STREAM_QOS)
    for name, proc in (("recorder", recorder), ("controller", ctrl)):
        assert probe.heard_by(name, 60.0), proc.output()[-3000:]

    def recorder_listens(topic: str) -> bool:
        return any(i.node_name == "recorder" for i in probe.node.get_subscriptions_info_by_topic(topic))

    # the recorder subscribes to a topic once the graph shows its type (here: the controller's subscription);
    # a latched message sent before that is gone for it once `send` exits
    assert probe.spin_until(lambda: recorder_listens("/target") and recorder_listens("/obstacles"), 30.0), \
        recorder.output()[-3000:]

    def send(*args: str) -> str:
        proc, _ = run_send(env, *args)
        assert proc.returncode == 0, (args, proc.stderr, ctrl.output()[-2000:])
        assert "may not get this message" not in proc.stderr, (args, proc.stderr)  # every listed reader matched
        return proc.stdout

    def settle_at(x1: float, within: float) -> None:
        def settled() -> bool:
            return bool(states) and abs(states[-1][0] - x1) < 0.05 and abs(states[-1][1]) < 0.05
        assert probe.spin_until(settled, within), (states[-3:], ctrl.output()[-3000:])

    line = send("target", "5")
    assert "/controller" in line and "/recorder" in line, line  # both readers acknowledged it
    settle_at(5.0, 40.0)
    send("obstacle", "ellipse", "--center", "2", "-0.5", "--axes", "0.4", "0.2")
    send("target", "-3")
    settle_at(-3.0, 40.0)
    send("delete", "1")
    assert "mu = 0.0" in send("param", "mu", "0")
    assert probe.spin_until(lambda: bool(diags) and diags[-1].get("mu") == "0" and diags[-1].get("regions") == "0",
                            5.0), diags[-1:]
    # a target change restarts the certificate's check: no WARN or ERROR for it (issue goal). The real-time
    # loop's own mismatch (the state's age, the command's latency) may still break the nominal decrease
    # elsewhere: that is a real violation under unchanged parameters, reported, and counted below
    restarts = [i for i, d in enumerate(diags) if "target" in json.loads(d.get("certificate_changed", "[]"))]
    assert len(restarts) >= 1, [d.get("certificate") for d in diags]
    for i in restarts:
        assert not [d["message"] for d in diags[i:i + 3] if "certificate violated" in d["message"]], diags[i:i + 3]
    violations = diags[-1]["certificate_violations"]
    assert recorder.stop() == 0
    for proc in (ctrl, plant):
        assert proc.stop() == 0

    bag = load_bag(bag_path)
    targets = [list(msg.data) for _, msg in bag.topics["/target"]]
    assert targets == [[5.0], [-3.0]], targets
    markers = [m for _, msg in bag.topics["/obstacles"] for m in msg.markers]
    assert [(m.ns, m.id, m.action) for m in markers] == [("send", 1, 0), ("send", 1, 2)], markers
    ellipse = markers[0]
    assert (ellipse.header.frame_id, ellipse.type, ellipse.pose.position.x, ellipse.pose.position.y,
            ellipse.scale.x, ellipse.scale.y) == ("state", 3, 2.0, -0.5, 0.8, 0.4)

    # the truth (issue 32): every state the plant published, at its own 20 Hz, keeps |x1 x2| <= 2 and the
    # state box |x2| <= 2 to the bound, the controller planning from the state predicted over its latency
    recorded = np.array([msg.data for _, msg in bag.topics["/state"]])
    worst_product, worst_x2 = np.max(np.abs(recorded[:, 0] * recorded[:, 1])), np.max(np.abs(recorded[:, 1]))
    # when the commands took effect against the instant each plan started from (printed: a failure says whether
    # the plant got its commands later than the controller predicted; BENCHMARKS.md, 'Command timing jitter')
    settings = ControllerSettings.from_params(load_params_file(LIVE).section("controller"))
    run = load_run(bag_path, settings=settings, bag=bag)
    timing = command_timing(bag, run, settings)
    print(f"\nrecorded plant states: {len(recorded)}, max |x1 x2| {worst_product:.5f}, max |x2| {worst_x2:.5f}; "
          f"commands after the predicted instant (ms): {json.dumps(timing)}")
    assert worst_product <= 2 + BOUND and worst_x2 <= 2 + BOUND, (worst_product, worst_x2)

    with_ellipse = [k for k, regions in enumerate(run.regions) if regions]
    assert with_ellipse, "the controller never solved with the ellipse in force"
    metrics = run_metrics(run, settings)
    print(f"\nREADME sequence live: {len(run.x)} samples, {len(with_ellipse)} with the ellipse; min clearance "
          f"{metrics['min_clearance_obstacles']:.4f} at the samples, "
          f"{metrics['between_samples']['min_clearance_obstacles']:.4f} between them; keep-in excess "
          f"{metrics['max_penetration_keep_in']:.2g}; fallbacks {metrics['fallbacks']}; solve "
          f"{json.dumps(metrics['solve_ms'])}; certificate violations {violations}")
    assert metrics["min_clearance_obstacles"] >= -BOUND, metrics
    assert metrics["between_samples"]["min_clearance_obstacles"] >= -BOUND, metrics
    # it passed the ellipse on its way from 5 to -3, close enough for the check to mean something
    passed = [x for x in run.x if 1.5 <= x[0] <= 2.5]
    assert passed and min(math.hypot((x[0] - 2.0) / 0.4, (x[1] + 0.5) / 0.2) for x in passed) < 5.0


def test_readme_documents_the_send_sequence() -> None:
    readme = (Path(ROOT) / "README.md").read_text()
    for command in ("send target 5", "send obstacle ellipse --center 2 -0.5 --axes 0.4 0.2", "send target -3",
                    "send delete 1", "send param mu 0"):
        assert f"python -m nmpc_avoid_ros {command}" in readme, command
