"""The terminal part of the tracking NLP: the equality x(N) = x_a (eq. 20h) or the general scheme's terminal
cost and set (eq. 7-8g), per the setting `terminal`.

With `terminal: set` the ingredients (core/problem/terminal.py) are computed once per model, Z, lambda, Ts,
discretisation and stage weights, and cached on disk beside the compiled solvers (core/nlp/codegen.py
`cache_dir`, sub-folder `terminal/`, one JSON file per key) and in this process. P(y_a) and alpha(y_a) enter
the NLP as CasADi expressions of the decision variable y_a, so a new target or new regions change nothing.

The terminal cost is computed for the settings' state_weights and input_weights: changing those at run time
keeps the same V_f and alpha, which are then no longer certified for the new stage cost (the stability
certificate would show it); a new controller recomputes them.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
from pathlib import Path

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..errors import ConfigError
from ..problem.model import Model
from ..problem.terminal import (
    FIT_DEGREE,
    MARGIN,
    TerminalIngredients,
    TerminalProblem,
    compute_terminal_ingredients,
    local_controller,
)
from .codegen import cache_dir
from .gauss_newton import upper_cholesky

#: bump when the computation changes: old cache files are then not read
CACHE_VERSION = "terminal-4"

log = logging.getLogger(__name__)


def terminal_problem(settings: ControllerSettings, model: Model) -> TerminalProblem:
    """The computation's inputs for these settings (the prediction map the NLP uses); `check_covered` first."""
    check_covered(settings)
    step = model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)
    return TerminalProblem(model, step, settings.state_weights, settings.input_weights, settings.state_min,
                           settings.state_max, settings.input_min, settings.input_max, settings.steady_state_scale)


def check_covered(settings: ControllerSettings) -> None:
    """ConfigError for what the set's certificate does not cover: hard `constraints` of Z (only its boxes are
    checked) and input_rate_max (kappa's input may change faster than the limit: the shifted candidate would not
    be feasible)."""
    if settings.constraints:
        raise ConfigError("terminal: set certifies the terminal set inside Z's boxes only; the hard constraints "
                          f"{list(settings.constraints)} are not covered: use terminal: equality")
    if settings.input_rate_max:
        raise ConfigError("terminal: set does not cover input_rate_max (the local controller's input may change "
                          "faster than the limit): use terminal: equality or no input_rate_max")


def cache_key(settings: ControllerSettings, model: Model) -> str:
    """SHA-256 (16 hex) of what the ingredients depend on: the prediction map, Z, lambda, Q, R and the method."""
    step = model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)
    x_s = ca.SX.sym("y", model.p)
    steady = ca.Function("g", [x_s], list(model.steady_state(x_s))) if model.steady_state else None
    digest = hashlib.sha256()
    parts = (CACHE_VERSION, ca.__version__, step.serialize(), steady.serialize() if steady else "",
             repr([settings.state_min, settings.state_max, settings.input_min, settings.input_max,
                   settings.steady_state_scale, settings.state_weights, settings.input_weights, MARGIN, FIT_DEGREE]))
    for part in parts:
        digest.update(part.encode())
    return digest.hexdigest()[:16]


def terminal_ingredients(settings: ControllerSettings, model: Model) -> TerminalIngredients:
    """The cached ingredients for these settings: this process's copy, else the disk cache's, else computed
    (and written there). ConfigError where they cannot be computed (core/problem/terminal.py says why)."""
    check_covered(settings)
    key = cache_key(settings, model)
    path = cache_dir(settings.cache_dir) / "terminal" / f"{key}.json"
    if path in _IN_PROCESS:
        return _IN_PROCESS[path]
    try:
        ingredients = TerminalIngredients.from_dict(json.loads(path.read_text()))
        ingredients.cache = "hit"
    except (OSError, ValueError, TypeError):
        ingredients = _compute_and_store(settings, model, path)
    _IN_PROCESS[path] = ingredients
    return ingredients


#: cache file -> ingredients read or computed in this process
_IN_PROCESS: dict[Path, TerminalIngredients] = {}


def _compute_and_store(settings: ControllerSettings, model: Model, path: Path) -> TerminalIngredients:
    ingredients = compute_terminal_ingredients(terminal_problem(settings, model))
    log.info("terminal set of %s computed in %.1f s, cached in %s", model.name, ingredients.seconds, path)
    try:  # written whole or not at all: a concurrent reader never sees half a file
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=path.parent, delete=False, suffix=".tmp") as tmp:
            json.dump(ingredients.to_dict(), tmp)
        os.replace(tmp.name, path)
    except OSError as exc:  # a read-only cache costs the recomputation next time, nothing else
        log.warning("terminal set not cached (%s)", exc)
    return ingredients


def terminal_constraint(settings: ControllerSettings, model: Model, x_n: ca.SX, x_a: ca.SX, y_a: ca.SX,
                        u_a: ca.SX) -> tuple[ca.SX | None, ca.SX, list[float], list[float]]:
    """(terminal cost or None, rows g, lbg, ubg) of the terminal condition on x(N) [n] given x_a [n], y_a [p], u_a [m].

    equality: x(N) - x_a = 0 (no cost). set: V_f = e' P(y_a) e with e = x(N) - x_a, and per level of alpha(y_a)
    (TerminalIngredients.levels, whose minimum alpha is) the row V_f / level - 1 <= 0 (scaled: alpha spans orders
    of magnitude over y_a)."""
    if settings.terminal == "equality":
        n = model.n
        return None, x_n - x_a, [0.0] * n, [0.0] * n
    ingredients = terminal_ingredients(settings, model)
    e = x_n - x_a
    v_f = ca.dot(e, ca.mtimes(ingredients.symbolic(y_a), e))
    levels = ingredients.levels(y_a, ca.vertcat(x_a, u_a))
    return v_f, ca.vertcat(*[v_f / level - 1 for level in levels]), [-np.inf] * len(levels), [0.0] * len(levels)


def terminal_residual(settings: ControllerSettings, model: Model, x_n: ca.SX, x_a: ca.SX, y_a: ca.SX, u_a: ca.SX
                      ) -> tuple[ca.SX, list[ca.SX]]:
    """The terminal cost and set rows as least squares, for the SQP paths' Gauss-Newton Hessian
    (core/nlp/gauss_newton.py): r = R(y_a) (x(N) - x_a) [n] with R'R = P(y_a) (the upper Cholesky factor of the
    fitted P), so |r|^2 = V_f; and per row of `terminal_constraint` (V_f / level - 1) r / sqrt(level)."""
    ingredients = terminal_ingredients(settings, model)
    r = ca.mtimes(upper_cholesky(ingredients.symbolic(y_a)), x_n - x_a)
    return r, [r / ca.sqrt(level) for level in ingredients.levels(y_a, ca.vertcat(x_a, u_a))]


class ShiftedTail:
    """The last input and state of the shifted candidate (the paper's Lemma 1; core/loop/certificate.py): with the
    equality (u_a, x_a); with the terminal set the local controller's u = kappa(x(N), y_a) and f(x(N), u)."""

    def __init__(self, settings: ControllerSettings, model: Model) -> None:
        self.with_set = settings.terminal == "set"
        if self.with_set:
            self.problem = terminal_problem(settings, model)
            self.ingredients = terminal_ingredients(settings, model)
            self.step = model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)

    def __call__(self, x_n: np.ndarray, y_a: np.ndarray, x_a: np.ndarray, u_a: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(u [m], x [n]) that extend a plan ending in x(N) [n] with steady state (y_a [p], x_a [n], u_a [m])."""
        if not self.with_set:
            return np.asarray(u_a, float), np.asarray(x_a, float)
        u = local_controller(self.problem, self.ingredients, x_n, np.ravel(y_a))
        return u, np.asarray(self.step(x_n, u), float).ravel()

    def rollout(self, x_n: np.ndarray, y_a: np.ndarray, x_a: np.ndarray, u_a: np.ndarray, steps: int,
                input_min: np.ndarray, input_max: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The set scheme's continuation of a plan after x(N) [n]: `steps` inputs of the local controller
        u = u_a + K(y_a)(x - x_a) clipped into [input_min, input_max] [steps, m] and the states they lead to
        x(N+1..N+steps) [steps, n]; None with the equality (a plan rests at (u_a, x_a) after its end) or where the
        continuation is not finite (a plan far outside the set)."""
        if not self.with_set:
            return None
        y = np.ravel(y_a)
        gain = self.problem.gain(y, self.ingredients.cost_matrix(y), self.ingredients.margin)
        x_a, u_a = np.ravel(x_a), np.ravel(u_a)
        x = np.asarray(x_n, float).ravel()
        inputs, states = [], []
        for _ in range(steps):
            u = np.clip(u_a + gain @ (x - x_a), input_min, input_max)
            x = np.asarray(self.step(x, u), float).ravel()
            inputs.append(u)
            states.append(x)
        inputs, states = np.array(inputs), np.array(states)
        return (inputs, states) if np.all(np.isfinite(states)) else None

    def values(self, x_n: np.ndarray, y_a: np.ndarray, x_a: np.ndarray, u_a: np.ndarray) -> tuple[float, float]:
        """(V_f(x(N) - x_a, y_a), alpha(y_a)) of a plan ending in x(N) [n]; (nan, nan) with the equality."""
        if not self.with_set or not np.all(np.isfinite(y_a)):
            return math.nan, math.nan
        e = np.asarray(x_n, float).ravel() - np.ravel(x_a)
        level = self.ingredients.alpha(y_a, np.concatenate([np.ravel(x_a), np.ravel(u_a)]))
        return float(e @ self.ingredients.cost_matrix(y_a) @ e), level
