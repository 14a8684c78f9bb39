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

`TieredNlp` is that NLP for the controller: it answers every question (layout, costs, depths,
violation) as the regular NLP and solves on the smallest tier that holds the current regions,
its guess and its answer in the regular layout (multipliers zero: FATROP and IPOPT as configured
here do not read initial multipliers; the SQP paths start their QPs cold on a tier). The
controller gives it the regular start, a cold start's guesses and the escape guesses; not the
passage mode's (its own NLP) nor a budget-cut iterate (continued by the regular NLP with its
multipliers).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from ..config.settings import ControllerSettings
from ..problem.models import Model
from ..problem.regions import Ellipse, Region
from .tracking import NlpBase


class TieredNlp:
    """The regular NLP, solved on the smallest ellipse tier that holds the regions (none: itself).

    Everything but `solve` is the regular NLP's (attribute access is forwarded to it).
    """

    def __init__(self, settings: ControllerSettings, model: Model, regular: NlpBase,
                 make_nlp: Callable[[ControllerSettings, Model], NlpBase]) -> None:
        self.regular = regular
        #: (capacity, NLP) of each tier, smallest first
        self.tiers: list[tuple[int, NlpBase]] = [
            (k, make_nlp(settings.replace(max_ellipses=k, max_polygons=0, ellipse_tiers=()), model))
            for k in sorted(set(settings.ellipse_tiers))]
        # the parameter vector before the slot block: x0, y_t, kappa, mu, weights, keep-in flags
        self._prefix = regular.parameter_count - regular.slot_layout.size
        self.tier: NlpBase | None = None  # the tier of the current regions, or None
        self._regions: tuple[Region, ...] = ()
        self._static_slots: np.ndarray | None = None
        self._time: float | None = None
        self._predict = False

    def __getattr__(self, name: str):
        return getattr(self.regular, name)

    @property
    def capacity(self) -> int | None:
        """The ellipse capacity of the tier `solve` runs on now (None: the regular NLP)."""
        return next((k for k, nlp in self.tiers if nlp is self.tier), None)

    @property
    def solver_builds(self) -> int:
        return sum(nlp.solver_builds for _, nlp in self.tiers)

    def set_regions(self, regions: Sequence[Region]) -> None:
        """Pick the smallest tier that holds the regions (ellipses only) and pack its static slots once."""
        self._regions = tuple(regions)
        self.tier = None
        if self.tiers and all(isinstance(r, Ellipse) for r in regions):
            self.tier = next((nlp for k, nlp in self.tiers if len(regions) <= k), None)
        self._static_slots = None if self.tier is None else self.tier.slot_layout.pack(
            list(regions), self.tier.output_frame_available, predict=False)

    def set_time(self, time: float | None, predict: bool) -> None:
        """The sample's time (s) for moving regions, and whether they are predicted (predict_obstacles)."""
        self._time, self._predict = time, predict

    def tier_parameters(self, par: np.ndarray) -> np.ndarray:
        """The tier's parameter vector: the regular `par` with its slot block replaced by the tier's."""
        tier = self.tier
        assert tier is not None
        moving = self._predict and any(r.moving for r in self._regions)
        slots = tier.slot_layout.pack(list(self._regions), tier.output_frame_available, self._time) if moving \
            else self._static_slots
        return np.concatenate([par[:self._prefix], slots])

    def holding(self, nlp: NlpBase, par: np.ndarray) -> tuple[NlpBase, np.ndarray]:
        """The NLP a plan of `nlp` at parameters `par` is answered on, and its parameters: where `nlp` is the regular
        NLP, the tier that holds the regions (the same problem without the empty slots), else `nlp` itself (a
        prepared plan's feedback law, core/sample/feedback.py)."""
        tier = self.tier
        return (tier, self.tier_parameters(par)) if nlp is self.regular and tier is not None else (nlp, par)

    def solve(self, w0: np.ndarray, par: np.ndarray, lam_x0: np.ndarray, lam_g0: np.ndarray, cold: bool = False,
              time_limit: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, float]:
        """NlpBase.solve in the regular layout, on the tier where one holds the regions (multipliers zero)."""
        tier, regular = self.tier, self.regular
        if tier is None:
            return regular.solve(w0, par, lam_x0, lam_g0, cold=cold, time_limit=time_limit)
        tier_par = self.tier_parameters(par)
        U, X, y_a, rest = regular.layout.split_w(w0)
        x0 = par[:regular.layout.n]
        guess = tier.fill_slacks(tier.layout.join_w(U, X, y_a, rest, x0=x0), tier_par)
        w, _, _, stats, seconds = tier.solve(guess, tier_par, np.zeros(tier.layout.n_w), np.zeros(tier.lbg.size),
                                             cold=cold, time_limit=time_limit)
        if np.all(np.isfinite(w)):
            U, X, y_a, rest = tier.layout.split_w(w)
            w = regular.fill_slacks(regular.layout.join_w(U, X, y_a, rest, x0=x0), par)
        else:
            w = np.full(regular.layout.n_w, np.nan)
        return w, np.zeros(regular.layout.n_w), np.zeros(regular.lbg.size), stats, seconds
