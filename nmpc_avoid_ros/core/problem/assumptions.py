"""Checks of the paper's assumptions that a model and its settings can be tested against at start.

Assumption 5 (paper section II): the linearisation of the prediction model at every steady state in
lambda Z is controllable. Where it fails, the tracking NMPC's convergence theorem says nothing (a
nonholonomic robot at rest is the standard case: its linearisation cannot move sideways); the
controller may still work, as the unicycle's does, but a user should know. Checked on a grid of
steady outputs y_a with the discrete map the NLP predicts with (Kalman rank of [B, AB, ...]).
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from .model import Model

#: grid points per output dimension (at most GRID_POINTS_TOTAL in all)
GRID_POINTS = 5
GRID_POINTS_TOTAL = 625
#: a singular value of the controllability matrix below this (relative to the largest) counts as zero
RANK_TOLERANCE = 1e-9


def steady_grid(model: Model, state_min: Sequence[float], state_max: Sequence[float], input_min: Sequence[float],
                input_max: Sequence[float], scale: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Steady states (y_s [p], x_s [n], u_s [m]) inside scale * Z on a grid of outputs; the outputs' range is that
    of h over the corners of the state box (each infinite bound taken as +-10). Models without a closed form use
    their guess near the origin (Model.steady_guess); none: []."""
    lo, hi = (np.clip(np.asarray(b, float), -10.0, 10.0) * scale for b in (state_min, state_max))
    corners = np.array(np.meshgrid(*zip(lo, hi))).reshape(model.n, -1).T[:64]
    outputs = np.array([np.asarray(model.output(c, np.zeros(model.m)), float).ravel() for c in corners])
    y_lo, y_hi = outputs.min(axis=0), outputs.max(axis=0)
    per_axis = max(2, min(GRID_POINTS, int(GRID_POINTS_TOTAL ** (1 / model.p))))
    axes = [np.linspace(a, b, per_axis) if b > a else np.array([a]) for a, b in zip(y_lo, y_hi)]
    box = (lo, hi, np.asarray(input_min, float) * scale, np.asarray(input_max, float) * scale)
    grid = []
    for y in np.array(np.meshgrid(*axes)).reshape(model.p, -1).T:
        if model.steady_state is not None:
            x_s, u_s = (np.asarray(v, float).ravel() for v in model.steady_state(y))
        elif model.steady_guess is not None:
            x_s, u_s = model.steady_guess(y, np.zeros(model.n))
        else:
            return []
        if np.all(box[0] - 1e-9 <= x_s) and np.all(x_s <= box[1] + 1e-9) and np.all(box[2] - 1e-9 <= u_s) \
                and np.all(u_s <= box[3] + 1e-9):
            grid.append((y, x_s, u_s))
    return grid


def uncontrollable_steady_states(model: Model, step: ca.Function,
                                 grid: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    """The outputs y_s of `grid` where the linearisation of the discrete map `step` (x[n], u[m]) -> x+ [n] is
    not controllable (paper Assumption 5)."""
    x, u = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m)
    x_next = step(x, u)
    jacobians = ca.Function("AB", [x, u], [ca.jacobian(x_next, x), ca.jacobian(x_next, u)])
    failed = []
    for y, x_s, u_s in grid:
        a, b = (np.asarray(j, float) for j in jacobians(x_s, u_s))
        blocks, power = [], b
        for _ in range(model.n):
            blocks.append(power)
            power = a @ power
        singular = np.linalg.svd(np.hstack(blocks), compute_uv=False)
        if singular.size < model.n or singular[model.n - 1] <= RANK_TOLERANCE * max(singular[0], 1e-300):
            failed.append(y)
    return failed


def assumption_5_warnings(model: Model, step: ca.Function, state_min: Sequence[float], state_max: Sequence[float],
                          input_min: Sequence[float], input_max: Sequence[float], scale: float) -> list[str]:
    """One warning (or none) naming where Assumption 5 fails on the grid of steady states in scale * Z."""
    grid = steady_grid(model, state_min, state_max, input_min, input_max, scale)
    failed = uncontrollable_steady_states(model, step, grid)
    if not failed:
        return []
    where = np.round(failed[0], 4).tolist()
    return [f"model {model.name}: the linearisation at {len(failed)} of {len(grid)} steady states in lambda Z is not "
            f"controllable (paper Assumption 5), e.g. at y_s = {where}: the convergence theorem does not cover "
            f"them (a robot that cannot move sideways at rest is the usual case; the controller may still converge)"]
