"""The value of a parameter `send param NAME VALUE...` sets (tools/send.py), typed as the node declared it:
`mu 0` is sent as 0.0 to a double; an undeclared (untyped) value is read as YAML reads it, as `ros2
param set` does; several values, or one `[a, b]`, make an array."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from ..core.errors import NmpcError

_TRUE, _FALSE = ("true", "yes", "on"), ("false", "no", "off")


def _scalar(text: str, kind: str, name: str) -> Any:
    """One value of a parameter of `kind` ('double', 'integer', 'bool', 'string')."""
    if kind == "string":
        return text
    if kind == "bool":
        if text.lower() in _TRUE or text.lower() in _FALSE:
            return text.lower() in _TRUE
        raise NmpcError(f"{name} is a bool: true or false, got {text!r}")
    try:
        value = int(text) if kind == "integer" else float(text)
    except ValueError:
        raise NmpcError(f"{name} takes {'integers' if kind == 'integer' else 'numbers'}, got {text!r}") from None
    if kind == "double" and not math.isfinite(value):
        raise NmpcError(f"{name} must be finite, got {text!r}")
    return value


def _infer(texts: Sequence[str]) -> str:
    """The kind of untyped values, as YAML reads them (ros2 param set does the same)."""
    def kind(text: str) -> str:
        if text.lower() in _TRUE + _FALSE:
            return "bool"
        for k, convert in (("integer", int), ("double", float)):
            try:
                convert(text)
                return k
            except ValueError:
                pass
        return "string"

    kinds = {kind(t) for t in texts}
    if kinds == {"integer", "double"}:
        return "double"
    return kinds.pop() if len(kinds) == 1 else "string"


def _items(values: Sequence[str]) -> list[str]:
    """The values of an array: several arguments, or one '[a, b]' / 'a,b'."""
    if len(values) == 1:
        text = values[0].strip()
        if text.startswith("[") and text.endswith("]"):
            text = text[1:-1]
        return [v.strip() for v in text.split(",") if v.strip()] if ("," in text or values[0].strip() != text) \
            else [text] if text else []
    return list(values)


def parameter_value(name: str, type_: int, values: Sequence[str]) -> Any:
    """The rclpy Parameter `name` from command-line texts, in the declared ParameterType `type_` (0:
    not set, inferred); NmpcError with the reason for a wrong number or kind of value."""
    from rclpy.parameter import Parameter

    T = Parameter.Type
    scalars = {T.DOUBLE: "double", T.INTEGER: "integer", T.BOOL: "bool", T.STRING: "string"}
    arrays = {T.DOUBLE_ARRAY: "double", T.INTEGER_ARRAY: "integer", T.BOOL_ARRAY: "bool", T.STRING_ARRAY: "string"}
    declared = T(type_)
    if declared == T.NOT_SET:  # untyped: one value is a scalar, several (or [..]) an array
        items = _items(values)
        kind = _infer(items)
        is_array = len(values) > 1 or values[0].strip().startswith("[")
        declared = {v: k for k, v in (arrays if is_array else scalars).items()}[kind]
    if declared in scalars:
        if len(values) != 1:
            raise NmpcError(f"{name} takes one value, got {len(values)}: {' '.join(values)}")
        return Parameter(name, declared, _scalar(values[0], scalars[declared], name))
    if declared in arrays:
        return Parameter(name, declared, [_scalar(v, arrays[declared], name) for v in _items(values)])
    raise NmpcError(f"{name} has type {declared.name}, which send cannot set")
