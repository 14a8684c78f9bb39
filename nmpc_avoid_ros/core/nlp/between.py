"""Avoidance between the samples: the rows a stage's slack bounds on the way from x(k) to x(k+1).

With integration_steps M > 1 the prediction integrates each sample in M sub-steps, p_0 = x(k), p_1 ..
p_{M-1}, p_M = x(k+1) (docs/design.md, 'Between the samples'). The stage's slack s bounds g at p_1 ..
p_{M-1} as well as at x(k). The straight chords between them are bounded too, for ellipses: in the
ellipse's normalised coordinates g = 1 - |z|^2 is a concave quadratic, so along a chord of normalised
length c

    g((1 - t) a + t b) = (1 - t) g(a) + t g(b) + t (1 - t) c^2.

If g(a) <= s - beta c^2 and g(b) <= s - gamma c^2, the chord stays at or below s wherever
(1 - t) beta + t gamma >= t (1 - t) for t in [0, 1]: beta = gamma = 1/4 between two sub-step states,
and beta = 0, gamma = 1 where one end is a sample state whose own row has no chord term (x(k) here;
x(k+1) in the next stage's row, so that end holds for max(s_k, s_k+1)). Each sub-step row therefore
carries c^2 / 4 of a chord to another sub-step state and the whole c^2 of a chord to x(k) or x(k+1):
with the plan's slacks at zero, every chord between its sub-step states is clear of every ellipse
(the real motion is not quite a chord; its bend at M = 8 is what region_margin covers). A keep-in
expression g quadratic in x (Hessian H) gets the same terms with c^2 = lambda_max(-H) / 2 |b - a|^2, an
upper bound of its bend -(b - a)' H (b - a) / 2 (|x1 x2| <= 2: |b - a|^2 / 2; a convex g such as a
speed limit: 0); a non-quadratic one keeps its point rows. Every term is a smooth quadratic of the
states (a positive part of the exact bend would have a kink at rest, which stalled the solver). Polygons keep
the point rows (a chord may cut a corner by its sagitta; region_margin mitres them). M = 1 adds
nothing: the paper's NLP row for row.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca

if TYPE_CHECKING:
    from .parts import ProblemParts

#: share of c^2 a sub-step row carries for a chord to another sub-step state, and for one to a sample state
INNER_CHORD, OUTER_CHORD = 0.25, 1.0


def between_samples(parts: ProblemParts, x_start: ca.SX, points: ca.SX, u: ca.SX, start: float,
                    sample_time: float) -> list[ca.SX]:
    """The rows [n_depth] each of the sub-step states strictly between two samples: g plus its chords' terms.

    x_start [n]: x(k); points [n, M]: Model.discrete_path from x(k) under u(k) (its last column is
    x(k+1), checked at its own stage); start: the time of x(k) after x(0), s. Empty for M = 1."""
    steps = points.size2()
    if steps == 1:
        return []
    states = [x_start] + [points[:, i] for i in range(steps)]
    times = [start + i * sample_time / steps for i in range(steps + 1)]
    chords = [parts.chord(states[i], states[i + 1], u, times[i], times[i + 1]) for i in range(steps)]
    share = [OUTER_CHORD if i in (0, steps - 1) else INNER_CHORD for i in range(steps)]
    return [parts.avoidance(states[j], u, times[j]) + share[j - 1] * chords[j - 1] + share[j] * chords[j]
            for j in range(1, steps)]


def worst_of(depth: ca.SX, between: list[ca.SX]) -> ca.SX:
    """Elementwise max of a stage's g at x(k) and its sub-step rows: the value its slack takes."""
    for extra in between:
        depth = ca.fmax(depth, extra)
    return depth
