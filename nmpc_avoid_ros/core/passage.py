"""Passage mode: a second NLP with a longer horizon for passages the regular one cannot plan.

Why: the terminal equality x(N) = x_a asks a plan to go from rest in front of a region to rest
beyond it within N samples. With van der Pol's N = 5 (2.5 s) and the keep-in |x1 x2| <= 2 that
is impossible past a long region: the stall escape's guesses (core/candidates.py) cannot help,
and the loop rests in front of it (campaign vdp-0100 at x1 = 3.757, target -7.57; vdp-0020 passes
with N = 15, not with N = 5).

What: the same problem with horizon `escape_horizon` (a structural setting; 0: off), built once in
the controller's constructor. The parameter vector does not depend on the horizon (moving
obstacles are placed at stage times k Ts from symbolic slot parameters), so one vector serves
both NLPs; the constructor checks that their parameter layouts agree.

When: only after the stall escape (same conditions: y_a stalled, a region across the steady
states towards the target) found nothing better with the short horizon; on the next sample that
is still stalled, the long NLP is solved from the escape guesses made for its horizon, within what
is left of the sample's budget. A plan enters the mode when it is usable (hard constraints),
predicts no penetration beyond VIOLATION_TOLERANCE and brings y_a past the block: a blocked steady
state lies between the short plan's y_a and its own, and its offset cost is below PASSAGE_GAIN
times the short plan's. Among those, the lowest total cost.

In the mode: every sample solves the long NLP warm-started from its shifted plan (the controller's
warm-start rules); a failure falls back as usual, the selector simulating the first N inputs of
the shifted long plan. The mode ends when the long plan stays within PASSAGE_REST (inf-norm) of
its x_a from stage N - 1 on: its first N stages, ending at x_a, are then a plan of the short NLP,
which takes over from them (at the latest when the state rests at x_a beyond the region). A long
plan whose y_a stalls again in front of a region ends the same way, and the short escape tries
again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .candidates import EscapeGuesses, Solution, guess_batch, solve_guess
from .errors import ConfigError
from .fallback import VIOLATION_TOLERANCE
from .models import Model
from .nlp import NlpBase
from .regions import Region
from .settings import ControllerSettings
from .step_result import Plan

#: a long plan enters the mode only if its offset cost is below this times the short plan's
PASSAGE_GAIN = 0.9
#: the mode ends when the long plan stays this close (inf-norm, state units) to its x_a from stage N - 1 on
PASSAGE_REST = 5e-2


class Passage:
    """The long-horizon NLP, its escape guesses and whether the controller is in passage mode.

    `nlp` is None when `escape_horizon` is 0 (then nothing is ever tried).
    """

    def __init__(self, nlp: NlpBase | None, short: NlpBase, model: Model, settings: ControllerSettings) -> None:
        self.nlp = nlp
        self.active = False  # in passage mode: the controller's plan is the long NLP's
        self.due = False  # the short escape found nothing: try the long NLP on the next stalled sample
        self.next_guess = 0  # with guesses per sample: the index of the next guess to solve
        self.horizon = 0 if nlp is None else nlp.layout.horizon
        self.guesses: EscapeGuesses | None = None
        if nlp is None:
            return
        if model.steady_state is None:
            raise ConfigError(f"escape_horizon needs the escape guesses, which need a closed-form steady state; "
                              f"model {model.name!r} has none: set escape_horizon 0")
        # the same model and settings but N: equal keep-in rows and slot layout give equal vectors
        if nlp.layout.n_keep_in != short.layout.n_keep_in or nlp.slot_layout != short.slot_layout:
            raise ConfigError("the passage NLP's parameter layout differs from the regular NLP's")
        self.guesses = EscapeGuesses(nlp, model, settings)

    @property
    def available(self) -> bool:
        return self.guesses is not None

    @property
    def solver_builds(self) -> int:
        """Solvers the long NLP constructed (NmpcController.nlp_builds counts them)."""
        return 0 if self.nlp is None else self.nlp.solver_builds

    def attempt(self, x: np.ndarray, y_t: np.ndarray, par: np.ndarray, base: Solution, regions: Sequence[Region],
                time_left: float, feasibility_tolerance: float, per_sample: int = 0
                ) -> tuple[Solution | None, list[str], float]:
        """Solve the long NLP from the escape guesses while time is left (`per_sample` > 0: that many from
        `next_guess` on; if none enters, the mode stays `due` for the next batch); the lowest-cost plan
        that may enter the mode (see the module docstring), or None. Returns (plan, one line per guess,
        seconds)."""
        assert self.nlp is not None and self.guesses is not None
        y_a = base.nlp.layout.split_w(base.w)[2].copy()
        offset = float(base.nlp.terms(base.w, par)[0][0])
        guesses = self.guesses.guesses(x, y_a, y_t, par, regions)
        batch, rest = guess_batch(guesses, self.next_guess, per_sample)
        self.due, self.next_guess = False, 0
        best, report, spent, slowest = None, [], 0.0, 0.0
        for guess in batch:
            if spent + slowest >= time_left:  # as in lowest_cost: start a solve only if it is likely to fit
                report.append(f"passage {guess.label}: not tried (sample budget spent)")
                continue
            candidate, line, seconds = solve_guess(self.nlp, x, par, guess, feasibility_tolerance)
            spent, slowest = spent + seconds, max(slowest, seconds)
            if candidate is None:
                report.append(f"passage {line}")
                continue
            long_offset = float(self.nlp.terms(candidate.w, par)[0][0])
            y_long = self.nlp.layout.split_w(candidate.w)[2]
            why = ("penetrates" if candidate.depth > VIOLATION_TOLERANCE else
                   "offset not lower" if long_offset >= PASSAGE_GAIN * offset else
                   "y_a not past the block" if not self.guesses.crosses_block(y_a, y_long, par) else "")
            report.append(f"passage {line}, offset {long_offset:.4g}" + (f" ({why})" if why else ""))
            if not why and (best is None or candidate.cost < best.cost):
                best = candidate
        if best is not None:
            best.label = f"passage:{best.label}"
        elif rest:
            self.due, self.next_guess = True, len(guesses) - rest
            report.append(f"passage: {rest} more next sample")
        return best, report, spent

    def can_hand_back(self, plan: Plan | None, horizon: int) -> bool:
        """The long plan, seen from now, stays within PASSAGE_REST of its x_a from stage `horizon` - 1 on:
        its first `horizon` stages, ending at x_a, are a plan of the regular NLP (the mode can end).
        A state at rest near x_a is the simplest case."""
        if plan is None:
            return False
        states = _padded(plan.states, plan.x_a, horizon)
        return float(np.max(np.abs(states[plan.age + horizon:] - plan.x_a))) <= PASSAGE_REST

    def hand_back(self, plan: Plan, short: NlpBase) -> Plan:
        """Leave the mode: the regular NLP's plan made of the long plan's first N stages (as of the last
        sample, like any kept plan; x(N) = x_a), with zero multipliers."""
        self.active = False
        N, a = short.layout.horizon, plan.age
        inputs, states = _padded(plan.inputs, plan.u_a, N), _padded(plan.states, plan.x_a, N)
        states = states[a:a + N + 1].copy()
        states[-1] = plan.x_a
        return Plan(inputs[a:a + N].copy(), states, plan.y_a.copy(), plan.x_a.copy(), plan.u_a.copy(),
                    np.zeros(short.layout.n_w), np.zeros(short.lbg.size), 0, plan.costs)


def _padded(rows: np.ndarray, last: np.ndarray, count: int) -> np.ndarray:
    """rows [K, d] followed by `count` copies of last [d] (a plan's steady tail)."""
    return np.vstack([rows, np.tile(last, (count, 1))])
