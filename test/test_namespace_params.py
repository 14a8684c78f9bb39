"""Namespaces work with the shipped params files (issue 32 item 4): every file under config/ keys its
nodes `/**/<node>`, so `-r __ns:=/robot1` (the README's line) or a launch file's namespace keeps the
file's settings; before, the keys matched the root namespace only and a namespaced controller ran the
defaults without a word. The offline tools read the same keys (core/config/settings.py
`load_params_file`).

The DDS tests start the nodes under a namespace and read, through each node's own parameter
service, every parameter the file sets: the values the node really has.
"""

from __future__ import annotations

import math
import time

import pytest
import yaml
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python
from rosgraph import ROOT

from nmpc_avoid_ros.core.config.settings import load_params_file, params_file_node

PARAMS_FILES = sorted((ROOT / "config").glob("*.yaml"))
#: top-level keys of a params file that are not nodes (the offline tools' scenario)
NOT_NODES = {"scenario"}


@pytest.mark.parametrize("path", PARAMS_FILES, ids=lambda p: p.name)
def test_every_shipped_params_file_keys_its_nodes_for_any_namespace(path):
    keys = [str(k) for k in yaml.safe_load(path.read_text())]
    nodes = [k for k in keys if k not in NOT_NODES]
    assert nodes and all(k.startswith("/**/") for k in nodes), keys
    params = load_params_file(path)
    for key in nodes:  # the offline tools find each node's section under its plain name
        assert params.section(params_file_node(key)) == yaml.safe_load(path.read_text())[key]["ros__parameters"]


def test_the_offline_reader_merges_a_nodes_sections_in_file_order(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**/controller:\n  ros__parameters: {mu: 1.0, kappa: 2.0}\n"
                    "controller:\n  ros__parameters: {mu: 3.0}\n"
                    "/robot1/controller:\n  ros__parameters: {mu: 4.0}\n")
    params = load_params_file(path)
    assert params.section("controller") == {"mu": 3.0, "kappa": 2.0}
    assert params.section("robot1/controller") == {"mu": 4.0}  # a namespaced key stays namespaced


#: s to wait for a get_parameters answer before the request is sent again
REQUEST_RETRY = 5.0


def node_parameters(probe, node: str, names: list[str], timeout: float = 30.0) -> dict:
    """{name: value} of `node` (fully qualified) through its get_parameters service. The request is sent again
    every REQUEST_RETRY s: the service answers only once it has discovered the client's response reader, and
    a reply sent before that is lost (a fresh clone's make test lost one: no answer in 60 s)."""
    client = probe.node.create_client(GetParameters, f"{node}/get_parameters")
    try:
        assert client.wait_for_service(timeout_sec=timeout), f"no {node}/get_parameters"
        end = time.monotonic() + timeout
        while True:
            future = client.call_async(GetParameters.Request(names=names))
            if probe.spin_until(future.done, min(REQUEST_RETRY, max(end - time.monotonic(), 0.0))):
                return {n: parameter_value_to_python(v) for n, v in zip(names, future.result().values)}
            assert time.monotonic() < end, f"{node} did not answer"
    finally:
        probe.node.destroy_client(client)


def same(a, b) -> bool:
    """Whether the node's value `a` is the file's `b`. PyYAML (YAML 1.1) reads `1.0e4` as a string, rcl
    as the number (the settings convert it: core/config/schema.py)."""
    if isinstance(a, float) and isinstance(b, str):
        b = float(b)
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return math.isclose(a, b, rel_tol=1e-12)
    return a == b


@pytest.mark.dds
@pytest.mark.slow
@pytest.mark.parametrize(("config", "namespace", "extra"), [
    # the README's line; autostart false: the node declares its parameters and answers at once, without
    # the first start's compile of the live config's solver (the settings are the same)
    ("van_der_pol_live.yaml", "/robot1", ["-p", "mu:=0.0", "-p", "autostart:=false"]),
    # a controller that builds and runs (IPOPT, nothing to compile), two namespace levels deep
    ("unicycle.yaml", "/fleet/robot2", []),
], ids=["readme-live", "unicycle-nested"])
def test_the_nodes_under_a_namespace_have_the_params_files_settings(ros_graph, config, namespace, extra):
    _, _, start, probe = ros_graph
    path = ROOT / "config" / config
    params = load_params_file(path)
    ctrl = start("controller", "--ros-args", "--params-file", str(path), *extra, "-r", f"__ns:={namespace}")
    plant = start("plant", "--ros-args", "--params-file", str(path), "-r", f"__ns:={namespace}")
    p = probe()
    expected = {"controller": {**params.section("controller"), "mu": 0.0} if "mu:=0.0" in extra
                else params.section("controller"), "plant": params.section("plant")}
    for node, section in expected.items():
        got = node_parameters(p, f"{namespace}/{node}", sorted(section), timeout=60.0)
        wrong = {k: (got[k], v) for k, v in section.items() if not same(got[k], v)}
        assert not wrong, (node, wrong, ctrl.output()[-2000:])
    print(f"{config} under {namespace}: {len(expected['controller'])} controller and {len(expected['plant'])} "
          f"plant parameters as the file sets them (e.g. discretization "
          f"{expected['controller'].get('discretization')}, integration_steps "
          f"{expected['controller'].get('integration_steps', 1)})")
    assert f"x0={params.section('plant')['initial_state']}" in plant.output()
    if not extra:  # built and active: the solver it reports is the file's
        assert p.spin_until(lambda: "controller active" in ctrl.output(), 60), ctrl.output()
        s = params.section("controller")
        assert f"{s['discretization']} solver={s['solver']}" in ctrl.output(), ctrl.output()
    assert ctrl.stop() == 0 and plant.stop() == 0
