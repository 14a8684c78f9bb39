"""`send` knows the answer (issue 32 item 5), through real DDS: it checks a target against the
controller's model before publishing (exit 2 naming the size), reads the controller's verdict from
/diagnostics after (a refusal: exit 1 with the controller's reason), and the recorder asks it for no
parameters (no WARN for `send_<pid>`).

The paper's config without a plant: the idle controller publishes diagnostics every sample, and the
verdict keys (`target_received`, `target_verdict`, `target_reason`, the same for `obstacles`) are
there from the first. `max_polygons:=0` gives a refusal only the controller can make (its store's
capacity); `--no-check` bypasses send's size check so the controller refuses the target itself.
"""

from __future__ import annotations

import pytest
from rosgraph import CONFIG, run_send

pytestmark = pytest.mark.dds

NO_COMPILE = ["-p", "codegen:=false"]


def test_send_reports_the_controllers_verdict_and_the_recorder_does_not_warn_about_it(ros_graph, tmp_path) -> None:
    _, env, start, probe_factory = ros_graph
    # its own logger at debug: the line that says it let a send node go without asking
    recorder = start("recorder", "--ros-args", "-p", f"output:={tmp_path / 'bag.mcap'}", "--log-level",
                     "recorder:=debug")
    ctrl = start("controller", "--ros-args", "--params-file", str(CONFIG), *NO_COMPILE, "-p", "max_polygons:=0")
    probe = probe_factory()
    diags = probe.diagnostics_of("/controller")
    for name, proc in (("recorder", recorder), ("controller", ctrl)):
        assert probe.heard_by(name, 60.0), proc.output()[-3000:]
    assert probe.spin_until(lambda: bool(diags), 10.0), ctrl.output()[-3000:]
    assert {k: diags[-1][k] for k in ("target_received", "target_verdict", "target_reason", "obstacles_received",
                                      "obstacles_verdict")} == {"target_received": "0", "target_verdict": "none",
                                                                "target_reason": "", "obstacles_received": "0",
                                                                "obstacles_verdict": "none"}

    # send's own check against the model: nothing published, exit 2, the size named
    proc, seconds = run_send(env, "target", "5", "0")
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "model van_der_pol takes 1 value (p = 1), got 2" in proc.stderr, proc.stderr
    print(f"\nsend target 5 0: exit 2 after {seconds:.1f} s")

    # the controller's own refusal of the same, the check bypassed: exit 1 with its reason
    proc, seconds = run_send(env, "target", "5", "0", "--no-check")
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert "/controller refused target [5.0, 0.0]: target: expected 1 values, got 2" in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    print(f"send target 5 0 --no-check: exit 1 after {seconds:.1f} s: {proc.stderr.strip()}")

    proc, _ = run_send(env, "target", "5")
    assert proc.returncode == 0, (proc.stdout, proc.stderr)
    assert "acknowledged by /controller" in proc.stdout and "; accepted by /controller" in proc.stdout, proc.stdout

    # a refusal send cannot foresee: the controller's store has no polygon slot
    proc, _ = run_send(env, "obstacle", "box", "--center", "1", "1", "--size", "0.6", "0.4")
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert "/controller refused box (ns 'send', id 1): marker send/1: capacity of 0 polygons" in proc.stderr, \
        proc.stderr
    proc, _ = run_send(env, "obstacle", "ellipse", "--center", "2", "-0.5", "--axes", "0.4", "0.2")
    assert proc.returncode == 0 and "; accepted by /controller" in proc.stdout, (proc.stdout, proc.stderr)

    assert probe.spin_until(lambda: diags[-1]["obstacles_received"] == "2", 5.0), diags[-1]
    last = diags[-1]
    assert (last["target_received"], last["target_verdict"], last["target_reason"]) == ("2", "accepted", "")
    assert (last["obstacles_verdict"], last["obstacles_reason"]) == ("accepted", "")

    probe.spin_for(3.0)  # the recorder's graph poll sees the send nodes gone
    assert recorder.stop() == 0
    assert ctrl.stop() == 0
    log = recorder.output()
    warnings = [line for line in log.splitlines() if "WARN" in line and "send_" in line]
    assert not warnings, warnings
    assert "it left without parameter services" in log, log[-3000:]
