"""docs/own_model.md as a new user runs it: every file and command comes from the page's fenced blocks.

Blocks are found by their info string: ```yaml file=NAME``` is written to NAME in a fresh folder (the
working directory of everything); ```sh offline```, ```sh ros```, ```sh launch```, ```sh register```
are commands run one by one (bash, in that folder), ```sh terminal``` a long-running command started
in its own process group and stopped by PID with SIGINT (Ctrl-C). `ros2 run nmpc_avoid_ros X` reaches
the venv's console script X through a `ros2` stand-in on PATH (the ROS 2 CLI is not among the
wheels); `ros2 launch` is read with the stand-in launch modules of test_launch_files.py and its nodes
are started as `ros2 launch` would start them. `pip install` gets `--no-deps --no-build-isolation
--no-index --target DIR` so that the venv is not touched (DIR on PYTHONPATH, as an installed package).
The DDS tests run in an isolated domain (conftest.py `ros_graph`).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rosgraph import ROOT, NodeProcess
from std_msgs.msg import Float64MultiArray
from test_launch_files import Resolver, load_launch, nodes_of

from nmpc_avoid_ros.core.problem.models import ModelFileError, make_model
from nmpc_avoid_ros.ros.parameters import STREAM_QOS

DOC = ROOT / "docs" / "own_model.md"
PACKAGE = ROOT / "docs" / "own_model" / "crane_model"
VENV_BIN = Path(sys.executable).parent
BLOCK = re.compile(r"^```(\w+)[ \t]*([^\n]*)\n(.*?)^```", re.MULTILINE | re.DOTALL)
ROS2_STAND_IN = """#!/bin/sh
# `ros2 run nmpc_avoid_ros X ...` -> the venv's console script X
if [ "$1" = run ] && [ "$2" = nmpc_avoid_ros ]; then shift 2; exec "$@"; fi
echo "ros2 stand-in: only 'ros2 run nmpc_avoid_ros ...' (ros2 launch is read by the test)" >&2
exit 2
"""
#: a solve time in simulate's line: the only part that differs between runs
SOLVE_TIMES = re.compile(r"solve median [\d.]+ ms max [\d.]+ ms")


def blocks() -> list[tuple[str, str, str]]:
    """(language, info after it, body) of every fenced block of the page."""
    return [(lang, info.strip(), body) for lang, info, body in BLOCK.findall(DOC.read_text())]


def doc_files() -> dict[str, str]:
    return {info.removeprefix("file="): body for _, info, body in blocks() if info.startswith("file=")}


def commands(tag: str) -> list[str]:
    """The command lines of the ```sh TAG``` blocks, in page order (comment and blank lines left out)."""
    return [line.strip() for lang, info, body in blocks() if lang == "sh" and info == tag
            for line in body.splitlines() if line.strip() and not line.strip().startswith("#")]


def printed(prefix: str) -> list[str]:
    """The lines of the page's ```text``` blocks that start with prefix (what the page says is printed)."""
    return [line for lang, _, body in blocks() if lang == "text" for line in body.splitlines()
            if line.startswith(prefix)]


def user_folder(tmp_path: Path, env: dict[str, str]) -> tuple[Path, dict[str, str]]:
    """A fresh folder with the page's files, and an environment whose PATH has `ros2` and the venv."""
    folder = tmp_path / "work"
    folder.mkdir()
    for name, text in doc_files().items():
        (folder / name).write_text(text)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "ros2").write_text(ROS2_STAND_IN)
    (bin_dir / "ros2").chmod(0o755)
    env = {**env, "PATH": os.pathsep.join([str(bin_dir), str(VENV_BIN), env.get("PATH", "")]),
           "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    return folder, env


def shell(line: str, folder: Path, env: dict[str, str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    proc = subprocess.run(["bash", "-c", line], cwd=folder, env=env, capture_output=True, text=True,
                          timeout=timeout, start_new_session=True)
    assert proc.returncode == 0, (line, proc.stdout, proc.stderr)
    return proc


def wait_for(procs: list[NodeProcess], words: tuple[str, ...] = ("ready", "recording"), timeout: float = 60.0):
    """Until each process printed one of words (a node that is up), as the page tells the user to wait."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not all(any(w in p.output() for w in words) for p in procs):
        assert all(p.alive() for p in procs), [p.output() for p in procs]
        time.sleep(0.2)
    assert all(any(w in p.output() for w in words) for p in procs), [p.output() for p in procs]


def at_rest(states: list[list[float]], position: float) -> bool:
    """The last state: the trolley at `position` within 1 cm, the load hanging straight down, everything still."""
    return bool(states) and abs(states[-1][0] - position) < 0.01 and max(map(abs, states[-1][1:])) < 0.02


def test_the_pages_files_are_the_example_packages_and_its_claims_hold(tmp_path):
    files = doc_files()
    assert set(files) == {"crane.yaml", "crane_params.yaml"}
    assert files["crane.yaml"] == (PACKAGE / "crane_model" / "crane.yaml").read_text()
    snippets = {"python": PACKAGE / "crane_model" / "__init__.py", "toml": PACKAGE / "pyproject.toml"}
    for lang, _, body in blocks():
        if lang in snippets:  # excerpts: each paragraph as it is in the file
            assert all(part in snippets[lang].read_text() for part in body.split("\n\n")), (lang, body)
    # the typo the page quotes is refused so, on the line it names
    typo = tmp_path / "crane.yaml"
    typo.write_text(files["crane.yaml"].replace("m*l*omega**2*sin(theta)*", "m*l*omgea**2*sin(theta)*"))
    with pytest.raises(ModelFileError) as info:
        make_model(str(typo))
    page = DOC.read_text().replace("\n", " ")
    quoted = re.search(r"`(crane\.yaml:\d+: dynamics\.omega: unknown name [^`]*)`", page)
    assert str(info.value) == f"{tmp_path}/{quoted.group(1)}"


@pytest.mark.slow
def test_offline_the_trolley_reaches_its_target_with_the_swing_kept_small(tmp_path):
    folder, env = user_folder(tmp_path, {**os.environ, "PYTHONPATH": str(ROOT)})
    lines = commands("offline")
    assert len(lines) == 2 and all(line.startswith("simulate --config crane_params.yaml") for line in lines)
    outputs = [shell(line, folder, env).stdout.strip() for line in lines]
    # what the page says it prints, but for the solve times
    assert [SOLVE_TIMES.sub("", out) for out in outputs] == [SOLVE_TIMES.sub("", line) for line in printed("simulate:")]
    run = json.loads((folder / "crane_run.json").read_text())
    x = np.array(run["x"])
    assert abs(x[-1, 0] - 1.0) < 5e-3 and np.max(np.abs(x[-1, 1:])) < 0.02
    assert np.max(np.abs(x[:, 1])) <= 0.1502 and run["summary"]["fallbacks"] == 0
    assert run["summary"]["max_penetration_keep_in"] < 1e-4
    without = float(re.search(r"keep-in penetration (\S+)", outputs[1]).group(1))
    assert without > 0.02  # theta^2 - 0.15^2 > 0.02: the load swings past 0.2 rad without avoidance


@pytest.mark.dds
def test_through_ros_plant_controller_recorder_send_and_analyze(ros_graph, tmp_path, monkeypatch):
    _, env, _, probe = ros_graph
    folder, env = user_folder(tmp_path, env)
    monkeypatch.chdir(folder)  # the terminals' working directory
    p = probe()
    states: list[list[float]] = []
    lines = commands("terminal")
    assert [shlex.split(line)[3] for line in lines] == ["plant", "controller", "recorder"]
    terminals = [NodeProcess(f"terminal{i}", [], env, tmp_path / "logs", program=["bash", "-c", f"exec {line}"])
                 for i, line in enumerate(lines)]
    try:
        wait_for(terminals)
        # listening only now: the plant starts once its 2 readers (controller, recorder) match, not the probe
        p.node.create_subscription(Float64MultiArray, "state", lambda m: states.append(list(m.data)), STREAM_QOS)
        assert "controller ready: model=crane" in terminals[1].output()
        send, analyze = commands("ros")
        out = shell(send, folder, env)
        assert "target [1.0] on /target" in out.stdout and "accepted by /controller" in out.stdout, out
        assert p.spin_until(lambda: at_rest(states, 1.0), timeout=30), states[-1:]
        p.spin_for(0.5)
        assert all(abs(s[1]) < 0.16 for s in states), max(abs(s[1]) for s in states)
        # Ctrl-C: the recorder first (it closes the bag), then the controller and the plant
        for terminal in reversed(terminals):
            assert terminal.stop() == 0, terminal.output()
        out = shell(analyze, folder, env)
        assert "analyze: crane: 1 target segment(s)" in out.stdout
    finally:
        for terminal in terminals:
            terminal.stop()
    metrics = json.loads((folder / "crane_analysis" / "metrics.json").read_text())["bags"][0]
    assert metrics["config"]["source"] == "the bag's /controller parameters"
    assert metrics["final_error"] < 0.01 and metrics["settling_time"] < 4.0
    keep_in = metrics["clearance"]["recorded_states"]["keep_in"][0]
    assert keep_in["expression"] == "theta**2 <= 0.15**2" and keep_in["max_g"] < 2e-3  # |theta| < 0.157


@pytest.mark.dds
def test_ros2_launch_with_the_params_file_goes_to_the_nearest_admissible_steady_state(ros_graph, tmp_path,
                                                                                     monkeypatch):
    _, env, start, probe = ros_graph
    folder, env = user_folder(tmp_path, env)
    monkeypatch.chdir(folder)  # where `ros2 launch` runs: the model path and bags/ are relative to it
    launch, send = commands("launch")
    words = shlex.split(launch.replace("$PWD", str(folder)))
    assert words[:4] == ["ros2", "launch", "nmpc_avoid_ros", "demo.launch.py"]
    description = load_launch(ROOT / "launch" / words[3], monkeypatch)
    resolve = Resolver(description)
    arguments = dict(word.split(":=", 1) for word in words[4:])
    assert set(arguments) <= set(resolve.defaults)
    resolve.defaults.update(arguments)
    p = probe()
    states: list[list[float]] = []
    procs = []
    for node in nodes_of(description):
        kw = node.kwargs
        if "condition" in kw and not resolve(kw["condition"]):
            continue
        args = ["--ros-args", "-r", f"__node:={kw['name']}"]
        for item in kw.get("parameters", []):
            if isinstance(item, dict):
                args += [a for key, value in item.items() for a in ("-p", f"{key}:={json.dumps(resolve(value))}")]
            else:
                args += ["--params-file", resolve(item)]
        procs.append(start(kw["executable"], *args))
    try:
        wait_for(procs)
        p.node.create_subscription(Float64MultiArray, "state", lambda m: states.append(list(m.data)), STREAM_QOS)
        # y_t = 5 is off the 3 m rail: the trolley stops at 0.99 * 3 m
        assert p.spin_until(lambda: at_rest(states, 2.97), timeout=30), states[-1:]
        out = shell(send, folder, env)
        assert "accepted by /controller" in out.stdout, out
        assert p.spin_until(lambda: at_rest(states, 1.0), timeout=30), states[-1:]
        for proc in reversed(procs):
            assert proc.stop() == 0, proc.output()
    finally:
        for proc in procs:
            proc.stop()
    swing = max(range(len(states)), key=lambda k: abs(states[k][1]))
    assert max(s[0] for s in states) < 3.01 and abs(states[swing][1]) < 0.16, (
        f"|theta| {abs(states[swing][1]):.3f} at state {swing} of {len(states)}",
        states[max(0, swing - 30):swing + 1:5],
        [proc.output()[-2500:] for proc in procs])
    assert len(list((folder / "bags").glob("*.mcap"))) == 1


@pytest.mark.slow
def test_the_model_registered_by_the_example_package_is_named_by_the_config(tmp_path):
    site = tmp_path / "site"
    folder, env = user_folder(tmp_path, {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"),
                                                                                       str(ROOT)])})
    shutil.copytree(PACKAGE, folder / "crane_model")  # "copy that folder next to your files"
    install, edit, run = commands("register")
    assert install == "pip install ./crane_model"
    shell(f"{install} --no-deps --no-build-isolation --no-index --target {site}", folder, env)
    assert (site / "crane_model" / "crane.yaml").is_file()
    shell(edit, folder, env)
    params = (folder / "crane_params.yaml").read_text()
    assert params.count("model: crane") == 2 and "model: crane.yaml" not in params
    out = shell(run, folder, env).stdout.strip()
    assert SOLVE_TIMES.sub("", out) == SOLVE_TIMES.sub("", printed("simulate:")[0])
