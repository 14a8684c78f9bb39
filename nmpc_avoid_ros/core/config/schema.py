"""One declaration per setting: type, default, range or choices, run time or rebuild, description.

A setting is a field of a frozen dataclass whose default is `setting(...)`:

    mu: float = setting(1.0e8, "avoidance weight: V_a = mu (F(x_a) + sum_j F(x(j)))", runtime=True, low=0.0)

Its type comes from the annotation (float, int, bool, str, tuple[float, ...], tuple[int, ...],
tuple[str, ...], optionally `| None` for "unset"). Everything else is derived from that one line:
    - validation and normalisation (`Setting.coerce`: ints to floats, lists to tuples; ConfigError
      naming the setting otherwise), run by the dataclass's `__post_init__`;
    - the read-only set: `runtime=False` means the value is baked into the NLP or its solver and
      a change needs a new controller (an NLP or solver rebuild); `runtime=True` means it may
      change while the controller runs, without a rebuild;
    - the ROS parameter descriptors (ros/parameters.py: type, description, range, read_only);
    - the parameter tables of docs/reference.md (tools/readme_tables.py writes them; a test keeps them equal).

Adding a setting is a one-place change:
    1. add the field with `setting(...)` to `ControllerSettings` (core/config/settings.py; it then also
       enters `structure_key` unless runtime) or, for a parameter only the controller node uses,
       to `NodeSettings` there;
    2. use it where it acts (the NLP build, the controller step, or the node);
    3. run `make readme` to regenerate the tables of docs/reference.md (test_settings_schema.py fails until then).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigError

#: the kinds of value a setting can hold (ROS: double, integer, bool, string and their arrays)
KINDS = {float: "float", int: "int", bool: "bool", str: "str"}


@dataclass(frozen=True)
class Setting:
    """The declaration of one setting.

    kind: 'float', 'int', 'bool', 'str', or 'float[]', 'int[]', 'str[]' for tuples.
    low, high: inclusive bounds of the value (of each element for arrays); `low_open` makes the
    lower one exclusive. finite: floats must be finite (bounds of a box may be +-inf otherwise).
    choices: the allowed strings. length: the exact number of elements of an array.
    optional: None (unset) is allowed.
    """

    name: str
    kind: str
    default: Any
    description: str
    runtime: bool = False
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    finite: bool = True
    choices: tuple[str, ...] = ()
    length: int | None = None
    optional: bool = False

    @property
    def constrained(self) -> bool:
        """Whether the declaration limits the values beyond their kind."""
        return bool(self.choices) or (self.low, self.high, self.length) != (None, None, None)

    @property
    def is_array(self) -> bool:
        return self.kind.endswith("[]")

    @property
    def element_kind(self) -> str:
        return self.kind[:-2] if self.is_array else self.kind

    def rule(self) -> str:
        """The allowed values in words, e.g. 'a finite number in (0, 1]' or 'one of euler, rk4'."""
        if self.choices:
            return "one of " + ", ".join(self.choices)
        noun = {"float": "a finite number" if self.finite else "a number", "int": "an integer",
                "bool": "true or false", "str": "a string"}[self.element_kind]
        if self.low is not None and self.high is not None:
            noun += f" in {'(' if self.low_open else '['}{_fmt(self.low)}, {_fmt(self.high)}]"
        elif self.low is not None:
            noun += f" {'>' if self.low_open else '>='} {_fmt(self.low)}"
        elif self.high is not None:
            noun += f" <= {_fmt(self.high)}"
        if self.is_array:
            count = f"{self.length} " if self.length is not None else ""
            noun = f"a list of {count}values, each {noun}"
        return noun

    def coerce(self, value: Any) -> Any:
        """The value in its canonical form (float for float, tuple for arrays), else ConfigError."""
        if value is None and self.optional:
            return None
        if not self.is_array:
            return self._element(value, value)
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__") or isinstance(value, Mapping):
            raise ConfigError(f"{self.name} must be a list, got {_short(value)}")
        items = tuple(value)
        if self.length is not None and len(items) != self.length:
            raise ConfigError(f"{self.name} must be {self.rule()}, got {_short(value)}")
        return tuple(self._element(item, value) for item in items)

    def _element(self, item: Any, whole: Any) -> Any:
        kind = self.element_kind
        ok = True
        if kind == "bool":
            ok = isinstance(item, bool)
        elif kind == "str":
            ok = isinstance(item, str) and (not self.choices or item in self.choices)
            if isinstance(item, str) and not ok:
                raise ConfigError(f"{self.name} must be {self.rule()}; unknown {_short(item)}")
        elif kind == "int":
            ok = isinstance(item, numbers.Integral) and not isinstance(item, bool)
            item = int(item) if ok else item
        else:
            ok = isinstance(item, numbers.Real) and not isinstance(item, bool)
            try:
                item = float(item) if ok else item
            except OverflowError:  # an int beyond float range
                ok = False
            ok = ok and not math.isnan(item) and (not self.finite or math.isfinite(item))
        if ok and kind in ("int", "float"):
            ok = ((self.low is None or (item > self.low if self.low_open else item >= self.low))
                  and (self.high is None or item <= self.high))
        if not ok:
            raise ConfigError(f"{self.name} must be {self.rule()}, got {_short(whole)} ({self.description})")
        return item


def _short(value: Any, limit: int = 60) -> str:
    """repr of a value, cut to `limit` characters (a fuzzed 400-digit integer stays readable)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _fmt(bound: float) -> str:
    return f"{bound:g}"


def setting(default: Any, description: str, *, runtime: bool = False, low: float | None = None,
            high: float | None = None, low_open: bool = False, finite: bool = True, choices: tuple[str, ...] = (),
            length: int | None = None) -> Any:
    """A dataclass field declaring a setting (see the module docstring); the kind comes from the annotation."""
    return dataclasses.field(default=default, metadata={"setting": dict(
        default=default, description=description, runtime=runtime, low=low, high=high, low_open=low_open,
        finite=finite, choices=tuple(choices), length=length)})


@functools.cache
def schema(cls: type) -> Mapping[str, Setting]:
    """name -> Setting of every field of a settings dataclass, in declaration order."""
    hints = typing.get_type_hints(cls)
    settings = {}
    for f in dataclasses.fields(cls):
        kind, optional = _kind(f.name, hints[f.name])
        settings[f.name] = Setting(name=f.name, kind=kind, optional=optional, **f.metadata["setting"])
    return types.MappingProxyType(settings)


def _kind(name: str, hint: Any) -> tuple[str, bool]:
    """(kind, optional) from a type annotation."""
    args = typing.get_args(hint)
    optional = typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args
    if optional:
        (hint,) = [a for a in args if a is not type(None)]
        args = typing.get_args(hint)
    if hint in KINDS:
        return KINDS[hint], optional
    if typing.get_origin(hint) is tuple and args and args[0] in KINDS and all(a in (args[0], Ellipsis) for a in args):
        return KINDS[args[0]] + "[]", optional
    raise TypeError(f"setting {name}: unsupported annotation {hint!r}")


def normalise(instance: Any) -> None:
    """Coerce every field of a frozen settings dataclass in place (ConfigError names the first bad one)."""
    for spec in schema(type(instance)).values():
        object.__setattr__(instance, spec.name, spec.coerce(getattr(instance, spec.name)))
