"""ROS parameters <-> core settings, and the named QoS profiles of docs/design.md ("Interfaces").

The controller's parameters are declared once, in core/config/settings.py (core/config/schema.py explains how);
here each declaration becomes a ParamSpec: a ParameterDescriptor with the description, the
allowed values, the range and read_only for what is not run time. The plant and the recorder
declare their ParamSpecs directly. `markdown_table` writes any node's table for docs/reference.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.config.schema import Setting
from ..core.config.settings import BOUNDS, NODE_SETTINGS, SETTINGS, ControllerSettings, NodeSettings

#: state, command, diagnostics, prediction, clock: reliable, keep last 100. A reliable writer drops
#: samples a reader has not acknowledged once its history is full: with 10, a recorder busy for
#: half a second (start-up, a chunk write on a loaded machine) lost states published at 20 Hz
STREAM_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
#: what a control loop reads to act on now (the controller's state, the plant's command): the latest
#: message only. With STREAM_QOS's 100 a busy executor hands out queued messages oldest first: the
#: controller solved on states 0.3-0.37 s old, stamped as fresh, while a walker crossed at 0.5 m/s
#: (test_moving_dds, clearance -0.18 to -0.4 in 1 run of 4). Reliable, so that writers of
#: STREAM_QOS match it
LATEST_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
#: target and obstacles: the latest value reaches late joiners (a restarted controller)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter: name, default (None: typed but unset), description and limits."""

    name: str
    default: Any
    description: str
    type_: int
    read_only: bool = False
    float_range: tuple[float, float] | None = None
    int_range: tuple[int, int] | None = None
    choices: tuple[str, ...] = ()
    #: the allowed values in words, for docs/reference.md (core settings: their declared rule)
    rule: str = ""

    def descriptor(self) -> ParameterDescriptor:
        text = self.description + (f" (one of: {', '.join(self.choices)})" if self.choices else "")
        d = ParameterDescriptor(name=self.name, type=self.type_, description=text, read_only=self.read_only,
                                additional_constraints=self.rule)
        if self.float_range:
            d.floating_point_range = [FloatingPointRange(from_value=self.float_range[0], to_value=self.float_range[1])]
        if self.int_range:
            d.integer_range = [IntegerRange(from_value=self.int_range[0], to_value=self.int_range[1], step=1)]
        return d


#: ROS parameter type of each kind of setting (core/config/schema.py)
ROS_TYPES = {
    "float": ParameterType.PARAMETER_DOUBLE, "int": ParameterType.PARAMETER_INTEGER,
    "bool": ParameterType.PARAMETER_BOOL, "str": ParameterType.PARAMETER_STRING,
    "float[]": ParameterType.PARAMETER_DOUBLE_ARRAY, "int[]": ParameterType.PARAMETER_INTEGER_ARRAY,
    "str[]": ParameterType.PARAMETER_STRING_ARRAY,
}


def spec_of(setting: Setting) -> ParamSpec:
    """The ROS declaration of a core setting: read-only unless run time; the range of a scalar number."""
    default = setting.default
    if isinstance(default, tuple):
        # an empty list has no ROS type: declare typed and unset
        default = list(default) if default else None
    if setting.name in BOUNDS:  # unset: Z's box comes from the model file (settings_from_values), as offline
        default = None
    float_range = int_range = None
    if not setting.is_array and setting.kind in ("float", "int") and (setting.low, setting.high) != (None, None):
        bounds = (-math.inf if setting.low is None else setting.low, math.inf if setting.high is None else setting.high)
        if setting.kind == "float":
            float_range = (float(bounds[0]), float(bounds[1]))
        else:
            int_range = (int(bounds[0]), int(bounds[1]))
    return ParamSpec(setting.name, default, setting.description, ROS_TYPES[setting.kind],
                     read_only=not setting.runtime, float_range=float_range, int_range=int_range,
                     choices=setting.choices, rule=setting.rule() if setting.constrained else "")


def settings_specs() -> list[ParamSpec]:
    """A ParamSpec per core controller setting, in declaration order."""
    return [spec_of(setting) for setting in SETTINGS.values()]


def node_settings_specs() -> list[ParamSpec]:
    """A ParamSpec per parameter of the controller node itself (core NodeSettings)."""
    return [spec_of(setting) for setting in NODE_SETTINGS.values()]


def settings_from_values(values: Mapping[str, Any]) -> ControllerSettings:
    """Core settings from declared parameter values (unset ones take the default, the bounds of Z the model
    file's, as ControllerSettings.from_params does; ConfigError names a bad one)."""
    return ControllerSettings.from_params(_declared(values, SETTINGS))


def node_settings_from_values(values: Mapping[str, Any]) -> NodeSettings:
    """The controller node's own settings from declared parameter values (as settings_from_values)."""
    return NodeSettings(**_declared(values, NODE_SETTINGS))


def _declared(values: Mapping[str, Any], declared: Mapping[str, Setting]) -> dict[str, Any]:
    return {k: v for k, v in values.items() if k in declared and v is not None}


def markdown_table(specs: Iterable[ParamSpec]) -> str:
    """docs/reference.md's parameter table of one node: parameter, default, change, meaning."""
    rows = ["| parameter | default | change | meaning |", "|---|---|---|---|"]
    for spec in specs:
        if spec.name in BOUNDS and spec.default is None:
            default = "the model file's `bounds`"
        elif spec.default is None:
            default = "(unset)"
        elif spec.default == "":
            default = "(empty)"
        else:
            default = f"`{spec.default!r}`" if not isinstance(spec.default, str) else f"`{spec.default}`"
        meaning = spec.description + "."
        limits = spec.float_range or spec.int_range
        if spec.rule:
            meaning += f" Allowed: {spec.rule}."
        elif spec.choices:
            meaning += f" One of: {', '.join(spec.choices)}."
        elif limits:
            meaning += f" Range: [{limits[0]}, {limits[1]}]."
        rows.append(f"| `{spec.name}` | {default} | {'read-only' if spec.read_only else 'run time'} | "
                    f"{meaning.replace('|', chr(92) + '|')} |")
    return "\n".join(rows) + "\n"


def declare(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare every spec (overrides from --params-file / -p apply); returns name -> value."""
    values = {}
    for spec in specs:
        default = spec.default if spec.default is not None else Parameter.Type(spec.type_)
        param = node.declare_parameter(spec.name, default, spec.descriptor())
        values[spec.name] = param.value
    return values


def finite_vector(value: Any, size: int, name: str) -> list[float]:
    """Validate a parameter array: `size` finite numbers, else ValueError with the reason."""
    try:
        seq = [float(v) for v in value]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a list of {size} numbers") from None
    if len(seq) != size:
        raise ValueError(f"{name} needs {size} values, got {len(seq)}")
    if not all(math.isfinite(v) for v in seq):
        raise ValueError(f"{name} must be finite, got {seq}")
    return seq
