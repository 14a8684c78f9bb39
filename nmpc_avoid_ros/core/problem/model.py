"""The model type: continuous dynamics, output map, discretisation and steady-state maps.

A model is a set of CasADi functions over named states, inputs and outputs (declared in a model file,
core/problem/model_files.py; the registry of names is core/problem/models.py). The NMPC predicts
with a discretisation of the continuous dynamics (explicit Euler as in the paper, or RK4); the
plant simulator integrates the continuous dynamics accurately under zero-order hold.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import ConfigError

DISCRETISATIONS = ("euler", "rk4")


@dataclass(frozen=True)
class PlanarMap:
    """How a planar robot's model meets the standard messages (ros/robot.py, the plant's views).

    x, y: state indices of the position (m); yaw: the heading's state index (rad), or None for a model that
    heads where it moves, with `velocity` the indices of its velocity states. command: CasADi Function
    (x[n], u[m]) -> [linear (m/s), angular (rad/s)], the velocity command (Twist) an input gives; from_command:
    (x[n], [linear, angular]) -> u[m], the input a received command means (the plant simulator). Both None:
    the model has a pose for the views but no velocity-command interface."""

    x: int
    y: int
    yaw: int | None
    velocity: tuple[int, int] | None = None
    command: ca.Function | None = None
    from_command: ca.Function | None = None


@dataclass(frozen=True)
class Model:
    """A continuous-time model x' = f(x, u), y = h(x, u).

    Attributes:
        name: registry name.
        state_names, input_names, output_names: symbol names (n, m, p of them); algebraic
            region expressions refer to these.
        dynamics: CasADi Function (x[n], u[m]) -> x'[n], units of the state per second.
        output: CasADi Function (x[n], u[m]) -> y[p].
        steady_state: optional closed-form maps y_s[p] -> (x_s[n], u_s[m]) (the paper's g_x, g_u)
            written with CasADi operations so they work on symbols; None means the equilibrium is
            imposed as constraints (paper eq. 8e-8f).
        default_plane: the two state indices that obstacle markers in the `state` frame map to.
        steady_guess: optional numeric (y_s[p], x[n]) -> (x_s[n], u_s[m]), a steady state near the
            measured x for the first initial guess of a model without closed-form maps.
        turn_guess: optional numeric (x[n], y_t[p], horizon, sample_time, input_min[m], input_max[m],
            behind_only) -> (x(1..N) [N, n], u(0..N-1) [N, m]) or None: for a model that moves only along its
            heading and cannot reverse (input bounds), a plan that turns on the spot towards the target, then
            drives; None where it does not apply (reversing allowed, the target near or, `behind_only`, ahead).
            The initial guess of a cold start, and of a start at rest with the target behind
            (core/sample/warm_start.py): from rest no small change of the plan approaches a target behind
            such a model (turning alone does not move its output), so the solver would stay put.
        rest: optional CasADi Function (x[n], u[m]) -> r[k] whose zeros are exactly the equilibria f(x, u) = 0 and
            whose Jacobian has full row rank there; None: the dynamics themselves are (see `equilibrium`).
        angle_outputs: (output index, state index) of each output that is an angle (rad) equal to an unwrapped
            state: a target's angle is taken modulo 2 pi (`nearest_target`, `output_error`).
        planar: how a planar robot's pose and velocity command map to the model (PlanarMap), or None.
        units: "state" / "output" -> one unit name per entry (m, rad, m/s), where the model file says.
        bounds: the model file's Z: state_min/state_max/input_min/input_max, the defaults of a config's bounds.
        parameters: the constants the model was built with (name -> value).
        source: the model file it was read from ("" for a model built in Python).
        discrete_map: a discrete-time model's own map (x[n], u[m]) -> x(k+1)[n] over `map_sample_time` s, or
            None (continuous time). Its `dynamics` are then (F(x, u) - x) / Ts, zero exactly at its equilibria;
            it has no state between its samples: it predicts with integration_steps 1 at its own sample time,
            latency prediction draws the straight line between two samples, and only its map simulates it.
    """

    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    dynamics: ca.Function
    output: ca.Function
    steady_state: Callable[[ca.MX | ca.SX], tuple[ca.MX | ca.SX, ca.MX | ca.SX]] | None = None
    default_plane: tuple[int, int] = (0, 1)
    steady_guess: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    turn_guess: Callable[..., tuple[np.ndarray, np.ndarray] | None] | None = None
    rest: ca.Function | None = None
    angle_outputs: tuple[tuple[int, int], ...] = ()
    planar: PlanarMap | None = None
    units: dict[str, tuple[str, ...]] = field(default_factory=dict, compare=False)
    bounds: dict[str, tuple[float, ...]] = field(default_factory=dict, compare=False)
    parameters: dict[str, float] = field(default_factory=dict, compare=False)
    source: str = ""
    description: str = ""
    discrete_map: ca.Function | None = None
    map_sample_time: float | None = None

    def nearest_target(self, y_t: np.ndarray, x: np.ndarray) -> np.ndarray:
        """y_t [p] with each angle output moved by whole turns to within pi of its state in x [n] (the turn the
        robot makes is the short one; the target stays put until the state crosses the opposite angle)."""
        if not self.angle_outputs:
            return y_t
        y_t = np.array(y_t, float)
        for i, j in self.angle_outputs:
            y_t[i] += 2 * math.pi * round((x[j] - y_t[i]) / (2 * math.pi))
        return y_t

    def output_error(self, y: np.ndarray, y_t: np.ndarray) -> np.ndarray:
        """y - y_t [p], angle outputs wrapped to [-pi, pi]."""
        error = np.asarray(y, float) - np.asarray(y_t, float)
        for i, _ in self.angle_outputs:
            error[i] = math.remainder(error[i], 2 * math.pi)
        return error

    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return len(self.input_names)

    @property
    def p(self) -> int:
        return len(self.output_names)

    def equilibrium(self, x: ca.SX | ca.MX, u: ca.SX | ca.MX) -> ca.SX | ca.MX:
        """Rows r(x, u) = 0 that impose the equilibrium f(x, u) = 0 without a closed form (the NLP's (x_a, u_a),
        paper eq. 8e; the target projection): the model's `rest` where it has one, else f itself.

        Where f = 0 is degenerate, a solver needs `rest`: the unicycle's f = (v cos theta, v sin theta, omega)
        vanishes at v = omega = 0, but its first two rows have the same gradient direction there (theta enters
        multiplied by v), so the equality Jacobian loses rank at every equilibrium and IPOPT's step computation
        fails near them (measured, config/unicycle.yaml on the continuous plant: 27 % of the samples unconverged,
        138 of 800 with Error_In_Step_Computation; with `rest` = (v, omega): every sample Solve_Succeeded)."""
        return (self.rest or self.dynamics)(x, u)

    def discrete(self, sample_time: float, method: str = "euler", steps: int = 1) -> ca.Function:
        """Discrete map (x[n], u[m]) -> x(k+1)[n] over one sample of `sample_time` s, in `steps`
        sub-steps of `method` (h = sample_time / steps)."""
        x, u = ca.SX.sym("x", self.n), ca.SX.sym("u", self.m)
        path = self.discrete_path(sample_time, method, steps)(x, u)
        return ca.Function(f"{self.name}_{method}", [x, u], [path[:, -1]], ["x", "u"], ["x_next"])

    def discrete_path(self, sample_time: float, method: str = "euler", steps: int = 1) -> ca.Function:
        """(x[n], u[m]) -> the sub-step states [n, steps] at times j h, j = 1..steps (h = sample_time /
        steps, input held): the last column is x(k+1); the others are where the prediction says the
        plant passes between two samples (the regions are avoided there too, core/nlp/tracking.py)."""
        if method not in DISCRETISATIONS:
            raise ConfigError(f"discretization must be one of {DISCRETISATIONS}, got {method!r}")
        if not (np.isfinite(sample_time) and sample_time > 0):
            raise ConfigError(f"sample_time must be a positive number of seconds, got {sample_time}")
        if int(steps) != steps or steps < 1:
            raise ConfigError(f"integration_steps must be a whole number >= 1, got {steps}")
        x = ca.SX.sym("x", self.n)
        u = ca.SX.sym("u", self.m)
        if self.discrete_map is not None:
            self._check_map(sample_time, steps)
            return ca.Function(f"{self.name}_map_path", [x, u], [self.discrete_map(x, u)], ["x", "u"], ["points"])
        points = _sub_steps(self.dynamics, x, u, sample_time / int(steps), int(steps), method)
        return ca.Function(f"{self.name}_{method}_path", [x, u], [ca.horzcat(*points)], ["x", "u"], ["points"])

    def flow(self, method: str = "rk4", steps: int = 4) -> ca.Function:
        """(x[n], u[m], dt) -> x(dt)[n]: the state dt s later under the input held, in `steps` sub-steps of
        `method` (h = dt / steps). Predicts a measured state over the loop's latency and the state a plan
        expected at a measurement's own time (core/sample/latency.py); at dt = Ts it equals `discrete`."""
        if method not in DISCRETISATIONS:
            raise ConfigError(f"discretization must be one of {DISCRETISATIONS}, got {method!r}")
        x, u, dt = ca.SX.sym("x", self.n), ca.SX.sym("u", self.m), ca.SX.sym("dt")
        if self.discrete_map is not None:  # no state between the samples: the straight line, exact at 0 and Ts
            line = x + dt / self.map_sample_time * (self.discrete_map(x, u) - x)
            return ca.Function(f"{self.name}_map_flow", [x, u, dt], [line], ["x", "u", "dt"], ["x_dt"])
        state = _sub_steps(self.dynamics, x, u, dt / int(steps), int(steps), method)[-1]
        return ca.Function(f"{self.name}_{method}_flow", [x, u, dt], [state], ["x", "u", "dt"], ["x_dt"])

    def _check_map(self, sample_time: float, steps: int) -> None:
        if not math.isclose(sample_time, self.map_sample_time, rel_tol=1e-12):
            raise ConfigError(f"model {self.name} is a discrete map over {self.map_sample_time} s: sample_time must be "
                              f"that, got {sample_time}")
        if steps != 1:
            raise ConfigError(f"model {self.name} is a discrete map: it has no states between its samples "
                              f"(integration_steps must be 1, got {steps})")

    def symbol_table(self, x: ca.SX | ca.MX, u: ca.SX | ca.MX) -> dict[str, ca.SX | ca.MX]:
        """Names -> symbolic entries of x, u and y = h(x, u), for algebraic region expressions."""
        y = self.output(x, u)
        table: dict[str, ca.SX | ca.MX] = {}
        for names, vec in ((self.state_names, x), (self.input_names, u), (self.output_names, y)):
            for i, name in enumerate(names):
                table[name] = vec[i]
        return table


def _sub_steps(f: ca.Function, x: ca.SX, u: ca.SX, h: ca.SX | float, steps: int, method: str) -> list[ca.SX]:
    """The states after each of `steps` sub-steps of length h of `method` (euler or rk4) from x, u held."""
    points, state = [], x
    for _ in range(steps):
        if method == "euler":
            state = state + h * f(state, u)
        else:
            k1 = f(state, u)
            k2 = f(state + h / 2 * k1, u)
            k3 = f(state + h / 2 * k2, u)
            k4 = f(state + h * k3, u)
            state = state + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        points.append(state)
    return points


#: m: a target nearer than this is not turned towards (parked a little past a goal, the robot stays put)
TURN_GUESS_DISTANCE = 0.05


def unicycle_turn_guess(x: np.ndarray, y_t: np.ndarray, horizon: int, sample_time: float, input_min: np.ndarray,
                        input_max: np.ndarray, behind_only: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """A forward-only unicycle's plan to a target behind it: turn on the spot towards y_t (to the left when
    exactly behind, as fast as omega's bounds allow), then drive straight at up to v's bound and stop there
    (Model.turn_guess). None when it can reverse (v's lower bound < 0), the target is nearer than
    TURN_GUESS_DISTANCE or, with `behind_only`, within 90 degrees of the heading (driving ahead approaches it)."""
    x, y_t = np.asarray(x, float), np.asarray(y_t, float)
    v_max, (w_lo, w_hi) = float(input_max[0]), (float(input_min[1]), float(input_max[1]))
    if input_min[0] < 0 or v_max <= 0:
        return None
    offset = y_t[:2] - x[:2]
    distance = float(np.hypot(*offset))
    turn = math.remainder(math.atan2(offset[1], offset[0]) - x[2], 2 * math.pi)  # (-pi, pi]
    if distance < TURN_GUESS_DISTANCE or (behind_only and abs(turn) <= math.pi / 2):
        return None
    rate = w_hi if turn >= 0 else -w_lo  # the fastest turn that way
    if rate <= 0 and abs(turn) > 1e-9:
        return None
    px, py, theta = x[:3]
    heading = theta + turn
    states, inputs = np.empty((horizon, 3)), np.zeros((horizon, 2))
    for k in range(horizon):
        left = heading - theta
        if abs(left) > 1e-9:  # turning on the spot
            omega = math.copysign(min(rate, abs(left) / sample_time), left)
            inputs[k, 1] = omega
            theta += omega * sample_time
        else:
            remaining = math.hypot(y_t[0] - px, y_t[1] - py)
            v = min(v_max, remaining / sample_time)
            inputs[k, 0] = v
            px, py = px + v * sample_time * math.cos(theta), py + v * sample_time * math.sin(theta)
        states[k] = px, py, theta
    return states, inputs
