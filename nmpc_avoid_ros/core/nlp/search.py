"""The one search of a sample: solve an ordered list of starts within a budget and keep the best.

Every solver call of the controller's sample goes through `search` (the regular start, a cold
start's guesses, the local-minimum escape's and the passage mode's guesses), so there is one
budget rule and one ranking:

* budget: the first start is always solved; a further one only while the time spent plus the
  slowest call so far stays below the time left (a call's own limit is fixed when its solver is
  built; the worker abandons any call at the sample's deadline, core/nlp/worker.py);
* ranking: a usable plan (hard constraints met: solved, or violation below the feasibility
  tolerance) that predicts no penetration beyond VIOLATION_TOLERANCE beats one that does, then the
  lower cost V_o + V_a + tracking; `admit` may refuse a candidate with a reason (an escape must not
  buy progress with penetration; a passage plan must pass the block);
* `stop_at_clear`: the search ends at the first admitted clear plan (a start needs one good plan,
  an escape compares them all).

What was tried is a `SearchReport`: one `Tried` per start (label, phase, solver status, cost,
predicted depth, seconds, outcome, the ellipse tier that ran it). The campaign, the tests and the
diagnostics read it; the diagnostics string is rendered from it (`SearchReport.render`), and nothing
parses that string.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from .tiers import TieredNlp
from .tracking import BUDGET_EXHAUSTED, SOLVED, NlpBase

#: solver statuses of a solve the clock cut (not its iteration count)
TIME_CUT = BUDGET_EXHAUSTED - {"Maximum_Iterations_Exceeded"}

#: predicted violations up to this count as none (region g and state units): a plan's own penalty optimum
#: predicts ~1e-4 of penetration, which must not lose to a recovery solve over rounding (core/sample/fallback.py)
VIOLATION_TOLERANCE = 1e-3
#: solver status of a start whose guess or parameters were not finite (no solver was called)
NON_FINITE_GUESS = "non_finite_guess"


@dataclass
class Start:
    """One initial guess for one NLP: w0 [n_w] (slacks filled), multipliers, the call's iteration budget and
    its time limit, s (the call is abandoned then, if the sample's deadline does not come first)."""

    label: str
    nlp: NlpBase
    w0: np.ndarray
    lam_x0: np.ndarray
    lam_g0: np.ndarray
    budget: int
    cold: bool = False
    time_limit: float = math.inf


@dataclass
class Candidate:
    """A solver call's outcome: w [n_w] in its NLP's layout, multipliers, how it ended, cost and depth;
    `tier`: the ellipse capacity of the tier that ran the call (None: not on a tier, or no call)."""

    label: str
    nlp: NlpBase
    w: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    solver_status: str
    iterations: int
    seconds: float
    solved: bool
    usable: bool
    budget_cut: bool
    finite: bool
    cost: float = math.nan
    depth: float = math.nan
    tier: int | None = None
    #: the depth a plan from its sample's x(0) cannot avoid, plus the tolerance (`depth_allowance`)
    allowance: float = VIOLATION_TOLERANCE

    @property
    def clear(self) -> bool:
        return self.depth <= self.allowance

    def rank(self) -> tuple[bool, float]:
        """The one ranking: clear before penetrating, then the lower cost."""
        return (not self.clear, self.cost)


class Outcome(StrEnum):
    """What became of a start (Tried.outcome); each member is its string, as in the diagnostics."""

    #: the best so far when the search ended: the plan applied (or, in a later phase, its base)
    KEPT = "kept"
    #: usable but ranked below the kept one
    WORSE = "worse"
    #: not finite, or neither solved nor feasible to the tolerance
    UNUSABLE = "unusable"
    #: the sample's budget was spent before its turn
    NOT_TRIED = "not tried (sample budget spent)"
    #: `admit` refused it; Tried.refusal says why
    REFUSED = "refused"


@dataclass
class Tried:
    """One line of the report: a start, what its solve gave and what became of it (`outcome`; for a
    refused one, `refusal`: why `admit` refused it); `tier`: the ellipse capacity of the tier that ran
    the solver call (core/nlp/tiers.py; None: the start's own NLP, or no call)."""

    label: str
    phase: str
    solver_status: str = ""
    cost: float = math.nan
    depth: float = math.nan
    seconds: float = 0.0
    outcome: Outcome | None = None
    refusal: str = ""
    tier: int | None = None

    @property
    def solver_called(self) -> bool:
        """A solver ran for this start (not skipped for the budget, not refused as a non-finite guess)."""
        return self.outcome is not Outcome.NOT_TRIED and self.solver_status != NON_FINITE_GUESS


#: phases of a sample (SearchReport.phase)
PHASES = ("warm", "cold", "continue", "escape", "passage_try", "passage", "passage_ended", "no_solve", "feedback")


@dataclass
class SearchReport:
    """What one sample's search did.

    phase: the sample's last phase (PHASES): 'warm' (the shifted plan), 'cold' (no plan: the cold-start
        starts), 'continue' (a budget-cut iterate continued), 'escape' (local-minimum escape guesses),
        'passage_try' (the passage NLP's guesses), 'passage' (a sample in the passage mode),
        'passage_ended' (the sample that handed back to the regular horizon), 'no_solve', 'feedback' (the
        plan prepared for the sample answered, no solver call: core/sample/feedback.py).
    kept: the label of the plan applied ('' when none was usable).
    entered_passage: this sample's plan entered the passage mode.
    more_next_sample: guesses left for the next sample (escape_guesses_per_sample).
    tried: one Tried per start, in order.
    """

    phase: str = "warm"
    kept: str = ""
    entered_passage: bool = False
    more_next_sample: int = 0
    tried: list[Tried] = field(default_factory=list)

    @property
    def guesses_tried(self) -> bool:
        """Escape or passage guesses were solved at this sample."""
        return self.phase in ("escape", "passage_try") and any(t.phase == self.phase for t in self.tried)

    @property
    def cut_by_time(self) -> int:
        """Starts the sample's clock cut: solves stopped at its deadline, and starts not tried because its budget
        was spent. They depend on the machine's speed and load: a run with them may end otherwise on another
        machine (a campaign scene that converges alone fails beside a second job)."""
        return sum(t.outcome is Outcome.NOT_TRIED or t.solver_status in TIME_CUT for t in self.tried)

    @property
    def guess_taken(self) -> bool:
        """The applied plan came from an escape or passage guess (not the shifted plan)."""
        return self.guesses_tried and self.kept not in ("", "shifted")

    def render(self) -> str:
        """One line for people (diagnostics `escape`, logs): the phase and kept plan, then each start."""
        if self.phase in ("warm", "continue", "feedback") and len(self.tried) <= 1:
            return ""
        if self.phase in ("passage", "passage_ended") and len(self.tried) <= 1:
            return self.phase.replace("_", " ")
        lines = [f"{self.phase}: kept {self.kept or 'none'}"]
        for t in self.tried:
            if t.outcome is Outcome.NOT_TRIED:
                lines.append(f"{t.label}: {t.outcome}")
            elif math.isnan(t.cost):
                lines.append(f"{t.label}: unusable ({t.solver_status})")
            else:
                lines.append(f"{t.label}: cost {t.cost:.6g}, depth {t.depth:.2g}, {t.refusal or t.outcome}")
        if self.more_next_sample:
            lines.append(f"{self.more_next_sample} more next sample")
        return "; ".join(lines)


def solve_start(start: Start, par: np.ndarray, feasibility_tolerance: float) -> Candidate:
    """One solver call from `start` at the parameters `par` (its NLP's vector), judged: usable when
    finite and solved or feasible to `feasibility_tolerance` (the paper's recursive feasibility needs
    feasibility, not optimality); cost and depth evaluated for a usable one."""
    nlp = start.nlp
    if not (np.all(np.isfinite(start.w0)) and np.all(np.isfinite(par))):
        # never handed to a solver: FATROP loops without end on a NaN guess (measured)
        return Candidate(start.label, nlp, start.w0, start.lam_x0, start.lam_g0, NON_FINITE_GUESS, 0, 0.0,
                         False, False, False, False)
    tier = nlp.capacity if isinstance(nlp, TieredNlp) else None  # where TieredNlp.solve runs it
    w, lam_x, lam_g, stats, seconds = nlp.solve(start.w0, par, start.lam_x0, start.lam_g0, cold=start.cold,
                                                time_limit=start.time_limit)
    status = str(stats.get("return_status", "unknown"))
    iterations = int(stats.get("iter_count", -1))
    solved = status in SOLVED
    budget_cut = status in BUDGET_EXHAUSTED or (not solved and iterations >= start.budget)
    finite = bool(np.all(np.isfinite(w)))
    usable = finite and (solved or nlp.violation(w, par) <= feasibility_tolerance)
    candidate = Candidate(start.label, nlp, w, lam_x, lam_g, status, iterations, seconds, solved, usable,
                          budget_cut, finite, tier=tier)
    if usable:
        candidate.cost = plan_cost(nlp, w, par)
        candidate.depth = nlp.max_depth(w, par)
    return candidate


def depth_allowance(initial_depth: float) -> float:
    """The depth [g] a plan may predict and count as clear, given the depth of the region rows at its x(0)
    (measured, not decided) where x(0) lies in a keep-in margin's band only (inside the keep-in sets themselves;
    the caller tells, core/sample/fallback.py `allowance`): VIOLATION_TOLERANCE, or that depth plus it where it
    is deeper than the tolerance. Every plan's first slack holds x(0)'s rows, so judged by the absolute depth every plan
    from a state in the band "penetrates", and the search went on to the escape guesses: the live mobile
    robot's searches at its speed limit took 0.13-0.21 s instead of ~15 ms. A state outside a keep-in set, or
    in an obstacle's margin, is judged as before: its plans penetrate, and the guard says whether it can be
    left."""
    return VIOLATION_TOLERANCE + (initial_depth if initial_depth > VIOLATION_TOLERANCE else 0.0)


def plan_cost(nlp: NlpBase, w: np.ndarray, par: np.ndarray) -> float:
    """V_o + V_a + tracking of the plan w (the paper's cost, with the penalty's max(0, g)^2)."""
    return float(sum(float(term[0]) for term in nlp.terms(w, par)))


def search(starts: Iterable[Start], par: np.ndarray, time_left: float, report: SearchReport, phase: str,
           feasibility_tolerance: float, base: Candidate | None = None,
           admit: Callable[[Candidate], str] | None = None, stop_at_clear: bool = False,
           allowance: float = VIOLATION_TOLERANCE) -> tuple[Candidate | None, Candidate | None, float]:
    """Solve the starts in order within `time_left` s; the best admitted usable candidate by `Candidate.rank`
    (`base`, an earlier phase's plan, competes and is kept on a tie); a candidate is clear within `allowance`
    (`depth_allowance` of the sample's x(0)).

    Returns (best or None, the last candidate solved (the caller's fallback reads a budget-cut iterate
    from it), seconds spent). Each start appends a Tried line to `report` under `phase`.
    """
    best, last, spent, slowest = base, None, 0.0, 0.0
    best_line = next((line for line in reversed(report.tried) if base is not None and line.label == base.label
                      and line.outcome is Outcome.KEPT), None)
    for start in starts:
        if last is not None and spent + slowest >= time_left:
            report.tried.append(Tried(start.label, phase, outcome=Outcome.NOT_TRIED))
            continue
        candidate = last = solve_start(start, par, feasibility_tolerance)
        candidate.allowance = allowance
        spent += candidate.seconds
        slowest = max(slowest, candidate.seconds)
        line = Tried(candidate.label, phase, candidate.solver_status, candidate.cost, candidate.depth,
                     candidate.seconds, tier=candidate.tier)
        report.tried.append(line)
        if not candidate.usable:
            line.outcome = Outcome.UNUSABLE
            continue
        refused = admit(candidate) if admit is not None else ""
        if refused:
            line.outcome, line.refusal = Outcome.REFUSED, refused
            continue
        line.outcome = Outcome.WORSE
        if best is None or candidate.rank() < best.rank():
            if best_line is not None:
                best_line.outcome = Outcome.WORSE
            best, best_line, line.outcome = candidate, line, Outcome.KEPT
        if stop_at_clear and best is candidate and candidate.clear:
            break
    return best, last, spent
