"""A passage guess that is a trajectory of the model: a breadth-first search over held inputs.

Why: the passage NLP (core/sample/passage.py) starts from the escape guesses, straight lines and
detours through the state space that ignore the dynamics. Past an ellipse across van der Pol's
steady states, with |x1 x2| <= 2 beside it, the way round is a swing the polylines do not resemble:
FATROP from them was abandoned at the deadline, or converged to plans through the region, and the
loop rested in front of it while a clear way existed (campaign vdp-0005, 0033, 0144 and 5 more of the
first 200 live scenes, `local_minimum`: the campaign's own search, evaluation/campaign/reachability.py,
found each way offline at a finer grid). From their rest states this search finds 7 of the 8 ways in
44-335 ms, and FATROP solves each guess to a clear long plan (docs/design.md, 'Passage mode').

What: from x, every input on a grid (LEVELS values of each input across its box) held one sample,
predicted and judged as the NLP does (core/nlp/stagewise.py: its discretisation and sub-steps, the
region rows at them with their chords' terms, the margins; a fast swing whose sub-step states were
clear bent through a region's rows) and inside the state box, within the search's tolerance
VIOLATION_TOLERANCE; a successor is kept when its cell (CELL_FRACTION of each state's box width) is
new. The search ends at the first state at rest (within REST_CELLS cells of its output's steady state)
whose output lies past the blocked stretch (beyond `y_beyond` in the direction of the way), at the
passage horizon's depth less one, or at `end`. The guess is that path, then a straight line to the
steady state of y_beyond over the remaining stages. A path that ended under way past the block, with
that line as its tail, was dynamically far from feasible, and FATROP went from it into the region.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..nlp.between import between_samples, worst_of
from ..nlp.codegen import cache_dir, serve_compiled
from ..nlp.parts import problem_parts
from ..nlp.search import VIOLATION_TOLERANCE
from ..problem.models import Model
from .candidates import Guess

#: values of each input on the search grid (25 for one input, as the campaign's own search; fewer each for more
#: inputs, at least 3)
LEVELS = 25
#: one state kept per cell of this fraction of each state's box width
CELL_FRACTION = 2e-2
#: the search ends at a state past the block within this many cells of its output's steady state (at rest there)
REST_CELLS = 2.0
#: sizes of the mapped stage function (each map costs 6.5 ms to build): a call takes the largest that the successors
#: left fill and that ends by the search's end at the last call's pace
CHUNKS = tuple(4 ** k for k in range(2, 7))


class TrajectorySearch:
    """The breadth-first search of one settings structure (built once; `find` per passage try). With `codegen` its
    stage function is compiled (core/nlp/codegen.py `serve_compiled`): 2x faster."""

    def __init__(self, settings: ControllerSettings, model: Model, horizon: int) -> None:
        self.settings, self.model, self.horizon = settings, model, horizon
        n, m = model.n, model.m
        parts = problem_parts(settings, model)
        # one sample as the NLP predicts and judges it (module doc)
        ts = settings.sample_time
        path = model.discrete_path(ts, settings.discretization, settings.integration_steps)
        x, u, par, elapsed = ca.SX.sym("x", n), ca.SX.sym("u", m), parts.par, ca.SX.sym("t")
        points = path(x, u)
        lo, hi = np.array(settings.state_min, float), np.array(settings.state_max, float)
        rows = worst_of(parts.avoidance(x, u, elapsed), between_samples(parts, x, points, u, elapsed, ts))
        end = points[:, -1]
        excess = ca.vertcat(rows, parts.avoidance(end, u, elapsed + ts), end - hi, lo - end)
        y = ca.SX.sym("y", model.p)
        self._steady = ca.Function("trajectory_steady", [y], list(model.steady_state(y)))  # Passage requires it
        # the end's output and how far (state units) the end is from that output's steady state
        y_end = model.output(end, u)
        stage = ca.Function("trajectory_stage", [x, u, par, elapsed],
                            [end, ca.mmax(excess), y_end, ca.fabs(end - self._steady(y_end)[0])])
        # with `codegen` compiled (cached as the feedback law's answer is; swapped in with one assignment: a search
        # uses either)
        serve_compiled(stage, cache_dir(settings.cache_dir) if settings.codegen else None, settings.codegen_background,
                       lambda function: setattr(self, "_maps", self._mapped(function)),
                       "the passage's trajectory search")
        per_input = max(3, int(round(LEVELS ** (1.0 / m))))
        grids = np.meshgrid(*[np.linspace(a, b, per_input) for a, b in zip(settings.input_min, settings.input_max)])
        self._levels = np.array(grids).reshape(m, -1)  # [m, per_input**m]
        self._cell = CELL_FRACTION * (hi - lo)
        #: s per stage evaluation, as the last call took (0 before the first: the smallest map is called)
        self._per_evaluation = 0.0

    @staticmethod
    def _mapped(stage: ca.Function) -> dict[int, ca.Function]:
        return {size: stage.map(size) for size in CHUNKS}

    def find(self, x: np.ndarray, y_from: np.ndarray, y_beyond: np.ndarray, par: np.ndarray, end: float
             ) -> Guess | None:
        """A guess [horizon stages] whose first stages are a clear trajectory from x [n] to an output past
        y_beyond [p] (seen from y_from [p]), resting at y_beyond's steady state; None if none was found by
        `end` (time.perf_counter s) or within the horizon less one sample. `par`: the NLP's parameters."""
        direction = np.asarray(y_beyond, float) - np.asarray(y_from, float)
        if not np.any(direction):
            return None
        levels, k = self._levels, self._levels.shape[1]
        nodes_x, nodes_u, parent = [np.asarray(x, float)], [np.zeros(self.model.m)], [-1]
        frontier = [0]
        seen = {tuple(np.floor(x / self._cell).astype(int))}
        for depth in range(self.horizon - 1):
            if not frontier or time.perf_counter() >= end:
                return None
            fresh = []
            total, begin = len(frontier) * k, 0
            while begin < total:
                # the largest map that the successors left fill (the smallest, padded, for the last few) and that
                # ends by `end` at the last call's pace: a call is not interrupted
                left = end - time.perf_counter()
                fits = [c for c in CHUNKS if c * self._per_evaluation <= left]
                if not fits:
                    return None
                size = max((c for c in fits if c <= total - begin), default=fits[0])
                pairs = np.arange(begin, min(begin + size, total))
                begin += len(pairs)
                which = [frontier[j] for j in pairs // k]
                stage = self._maps[size]
                starts = np.zeros((self.model.n, size))
                inputs = np.zeros((self.model.m, size))
                starts[:, :len(pairs)] = np.array([nodes_x[j] for j in which]).T
                inputs[:, :len(pairs)] = levels[:, pairs % k]
                called = time.perf_counter()
                ends, excess, ys, rest = (np.asarray(v) for v in stage(starts, inputs, par,
                                                                        depth * self.settings.sample_time))
                self._per_evaluation = (time.perf_counter() - called) / size
                for j in np.flatnonzero(excess[0, :len(pairs)] <= VIOLATION_TOLERANCE):
                    cell = tuple(np.floor(ends[:, j] / self._cell).astype(int))
                    if cell in seen:
                        continue
                    seen.add(cell)
                    nodes_x.append(ends[:, j].copy())
                    nodes_u.append(inputs[:, j].copy())
                    parent.append(which[j])
                    fresh.append(len(nodes_x) - 1)
                    if (float(np.dot(ys[:, j] - y_beyond, direction)) >= 0.0
                            and np.all(rest[:, j] <= REST_CELLS * self._cell)):
                        return self._guess(fresh[-1], nodes_x, nodes_u, parent, y_beyond)
            frontier = fresh
        return None

    def _guess(self, leaf: int, nodes_x: list, nodes_u: list, parent: list, y_beyond: np.ndarray) -> Guess:
        """The path to `leaf`, then a straight line to y_beyond's steady state over the horizon's remaining stages."""
        x_beyond, u_beyond = (np.asarray(v, float).ravel() for v in self._steady(y_beyond))
        chain = []
        while parent[leaf] >= 0:
            chain.append(leaf)
            leaf = parent[leaf]
        chain.reverse()
        states = [nodes_x[j] for j in chain]
        inputs = [nodes_u[j] for j in chain]
        rest = self.horizon - len(chain)
        for i in range(1, rest + 1):
            states.append(states[-1] + (x_beyond - states[-1]) / (rest - i + 1))
            inputs.append(u_beyond)
        states[-1] = x_beyond
        return Guess("trajectory", np.asarray(y_beyond, float).copy(), np.array(states), np.array(inputs))
