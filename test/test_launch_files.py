"""The launch files, without the launch packages (they are not among the PyPI wheels).

Each launch file is imported with stand-in `launch` / `launch_ros` modules whose classes only
record what they are given. From that record: every argument the README promises is declared,
every LaunchConfiguration used is declared, every node is an installed executable of this
package, every params file exists and is installed, every parameter given is one the node
declares and validates; then each node is started as `ros2 launch` would start it with the
default arguments, and must come up.
"""

from __future__ import annotations

import ast
import importlib.util
import sys
import time
import types
from pathlib import Path

import pytest
import yaml
from rosgraph import ROOT

from nmpc_avoid_ros.cli import COMMANDS
from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.nodes.controller import NODE_SPECS
from nmpc_avoid_ros.nodes.obstacles import OBSTACLE_SPECS
from nmpc_avoid_ros.nodes.obstacles_sensed import SENSED_SPECS
from nmpc_avoid_ros.nodes.plant import PLANT_SPECS
from nmpc_avoid_ros.nodes.recorder import RECORDER_SPECS
from nmpc_avoid_ros.ros.parameters import settings_specs

PACKAGE = "nmpc_avoid_ros"
DECLARED = {"controller": {s.name for s in settings_specs() + NODE_SPECS}, "plant": {s.name for s in PLANT_SPECS},
            "recorder": {s.name for s in RECORDER_SPECS},
            "obstacles": {s.name for s in OBSTACLE_SPECS + SENSED_SPECS}}
STAND_INS = {
    "launch": ["LaunchDescription"],
    "launch.actions": ["DeclareLaunchArgument"],
    "launch.conditions": ["IfCondition"],
    "launch.substitutions": ["LaunchConfiguration", "PathJoinSubstitution"],
    "launch_ros.actions": ["Node"],
    "launch_ros.parameter_descriptions": ["ParameterValue"],
    "launch_ros.substitutions": ["FindPackageShare"],
}
EXPECTED_ARGUMENTS = {"demo.launch.py": {"config", "mu", "record", "namespace"},
                      "robot.launch.py": {"config", "namespace"},
                      "world.launch.py": {"config", "world", "walkers", "namespace"}}


class Recorded:
    """A stand-in action or substitution: keeps its arguments."""

    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


def load_launch(path: Path, monkeypatch) -> Recorded:
    for module_name, classes in STAND_INS.items():
        module = types.ModuleType(module_name)
        for cls in classes:
            setattr(module, cls, type(cls, (Recorded,), {}))
        monkeypatch.setitem(sys.modules, module_name, module)
    spec = importlib.util.spec_from_file_location(path.stem.replace(".", "_"), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def walk(value):
    """Every Recorded object inside value (depth first)."""
    if isinstance(value, Recorded):
        yield value
        for item in (*value.args, *value.kwargs.values()):
            yield from walk(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from walk(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from walk(item)


class Resolver:
    """Evaluates the stand-in substitutions with the arguments' defaults, as `ros2 launch` would."""

    def __init__(self, description: Recorded) -> None:
        self.defaults = {a.args[0]: a.kwargs["default_value"] for a in walk(description)
                         if type(a).__name__ == "DeclareLaunchArgument"}

    def __call__(self, value):
        kind = type(value).__name__
        if kind == "LaunchConfiguration":
            return self(self.defaults[value.args[0]])
        if kind == "FindPackageShare":
            assert value.args == (PACKAGE,)
            return str(ROOT)  # the source tree stands for share/nmpc_avoid_ros (setup.py installs it so)
        if kind == "PathJoinSubstitution":
            return str(Path(*(self(part) for part in value.args[0])))
        if kind == "ParameterValue":
            return value.kwargs["value_type"](self(value.args[0]))
        if kind == "IfCondition":
            return self(value.args[0]).lower() == "true"
        return value


def installed_share_globs() -> list[str]:
    """The source globs setup.py installs under share/nmpc_avoid_ros (its data_files)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    return [node.args[0].value for node in ast.walk(tree) if isinstance(node, ast.Call)
            and getattr(node.func, "id", "") == "glob"]


def nodes_of(description: Recorded) -> list[Recorded]:
    return [a for a in walk(description) if type(a).__name__ == "Node"]


@pytest.mark.parametrize("launch_file", sorted(EXPECTED_ARGUMENTS))
def test_launch_file_names_only_what_exists_and_what_the_nodes_declare(launch_file, monkeypatch):
    path = ROOT / "launch" / launch_file
    description = load_launch(path, monkeypatch)
    resolve = Resolver(description)
    assert set(resolve.defaults) == EXPECTED_ARGUMENTS[launch_file]
    used = {c.args[0] for c in walk(description) if type(c).__name__ == "LaunchConfiguration"}
    assert used <= set(resolve.defaults), used - set(resolve.defaults)
    assert any(Path(path.name).match(pattern.split("/")[-1]) for pattern in installed_share_globs()
               if pattern.startswith("launch/"))
    for node in nodes_of(description):
        kw = node.kwargs
        assert kw["package"] == PACKAGE and kw["executable"] in COMMANDS
        name = kw["name"]
        assert name == kw["executable"] and name in DECLARED  # the params file's section is the node's name
        overrides = {}
        for item in kw.get("parameters", []):
            if isinstance(item, dict):
                overrides.update({k: resolve(v) for k, v in item.items()})
                continue
            params_file = Path(resolve(item))
            assert params_file.is_file() and params_file.parent == ROOT / "config", params_file
            assert any(params_file.match(pattern.split("/")[-1]) for pattern in installed_share_globs()
                       if pattern.startswith("config/"))
            section = load_params_file(params_file).section(name)
            assert set(section) <= DECLARED[name] | {"use_sim_time"}, set(section) - DECLARED[name]
            overrides = {**section, **overrides}
        assert set(overrides) <= DECLARED[name], set(overrides) - DECLARED[name]
        if name == "controller":
            ControllerSettings.from_params(overrides)  # the controller validates them (ConfigError otherwise)


@pytest.mark.dds
@pytest.mark.parametrize("launch_file", sorted(EXPECTED_ARGUMENTS))
def test_nodes_start_as_ros2_launch_would_start_them(launch_file, monkeypatch, ros_graph, tmp_path):
    _, _, start, _ = ros_graph
    description = load_launch(ROOT / "launch" / launch_file, monkeypatch)
    resolve = Resolver(description)
    procs = []
    for node in nodes_of(description):
        kw = node.kwargs
        if "condition" in kw and not resolve(kw["condition"]):
            continue
        args = ["--ros-args", "-r", f"__node:={kw['name']}"]
        if resolve(kw.get("namespace", "")):
            args += ["-r", f"__ns:={resolve(kw['namespace'])}"]
        for item in kw.get("parameters", []):
            if isinstance(item, dict):
                for key, value in item.items():
                    args += ["-p", f"{key}:={yaml.safe_dump(resolve(value), default_flow_style=True).strip()}"]
            else:
                args += ["--params-file", resolve(item)]
        if kw["executable"] == "recorder":
            args += ["-p", f"output:={tmp_path / 'launch.mcap'}"]  # not into the working directory
        procs.append(start(kw["executable"], *args))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not all("ready" in p.output() or "recording" in p.output()
                                                     for p in procs):
        assert all(p.alive() for p in procs), [p.output() for p in procs]
        time.sleep(0.2)
    outputs = [p.output() for p in procs]
    assert all("ready" in out or "recording" in out for out in outputs), outputs
    assert not any("configuration error" in out or "Traceback" in out for out in outputs), outputs
    assert all(p.stop() == 0 for p in procs)
