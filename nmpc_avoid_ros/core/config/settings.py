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
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigError
from ..problem.models import DISCRETISATIONS, Model, check_model_name, make_model, model_bounds, parse_model_parameters

# the params-file readers live in params_file.py; the tools and tests import them from here too
from .params_file import NAMESPACE_WILDCARDS, ParamsFile, default_config_path, load_params_file, params_file_node  # noqa: F401
from .schema import Setting, normalise, schema, setting

#: solver paths: name -> one-line description (core/nlp/tracking.py builds them)
SOLVER_PATHS: dict[str, str] = {
    "ipopt": "multiple shooting, IPOPT interior point (the reference)",
    "fatrop": "stage-wise formulation, FATROP structure-exploiting interior point",
    "sqp": "stage-wise formulation, SQP with a Gauss-Newton Hessian and the qrqp active-set QP solver",
    "sqp_hpipm": "stage-wise formulation, SQP with a Gauss-Newton Hessian and the HPIPM QP solver",
}
SOLVERS = tuple(SOLVER_PATHS)
#: the terminal conditions of the plan (core/nlp/terminal.py)
TERMINALS = ("equality", "set")


@dataclass(frozen=True)
class ControllerSettings:
    """Everything that defines the NMPC problem and its solver (defaults: the paper's example).

    Each field is declared once with `setting(...)` (core/config/schema.py: type, default, range,
    run time or not, description). Units: times in seconds; bounds in the units of the model's
    states and inputs. Fields without `runtime=True` are baked into the NLP or its solver: a
    change needs a new controller. That includes the solver budgets max_iterations,
    max_solve_time and tolerance: they are options of the CasADi solver Function, fixed when it
    is constructed. Run-time fields are NLP parameters (or a check of the result) and change
    between samples without a rebuild.
    """

    model: str = setting("van_der_pol", "plant model of the prediction: a shipped model (van_der_pol, "
                         "double_integrator_2d, unicycle, unicycle_pose, bicycle), one a package registers, or the "
                         "path of a model file (docs/own_model.md)")
    model_parameters: tuple[str, ...] = setting(
        (), "values of the model file's parameters, 'name=value' each (e.g. 'wheelbase=0.6'); the file's defaults "
            "for the rest; a parameter the file does not declare is refused")
    sample_time: float = setting(0.5, "sample time Ts of the controller and of the discretisation, s",
                                 low=0.0, low_open=True)
    horizon: int = setting(5, "prediction horizon N (samples)", low=1, high=2000)  # an upper limit keeps
    # a typo (horizon: 1e30) from hanging the NLP build; likewise for the other integer capacities
    escape_horizon: int = setting(0, "horizon of the passage mode's second NLP (samples), tried when y_a stalls in "
                                     "front of a region the N-sample plan cannot pass (core/sample/passage.py); "
                                     "0: off, else greater than horizon", low=0, high=2000)
    escape_guesses_per_sample: int = setting(
        0, "local-minimum escape and passage-mode guesses solved per sample (core/sample/candidates.py); the rest "
           "follow on the next samples while y_a stays stalled, so one sample's work stays bounded (a real-time "
           "path's worst sample); 0: all in one sample", runtime=True, low=0, high=1000)
    terminal: str = setting(
        "equality", "terminal condition of the plan: equality (x(N) = x_a, the paper's simplified scheme eq. 19-20) "
                    "or set (the general scheme eq. 7-8: terminal cost V_f and a certified terminal set, computed "
                    "offline and cached; models with a closed-form steady state and one output, or linear ones; "
                    "every solver path; docs/terminal_set.md)", choices=TERMINALS)
    discretization: str = setting("euler", "prediction model discretisation: euler (as in the paper) or rk4",
                                  choices=DISCRETISATIONS)
    integration_steps: int = setting(
        1, "sub-steps of the discretisation per sample (h = Ts / steps); the regions are avoided at every "
           "sub-step state, so also between the samples (docs/design.md, 'Between the samples'); 1 as in the paper",
        low=1, high=100)
    state_min: tuple[float, ...] | None = setting(
        None, "lower bounds of the state box of Z (n values)", high=0.0, finite=False)
    state_max: tuple[float, ...] | None = setting(
        None, "upper bounds of the state box of Z (n values)", low=0.0, finite=False)
    input_min: tuple[float, ...] | None = setting(
        None, "lower bounds of the input box of Z (m values)", high=0.0, finite=False)
    input_max: tuple[float, ...] | None = setting(
        None, "upper bounds of the input box of Z (m values)", low=0.0, finite=False)
    steady_state_scale: float = setting(0.99, "lambda: the artificial steady state (x_a, u_a) lies in lambda * Z",
                                        low=0.0, low_open=True, high=1.0)
    constraints: tuple[str, ...] = setting((), "hard inequalities of Z over state/input/output names, "
                                               "e.g. 'x1 + x2 <= 3'")
    keep_in: tuple[str, ...] = setting(("x1*x2 - 2 <= 0", "-x1*x2 - 2 <= 0"),
                                       "penalised regions to stay in, e.g. 'x1*x2 - 2 <= 0' (penalty mu * max(0, g)^2)")
    keep_in_margin: float = setting(
        0.0, "the keep-in expressions are planned as g + keep_in_margin <= 0, in their own units: a plan accepted "
             "as clear (predicted g up to the penetration tolerance 1e-3, e.g. a budget-cut iterate) then keeps the "
             "real g <= 0 at its states, sub-step states and chords (docs/design.md, 'Between the samples'); "
             "0 as in the paper", low=0.0, high=1.0e3)
    use_closed_form_steady_state: bool = setting(
        True, "use the model's g_x, g_u; false imposes the equilibrium as constraints (eq. 8e-8f)")
    plane: tuple[int, ...] = setting((0, 1), "the two state indices that 'state'-frame obstacle markers map to",
                                     low=0, length=2)
    output_plane: tuple[int, ...] = setting((0, 1), "the two output indices that 'output'-frame obstacle markers "
                                                    "map to", low=0, length=2)
    max_ellipses: int = setting(8, "capacity of ellipse obstacle slots (CYLINDER/SPHERE markers)", low=0, high=256)
    max_polygons: int = setting(4, "capacity of polygon obstacle slots (CUBE/LINE_STRIP markers)", low=0, high=256)
    max_polygon_vertices: int = setting(8, "largest number of vertices of a polygon obstacle", low=3, high=64)
    ellipse_tiers: tuple[int, ...] = setting(
        (), "ellipse capacities of smaller copies of the regular NLP (no polygon slots), built once: a sample whose "
            "regions fit one solves the smallest that does (core/nlp/tiers.py; a structure-exploiting solver pays for "
            "every slot, used or not); each below max_ellipses; empty: off", low=0, high=256)
    solver: str = setting("ipopt", "NLP solver path (simulate --solver list describes them)", choices=SOLVERS)
    codegen: bool = setting(False, "generate the solver's functions as C, compile them (cc) and cache the library "
                                   "by problem hash")
    cache_dir: str = setting("", "folder of compiled solvers and the feedback laws' saved derivatives; empty: "
                                 "$NMPC_AVOID_ROS_CACHE, else ~/.cache/nmpc_avoid_ros")
    codegen_background: bool = setting(
        False, "with codegen, a library missing from the cache (a first start) compiles in a background process while "
               "the same solvers run interpreted (slower solves, but commands from the first sample, not after a "
               "compile of up to minutes); each compiled one is swapped in between samples once ready "
               "(core/nlp/background.py; background.wait_compiled() waits for them). False: the constructor waits for "
               "the compile (offline tools, benchmarks and tests get the compiled solvers from the first solve)")
    state_weights: tuple[float, ...] = setting((1.0, 1.0), "diagonal of Q in the stage cost |x - x_a|_Q^2 "
                                                           "(n values)", runtime=True, low=0.0)
    input_weights: tuple[float, ...] = setting((1.0,), "diagonal of R in the stage cost |u - u_a|_R^2 (m values)",
                                               runtime=True, low=0.0)
    kappa: float = setting(1.0e4, "offset cost weight: V_o = kappa |y_a - y_t|^2", runtime=True, low=0.0)
    output_weights: tuple[float, ...] = setting(
        (), "diagonal of W in the offset cost V_o = kappa |y_a - y_t|_W^2 (p values, each > 0), e.g. how much a "
            "unicycle_pose's goal heading (rad) counts against its position (m); empty: all 1, the paper's "
            "|y_a - y_t|^2. Fixed at construction", low=0.0, low_open=True)
    mu: float = setting(1.0e8, "avoidance weight: V_a = mu (F(x_a) + sum_j F(x(j))); 0 disables avoidance",
                        runtime=True, low=0.0)
    max_iterations: int = setting(200, "solver iteration budget per sample, the fast paths' real-time work budget "
                                       "(a cold start without a plan that no ellipse tier holds is solved by IPOPT "
                                       "with >= 200 iterations and 10x the time budget); a solver option, fixed at "
                                       "construction",
                                  low=1, high=100000)
    max_solve_time: float = setting(2.0, "solver wall-time budget per sample, s (enforced by IPOPT; the fast paths "
                                         "are bounded by max_iterations); a solver option, fixed at construction",
                                    low=0.0, low_open=True)
    command_budget: float = setting(
        0.0, "with `feedback`: a sample its prepared plan does not answer searches at most this long (s) before its "
             "command (then the budget-cut plan if feasible, else the fallback), and the preparation after the command "
             "goes on with the whole max_solve_time for the sample to come; 0: max_solve_time before the command. Not "
             "the first sample (no command in force yet)", runtime=True, low=0.0)
    solve_domain_margin: float = setting(
        1.0, "a state further outside the state box than this many box widths (in any bounded coordinate) gets no "
             "solver call: the NLP's x(1) in the box is out of reach from there, and FATROP may not return on such "
             "states; the sample applies the fallback at once (docs/design.md, 'A hard time bound')",
        runtime=True, low=0.0)
    tolerance: float = setting(1e-8, "solver convergence tolerance; a solver option, fixed at construction",
                               low=0.0, low_open=True)
    acceptable_tolerance: float = setting(
        0.0, "IPOPT and FATROP stop at an acceptable point: a KKT error below this for ACCEPTABLE_ITERATIONS "
             "iterations in a row (their acceptable_tol / tol_acceptable); 0: off. A solver option, fixed at "
             "construction (docs/design.md, 'Acceptable points')", low=0.0)
    input_rate_max: tuple[float, ...] = setting(
        (), "largest change of each input per second (m values, units/s; inf: none), e.g. a robot's acceleration "
            "limits: the plan keeps |u(0) - u_prev| and |u(j) - u(j-1)| within input_rate_max * sample_time, u_prev "
            "the command in force (none yet: the safe input); the fallbacks' inputs follow the limits from it too. "
            "Empty: off. Every solver path (the stage-wise ones carry the limited inputs before each stage's own as "
            "states)", low=0.0,
        low_open=True, finite=False)
    feedback: bool = setting(
        False, "answer a sample from the plan prepared for it: a caller that calls prepare() after each command gets "
               "the next sample's problem solved ahead for the predicted state, and the command from its first-order "
               "feedback law when the state arrives, no solver call (core/sample/feedback.py); the sample searches as "
               "before where the law does not hold. False: every sample searches")
    feedback_qp: bool = setting(False, "with `feedback`: where the law's move is refused, one QP on its "
                                "linearisation answers if it passes the law's checks (core/sample/feedback_qp.py)")
    feasibility_tolerance: float = setting(1e-6, "a budget-cut iterate is applied only if its constraint violation "
                                                 "is below this", runtime=True, low=0.0, low_open=True)
    region_margin: float = setting(
        0.0, "obstacles are planned around inflated by this much, plane units (ellipse semi-axes longer, polygon "
             "edges moved out): room for what the prediction does not see, the motion between samples and the "
             "loop's latency (docs/design.md, 'Clearance margin'); the recorded clearance is the real regions'",
        runtime=True, low=0.0)
    footprint_radius: float = setting(
        0.0, "the robot's body, a disc of this radius (m) about the point the plane tracks (base_link): obstacles "
             "are planned around grown by body_radius, the larger of this and footprint's, on top of region_margin, "
             "so the plan keeps the body clear; analyze reports min_body_distance, the obstacle distance minus it",
        runtime=True, low=0.0)
    footprint: tuple[float, ...] = setting(
        (), "the body as a polygon x1, y1, x2, y2, ... (m, base_link; at least 3 corners), approximated by its "
            "circumscribed disc about base_link (body_radius; exact for a round robot, generous for a long one); "
            "empty: footprint_radius alone", runtime=True)
    input_delay: float = setting(
        0.0, "s from the moment a command reaches the plant to the moment it acts (the actuator's own delay; "
             "the node adds the DDS delivery, transport_delay). Each step predicts the measured state forward, "
             "with the model and the command in force, by the state's age, the node's expected solve-and-publish "
             "time and this, and plans from there (docs/design.md, 'Latency')", runtime=True, low=0.0, high=10.0)
    mismatch_gain: float = setting(
        0.0, "obstacles are planned around inflated, on top of region_margin, by this multiple of the largest "
             "one-step prediction error (plane units) measured over the last mismatch_window samples: room for "
             "what the model gets wrong (1: round obstacles and polygons, 2.5: any ellipse; docs/design.md, "
             "'Mismatch margin'); 0: off", runtime=True, low=0.0, high=100.0)
    mismatch_window: int = setting(20, "samples over which the largest one-step prediction error is taken for "
                                       "mismatch_gain", runtime=True, low=1, high=100000)
    max_mismatch_margin: float = setting(0.5, "largest margin mismatch_gain may add, plane units (a jump of the "
                                              "state, e.g. a plant reset, must not swell the obstacles over the "
                                              "whole plane)", runtime=True, low=0.0)
    predict_obstacles: bool = setting(True, "predict moving obstacles over the horizon (stage k sees c + v (t_k - "
                                            "stamp)); false: each stays where it was last seen", runtime=True)
    max_obstacle_speed: float = setting(3.0, "largest obstacle speed accepted, plane units/s: a faster given velocity "
                                             "is refused, a faster apparent motion between two stamped updates is a "
                                             "jump and resets the estimate", runtime=True, low=0.0, low_open=True)
    max_obstacle_stamp_skew: float = setting(2.0, "a moving obstacle whose header.stamp lies further than this (s) "
                                                  "from its receipt is refused (given velocity) or its estimate reset",
                                             runtime=True, low=0.0, low_open=True)
    certificate_tolerance: float = setting(
        100.0, "stability certificate: a decrease above the bound by more than this x tolerance x max(1, |V_N|) "
               "is a violation (docs/certificate.md)", runtime=True, low=0.0)
    certificate_error_after: int = setting(
        3, "stability certificate: this many violations in a row are an ERROR (one alone is a WARN)",
        runtime=True, low=1, high=1000000)

    def __post_init__(self) -> None:
        normalise(self)
        unset = [name for name in BOUNDS if getattr(self, name) is None]
        if unset:  # Z's box from the model file (the paper's |x1| <= 6, |x2| <= 2, |u| <= 6 for van der Pol)
            declared = model_bounds(self.model, self.model_parameters)
            for name in unset:
                if name not in declared:
                    raise ConfigError(f"{name} is unset and model {self.model} declares no bounds: set it")
                object.__setattr__(self, name, SETTINGS[name].coerce(declared[name]))
        self._check_relations()

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid setting."""
        for spec in SETTINGS.values():
            spec.coerce(getattr(self, spec.name))
        self._check_relations()

    def _check_relations(self) -> None:
        """What one setting's declaration cannot say: relations between values."""
        check_model_name(self.model)
        if self.model_parameters:  # a parameter the model does not declare: refused now, not at the first build
            model_bounds(self.model, self.model_parameters)
        for lo_name, hi_name in (("state_min", "state_max"), ("input_min", "input_max")):
            lo, hi = getattr(self, lo_name), getattr(self, hi_name)
            if len(lo) != len(hi):
                raise ConfigError(f"{lo_name} and {hi_name} must have the same length")
            if any(a == b for a, b in zip(lo, hi)):
                # lambda * Z needs Z to contain the origin (paper section II) and be a real box
                raise ConfigError(f"{lo_name}/{hi_name}: need min <= 0 <= max and min < max, got {lo}, {hi}")
        if self.escape_horizon and self.escape_horizon <= self.horizon:
            raise ConfigError(f"escape_horizon must be 0 (off) or greater than horizon = {self.horizon} "
                              f"(the passage mode plans further than the regular NLP), got {self.escape_horizon}")
        if any(k >= self.max_ellipses for k in self.ellipse_tiers):
            raise ConfigError(f"ellipse_tiers must each be below max_ellipses = {self.max_ellipses} (a tier is a "
                              f"smaller copy of the NLP), got {list(self.ellipse_tiers)}")
        if self.footprint and (len(self.footprint) % 2 or len(self.footprint) < 6):
            raise ConfigError(f"footprint must be empty or x, y pairs of at least 3 corners, got "
                              f"{len(self.footprint)} values")
        for name in ("plane", "output_plane"):
            plane = getattr(self, name)
            if plane[0] == plane[1]:
                raise ConfigError(f"{name} must be two different non-negative indices, got {plane}")

    def build_model(self) -> Model:
        """The model these settings name, with their model_parameters (core/problem/models.py make_model)."""
        return make_model(self.model, parse_model_parameters(self.model_parameters))

    @property
    def body_radius(self) -> float:
        """The body's radius (m): footprint_radius or the footprint polygon's circumscribed radius about base_link,
        the larger; every obstacle is planned around grown by it."""
        corners = zip(self.footprint[0::2], self.footprint[1::2], strict=True)
        return max([self.footprint_radius, *(math.hypot(x, y) for x, y in corners)])

    @property
    def planning_margin(self) -> float:
        """How much every obstacle grows before it reaches the slots (plane units): region_margin + body_radius
        (the mismatch margin, measured at run time, comes on top)."""
        return self.region_margin + self.body_radius

    def replace(self, **changes: Any) -> ControllerSettings:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> ControllerSettings:
        """Settings from the `ros__parameters` mapping of the controller (unknown keys refused)."""
        if not isinstance(params, Mapping):
            raise ConfigError(f"controller parameters must be a mapping, got {type(params).__name__}")
        unknown = sorted(map(str, set(params) - set(SETTINGS) - NODE_ONLY_PARAMETERS))
        if unknown:
            raise ConfigError(f"unknown controller parameter(s): {', '.join(unknown)}")
        return cls(**{k: _yaml_number(SETTINGS[k], v) for k, v in params.items() if k in SETTINGS})

    def structure_key(self) -> tuple:
        """The fields that define the NLP and its solver (equal keys -> the same NLP and solver)."""
        return tuple(getattr(self, name) for name, spec in SETTINGS.items() if not spec.runtime)


#: the settings of Z's box, which a model file's `bounds` provide where a config leaves them out
BOUNDS = ("state_min", "state_max", "input_min", "input_max")


def _yaml_number(spec: Setting, value: Any) -> Any:
    """YAML 1.1 (PyYAML) reads `1.0e4` as a string; ROS reads it as a double: so do we."""
    if spec.kind == "float" and isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value  # refused with the setting's rule by ControllerSettings
    return value


#: how the controller node commands while the state is stale or missing
STALE_BEHAVIORS = ("hold_steady", "zero", "safe_input", "last")
#: how the controller node talks to the plant (nodes/controller_io.py)
INTERFACES = ("array", "robot")


@dataclass(frozen=True)
class NodeSettings:
    """The controller node's own parameters: not part of the NLP (nodes/controller.py applies them).

    Declared like ControllerSettings (core/config/schema.py); the node checks the sizes of target and
    safe_input against the model, which these declarations do not know.
    """

    target: tuple[float, ...] | None = setting(
        None, "initial target y_t (p values); later targets arrive on 'target' or by param set", runtime=True)
    state_timeout: float = setting(1.5, "a state older than this (s, node clock) is stale: no solve, safe "
                                        "behaviour", runtime=True, low=0.0, high=3600.0)
    stale_behavior: str = setting("hold_steady", "command while the state is stale or missing", runtime=True,
                                  choices=STALE_BEHAVIORS)
    safe_input: tuple[float, ...] | None = setting(None, "the model's safe command (m values within the input "
                                                         "box; default zeros): stale_behavior safe_input, and a "
                                                         "fallback candidate", runtime=True)
    lockstep: bool = setting(False, "solve once per arriving state instead of on the timer (with a lockstep "
                                    "plant)")
    log_throttle: float = setting(2.0, "minimum seconds between repeated warnings of one kind", runtime=True,
                                  low=0.0, high=3600.0)
    autostart: bool = setting(True, "walk the lifecycle to active at start-up (false: wait for a lifecycle "
                                    "manager's configure and activate)")
    interface: str = setting("array", "plant interface: array (Float64MultiArray on state/command) or robot "
                                      "(Odometry on odom, TwistStamped/Twist on cmd_vel, PoseStamped on goal_pose)",
                             choices=INTERFACES)
    cmd_vel_stamped: bool = setting(True, "robot interface: command geometry_msgs/TwistStamped (as Jazzy's "
                                          "diff_drive_controller expects) instead of Twist")
    odom_frame: str = setting("odom", "robot interface: the frame of odometry poses and goals (REP 105); obstacle "
                                      "markers in it are positions; everything drawn is in it")
    base_frame: str = setting("base_link", "robot interface: child_frame_id of the odometry and frame of cmd_vel")
    latency_compensation: bool = setting(
        True, "real time: plan from the state predicted to the moment the command acts (its age, the expected "
              "solve-and-publish time measured over the last samples, input_delay; docs/design.md, 'Latency'); "
              "false: from the measured state (lockstep never predicts: its plant waits for the command)",
        runtime=True)
    command_latency: float = setting(
        0.0, "latency compensation: the command is published this long (s) after the sample starts, held back "
             "until then, and the plan starts from the state predicted for that instant: the timing the prediction "
             "assumes is then the timing the plant gets, however long the solve took below it (a longer solve "
             "publishes at once: late_commands). 0: publish at once, predicting the median solve-and-publish "
             "time of the last samples", runtime=True, low=0.0, high=10.0)
    transport_delay: float = setting(
        0.0, "latency compensation: s the command takes from its publication to the plant (the DDS delivery; "
             "on loopback ~0.5 ms): added to the delay the plan predicts over. The plant's own actuator delay is "
             "input_delay, a controller setting that offline loops use too", runtime=True, low=0.0, high=1.0)
    deactivate_command: str = setting("zero", "the one command published when an active controller is "
                                              "deactivated or shut down", runtime=True, choices=STALE_BEHAVIORS)
    goal_tolerance: float = setting(
        0.0, "goal reached: the output within this distance of the target (output units; m for a robot) at rest "
             "(goal_rest_speed): the command is zero and ~/goal_reached (std_msgs/Bool, transient local) true until "
             "the output leaves it by goal_hysteresis more or a new target arrives (nodes/controller_goal.py); 0: off",
        runtime=True, low=0.0)
    goal_hysteresis: float = setting(0.1, "a reached goal resumes control when the output is further than "
                                          "goal_tolerance + this from it (output units)", runtime=True, low=0.0)
    goal_rest_speed: float = setting(
        0.02, "goal reached only at rest: every rate of the state under the zero command, |f(x, 0)|, at most this "
              "(state units per s; a unicycle always is at rest, a double integrator below this speed)",
        runtime=True, low=0.0)

    def __post_init__(self) -> None:
        normalise(self)

    def replace(self, **changes: Any) -> NodeSettings:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


#: the declarations of every controller setting and of the controller node's own parameters
SETTINGS = schema(ControllerSettings)
NODE_SETTINGS = schema(NodeSettings)

#: fields that are NLP parameters (or checks of the result), changeable without a rebuild
RUNTIME_FIELDS = frozenset(name for name, spec in SETTINGS.items() if spec.runtime)

#: controller-node parameters that are not core settings (use_sim_time: declared by rclpy itself)
NODE_ONLY_PARAMETERS = frozenset(NODE_SETTINGS) | {"use_sim_time"}

#: one-line documentation of every controller setting
SETTING_DOCS: dict[str, str] = {name: spec.description for name, spec in SETTINGS.items()}
