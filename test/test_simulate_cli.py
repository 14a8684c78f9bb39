"""`python -m nmpc_avoid_ros simulate` and `figures`: JSON layout, overrides, errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from nmpc_avoid_ros.bag.figures import Trace, covering_limits, phase_portrait
from nmpc_avoid_ros.core.sample.status import StepStatus
from nmpc_avoid_ros.tools.simulate import main as simulate_main


def test_simulate_json_layout_and_overrides(tmp_path, capsys):
    out = tmp_path / "run.json"
    code = simulate_main(["--steps", "12", "--x0", "-4", "0.5", "--target", "3", "--mu", "0", "--plant",
                          "continuous", "--json", str(out)])
    assert code == 0
    data = json.loads(out.read_text())
    assert len(data["x"]) == 13 and all(len(r) == 2 for r in data["x"])
    assert data["x"][0] == [-4.0, 0.5]
    assert len(data["u"]) == 12 and len(data["y_a"]) == 12 and len(data["solve_ms"]) == 12
    assert set(data["status"]) <= {status.value for status in StepStatus}
    assert data["target"][0] == [3.0]
    assert data["summary"]["steps"] == 12
    line = capsys.readouterr().out.strip()
    assert line.startswith("simulate: 12 steps, plant=continuous, mu=0")


def test_simulate_matches_the_library_run(paper, tmp_path):
    out = tmp_path / "run.json"
    assert simulate_main(["--steps", "50", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    ref = paper(1e8, "euler")
    np.testing.assert_allclose(data["x"], ref.x, atol=1e-9)
    assert data["summary"]["max_abs_x1x2"] <= 2.001


@pytest.mark.parametrize("args, message", [(["--x0", "1"], "x0"), (["--mu", "-2"], "mu"),
                                            (["--config", "/nonexistent.yaml"], "cannot read")])
def test_simulate_bad_input_is_a_clear_error(args, message, capsys):
    assert simulate_main(["--steps", "2", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.slow
def test_module_dispatch_lists_commands_and_runs_figures(tmp_path):
    listing = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", "--help"], capture_output=True, text=True)
    assert listing.returncode == 0 and "simulate" in listing.stdout and "controller" in listing.stdout
    res = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", "figures", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    for name in ("phase_portrait.png", "time_series.png", "metrics.json"):
        assert (tmp_path / name).stat().st_size > 1000 or name == "metrics.json"
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["runs"]["with_avoidance"]["max_abs_x1x2"] <= 2.001
    assert metrics["runs"]["without_avoidance"]["max_abs_x1x2"] > 9


def test_reference_documents_every_parameter_executable_and_topic():
    """docs/reference.md lists them (the README is the front door: the two commands, and it points there)."""
    from pathlib import Path

    from nmpc_avoid_ros.cli import COMMANDS
    from nmpc_avoid_ros.nodes.controller import NODE_SPECS
    from nmpc_avoid_ros.nodes.plant import PLANT_SPECS
    from nmpc_avoid_ros.nodes.recorder import RECORDER_SPECS
    from nmpc_avoid_ros.ros.parameters import settings_specs

    root = Path(__file__).resolve().parents[1]
    reference = (root / "docs" / "reference.md").read_text()
    for spec in settings_specs() + NODE_SPECS + PLANT_SPECS + RECORDER_SPECS:
        assert f"| `{spec.name}` |" in reference, spec.name
    for command in COMMANDS:
        assert f"| `{command}` |" in reference, command
    for topic in ("state", "command", "target", "obstacles", "/diagnostics", "~/prediction", "/clock"):
        assert f"| `{topic}` |" in reference, topic
    readme = (root / "README.md").read_text()
    assert "make demo" in readme and "make test" in readme and "docs/reference.md" in readme


def test_params_file_keys_of_the_controller_node_are_exactly_its_declared_parameters():
    """core.settings accepts node-only keys by name (core cannot import the node): keep the two lists equal."""
    from nmpc_avoid_ros.core.config.settings import NODE_ONLY_PARAMETERS
    from nmpc_avoid_ros.nodes.controller import NODE_SPECS

    assert NODE_ONLY_PARAMETERS == {spec.name for spec in NODE_SPECS} | {"use_sim_time"}


def test_the_phase_portrait_spans_every_trajectory(tmp_path):
    """The run without avoidance reaches |x2| = 2.24, beyond the paper's +-2 window: the axes widen to
    hold it (and never shrink below the window)."""
    t = np.arange(4) * 0.5
    inside = Trace("inside", t, np.array([[-5.0, 0.0], [-1.0, 1.0], [2.0, -1.5], [5.0, 0.0]]), np.zeros((3, 1)))
    beyond = Trace("beyond", t, np.array([[-5.0, 0.0], [-1.0, 2.24], [7.5, -2.6], [5.0, np.nan]]), np.zeros((3, 1)))
    assert covering_limits([inside], (-6.0, 6.0), (-2.0, 2.0)) == ((-6.0, 6.0), (-2.0, 2.0))
    (x_lo, x_hi), (y_lo, y_hi) = covering_limits([inside, beyond], (-6.0, 6.0), (-2.0, 2.0))
    assert x_lo == -6.0 and x_hi > 7.5 and y_lo < -2.6 and y_hi > 2.24
    assert phase_portrait([inside, beyond], tmp_path / "p.png").stat().st_size > 10_000


def test_simulate_json_carries_the_two_phases_of_each_sample(tmp_path):
    """With feedback on, each sample's preparation and feedback times and what became of its prepared plan."""
    config = tmp_path / "feedback.yaml"
    config.write_text("/**/controller:\n  ros__parameters:\n    feedback: true\n")
    out = tmp_path / "run.json"
    assert simulate_main(["--config", str(config), "--steps", "12", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert len(data["feedback_ms"]) == len(data["preparation_ms"]) == len(data["feedback"]) == 12
    answered = [k for k, outcome in enumerate(data["feedback"]) if outcome == "answered"]
    assert len(answered) >= 8 and data["feedback"][0] == ""  # the first sample had nothing prepared
    for k in answered:  # the feedback alone is a fraction of the sample's solver time, which counts both
        assert 0 < data["feedback_ms"][k] < data["solve_ms"][k] and data["preparation_ms"][k] > 0
