"""Reading a model file: YAML whose strings remember their lines, and errors that name `file:line`.

The model it declares is built by core/problem/model_files.py.
"""

from __future__ import annotations

import keyword
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError, ExpressionError
from .expressions import ALLOWED_CONSTANTS, ALLOWED_FUNCTIONS, parse_expression

#: a model file larger than this is refused before it is parsed (bytes)
MAX_FILE_SIZE = 200_000
#: states, inputs or outputs a model may declare
MAX_DIMENSION = 100
KEYS = ("name", "description", "parameters", "states", "inputs", "outputs", "units", "dynamics", "discrete",
        "sample_time", "output", "steady_state", "rest", "near_rest", "bounds", "plane", "angle_outputs",
        "turn_on_spot", "planar")
REQUIRED = ("name", "states", "inputs", "outputs", "output")


class ModelFileError(ConfigError):
    """A model file that cannot be used: `file:line: what` in one line."""


class _Text(str):
    """A YAML string that remembers its line (1-based)."""

    line: int = 0


class _Loader(yaml.SafeLoader):
    """SafeLoader whose strings (keys and values) carry their line numbers."""


def _text(loader: _Loader, node: yaml.ScalarNode) -> _Text:
    text = _Text(loader.construct_scalar(node))
    text.line = node.start_mark.line + 1
    return text


_Loader.add_constructor("tag:yaml.org,2002:str", _text)


def _line(*items: Any) -> int:
    """The first known line among items (a _Text, or a mapping/list holding one)."""
    for item in items:
        if isinstance(item, _Text):
            return item.line
        if isinstance(item, Mapping):
            found = _line(*item.keys())
        elif isinstance(item, list):
            found = _line(*item)
        else:
            continue
        if found:
            return found
    return 0


class ModelFile:
    """One model file being read: where errors point."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def error(self, where: Any, message: str) -> ModelFileError:
        line = _line(where) if not isinstance(where, int) else where
        return ModelFileError(f"{self.path}:{line}: {message}" if line else f"{self.path}: {message}")

    def names(self, data: Mapping, key: str) -> tuple[str, ...]:
        value = data[key]
        if not isinstance(value, list) or not value or len(value) > MAX_DIMENSION:
            raise self.error(key_of(data, key), f"{key} must be a list of 1..{MAX_DIMENSION} names, got {value!r}")
        for name in value:
            if not (isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)) \
                    or name in ALLOWED_FUNCTIONS or name in ALLOWED_CONSTANTS:
                raise self.error(name if isinstance(name, _Text) else key_of(data, key),
                                 f"{key}: {name!r} is not a usable name (an identifier that is not a function "
                                 f"or constant of the expressions)")
        return tuple(str(n) for n in value)

    def table(self, data: Mapping, key: str, names: tuple[str, ...], symbols: Mapping[str, Any]) -> list[Any]:
        """The expressions of `key` (a mapping name -> expression), one per name, in the order of names."""
        section = data.get(key)
        if not isinstance(section, Mapping):
            raise self.error(key_of(data, key), f"{key} must map each of {list(names)} to an expression")
        missing = [n for n in names if n not in section]
        extra = [k for k in section if k not in names]
        if missing or extra:
            where = extra[0] if extra else key_of(data, key)
            what = f"missing {missing}" if missing else f"unknown {[str(e) for e in extra]}"
            raise self.error(where, f"{key}: {what} (declared: {list(names)})")
        return [self.expression(section[n], symbols, f"{key}.{n}", n) for n in names]

    def expression(self, text: Any, symbols: Mapping[str, Any], what: str, where: Any) -> Any:
        if isinstance(text, (int, float)) and not isinstance(text, bool):
            text = repr(float(text))
        try:
            return parse_expression(text, symbols)
        except ExpressionError as exc:
            raise self.error(text if isinstance(text, _Text) else where, f"{what}: {exc}") from None


def key_of(data: Mapping, key: str) -> Any:
    """The key object itself (a _Text with its line) of `key` in data, else key."""
    return next((k for k in data if k == key), key)


def read_model_file(path: Path) -> tuple[ModelFile, Mapping]:
    file = ModelFile(path)
    try:
        size = path.stat().st_size
        if size > MAX_FILE_SIZE:
            raise file.error(0, f"model file is too large ({size} > {MAX_FILE_SIZE} bytes)")
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_Loader)
    except (OSError, UnicodeDecodeError) as exc:
        raise file.error(0, f"cannot read the model file: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise file.error(mark.line + 1 if mark else 0, f"not YAML: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(data, Mapping):
        raise file.error(0, f"a model file is a mapping of {', '.join(REQUIRED)} (and optional keys)")
    unknown = [k for k in data if k not in KEYS]
    if unknown:
        raise file.error(unknown[0], f"unknown key {str(unknown[0])!r} (known: {', '.join(KEYS)})")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise file.error(0, f"missing key(s): {', '.join(missing)}")
    if ("dynamics" in data) == ("discrete" in data):
        raise file.error(0, "declare the dynamics either in continuous time (`dynamics`) or as a discrete map "
                            "(`discrete` with its `sample_time`), not both or neither")
    if ("sample_time" in data) != ("discrete" in data):
        raise file.error(key_of(data, "sample_time") if "sample_time" in data else key_of(data, "discrete"),
                         "`sample_time` (s) goes with a `discrete` map, and only with it")
    return file, data
