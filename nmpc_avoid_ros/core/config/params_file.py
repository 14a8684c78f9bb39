"""ROS 2 params files: node name -> its `ros__parameters` (the controller's settings, the plant's, the scenario).

Read by the offline tools and the tests; the nodes get the same values from rclpy.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError

#: prefixes of a params file's node key that match any namespace (rcl's wildcards): the shipped files
#: key `/**/controller`, so that `-r __ns:=/robot1` and a launch file's namespace keep their settings
NAMESPACE_WILDCARDS = ("/**/", "/*/")


def params_file_node(key: str) -> str:
    """The node a params file's top-level key names, for the offline tools (which run no namespace):
    `controller`, `/controller` and `/**/controller` all name `controller`."""
    for wildcard in NAMESPACE_WILDCARDS:
        if key.startswith(wildcard):
            return key[len(wildcard):]
    return key.lstrip("/")


@dataclass(frozen=True)
class ParamsFile:
    """A ROS 2 params file: node name -> its `ros__parameters` mapping (the sections of one node, in
    any namespace or the root one, merged in the file's order: a later key wins)."""

    path: Path | None
    nodes: dict[str, dict[str, Any]] = field(default_factory=dict)

    def section(self, node: str) -> dict[str, Any]:
        """Parameters of one node ({} if absent)."""
        return dict(self.nodes.get(node, {}))


def load_params_file(path: str | Path) -> ParamsFile:
    """Read a ROS 2 params file; ConfigError for a missing, unreadable or malformed file."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read params file {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"params file {p} is not UTF-8 text (byte {exc.start})") from None
    except ValueError as exc:  # e.g. a NUL byte in the path
        raise ConfigError(f"cannot read params file {p!r}: {exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"params file {p} is not valid YAML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"params file {p} is nested too deeply to be a params file") from None
    if not isinstance(data, dict):
        raise ConfigError(f"params file {p}: expected node names as top-level keys")
    nodes: dict[str, dict[str, Any]] = {}
    for key, body in data.items():
        name = params_file_node(str(key))
        if not isinstance(body, dict) or not isinstance(body.get("ros__parameters"), dict):
            raise ConfigError(f"params file {p}: node {name!r} needs a 'ros__parameters' mapping")
        nodes[name] = {**nodes.get(name, {}), **body["ros__parameters"]}
    return ParamsFile(p, nodes)


def default_config_path() -> Path:
    """The shipped van der Pol params file: the source tree's, else the installed share/ copy."""
    source = Path(__file__).resolve().parents[3] / "config" / "van_der_pol.yaml"
    installed = Path(sys.prefix) / "share" / "nmpc_avoid_ros" / "config" / "van_der_pol.yaml"
    for candidate in (source, installed):
        if candidate.exists():
            return candidate
    raise ConfigError(f"cannot find the shipped van_der_pol.yaml (looked at {source} and {installed})")
