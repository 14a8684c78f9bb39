"""The initial guess of a sample's regular solve: the budget-cut iterate, the shifted plan, or a straight line.

Kept apart from the controller (core/sample/controller.py) because it is pure bookkeeping on the NLP's
layout: no solver is called here.
"""

from __future__ import annotations

import numpy as np

from ..config.settings import ControllerSettings
from ..nlp.tracking import NlpBase
from ..problem.models import Model
from .step_result import Plan


def initial_guess(nlp: NlpBase, x: np.ndarray, y_t: np.ndarray, plan: Plan | None,
                  pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None, settings: ControllerSettings,
                  model: Model, keep_duals: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(w [n_w], lam_x [n_w], lam_g [n_g]) of `nlp` for the state x [n] and target y_t [p].

    - `pending`, the last iterate of a budget-cut solve that could not be applied (w, lam_x, lam_g):
      shifted by one sample, so that the optimisation goes on where the budget stopped it;
    - else the shifted `plan` (u(1..N-1), u_a; x(2..N), x_a), its multipliers shifted with it when
      `keep_duals` (the plan was made by `nlp`; another NLP's multipliers do not fit: zeros);
    - else a straight line from x to the steady state of y_t, clipped into the bounds.
    """
    layout = nlp.layout
    N = layout.horizon
    if pending is not None:
        w, lam_x, lam_g = pending
        U, X, y_a, rest = layout.split_w(w)
        x_a, u_a = (v.copy() for v in nlp.steady(w))
        U = np.vstack([U[1:], u_a])
        X = np.vstack([X[1:], x_a])
        lam_x, lam_g = nlp.shift_duals(lam_x, lam_g, 1)
        return layout.join_w(U, X, y_a, rest, x0=x), lam_x, lam_g
    if plan is None:
        y_a, X, U = straight_line(x, y_t, N, settings, model)
        rest = None if layout.closed_form else np.concatenate([X[-1], U[-1]])
        return layout.join_w(U, X, y_a, rest, x0=x), np.zeros(layout.n_w), np.zeros(nlp.lbg.size)
    shift = plan.age + 1
    U = np.vstack([plan.inputs[shift:], np.tile(plan.u_a, (min(shift, N), 1))])
    X = np.vstack([plan.states[1 + shift:], np.tile(plan.x_a, (min(shift, N), 1))])
    rest = None if layout.closed_form else np.concatenate([plan.x_a, plan.u_a])
    w0 = layout.join_w(U, X, plan.y_a, rest, x0=x)
    if not keep_duals:
        return w0, np.zeros(layout.n_w), np.zeros(nlp.lbg.size)
    lam_x, lam_g = nlp.shift_duals(plan.lam_x, plan.lam_g, shift)
    return w0, lam_x, lam_g


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
