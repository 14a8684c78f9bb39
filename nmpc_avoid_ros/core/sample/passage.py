"""Passage mode: a second NLP with a longer horizon for passages the regular one cannot plan.

Why: the terminal equality x(N) = x_a asks a plan to go from rest in front of a region to rest
beyond it within N samples. With van der Pol's N = 5 (2.5 s) and the keep-in |x1 x2| <= 2 that
is impossible past a long region: the stall escape's guesses (core/sample/candidates.py) cannot help,
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

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..config.settings import ControllerSettings
from ..errors import ConfigError
from ..nlp.search import Candidate, Start
from ..nlp.tracking import NlpBase
from ..problem.models import Model
from ..problem.regions import Region
from .candidates import EscapeGuesses, Guess
from .guess_starts import guess_batch, guess_start
from .step_result import Plan
from .trajectory_guess import TrajectorySearch

#: a long plan enters the mode only if its offset cost is below this times the short plan's
PASSAGE_GAIN = 0.9


@dataclass(frozen=True)
class Turn:
    """A turn in the passage's list of guesses that is not a Guess: the trajectory search, or its guess's solve."""

    name: str


SEARCH, SOLVE = Turn("trajectory_search"), Turn("trajectory_solve")
#: the mode ends when the long plan stays this close (inf-norm, state units) to its x_a from stage N - 1 on
PASSAGE_REST = 5e-2


class Passage:
    """The long-horizon NLP and its escape guesses (stateless: whether the controller is in the mode
    lives in its SampleMemory, core/sample/memory.py).

    `nlp` is None when `escape_horizon` is 0 (then nothing is ever tried).
    """

    def __init__(self, nlp: NlpBase | None, short: NlpBase, model: Model, settings: ControllerSettings) -> None:
        self.nlp = nlp
        self.horizon = 0 if nlp is None else nlp.layout.horizon
        self.guesses: EscapeGuesses | None = None
        self.search: TrajectorySearch | None = None
        if nlp is None:
            return
        if model.steady_state is None:
            raise ConfigError(f"escape_horizon needs the escape guesses, which need a closed-form steady state; "
                              f"model {model.name!r} has none: set escape_horizon 0")
        # the same model and settings but N: equal keep-in rows and slot layout give equal vectors
        if nlp.layout.n_keep_in != short.layout.n_keep_in or nlp.slot_layout != short.slot_layout:
            raise ConfigError("the passage NLP's parameter layout differs from the regular NLP's")
        self.guesses = EscapeGuesses(nlp, model, settings)
        self.search = TrajectorySearch(settings, model, self.horizon)

    @property
    def available(self) -> bool:
        return self.guesses is not None

    @property
    def solver_builds(self) -> int:
        """Solvers the long NLP constructed (NmpcController.nlp_builds counts them)."""
        return 0 if self.nlp is None else self.nlp.solver_builds

    def starts(self, x: np.ndarray, y_t: np.ndarray, par: np.ndarray, base: Candidate, regions: Sequence[Region],
               next_guess: int, per_sample: int, end: float, found: Guess | None
               ) -> tuple[list[Start], int, int, Guess | None]:
        """The long NLP's starts from its guesses (`per_sample` > 0: that many from `next_guess` on), the index
        of the guess after them, how many guesses remain after them, and the trajectory found.

        The first two turns are the trajectory search's (core/sample/trajectory_guess.py): a trajectory of the
        model past the first blocked stretch, searched until `end` (time.perf_counter s), then its solve (from
        `found`, the one an earlier sample found, or this sample's); then the escape guesses. The search and the
        solve take a sample each (measured on the 8 stalled live van der Pol scenes with a way past: 44-335 ms
        to find it, 37-172 ms to solve it)."""
        assert self.nlp is not None and self.guesses is not None and self.search is not None
        y_a = base.nlp.layout.y_a(base.w).copy()
        beyond = self.guesses.beyond_blocks(y_a, self.guesses.aim(y_t), par)
        guesses: list[Guess | Turn] = [SEARCH, SOLVE] if beyond else []
        guesses += self.guesses.guesses(x, y_a, y_t, par, regions, beyond)
        batch, rest = guess_batch(guesses, next_guess, per_sample)
        if SEARCH in batch:
            found = self.search.find(x, y_a, beyond[0], par, end)
        chosen = [found if guess is SOLVE else guess for guess in batch if guess is not SEARCH]
        starts = [guess_start(self.nlp, x, par, guess, f"passage:{guess.label}") for guess in chosen
                  if isinstance(guess, Guess)]
        return starts, len(guesses) - rest, rest, found

    def admit(self, base: Candidate, par: np.ndarray) -> Callable[[Candidate], str]:
        """Why a long plan may not enter the mode ('' if it may): it penetrates, its offset cost is not
        below PASSAGE_GAIN times the short plan's, or its y_a is not past the block."""
        assert self.nlp is not None and self.guesses is not None
        y_a = base.nlp.layout.y_a(base.w).copy()
        offset = float(base.nlp.terms(base.w, par)[0][0])
        nlp, guesses = self.nlp, self.guesses

        def why(candidate: Candidate) -> str:
            long_offset = float(nlp.terms(candidate.w, par)[0][0])
            y_long = nlp.layout.y_a(candidate.w)
            return ("penetrates" if not candidate.clear else
                    "offset not lower" if long_offset >= PASSAGE_GAIN * offset else
                    "y_a not past the block" if not guesses.crosses_block(y_a, y_long, par) else "")

        return why

    def can_hand_back(self, plan: Plan | None, horizon: int) -> bool:
        """The long plan, seen from now, stays within PASSAGE_REST of its x_a from stage `horizon` - 1 on:
        its first `horizon` stages, ending at x_a, are a plan of the regular NLP (the mode can end).
        A state at rest near x_a is the simplest case."""
        if plan is None:
            return False
        states = plan.shifted(plan.age + 1)[1]  # seen from now
        return float(np.max(np.abs(states[horizon - 1:] - plan.x_a))) <= PASSAGE_REST

    def hand_back(self, plan: Plan, short: NlpBase) -> Plan:
        """The regular NLP's plan made of the long plan's first N stages (as of the last sample, like any
        kept plan; x(N) = x_a), with zero multipliers: the mode ends with it. A prepared plan (age -1, for
        this sample: core/sample/feedback.py) stays one."""
        N = short.layout.horizon
        inputs, states = plan.shifted(max(plan.age, 0))
        states = states[:N + 1].copy()
        states[-1] = plan.x_a
        return Plan(inputs[:N].copy(), states, plan.y_a.copy(), plan.x_a.copy(), plan.u_a.copy(),
                    np.zeros(short.layout.n_w), np.zeros(short.lbg.size), min(plan.age, 0), plan.costs)
