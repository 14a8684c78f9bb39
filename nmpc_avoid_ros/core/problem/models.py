"""Which models a config can name: the shipped model files, models registered by other packages, and files.

`model:` in a config is one of
- a shipped model: a file in nmpc_avoid_ros/models/ (van_der_pol, double_integrator_2d, unicycle,
  unicycle_pose, bicycle), declared exactly as a user's model is;
- a model registered by an installed Python package under the entry-point group `nmpc_avoid_ros.models`:
  the entry point is a callable returning a `Model` or the path of a model file (docs/own_model.md);
- the path of a model file (ends in .yaml or .yml; relative paths from the working directory).

A model file's `parameters` take their defaults unless a config's `model_parameters` ('name=value') override them.
Each call builds the model afresh (a few milliseconds): nothing CasADi holds is shared between controllers.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Mapping
from importlib import metadata
from pathlib import Path

from ..errors import ConfigError
from .model import DISCRETISATIONS, Model, PlanarMap, unicycle_turn_guess
from .model_files import ModelFileError, load_model_file

__all__ = ["DISCRETISATIONS", "MODELS", "ENTRY_POINT_GROUP", "Model", "ModelFileError", "PlanarMap", "check_model_name",
           "make_model", "model_bounds", "model_names", "parse_model_parameters",
           "unicycle_turn_guess"]

#: the shipped model files
MODEL_DIR = Path(__file__).resolve().parents[2] / "models"
#: the entry-point group through which other packages register models
ENTRY_POINT_GROUP = "nmpc_avoid_ros.models"
MODEL_FILE_SUFFIXES = (".yaml", ".yml")


def _shipped(name: str) -> Callable[[], Model]:
    return lambda: load_model_file(MODEL_DIR / f"{name}.yaml")


#: the shipped models by name -> a factory (each reads its file in nmpc_avoid_ros/models/)
MODELS: dict[str, Callable[[], Model]] = {p.stem: _shipped(p.stem) for p in sorted(MODEL_DIR.glob("*.yaml"))}


def _registered() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def model_names() -> list[str]:
    """Every name a config can use besides a file path: shipped and registered models."""
    return sorted({*MODELS, *_registered()})


def is_model_file(name: str) -> bool:
    """Whether `model:` names a file rather than a shipped or registered model."""
    return name.endswith(MODEL_FILE_SUFFIXES) or "/" in name


def check_model_name(name: str) -> Path:
    """A shipped or registered name as is, a model file's path resolved; ConfigError if neither exists (cheap:
    nothing is built; make_model reports what is wrong inside a file)."""
    if not isinstance(name, str) or not name:
        raise ConfigError(f"model must be a name or a model file path, got {name!r}")
    if not is_model_file(name):
        if name not in MODELS and name not in _registered():
            raise ConfigError(f"unknown model {name!r}; known models: {', '.join(model_names())} "
                              f"(or the path of a model file, *.yaml)")
        return Path(name)
    path = Path(name).expanduser()
    if not path.is_file():
        raise ConfigError(f"model file {name!r} does not exist (relative paths start at {Path.cwd()})")
    return path.resolve()


def parse_model_parameters(items: Iterable[str]) -> dict[str, float]:
    """'name=value' strings (a config's model_parameters) as {name: value}; ConfigError naming a malformed one."""
    values: dict[str, float] = {}
    for item in items:
        name, sep, text = str(item).partition("=")
        name = name.strip()
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not sep or not name.isidentifier() or not math.isfinite(value):
            raise ConfigError(f"model_parameters: {item!r} is not 'name=value' with a finite number "
                              f"(e.g. 'wheelbase=0.6')")
        if name in values:
            raise ConfigError(f"model_parameters: {name!r} given twice")
        values[name] = value
    return values


def make_model(name: str, parameters: Mapping[str, float] | None = None) -> Model:
    """The model a config names (shipped, registered or a file path), with `parameters` overriding the defaults
    of its model file; ConfigError naming what is known, a ModelFileError (file:line: cause) for a file that is
    wrong (an undeclared parameter included)."""
    resolved = check_model_name(name)
    if is_model_file(name):
        return load_model_file(resolved, parameters)
    if name in MODELS:
        return load_model_file(MODEL_DIR / f"{name}.yaml", parameters)
    entry = _registered()[name]
    try:
        made = entry.load()()
    except ConfigError:
        raise
    except Exception as exc:  # a plugin's own failure, named with its entry point
        raise ConfigError(f"model {name!r} registered by {entry.value!r} failed: {type(exc).__name__}: {exc}") \
            from None
    if isinstance(made, (str, Path)):
        return load_model_file(made, parameters)
    if not isinstance(made, Model):
        raise ConfigError(f"model {name!r} registered by {entry.value!r} returned {type(made).__name__}, "
                          f"not a Model or a model file path")
    if parameters:
        raise ConfigError(f"model {name!r} registered by {entry.value!r} is built in Python: it takes no "
                          f"model_parameters (got {sorted(parameters)})")
    return made


def model_bounds(name: str, parameters: Iterable[str] = ()) -> dict[str, tuple[float, ...]]:
    """The bounds of Z a model declares (state_min, state_max, input_min, input_max, as far as it does), with the
    'name=value' `parameters`: a config's defaults. Cached per name, parameters (and a file's modification time):
    settings are built often, a model is parsed once."""
    resolved = check_model_name(name)
    stamp = resolved.stat().st_mtime_ns if is_model_file(name) else 0
    return dict(_bounds(name, tuple(parameters), stamp))


@functools.lru_cache(maxsize=128)
def _bounds(name: str, parameters: tuple[str, ...], _stamp: int) -> tuple[tuple[str, tuple[float, ...]], ...]:
    return tuple(make_model(name, parse_model_parameters(parameters)).bounds.items())
