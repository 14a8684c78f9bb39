"""The initial guess of a sample's regular solve: the budget-cut iterate, the shifted plan, or a straight line
(for a forward-only model at rest with its target behind it: the model's turn, `turn_start`).

Kept apart from the controller (core/sample/controller.py) because it is pure bookkeeping on the NLP's
layout: no solver is called here.
"""

from __future__ import annotations

import numpy as np

from ..config.settings import ControllerSettings
from ..nlp.terminal import ShiftedTail
from ..nlp.tracking import NlpBase
from ..problem.models import Model
from .step_result import Plan, shifted_rows


def initial_guess(nlp: NlpBase, x: np.ndarray, y_t: np.ndarray, plan: Plan | None,
                  pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None, settings: ControllerSettings,
                  model: Model, keep_duals: bool = True, tail: ShiftedTail | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(w [n_w], lam_x [n_w], lam_g [n_g]) of `nlp` for the state x [n] and target y_t [p].

    - `pending`, the last iterate of a budget-cut solve that could not be applied (w, lam_x, lam_g):
      shifted by one sample, so that the optimisation goes on where the budget stopped it (its last stage: u_a, x_a,
      or with `terminal: set` the local controller's kappa(x(N), y_a) and the state it leads to, from `tail`);
    - else the shifted `plan` (u(1..N-1), u_a; x(2..N), x_a; with `terminal: set` its continuation by kappa in
      place of u_a, x_a: Plan.tail), its multipliers shifted with it when
      `keep_duals` (the plan was made by `nlp`; another NLP's multipliers do not fit: zeros);
    - else a straight line from x to the steady state of y_t, clipped into the bounds.

    A forward-only model's turn towards y_t (Model.turn_guess, `turn_start`) replaces the straight line, and
    a resting plan where y_t lies behind it.
    """
    layout = nlp.layout
    N = layout.horizon
    if pending is None and (plan is None or plan_rests(plan)):
        turn = turn_start(nlp, x, y_t, settings, model, behind_only=plan is not None)
        if turn is not None:
            return turn
    if pending is not None:
        w, lam_x, lam_g = pending
        U, X, y_a, rest = layout.split_w(w)
        x_a, u_a = (v.copy() for v in nlp.steady(w))
        continued = None if tail is None else tail.rollout(X[-1], y_a, x_a, u_a, 1, settings.input_min,
                                                           settings.input_max)
        U, X = (shifted_rows(U, u_a, 1), shifted_rows(X, x_a, 1)) if continued is None else (
            np.vstack([U[1:], continued[0]]), np.vstack([X[1:], continued[1]]))
        lam_x, lam_g = nlp.shift_duals(lam_x, lam_g, 1)
        return layout.join_w(U, X, y_a, rest, x0=x), lam_x, lam_g
    if plan is None:
        y_a, X, U = straight_line(x, y_t, N, settings, model)
        rest = None if layout.closed_form else np.concatenate([X[-1], U[-1]])
        return layout.join_w(U, X, y_a, rest, x0=x), np.zeros(layout.n_w), np.zeros(nlp.lbg.size)
    shift = plan.age + 1
    U, states = plan.shifted(shift)
    X = states[1:]  # x(0) is the measurement x
    rest = None if layout.closed_form else np.concatenate([plan.x_a, plan.u_a])
    w0 = layout.join_w(U, X, plan.y_a, rest, x0=x)
    if not keep_duals:
        return w0, np.zeros(layout.n_w), np.zeros(nlp.lbg.size)
    lam_x, lam_g = nlp.shift_duals(plan.lam_x, plan.lam_g, shift)
    return w0, lam_x, lam_g


#: a plan whose remaining inputs and states are this close to its steady state (inf-norm) rests
REST_TOLERANCE = 1e-3


def plan_rests(plan: Plan) -> bool:
    """Whether the plan's shifted rest (inputs u(age+1..), states x(age+2..)) is its steady state (x_a, u_a)."""
    inputs, states = plan.shifted(plan.age + 1)  # padded with (u_a, x_a) themselves: no other answer
    return bool(np.all(np.abs(inputs - plan.u_a) <= REST_TOLERANCE) and
                np.all(np.abs(states[1:] - plan.x_a) <= REST_TOLERANCE))


def turn_start(nlp: NlpBase, x: np.ndarray, y_t: np.ndarray, settings: ControllerSettings, model: Model,
               behind_only: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The model's turn towards y_t [p] from x [n] as (w, zero multipliers), or None where it has none
    (with `behind_only`, also where y_t is not behind it).

    A unicycle that may not reverse (v >= 0) and rests with its target behind it is at a local minimum:
    at v = 0 turning does not move its output and driving ahead moves it away, so a solver started from
    rest (or the straight line, which runs backwards) stays there (measured: the goal 3 m straight behind,
    v = omega = 0 for ever). Started from the turn it turns, then drives. Without a plan (a cold start) the
    turn replaces the straight line for a target ahead too: the straight line runs sideways, which such a
    model cannot, and IPOPT stopped on it (Error_In_Step_Computation on the two-ellipse scene with v >= 0)."""
    if model.turn_guess is None:
        return None
    layout = nlp.layout
    turn = model.turn_guess(x, y_t, layout.horizon, settings.sample_time, np.asarray(settings.input_min, float),
                            np.asarray(settings.input_max, float), behind_only)
    if turn is None:
        return None
    states, inputs = turn
    x_a, u_a = steady_of(model, np.asarray(model.output(states[-1], np.zeros(model.m))).ravel(), states[-1])
    y_a = np.asarray(model.output(x_a, u_a)).ravel()
    rest = None if layout.closed_form else np.concatenate([x_a, u_a])
    return layout.join_w(inputs, states, y_a, rest, x0=x), np.zeros(layout.n_w), np.zeros(nlp.lbg.size)


def straight_line(x: np.ndarray, y_t: np.ndarray, horizon: int, settings: ControllerSettings, model: Model
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plan that runs straight from x [n] to y_t's steady state (clipped into the bounds) and holds
    its input: (y_a = y_t [p], x(1..N) [N, n] ending at x_a, u(0..N-1) [N, m] all u_a)."""
    y_a = np.asarray(y_t, float).copy()
    x_a, u_a = steady_of(model, y_a, x)
    x_a = np.clip(x_a, settings.state_min, settings.state_max)
    u_a = np.clip(u_a, settings.input_min, settings.input_max)
    ramp = np.linspace(0, 1, horizon + 1)[1:, None]
    return y_a, (1 - ramp) * x + ramp * x_a, np.tile(u_a, (horizon, 1))


def steady_of(model: Model, y: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A steady state (x_s [n], u_s [m]) of output y: closed form, else the model's guess near x, else zeros."""
    if model.steady_state is not None:
        x_s, u_s = model.steady_state(y)
        return np.asarray(x_s, float).ravel(), np.asarray(u_s, float).ravel()
    if model.steady_guess is not None:
        return model.steady_guess(np.asarray(y, float), np.asarray(x, float))
    return np.zeros(model.n), np.zeros(model.m)
