"""The fallback input when a sample has no usable solution, chosen by the violation it predicts.

Candidates, in order of preference among those predicting the least violation (violations up to
VIOLATION_TOLERANCE count as none):

* ``shift``: the rest of the last plan, then its u_a (the candidate of the paper's recursive
  feasibility proof; available while the plan lasts); with `terminal: set` the plan's continuation by the local
  controller kappa(x, y_a) = u_a + K(y_a)(x - x_a) instead of u_a (Plan.tail, the proof's candidate there);
* ``steady``: u_a of the last plan, held; with `terminal: set` the local controller from the current state (its
  inputs along the predicted states: core/nlp/terminal.py ShiftedTail.rollout);
* ``safe``: the model's configured safe input (`safe_input`; zero clipped to the input box if unset);
* ``recovery``: a short solve that minimises the predicted penalty and constraint violation over
  the input sequence alone (input box only, so it is always feasible); tried only when every
  other candidate predicts more than VIOLATION_TOLERANCE.

Each candidate's input sequence is simulated with the prediction model over `horizon` samples;
its predicted violation is the largest, over those samples, of: region functions g (keep-in
expressions and obstacles, active ones), state-box excess and hard-constraint excess. The one
with the least is applied (never blindly u = 0: measured in the campaign, u = 0 after a failed
cold start drove van der Pol to |x1 x2| - 2 = 4.11). With `by_sum` (the guard's N samples in a row whose
candidates all violate) such candidates rank by their summed squared excess, the recovery's measure, and the
recovery starts from each of them: by the largest, the first rows' (which no input changes), a stop held a unicycle
against a pillar for good.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..errors import InputError
from ..nlp.buffered import Buffered
from ..nlp.parts import command_index, depth_function, problem_parts
from ..nlp.search import VIOLATION_TOLERANCE, depth_allowance
from ..nlp.stop_at import StopAt
from ..nlp.tracking import COLD_START_TIME_FACTOR, SEARCH_SHARE, NlpBase
from ..problem.models import Model
from .step_result import validate_vector

#: candidates in order of preference among equal predicted violations
CANDIDATES = ("shift", "steady", "safe", "recovery")
#: a solved plan predicting more penetration than this is replaced by a candidate that avoids the
#: regions (see FallbackSelector.check_plan). The goal's bound: at 1e-2, campaign vdp-0336 applied
#: plans that squeezed between an ellipse and |x1 x2| <= 2 at a keep-in depth of 1.1e-3 while an
#: input that stays clear existed (test/test_cold_start.py)
PLAN_OVERRIDE = VIOLATION_TOLERANCE
#: the keep-in expressions are judged tightened by `keep_in_margin` up to this much (the penetration tolerance):
#: a larger margin is the plan's room, not the set. Judged with the whole margin, a state a hair inside the
#: margin's band (the live robot cruising at 1.197 m/s against a 1.2 m/s limit planned at 1.195) made the first
#: sub-steps of every plan from it "penetration" (they share x(0)'s slack), and the safe input braked the robot
#: (test/test_fallback_keep_in_margin.py). With it a row counts as penetrating when the set itself is entered
#: (g > 0 for any margin >= the tolerance, g > 1e-3 without a margin, as before)
JUDGED_KEEP_IN_MARGIN = VIOLATION_TOLERANCE
#: iteration budget of the recovery solve
RECOVERY_ITERATIONS = 100
#: a recovery solve is not started with less time than this left before its end, s
RECOVERY_MIN_TIME = 1e-3
#: weight of |u - u_ref|^2 in the recovery solve: picks the input nearest the reference among
#: equally safe ones (small against any violation worth removing)
RECOVERY_REGULARISATION = 1e-6


@dataclass
class FallbackChoice:
    """The chosen candidate: its name, inputs [H, m], predicted states x(0..H) [H+1, n], its
    predicted violation, every candidate's predicted violation (name -> region g / state units) over
    `horizon` samples; `reason` renders them for people."""

    kind: str
    inputs: np.ndarray
    states: np.ndarray
    violation: float
    predicted: dict[str, float]
    horizon: int
    solve_time: float = 0.0
    unavoidable: bool = False  # every candidate predicts a violation (see FallbackSelector.check_plan)
    #: chosen by the least summed squared excess (every candidate violated, N samples in a row)
    by_sum: bool = False

    @property
    def reason(self) -> str:
        """One line: the kind applied and every candidate's predicted violation."""
        others = ", ".join(f"{k} {v:.3g}" for k, v in self.predicted.items())
        measure = "least summed squared violation" if self.by_sum else "least predicted violation"
        return f"{self.kind}: {measure} over {self.horizon} samples (largest: {others})"


class FallbackSelector:
    """Simulates candidate input sequences and solves the recovery problem of one settings structure."""

    def __init__(self, nlp: NlpBase, model: Model, settings: ControllerSettings) -> None:
        self.model, self.settings = model, settings
        H = self.horizon = settings.horizon
        n, m = model.n, model.m
        parts = problem_parts(settings, model)
        path = model.discrete_path(settings.sample_time, settings.discretization, settings.integration_steps)
        x0, par = ca.SX.sym("x0", n), ca.SX.sym("p", parts.par.numel())
        U = ca.SX.sym("U", m, H)
        # the regions as planned (the obstacles with their margins), the keep-in sets with at most
        # JUDGED_KEEP_IN_MARGIN of their margin
        depth = self._judged_depth = depth_function(parts, model,
                                                    min(settings.keep_in_margin, JUDGED_KEEP_IN_MARGIN))
        # the keep-in rows at x(0) (the first rows of the region functions), which no plan from x(0) can change:
        # as the NLP plans them (keep_in_margin) and as judged (at most JUDGED_KEEP_IN_MARGIN)
        u0, keep = ca.SX.sym("u0", m), len(settings.keep_in)
        planned = depth_function(parts, model)(x0, u0, par, 0.0)[:keep]
        judged = depth(x0, u0, par, 0.0)[:keep]
        self._initial_keep_in_depth = Buffered(ca.Function("initial_keep_in_depth", [x0, u0, par], [
            ca.mmax(ca.vertcat(planned, 0)), ca.mmax(ca.vertcat(judged, 0))]))
        x_lo, x_hi = np.array(settings.state_min, float), np.array(settings.state_max, float)
        states, excess = [x0], []
        x = x0
        ts, steps = settings.sample_time, settings.integration_steps
        for k in range(H):
            points = path(x, U[:, k])
            # the regions also between the samples, at the sub-step states (none for 1 step)
            terms = [depth(points[:, i], U[:, k], par, (k + (i + 1) / steps) * ts) for i in range(steps - 1)]
            x = points[:, -1]
            states.append(x)
            u_next = U[:, min(k + 1, H - 1)]
            terms += [depth(x, u_next, par, (k + 1) * ts), x - x_hi, x_lo - x]
            if parts.n_hard:
                terms.append(parts.hard_g(x, u_next))
            excess.append(ca.vertcat(*terms))
        excess = ca.vertcat(*excess)  # [H * rows]: > 0 where violated
        self._rollout = ca.Function("fallback_rollout", [x0, U, par], [ca.horzcat(*states), ca.mmax(excess),
                                                                       ca.sumsqr(ca.fmax(excess, 0))])
        # recovery: min sum max(0, excess)^2 (smooth with slacks s >= excess, s >= 0) + small |u - u_ref|^2
        slack = ca.SX.sym("s", excess.numel())
        u_ref = ca.SX.sym("u_ref", m)
        cost = ca.sumsqr(slack) + RECOVERY_REGULARISATION * ca.sumsqr(U - ca.repmat(u_ref, 1, H))
        problem = {"x": ca.vertcat(ca.vec(U), slack), "p": ca.vertcat(x0, par, u_ref), "f": cost,
                   "g": slack - excess}
        self._stop_at = StopAt(problem["x"].numel(), excess.numel(), problem["p"].numel())
        options = {"print_time": False, "error_on_fail": False, "iteration_callback": self._stop_at,
                   "ipopt": {"print_level": 0, "sb": "yes", "max_iter": RECOVERY_ITERATIONS,
                             # the sample's end (StopAt) bounds it, a cold start's too; this only guards a
                             # call outside a sample (end = inf)
                             "max_wall_time": (1 - SEARCH_SHARE) * COLD_START_TIME_FACTOR * settings.max_solve_time,
                             "tol": 1e-8}}
        self._recovery = ca.nlpsol("fallback_recovery", "ipopt", problem, options)
        #: solvers constructed here (NmpcController.nlp_builds counts them): the recovery solve
        self.solver_builds = 1
        lo, hi = np.array(settings.input_min, float), np.array(settings.input_max, float)
        self._lbx = np.concatenate([np.tile(lo, H), np.zeros(slack.numel())])
        self._ubx = np.concatenate([np.tile(hi, H), np.full(slack.numel(), np.inf)])
        self._n_slack = slack.numel()
        self._input_lo, self._input_hi = lo, hi
        #: the model's safe input [m] (NmpcController.set_safe_input); zero clipped to the input box
        self.safe_input = np.clip(np.zeros(m), lo, hi)
        # input_rate_max: where par holds the command in force (rate_on right after it), the limited inputs, their
        # largest change per sample
        self._commanded = command_index(parts.par.numel(), parts.slot_par.numel(), m, bool(settings.input_rate_max))
        self._rate_limited, self._rate_step = list(parts.rate_limited), np.array(parts.rate_step, float)

    def check_safe_input(self, u: Sequence[float]) -> np.ndarray:
        """u as a safe input [m], or InputError if malformed or outside the input box."""
        u = validate_vector("safe_input", u, self.model.m)
        if np.any(u < self._input_lo) or np.any(u > self._input_hi):
            raise InputError(f"safe_input {u.tolist()} is outside the input box")
        return u

    def allowance(self, x: np.ndarray, u: np.ndarray | None, par: np.ndarray) -> float:
        """The depth [g] a plan from x [n] (under u [m]; None: the safe input) may predict and be clear at the
        regular NLP's parameters par: x(0)'s own keep-in depth where x(0) lies in the keep_in_margin band only
        (inside every keep-in set with at most JUDGED_KEEP_IN_MARGIN), else VIOLATION_TOLERANCE (core/nlp/search.py
        `depth_allowance`). The obstacles' margins get none: a plan from a state in an obstacle's band is judged
        penetrating as before, and its search goes on to the escape guesses, which is how the paper's Euler
        config passes the README ellipse (test_intersample)."""
        u = self.safe_input if u is None else u
        planned, judged = (float(v[0]) for v in self._initial_keep_in_depth(x, u, par))
        return depth_allowance(planned) if judged <= VIOLATION_TOLERANCE else VIOLATION_TOLERANCE

    def followed(self, inputs: np.ndarray, par: np.ndarray) -> np.ndarray:
        """inputs [H, m] as rate-limited actuators follow them from the command in force (in par): each input with
        an input_rate_max moves towards its value by at most its rate step a sample. Unchanged without limits or
        before the first command. A fallback that jumped (the safe input's wheels straight at once) left the next
        warm start's first rate row violated, and the car's FATROP solve was abandoned sample after sample."""
        if not self._rate_limited or par[self._commanded[-1] + 1] == 0:
            return inputs
        limited, step = self._rate_limited, self._rate_step
        followed = np.array(inputs, float)
        before = par[self._commanded][limited]
        for k in range(len(followed)):
            before = before + np.clip(followed[k, limited] - before, -step, step)
            followed[k, limited] = before
        return followed

    def predict(self, x: np.ndarray, inputs: np.ndarray, par: np.ndarray) -> tuple[np.ndarray, float]:
        """States x(0..H) [H+1, n] and the predicted violation (max excess, 0 if none) of inputs [H, m]."""
        states, worst, _ = self._simulate(x, inputs, par)
        return states, worst

    def _simulate(self, x: np.ndarray, inputs: np.ndarray, par: np.ndarray) -> tuple[np.ndarray, float, float]:
        """As `predict`, and the summed squared excess over the horizon (the recovery solve's measure)."""
        states, worst, total = self._rollout(x, np.asarray(inputs, float).T, par)
        states, worst, total = np.asarray(states).T, float(worst), float(total)
        # a rollout that overflows (a state far outside Z) predicts the worst, not none: max(0, nan) is 0
        if not (math.isfinite(worst) and math.isfinite(total)):
            return states, math.inf, math.inf
        return states, max(0.0, worst), total

    def recover(self, x: np.ndarray, par: np.ndarray, start: np.ndarray, end: float = math.inf
                ) -> tuple[np.ndarray | None, float]:
        """Inputs [H, m] minimising the predicted violation from the guess `start` [H, m] (None if the
        solve failed or less than RECOVERY_MIN_TIME was left), and its wall time in s. The solve ends
        by `end` (time.perf_counter s, the sample's time bound) plus one iteration."""
        begin = time.perf_counter()
        if end - begin < RECOVERY_MIN_TIME:
            return None, 0.0
        guess = np.concatenate([np.asarray(start, float).ravel(), np.zeros(self._n_slack)])  # = vec(U)
        self._stop_at.end = end
        sol = self._recovery(x0=guess, p=np.concatenate([x, par, start[0]]), lbx=self._lbx, ubx=self._ubx,
                             lbg=0.0, ubg=np.inf)
        seconds = time.perf_counter() - begin
        w = np.asarray(sol["x"]).ravel()
        m, H = self.model.m, self.horizon
        inputs = np.clip(w[: m * H].reshape(H, m), self._input_lo, self._input_hi)
        # judged by its simulated violation like the others, so an unconverged iterate may serve
        if not np.all(np.isfinite(inputs)):
            return None, seconds
        return inputs, seconds

    def choose(self, x: np.ndarray, par: np.ndarray, plan_inputs: np.ndarray | None, u_a: np.ndarray | None,
               plan_left: bool, recover: bool = True, end: float = math.inf, by_sum: bool = False) -> FallbackChoice:
        """The least-violating candidate for state x [n]. `plan_inputs` [H, m]: the shifted plan's
        inputs (padded with u_a); `u_a` [m], held, or the `steady` candidate's inputs [H, m] (the local controller
        with `terminal: set`); `plan_left`: the shifted plan still has inputs of its own; `recover`
        False: no recovery solve (a state outside the solve domain is handed to no solver); `end`: the
        recovery solve's end (time.perf_counter s); `by_sum`: when every candidate violates, the least summed
        squared excess wins instead of the least largest one (after N such samples in a row: SampleAnswers._guard)."""
        H = self.horizon
        sequences: dict[str, np.ndarray] = {}
        if plan_inputs is not None and plan_left:
            sequences["shift"] = np.asarray(plan_inputs, float)
        if u_a is not None:
            sequences["steady"] = np.tile(u_a, (H, 1)) if np.ndim(u_a) == 1 else np.asarray(u_a, float)
        sequences["safe"] = np.tile(self.safe_input, (H, 1))
        sequences = {kind: self.followed(seq, par) for kind, seq in sequences.items()}
        predicted = {kind: self._simulate(x, seq, par) for kind, seq in sequences.items()}
        seconds = 0.0
        rank = 2 if by_sum else 1  # the index in predicted's (states, largest excess, summed squared excess)
        if recover and min(v for _, v, _ in predicted.values()) > VIOLATION_TOLERANCE:
            # by the sum, from every candidate: a stop is a stationary point of the recovery (a unicycle must turn
            # before it can leave, and at rest turning changes no excess), a moving candidate breaks the tie
            for start in sorted(sequences, key=lambda k: predicted[k][rank])[:None if by_sum else 1]:
                inputs, spent = self.recover(x, par, sequences[start], end)
                seconds += spent
                if inputs is None:
                    continue
                inputs = self.followed(inputs, par)
                simulated = self._simulate(x, inputs, par)
                if "recovery" not in predicted or simulated[rank] < predicted["recovery"][rank]:
                    sequences["recovery"], predicted["recovery"] = inputs, simulated
        unavoidable = min(v for _, v, _ in predicted.values()) > VIOLATION_TOLERANCE
        measure = rank if unavoidable else 1
        least = min(p[measure] for p in predicted.values())
        least = least if measure == 2 else max(VIOLATION_TOLERANCE, least)
        kind = next(k for k in CANDIDATES if k in predicted and predicted[k][measure] <= least)
        states, violation, _ = predicted[kind]
        every = {k: predicted[k][1] for k in CANDIDATES if k in predicted}
        return FallbackChoice(kind, sequences[kind], states, violation, every, H, seconds, by_sum=measure == 2)

    def check_plan(self, x: np.ndarray, par: np.ndarray, plan_inputs: np.ndarray, end: float = math.inf,
                   by_sum: bool = False) -> FallbackChoice | None:
        """A better input than the solved plan's [H, m], or None to apply the plan (`end`: as in `choose`).

        Only for a plan predicting penetration beyond VIOLATION_TOLERANCE: the least-violating of
        the plan (kind 'plan'), the safe input and the recovery solve, when every one of them predicts
        a violation (a region that cannot be avoided from x: `unavoidable`), or when the plan predicts
        more than PLAN_OVERRIDE and another candidate avoids the regions. The soft penalty may trade
        a little penetration for progress (a squeeze between two regions balances their penalties);
        the controller overrides such a plan for at most N samples in a row, so that a plan the solver
        keeps choosing does not hold the plant still for good (NmpcController._bound_violation).
        """
        plan_violation = self.predict(x, plan_inputs, par)[1]
        if plan_violation <= VIOLATION_TOLERANCE:
            return None
        choice = self.choose(x, par, plan_inputs, None, True, end=end, by_sum=by_sum)
        # the 'shift' candidate here is the plan itself
        choice.predicted = {("plan" if k == "shift" else k): v for k, v in choice.predicted.items()}
        if choice.kind == "shift":
            choice.kind = "plan"
        choice.unavoidable = choice.violation > VIOLATION_TOLERANCE
        if not choice.unavoidable and plan_violation <= PLAN_OVERRIDE:
            return None
        return choice
