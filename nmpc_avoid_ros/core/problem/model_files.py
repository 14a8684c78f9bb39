"""Models declared as data: a YAML model file -> `Model`, parsed without `eval` by the region parser.

A model file (docs/own_model.md has the tutorial; the shipped models are files like it, in
nmpc_avoid_ros/models/):

    name: van_der_pol
    parameters: {damping: 0.2}          # optional: constants the expressions use
    states: [x1, x2]                     # names, in the order of the state vector
    inputs: [u]
    outputs: [y]
    dynamics:                            # continuous time x' = f(x, u), one expression per state
      x1: x2
      x2: damping*(1 - x1**2)*x2 - x1 + u
    # or, instead of `dynamics`, a discrete map over its own sample time:
    #   discrete: {x1: x1 + 0.5*x2, x2: ...}   and   sample_time: 0.5
    output: {y: x1}                      # y = h(x, u)
    steady_state:                        # optional closed form g_x(y), g_u(y) over the outputs
      states: {x1: y, x2: 0}
      inputs: {u: y}
    bounds: {state_min: [-6, -2], state_max: [6, 2], input_min: [-6], input_max: [6]}   # Z, optional

Optional keys: `description`; `units` (`states`, `outputs`: one unit per entry, e.g. m, rad);
`plane` (the two states obstacle markers in the `state` frame map to); `rest` (rows r(x, u) = 0 that
are exactly the equilibria, of full rank there: Model.rest); `near_rest` (states/inputs over the
outputs and the measured states: a steady state near x for a model without closed form,
Model.steady_guess); `angle_outputs` (output -> the state it equals, an angle); `turn_on_spot`
(true: a forward-only planar robot turns towards a target behind it first, Model.turn_guess);
`planar` (how the pose and the velocity command map to the model: PlanarMap).

Every problem is a ModelFileError naming the file, the line and the cause in one line; a model
is built completely or not at all. Steady-state maps are checked to be equilibria on a grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from .model import Model, PlanarMap, unicycle_turn_guess
from .model_yaml import ModelFile, ModelFileError, key_of, read_model_file  # noqa: F401 (ModelFileError: what it raises)

BOUND_KEYS = ("state_min", "state_max", "input_min", "input_max")
#: |f(g_x(y), g_u(y))| and |h(g_x(y), g_u(y)) - y| above this (relative to 1 + |y|) is not an equilibrium
STEADY_TOLERANCE = 1e-8
#: outputs (uniform in [-1, 1]^p, fixed seed) at which a closed-form steady state is checked
STEADY_CHECKS = 8


def _parameters(file: ModelFile, data: Mapping, overrides: Mapping[str, float] | None) -> dict[str, float]:
    section = data.get("parameters") or {}
    if not isinstance(section, Mapping):
        raise file.error(key_of(data, "parameters"), "parameters must map names to numbers")
    values: dict[str, float] = {}
    for name, value in {**section, **(overrides or {})}.items():
        if name not in section:
            raise file.error(key_of(data, "parameters"), f"parameter {name!r} is not declared in the model file")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise file.error(name, f"parameter {name!r} must be a finite number, got {value!r}")
        if not (isinstance(name, str) and name.isidentifier()):
            raise file.error(name, f"parameter name {name!r} is not an identifier")
        values[str(name)] = float(value)
    return values


def load_model_file(path: str | Path, parameters: Mapping[str, float] | None = None) -> Model:
    """The Model a model file declares (`parameters` override its defaults); ModelFileError naming the file,
    line and cause for anything wrong with it."""
    file, data = read_model_file(Path(path))
    params = _parameters(file, data, parameters)
    states, inputs, outputs = (file.names(data, k) for k in ("states", "inputs", "outputs"))
    everything = [*params, *states, *inputs, *outputs]
    twice = sorted({n for n in everything if everything.count(n) > 1})
    if twice:
        raise file.error(0, f"name(s) used twice among parameters, states, inputs and outputs: {twice}")
    name = str(data["name"])
    if not name.isidentifier():
        raise file.error(data["name"], f"name must be an identifier, got {name!r}")

    x, u = ca.SX.sym("x", len(states)), ca.SX.sym("u", len(inputs))
    constants = {k: ca.SX(v) for k, v in params.items()}
    xu = {**constants, **{s: x[i] for i, s in enumerate(states)}, **{s: u[i] for i, s in enumerate(inputs)}}
    discrete_map, map_sample_time = None, None
    if "discrete" in data:
        map_sample_time = data["sample_time"]
        if isinstance(map_sample_time, bool) or not isinstance(map_sample_time, (int, float)) \
                or not (math.isfinite(map_sample_time) and map_sample_time > 0):
            raise file.error(key_of(data, "sample_time"), f"sample_time must be a positive number of seconds, got "
                                                          f"{map_sample_time!r}")
        x_next = ca.vertcat(*file.table(data, "discrete", states, xu))
        discrete_map = ca.Function(f"{name}_map", [x, u], [x_next], ["x", "u"], ["x_next"])
        xdot = (x_next - x) / float(map_sample_time)  # zero exactly at the map's fixed points
    else:
        xdot = ca.vertcat(*file.table(data, "dynamics", states, xu))
    y = ca.vertcat(*file.table(data, "output", outputs, xu))
    dynamics = ca.Function(f"{name}_dynamics", [x, u], [xdot], ["x", "u"], ["xdot"])
    output = ca.Function(f"{name}_output", [x, u], [y], ["x", "u"], ["y"])

    steady = _steady_state(file, data, params, states, inputs, outputs, dynamics, output)
    rest = None
    if data.get("rest") is not None:
        rows = data["rest"]
        if not isinstance(rows, list) or not rows:
            raise file.error(key_of(data, "rest"), "rest must be a list of expressions over the states and inputs")
        r = ca.vertcat(*(file.expression(t, xu, "rest", key_of(data, "rest")) for t in rows))
        rest = ca.Function(f"{name}_rest", [x, u], [r], ["x", "u"], ["r"])
    planar = _planar(file, data, states, inputs, xu, x, u, constants)
    return Model(
        name, states, inputs, outputs, dynamics, output, steady,
        default_plane=_indices(file, data, "plane", states, 2) if "plane" in data else (0, 1),
        steady_guess=_near_rest(file, data, params, states, inputs, outputs),
        turn_guess=_turn_guess(file, data, planar), rest=rest,
        angle_outputs=_angles(file, data, states, outputs), planar=planar,
        units=_units(file, data, states, outputs), bounds=_bounds(file, data, states, inputs),
        parameters=params, source=str(path), description=str(data.get("description") or ""),
        discrete_map=discrete_map, map_sample_time=None if map_sample_time is None else float(map_sample_time))


def _steady_state(file: ModelFile, data: Mapping, params: Mapping[str, float], states: tuple[str, ...],
                  inputs: tuple[str, ...], outputs: tuple[str, ...], dynamics: ca.Function,
                  output: ca.Function) -> Callable | None:
    """g_x, g_u as a function of y (SX/MX: the expressions over its entries; numbers: DM); checked to be
    equilibria with h(g_x(y), g_u(y)) = y on a grid of outputs."""
    section = data.get("steady_state")
    if section is None:
        return None
    if not isinstance(section, Mapping) or set(section) != {"states", "inputs"}:
        raise file.error(key_of(data, "steady_state"), "steady_state must have exactly `states` and `inputs`")

    def build(y: ca.SX | ca.MX) -> tuple[Any, Any]:
        kind = type(y)
        table = {**{k: kind(v) for k, v in params.items()}, **{o: y[i] for i, o in enumerate(outputs)}}
        xs = file.table(section, "states", states, table)
        us = file.table(section, "inputs", inputs, table)
        return ca.vertcat(*xs), ca.vertcat(*us)

    y_sym = ca.SX.sym("y", len(outputs))
    numeric = ca.Function("steady_state", [y_sym], list(build(y_sym)))

    def steady(y: Any) -> tuple[Any, Any]:
        if isinstance(y, (ca.SX, ca.MX)):
            return build(y)
        return numeric(ca.DM(np.asarray(y, float).reshape(-1)))

    for y in np.random.default_rng(0).uniform(-1.0, 1.0, (STEADY_CHECKS, len(outputs))):
        xs, us = numeric(y)
        scale = 1.0 + float(np.max(np.abs(y)))
        rate = float(np.max(np.abs(np.asarray(dynamics(xs, us))))) / scale
        miss = float(np.max(np.abs(np.asarray(output(xs, us)).ravel() - y))) / scale
        if not (rate <= STEADY_TOLERANCE and miss <= STEADY_TOLERANCE):
            what = f"f(g_x(y), g_u(y)) = {rate * scale:.3g}, not 0" if rate > STEADY_TOLERANCE else \
                f"h(g_x(y), g_u(y)) misses y by {miss * scale:.3g}"
            raise file.error(key_of(data, "steady_state"),
                             f"steady_state is not an equilibrium at y = {np.round(y, 6).tolist()}: {what}")
    return steady


def _near_rest(file: ModelFile, data: Mapping, params: Mapping[str, float], states: tuple[str, ...],
               inputs: tuple[str, ...], outputs: tuple[str, ...]) -> Callable | None:
    section = data.get("near_rest")
    if section is None:
        return None
    y, x = ca.SX.sym("y", len(outputs)), ca.SX.sym("x", len(states))
    table = {**{k: ca.SX(v) for k, v in params.items()}, **{o: y[i] for i, o in enumerate(outputs)},
             **{s: x[i] for i, s in enumerate(states)}}
    if not isinstance(section, Mapping) or set(section) != {"states", "inputs"}:
        raise file.error(key_of(data, "near_rest"), "near_rest must have exactly `states` and `inputs`")
    xs = ca.vertcat(*file.table(section, "states", states, table))
    us = ca.vertcat(*file.table(section, "inputs", inputs, table))
    guess = ca.Function("near_rest", [y, x], [xs, us])

    def near_rest(y_s: np.ndarray, x_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xs_, us_ = guess(np.asarray(y_s, float), np.asarray(x_now, float))
        return np.asarray(xs_, float).ravel(), np.asarray(us_, float).ravel()

    return near_rest


def _indices(file: ModelFile, data: Mapping, key: str, names: tuple[str, ...], count: int) -> tuple[int, ...]:
    value = data[key]
    if not isinstance(value, list) or len(value) != count or any(v not in names for v in value):
        raise file.error(key_of(data, key), f"{key} must list {count} of {list(names)}, got {value!r}")
    return tuple(names.index(v) for v in value)


def _angles(file: ModelFile, data: Mapping, states: tuple[str, ...],
            outputs: tuple[str, ...]) -> tuple[tuple[int, int], ...]:
    section = data.get("angle_outputs") or {}
    if not isinstance(section, Mapping) or any(k not in outputs or v not in states for k, v in section.items()):
        raise file.error(key_of(data, "angle_outputs"), "angle_outputs must map outputs to the states they equal")
    return tuple((outputs.index(k), states.index(v)) for k, v in section.items())


def _units(file: ModelFile, data: Mapping, states: tuple[str, ...], outputs: tuple[str, ...]) -> dict[str, tuple]:
    section = data.get("units") or {}
    sizes = {"states": len(states), "outputs": len(outputs)}
    if not isinstance(section, Mapping) or any(k not in sizes for k in section):
        raise file.error(key_of(data, "units"), "units must have `states` and/or `outputs`")
    units = {}
    for key, value in section.items():
        if not isinstance(value, list) or len(value) != sizes[key] or not all(isinstance(v, str) for v in value):
            raise file.error(key, f"units.{key} must list {sizes[key]} unit names")
        units["state" if key == "states" else "output"] = tuple(str(v) for v in value)
    return units


def _bounds(file: ModelFile, data: Mapping, states: tuple[str, ...], inputs: tuple[str, ...]) -> dict[str, tuple]:
    section = data.get("bounds") or {}
    if not isinstance(section, Mapping) or any(k not in BOUND_KEYS for k in section):
        raise file.error(key_of(data, "bounds"), f"bounds may hold {', '.join(BOUND_KEYS)}")
    bounds = {}
    for key, value in section.items():
        size = len(states) if key.startswith("state") else len(inputs)
        numbers = [float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else
                   _yaml_float(v) for v in value] if isinstance(value, list) else []
        if len(numbers) != size or any(math.isnan(v) for v in numbers):
            raise file.error(key, f"bounds.{key} must list {size} numbers (.inf allowed, not NaN), got {value!r}")
        bounds[str(key)] = tuple(numbers)
    for lo, hi in (("state_min", "state_max"), ("input_min", "input_max")):
        if lo in bounds and hi in bounds and not all(a <= 0 <= b and a < b for a, b in zip(bounds[lo], bounds[hi])):
            raise file.error(lo, f"bounds: need {lo} <= 0 <= {hi} and {lo} < {hi} (Z contains the origin)")
    return bounds


def _yaml_float(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _planar(file: ModelFile, data: Mapping, states: tuple[str, ...], inputs: tuple[str, ...], xu: Mapping,
            x: ca.SX, u: ca.SX, constants: Mapping) -> PlanarMap | None:
    section = data.get("planar")
    if section is None:
        return None
    where = key_of(data, "planar")
    if not isinstance(section, Mapping) or not {"x", "y", "yaw"} <= set(section):
        raise file.error(where, "planar needs x, y (states) and yaw (a state, or `motion` with velocity)")
    unknown = set(section) - {"x", "y", "yaw", "velocity", "command", "from_command"}
    if unknown:
        raise file.error(next(iter(unknown)), f"planar: unknown key(s) {sorted(map(str, unknown))}")
    for key in ("x", "y"):
        if section[key] not in states:
            raise file.error(section[key], f"planar.{key} must be a state, got {section[key]!r}")
    velocity = None
    if section["yaw"] == "motion":
        velocity = section.get("velocity")
        if not isinstance(velocity, list) or len(velocity) != 2 or any(v not in states for v in velocity):
            raise file.error(where, "planar.yaw: motion needs velocity: [two states] (the heading where it moves)")
        velocity = tuple(states.index(v) for v in velocity)
    elif section["yaw"] not in states:
        raise file.error(section["yaw"], f"planar.yaw must be a state or `motion`, got {section['yaw']!r}")
    command = from_command = None
    if "command" in section or "from_command" in section:
        twist = file.table(section, "command", ("linear", "angular"), xu)
        command = ca.Function("command_twist", [x, u], [ca.vertcat(*twist)], ["x", "u"], ["twist"])
        speeds = ca.SX.sym("twist", 2)
        table = {**constants, **{s: x[i] for i, s in enumerate(states)}, "linear": speeds[0], "angular": speeds[1]}
        back = file.table(section, "from_command", inputs, table)
        from_command = ca.Function("twist_command", [x, speeds], [ca.vertcat(*back)], ["x", "twist"], ["u"])
    yaw = None if section["yaw"] == "motion" else states.index(section["yaw"])
    return PlanarMap(states.index(section["x"]), states.index(section["y"]), yaw, velocity, command, from_command)


def _turn_guess(file: ModelFile, data: Mapping, planar: PlanarMap | None) -> Callable | None:
    if not data.get("turn_on_spot"):
        return None
    if planar is None or (planar.x, planar.y, planar.yaw) != (0, 1, 2) or not _commands_inputs(planar):
        raise file.error(key_of(data, "turn_on_spot"), "turn_on_spot needs planar x, y, yaw as the first three "
                                                       "states and the inputs [linear, angular] as the command")
    return unicycle_turn_guess


def _commands_inputs(planar: PlanarMap) -> bool:
    """Whether the command (linear, angular) is the input vector itself (a unicycle's [v, omega])."""
    if planar.command is None or planar.command.size1_in(1) != 2:
        return False
    x = np.zeros(planar.command.size1_in(0))
    return all(np.allclose(np.asarray(planar.command(x, u)).ravel(), u) for u in ([0.3, -0.7], [-1.1, 0.2]))
