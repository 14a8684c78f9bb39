"""Controller settings and the ROS 2 params-file format shared by nodes and offline tools.

A params file has node names as top-level keys and `ros__parameters` beneath:

    controller:
      ros__parameters:
        model: van_der_pol
        mu: 1.0e8
        ...

`ControllerSettings.from_params` reads the `controller` section; unknown keys there are refused
so that a typo never silently falls back to a default.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError
from .models import DISCRETISATIONS, MODELS

#: solver paths: name -> one-line description (core/nlp.py builds them)
SOLVER_PATHS: dict[str, str] = {
    "ipopt": "multiple shooting, IPOPT interior point (the reference)",
    "fatrop": "stage-wise formulation, FATROP structure-exploiting interior point",
    "sqp": "stage-wise formulation, SQP with a Gauss-Newton Hessian and the qrqp active-set QP solver",
    "sqp_hpipm": "stage-wise formulation, SQP with a Gauss-Newton Hessian and the HPIPM QP solver",
}
SOLVERS = tuple(SOLVER_PATHS)


@dataclass(frozen=True)
class ControllerSettings:
    """Everything that defines the NMPC problem and its solver (defaults: the paper's example).

    Units: times in seconds; bounds in the units of the model's states and inputs.
    Fields marked structural change the NLP's structure; the others are NLP parameters and may
    change at run time without a rebuild.
    """

    model: str = "van_der_pol"  # structural
    sample_time: float = 0.5  # structural, s
    horizon: int = 5  # structural, N
    discretization: str = "euler"  # structural: euler | rk4
    state_min: tuple[float, ...] = (-6.0, -2.0)  # structural
    state_max: tuple[float, ...] = (6.0, 2.0)  # structural
    input_min: tuple[float, ...] = (-6.0,)  # structural
    input_max: tuple[float, ...] = (6.0,)  # structural
    steady_state_scale: float = 0.99  # structural: lambda of (x_a, u_a) in lambda * Z
    constraints: tuple[str, ...] = ()  # structural: hard 'expr <= c' inequalities, part of Z
    keep_in: tuple[str, ...] = ("x1*x2 - 2 <= 0", "-x1*x2 - 2 <= 0")  # structural: penalised
    use_closed_form_steady_state: bool = True  # structural: g_x, g_u vs. eq. 8e-8f
    plane: tuple[int, int] = (0, 1)  # structural: state coordinates of 'state'-frame regions
    output_plane: tuple[int, int] = (0, 1)  # structural: output coordinates of 'output'-frame regions
    max_ellipses: int = 8  # structural
    max_polygons: int = 4  # structural
    max_polygon_vertices: int = 8  # structural
    solver: str = "ipopt"  # structural: one of SOLVERS
    codegen: bool = False  # structural: generate, compile and cache the solver's functions as C
    cache_dir: str = ""  # where compiled solvers are cached ("" -> $NMPC_AVOID_ROS_CACHE or ~/.cache)
    state_weights: tuple[float, ...] = (1.0, 1.0)  # parameter: diag Q of l
    input_weights: tuple[float, ...] = (1.0,)  # parameter: diag R of l
    kappa: float = 1.0e4  # parameter: V_o = kappa |y_a - y_t|^2
    mu: float = 1.0e8  # parameter: avoidance weight
    max_iterations: int = 200  # solver budget per sample
    max_solve_time: float = 2.0  # s, solver wall-time budget per sample
    tolerance: float = 1e-8
    feasibility_tolerance: float = 1e-6  # a truncated iterate is used only if this feasible

    def __post_init__(self) -> None:
        for name in ("state_min", "state_max", "input_min", "input_max", "state_weights", "input_weights",
                     "plane", "output_plane", "constraints", "keep_in"):
            value = getattr(self, name)
            if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
                raise ConfigError(f"{name} must be a list, got {value!r}")
            object.__setattr__(self, name, tuple(value))
        self.validate()

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid setting."""
        for name in ("model", "discretization", "solver"):
            if not isinstance(getattr(self, name), str):
                raise ConfigError(f"{name} must be a string, got {getattr(self, name)!r}")
        if self.model not in MODELS:
            raise ConfigError(f"model: unknown {self.model!r}; known: {', '.join(sorted(MODELS))}")
        if self.discretization not in DISCRETISATIONS:
            raise ConfigError(f"discretization must be one of {DISCRETISATIONS}, got {self.discretization!r}")
        if not isinstance(self.codegen, bool):
            raise ConfigError(f"codegen must be true or false, got {self.codegen!r}")
        if not isinstance(self.cache_dir, str):
            raise ConfigError(f"cache_dir must be a path string, got {self.cache_dir!r}")
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        _positive("sample_time", self.sample_time)
        _positive("max_solve_time", self.max_solve_time)
        _positive("tolerance", self.tolerance)
        _positive("feasibility_tolerance", self.feasibility_tolerance)
        # upper limits keep a typo (horizon: 1e30) from hanging the NLP build
        ranges = {"horizon": (1, 2000), "max_iterations": (1, 100000), "max_ellipses": (0, 256),
                  "max_polygons": (0, 256), "max_polygon_vertices": (3, 64)}
        for name, (least, most) in ranges.items():
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not least <= value <= most:
                raise ConfigError(f"{name} must be an integer in [{least}, {most}], got {value!r}")
        if not isinstance(self.use_closed_form_steady_state, bool):
            raise ConfigError(f"use_closed_form_steady_state must be true or false, got "
                              f"{self.use_closed_form_steady_state!r}")
        _positive("steady_state_scale", self.steady_state_scale)
        if not 0 < self.steady_state_scale <= 1:
            raise ConfigError(f"steady_state_scale (lambda) must be in (0, 1], got {self.steady_state_scale}")
        _nonnegative("kappa", self.kappa)
        _nonnegative("mu", self.mu)
        for name in ("state_weights", "input_weights"):
            for w in getattr(self, name):
                _nonnegative(name, w)
        for lo_name, hi_name in (("state_min", "state_max"), ("input_min", "input_max")):
            lo, hi = getattr(self, lo_name), getattr(self, hi_name)
            if len(lo) != len(hi):
                raise ConfigError(f"{lo_name} and {hi_name} must have the same length")
            for a, b in zip(lo, hi):
                if not all(_is_real(v) for v in (a, b)):
                    raise ConfigError(f"{lo_name}/{hi_name} must be numbers, got {a!r}, {b!r}")
                if math.isnan(a) or math.isnan(b) or not a <= 0 <= b or a == b:
                    # lambda * Z needs Z to contain the origin (paper section II)
                    raise ConfigError(f"{lo_name}/{hi_name}: need min <= 0 <= max and min < max, got {a}, {b}")
        for name in ("plane", "output_plane"):
            plane = getattr(self, name)
            if (len(plane) != 2 or not all(isinstance(i, numbers.Integral) and not isinstance(i, bool) for i in plane)
                    or plane[0] == plane[1] or min(plane) < 0):
                raise ConfigError(f"{name} must be two different non-negative indices, got {plane}")
        for name in ("constraints", "keep_in"):
            for text in getattr(self, name):
                if not isinstance(text, str):
                    raise ConfigError(f"{name} must be a list of expression strings, got {text!r}")

    def replace(self, **changes: Any) -> ControllerSettings:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> ControllerSettings:
        """Settings from the `ros__parameters` mapping of the controller (unknown keys refused)."""
        if not isinstance(params, Mapping):
            raise ConfigError(f"controller parameters must be a mapping, got {type(params).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(map(str, set(params) - known - NODE_ONLY_PARAMETERS))
        if unknown:
            raise ConfigError(f"unknown controller parameter(s): {', '.join(unknown)}")
        values = {k: v for k, v in params.items() if k in known}
        for k in ("sample_time", "steady_state_scale", "kappa", "mu", "max_solve_time", "tolerance",
                  "feasibility_tolerance"):
            if k in values:
                values[k] = _as_float(k, values[k])
        return cls(**values)

    def structure_key(self) -> tuple:
        """The fields that define the NLP's structure (equal keys -> the same NLP)."""
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in RUNTIME_FIELDS)


#: fields that are NLP parameters (or checks of the result), changeable without a rebuild
RUNTIME_FIELDS = frozenset({"state_weights", "input_weights", "kappa", "mu", "feasibility_tolerance"})

#: controller-node parameters that are not core settings (see nodes/controller.py)
NODE_ONLY_PARAMETERS = frozenset({"target", "state_timeout", "stale_behavior", "safe_input", "lockstep",
                                  "use_sim_time", "log_throttle"})


def _as_float(name: str, value: Any) -> float:
    if isinstance(value, bool):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float range
        raise ConfigError(f"{name} must be a number, got {value!r}") from None


def _is_real(value: Any) -> bool:
    """A real number (not a bool) that converts to a float (possibly +-inf, not an overflowing int)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return False
    try:
        float(value)
    except OverflowError:
        return False
    return True


def _positive(name: str, value: float) -> None:
    if not (_is_real(value) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be a positive finite number, got {value!r}")


def _nonnegative(name: str, value: float) -> None:
    if not (_is_real(value) and math.isfinite(value) and value >= 0):
        raise ConfigError(f"{name} must be a finite number >= 0, got {value!r}")


@dataclass(frozen=True)
class ParamsFile:
    """A ROS 2 params file: node name -> its `ros__parameters` mapping."""

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
    for name, body in data.items():
        name = str(name).lstrip("/")
        if not isinstance(body, dict) or not isinstance(body.get("ros__parameters"), dict):
            raise ConfigError(f"params file {p}: node {name!r} needs a 'ros__parameters' mapping")
        nodes[name] = body["ros__parameters"]
    return ParamsFile(p, nodes)


def default_config_path() -> Path:
    """The shipped van der Pol params file: the source tree's, else the installed share/ copy."""
    source = Path(__file__).resolve().parents[2] / "config" / "van_der_pol.yaml"
    installed = Path(sys.prefix) / "share" / "nmpc_avoid_ros" / "config" / "van_der_pol.yaml"
    for candidate in (source, installed):
        if candidate.exists():
            return candidate
    raise ConfigError(f"cannot find the shipped van_der_pol.yaml (looked at {source} and {installed})")


#: one-line documentation of every controller setting (used by the node's parameter
#: descriptors and the README's parameter table)
SETTING_DOCS: dict[str, str] = {
    "model": "plant model of the prediction (van_der_pol, double_integrator_2d)",
    "sample_time": "sample time Ts of the controller and of the discretisation, s",
    "horizon": "prediction horizon N (samples)",
    "discretization": "prediction model discretisation: euler (as in the paper) or rk4",
    "state_min": "lower bounds of the state box of Z (n values; must be <= 0)",
    "state_max": "upper bounds of the state box of Z (n values; must be >= 0)",
    "input_min": "lower bounds of the input box of Z (m values; must be <= 0)",
    "input_max": "upper bounds of the input box of Z (m values; must be >= 0)",
    "steady_state_scale": "lambda in (0, 1]: the artificial steady state lies in lambda * Z",
    "constraints": "hard inequalities of Z over state/input/output names, e.g. 'x1 + x2 <= 3'",
    "keep_in": "penalised regions to stay in, e.g. 'x1*x2 - 2 <= 0' (penalty mu * max(0, g)^2)",
    "use_closed_form_steady_state": "use the model's g_x, g_u; false imposes the equilibrium as constraints",
    "plane": "the two state indices that 'state'-frame obstacle markers map to",
    "output_plane": "the two output indices that 'output'-frame obstacle markers map to",
    "max_ellipses": "capacity of ellipse obstacle slots (CYLINDER/SPHERE markers)",
    "max_polygons": "capacity of polygon obstacle slots (CUBE/LINE_STRIP markers)",
    "max_polygon_vertices": "largest number of vertices of a polygon obstacle",
    "solver": "NLP solver path: " + ", ".join(SOLVERS) + " (simulate --solver list describes them)",
    "codegen": "generate the solver's functions as C, compile them (cc) and cache the library by problem hash",
    "cache_dir": "folder of compiled solvers; empty: $NMPC_AVOID_ROS_CACHE, else ~/.cache/nmpc_avoid_ros",
    "state_weights": "diagonal of Q in the stage cost |x - x_a|_Q^2 (n values >= 0)",
    "input_weights": "diagonal of R in the stage cost |u - u_a|_R^2 (m values >= 0)",
    "kappa": "offset cost weight: V_o = kappa |y_a - y_t|^2",
    "mu": "avoidance weight: V_a = mu (F(x_a) + sum_j F(x(j))); 0 disables avoidance",
    "max_iterations": "solver iteration budget per sample (fast paths: a cold start without a plan is solved "
                      "by IPOPT with >= 200 iterations and 10x the time budget)",
    "max_solve_time": "solver wall-time budget per sample, s",
    "tolerance": "solver convergence tolerance",
    "feasibility_tolerance": "a budget-cut iterate is applied only if its constraint violation is below this",
}
