"""The terminal set's decrease proven on a shell, by branch and bound with interval bounds.

core/problem/terminal.py proves V_f(f(x, kappa)) - V_f(x) <= -l near the steady state with norm bounds on the
Taylor remainder; those bounds are loose further out. Around that inner set, in the coordinates
v = P^1/2 (x - x_a) (so V_f = |v|^2), this module proves

    phi(v) = V_f(f(x_a + e, u_a + K e) - x_a) - |v|^2 + l(e, K e) <= 0,   e = P^-1/2 v,

for every v of the shell alpha_inner < |v|^2 <= alpha: the shell is covered by boxes, and on each box B with
centre c and half-widths h the centred form phi(v) <= phi(c) + sum_i max_B |d phi / d v_i| h_i (mean value
theorem; the gradient enclosed by interval arithmetic, core/problem/intervals.py) must be negative. A box where
it is not is halved in every coordinate, up to MAX_BOXES boxes and MAX_ROUNDS halvings; then the shell is not
certified (False), never guessed.
"""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np

from .intervals import interval_evaluate_many

#: boxes per coordinate of the first cover of [-sqrt(alpha), sqrt(alpha)]^n
FIRST_SPLIT = 8
#: give up (not certified) beyond this many boxes at once or this many halvings
MAX_BOXES = 8000
MAX_ROUNDS = 24


def shell_decreases(step: ca.Function, q: np.ndarray, r: np.ndarray, p: np.ndarray, k: np.ndarray, x_s: np.ndarray,
                    u_s: np.ndarray, alpha_inner: float, alpha: float) -> bool:
    """Whether phi <= 0 on the whole shell alpha_inner < V_f <= alpha (module docstring) is proven.

    step: the discrete map (x [n], u [m]) -> x+ [n]; q [n, n], r [m, m]: the stage cost; p [n, n]: V_f's matrix;
    k [m, n]: the local controller's gain; x_s [n], u_s [m]: the steady state."""
    n = p.shape[0]
    w, basis = np.linalg.eigh(p)
    root_inv = basis @ np.diag(w ** -0.5) @ basis.T
    v = ca.SX.sym("v", n)
    e = ca.mtimes(ca.DM(root_inv), v)
    du = ca.mtimes(ca.DM(k), e)
    after = step(ca.DM(x_s) + e, ca.DM(u_s) + du) - ca.DM(x_s)
    phi = (ca.dot(after, ca.mtimes(ca.DM(p), after)) - ca.dot(v, v) + ca.dot(e, ca.mtimes(ca.DM(q), e))
           + ca.dot(du, ca.mtimes(ca.DM(r), du)))
    value = ca.Function("phi", [v], [phi])
    gradient = ca.Function("phi_gradient", [v], [ca.gradient(phi, v)])
    radius = np.sqrt(alpha)
    ticks = ((np.arange(FIRST_SPLIT) + 0.5) / FIRST_SPLIT * 2 - 1) * radius
    centres = np.array(np.meshgrid(*[ticks] * n)).reshape(n, -1)
    halves = np.full_like(centres, radius / FIRST_SPLIT)
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=n))).T  # [n, 2^n]
    for _ in range(MAX_ROUNDS):
        nearest = np.maximum(np.abs(centres) - halves, 0.0)
        farthest = np.abs(centres) + halves
        on_shell = ((nearest ** 2).sum(axis=0) <= alpha) & ((farthest ** 2).sum(axis=0) > alpha_inner)
        centres, halves = centres[:, on_shell], halves[:, on_shell]
        if not centres.shape[1]:
            return True
        at_centre = np.asarray(value.map(centres.shape[1])(centres), float).ravel()
        low, high = interval_evaluate_many(gradient, [centres - halves], [centres + halves])[0]
        bound = at_centre + (np.maximum(np.abs(low), np.abs(high)) * halves).sum(axis=0)
        open_boxes = ~(bound < -1e-12 * (1.0 + np.abs(at_centre)))  # a NaN bound stays open
        centres, halves = centres[:, open_boxes], halves[:, open_boxes]
        if not centres.shape[1]:
            return True
        if centres.shape[1] * corners.shape[1] > MAX_BOXES:
            return False
        halves = np.repeat(halves / 2, corners.shape[1], axis=1)
        centres = np.repeat(centres, corners.shape[1], axis=1) + np.tile(corners, centres.shape[1]) * halves
    return False
