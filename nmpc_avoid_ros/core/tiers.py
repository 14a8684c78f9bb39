"""Ellipse tiers: smaller copies of the regular NLP for samples with few regions.

Why: the region capacity (max_ellipses, max_polygons) is structure. Every slot adds a penalty
slack per stage, used or not (an empty slot's region function is a constant below zero), and a
structure-exploiting solver such as FATROP pays for each: its Riccati recursion grows with the
cube of the stage's controls, which carry the slacks, and the inactive rows cost interior-point
iterations. Measured on the mobile robot at N = 20 among 4 ellipses (FATROP, compiled): 7.6 ms a
sample with the shipped 6 ellipse + 3 polygon slots, 3.6 ms with 4 ellipse slots.

What: for each capacity k in `ellipse_tiers`, the same problem with k ellipse slots and no polygon
slots, built once in the controller's constructor (nothing is built at run time). A sample whose
regions are ellipses only, at most k of them, solves the smallest tier that holds them; its plan
(inputs, states, y_a) is written back in the regular NLP's layout, with the slacks filled from the
full parameter vector, so everything after the solve (escape, fallback, certificate, the next warm
start) sees the regular NLP. The tiers' parameter vectors are the regular one with the shorter
slot block: the problem is the same, only the empty slots are missing.

The escape guesses (core/candidates.py) are solved on the tier too, the plan kept written back
the same way, and so is a start without a plan (`cold_start`: FATROP from two guesses; the
reference solves it only if neither is usable). Not used: in the passage mode (its own
NLP), or after a budget-cut sample (its iterate is continued by the regular NLP).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from .candidates import Guess, Solution, guess_w, plan_cost
from .models import Model
from .nlp import NlpBase
from .regions import Ellipse, Region
from .settings import ControllerSettings
from .stagewise import COLD_START_ITERATIONS
from .step_result import Attempt, attempt


class Tiers:
    """The tier NLPs of one controller (none when `ellipse_tiers` is empty)."""

    def __init__(self, settings: ControllerSettings, model: Model, regular: NlpBase,
                 make_nlp: Callable[[ControllerSettings, Model], NlpBase]) -> None:
        self.regular = regular
        self.nlps: list[tuple[int, NlpBase]] = [
            (k, make_nlp(settings.replace(max_ellipses=k, max_polygons=0, ellipse_tiers=()), model))
            for k in sorted(set(settings.ellipse_tiers))]
        # the parameter vector before the slot block: x0, y_t, kappa, mu, weights, keep-in flags
        self._prefix = _parameter_count(regular) - regular.slot_layout.size

    @property
    def solver_builds(self) -> int:
        return sum(nlp.solver_builds for _, nlp in self.nlps)

    def pick(self, regions: Sequence[Region]) -> NlpBase | None:
        """The smallest tier that holds the regions (ellipses only), or None (the regular NLP)."""
        if not self.nlps or any(not isinstance(r, Ellipse) for r in regions):
            return None
        return next((nlp for k, nlp in self.nlps if len(regions) <= k), None)

    def parameters(self, par: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """A tier's parameter vector: the regular `par` with its slot block replaced by the tier's `slots`."""
        return np.concatenate([par[:self._prefix], slots])

    def to_regular(self, tier: NlpBase, w: np.ndarray, x: np.ndarray, par: np.ndarray) -> np.ndarray:
        """A tier's solution w in the regular NLP's layout, its slacks filled at the regular `par`."""
        U, X, y_a, rest = tier.layout.split_w(w)
        return self.regular.fill_slacks(self.regular.layout.join_w(U, X, y_a, rest, x0=x), par)

    def solve(self, tier: NlpBase, w0: np.ndarray, x: np.ndarray, par: np.ndarray, slots: np.ndarray,
              settings: ControllerSettings) -> Attempt:
        """Solve `tier` from w0 [its n_w] with its parameters (`parameters`); the outcome as an Attempt
        of the regular NLP: w in its layout, multipliers zero (FATROP and IPOPT as configured here do not
        read initial multipliers; the SQP paths start their QPs cold on a tier)."""
        tier_par = self.parameters(par, slots)
        result = attempt(tier, tier.fill_slacks(w0, tier_par), tier_par, np.zeros(tier.layout.n_w),
                         np.zeros(tier.lbg.size), settings.max_iterations, settings.feasibility_tolerance)
        return self._as_regular(result, x, par)

    def cold_start(self, tier: NlpBase, guesses: Sequence[Guess], x: np.ndarray, par: np.ndarray, slots: np.ndarray,
                   settings: ControllerSettings, clear_depth: float) -> tuple[Attempt | None, list[str], float]:
        """A start without a plan, solved on `tier` from the guesses in turn (candidates.EscapeGuesses.cold_guesses)
        until one gives a usable plan that predicts no penetration beyond `clear_depth`.

        Returns that plan, else the best of those tried (a clear one first, then the lowest cost, as
        candidates.lowest_cost), as an Attempt of the regular NLP whose solve_time counts every solve,
        or None when no guess gave a usable plan (the reference solves the start then); one report
        line per guess tried; the seconds all solves took. A guess is not started once the solves have
        spent the sample's `max_solve_time` (FATROP cannot be stopped by the clock).
        """
        tier_par = self.parameters(par, slots)
        best, best_rank, label, spent, report = None, (True, math.inf), "", 0.0, []
        for guess in guesses:
            if spent >= settings.max_solve_time:
                report.append(f"{guess.label}: not tried (sample budget spent)")
                continue
            result = attempt(tier, guess_w(tier, x, tier_par, guess), tier_par, np.zeros(tier.layout.n_w),
                             np.zeros(tier.lbg.size), max(settings.max_iterations, COLD_START_ITERATIONS),
                             settings.feasibility_tolerance, cold=True)
            spent += result.solve_time
            if not result.usable:
                report.append(f"{guess.label}: unusable ({result.solver_status})")
                continue
            cost, depth = plan_cost(tier, result.w, tier_par), tier.max_depth(result.w, tier_par)
            report.append(f"{guess.label}: cost {cost:.6g}, depth {depth:.2g}")
            rank = (depth > clear_depth, cost)
            if best is None or rank < best_rank:
                best, best_rank, label = result, rank, guess.label
            if depth <= clear_depth:
                break
        if best is None:
            return None, report, spent
        best = self._as_regular(best, x, par)
        best.solve_time = spent
        return best, [f"cold start: {label}"] + report, spent

    def _as_regular(self, result: Attempt, x: np.ndarray, par: np.ndarray) -> Attempt:
        """A tier's Attempt as one of the regular NLP: w in its layout, multipliers zero."""
        regular = self.regular
        result.w = self.to_regular(result.nlp, result.w, x, par) if result.finite else \
            np.full(regular.layout.n_w, np.nan)
        result.lam_x, result.lam_g, result.nlp = np.zeros(regular.layout.n_w), np.zeros(regular.lbg.size), regular
        return result

    def regular_solution(self, solution: Solution, x: np.ndarray, par: np.ndarray) -> Solution:
        """An escape candidate solved on a tier as a Solution of the regular NLP (multipliers zero)."""
        regular = self.regular
        return Solution(self.to_regular(solution.nlp, solution.w, x, par), np.zeros(regular.layout.n_w),
                        np.zeros(regular.lbg.size), regular, solution.solved, solution.cost, solution.depth,
                        solution.label)


def _parameter_count(nlp: NlpBase) -> int:
    """Length of the NLP's parameter vector (its solver's 'p' input)."""
    return int(nlp.solver.size1_in(nlp.solver.index_in("p")))
