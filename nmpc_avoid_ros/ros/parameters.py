"""ROS parameters <-> core settings, and the named QoS profiles of DESIGN.md section 4.

Every parameter is declared once, with a ParameterDescriptor (description, range, read_only for
what needs an NLP rebuild), from the core's field list and SETTING_DOCS.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.settings import RUNTIME_FIELDS, SETTING_DOCS, ControllerSettings

#: state, command, diagnostics, prediction, clock: reliable, keep last 100. A reliable writer drops
#: samples a reader has not acknowledged once its history is full: with 10, a recorder busy for
#: half a second (start-up, a chunk write on a loaded machine) lost states published at 20 Hz
STREAM_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
#: target and obstacles: the latest value reaches late joiners (a restarted controller)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

_NONNEGATIVE = {"kappa", "mu", "feasibility_tolerance"}


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

    def descriptor(self) -> ParameterDescriptor:
        text = self.description + (f" (one of: {', '.join(self.choices)})" if self.choices else "")
        d = ParameterDescriptor(name=self.name, type=self.type_, description=text, read_only=self.read_only)
        if self.float_range:
            d.floating_point_range = [FloatingPointRange(from_value=self.float_range[0], to_value=self.float_range[1])]
        if self.int_range:
            d.integer_range = [IntegerRange(from_value=self.int_range[0], to_value=self.int_range[1], step=1)]
        return d


def _ros_type(value: Any) -> int:
    if isinstance(value, bool):
        return ParameterType.PARAMETER_BOOL
    if isinstance(value, int):
        return ParameterType.PARAMETER_INTEGER
    if isinstance(value, float):
        return ParameterType.PARAMETER_DOUBLE
    if isinstance(value, str):
        return ParameterType.PARAMETER_STRING
    if isinstance(value, tuple) and value and all(isinstance(v, str) for v in value):
        return ParameterType.PARAMETER_STRING_ARRAY
    if isinstance(value, tuple) and value and all(isinstance(v, int) for v in value):
        return ParameterType.PARAMETER_INTEGER_ARRAY
    if isinstance(value, tuple):
        return ParameterType.PARAMETER_DOUBLE_ARRAY
    raise TypeError(f"no ROS parameter type for {value!r}")


def settings_specs(defaults: ControllerSettings | None = None) -> list[ParamSpec]:
    """A ParamSpec per core setting; structural ones read-only, weights ranged."""
    defaults = defaults or ControllerSettings()
    specs = []
    for f in dataclasses.fields(ControllerSettings):
        value = getattr(defaults, f.name)
        if f.name in ("constraints",) and not value:
            type_ = ParameterType.PARAMETER_STRING_ARRAY
            value = None  # an empty list has no ROS type: declare typed and unset
        else:
            type_ = _ros_type(value)
        if type_ == ParameterType.PARAMETER_DOUBLE_ARRAY:
            value = [float(v) for v in value]
        elif isinstance(value, tuple):
            value = list(value)
        specs.append(ParamSpec(
            f.name, value, SETTING_DOCS[f.name], type_, read_only=f.name not in RUNTIME_FIELDS,
            float_range=(0.0, 1e300) if f.name in _NONNEGATIVE else None,
        ))
    return specs


def declare(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare every spec (overrides from --params-file / -p apply); returns name -> value."""
    values = {}
    for spec in specs:
        default = spec.default if spec.default is not None else Parameter.Type(spec.type_)
        param = node.declare_parameter(spec.name, default, spec.descriptor())
        values[spec.name] = param.value
    return values


def settings_from_values(values: dict[str, Any]) -> ControllerSettings:
    """Core settings from declared parameter values (unset ones take the core default)."""
    fields = {f.name for f in dataclasses.fields(ControllerSettings)}
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in values.items() if k in fields and v is not None}
    for k, v in kwargs.items():
        if isinstance(v, tuple) and k not in ("constraints", "keep_in", "plane", "output_plane"):
            kwargs[k] = tuple(float(x) for x in v)
    return ControllerSettings(**kwargs)


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
