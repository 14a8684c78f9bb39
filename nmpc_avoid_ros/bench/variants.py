"""What a benchmark variant is: a `Stepper` (core/loop/closed_loop.py) that answers with a `Sample`.

Every variant (our controller with any solver path, the paper's Opti + IPOPT formulation,
do-mpc) is driven by the one closed-loop driver (`core.closed_loop.ClosedLoop`), the same one
`simulate`, `campaign` and the tests use, so their solve times and closed-loop quality are
comparable sample by sample.
"""

from __future__ import annotations

import math
import time as clock
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.loop.closed_loop import Stepper
from ..core.problem.models import Model
from ..core.problem.regions import Region
from ..core.sample.controller import NmpcController
from ..core.sample.status import StepStatus


@dataclass
class Sample:
    """One sample of a variant (a core.closed_loop.StepOutcome).

    Attributes:
        u: command applied [m].
        solve_time: wall time of the solver call alone, s.
        iterations: solver iterations (-1 if the solver does not say).
        failed: the solver returned no usable solution (whatever the variant then applied).
        fallback: the variant applied a fallback instead of a fresh solution.
        budget_exhausted: the iteration or time budget cut the solve.
        step_time: wall time of the whole step (validation, search, fallback), s; NaN for a peer
            that has no step beyond its solve.
    """

    u: np.ndarray
    solve_time: float
    iterations: int
    failed: bool = False
    fallback: bool = False
    budget_exhausted: bool = False
    step_time: float = math.nan


#: a factory builds a fresh stepper (answering with Samples) for (settings, model); variants are named factories
StepperFactory = Callable[[ControllerSettings, Model], Stepper]


class OursStepper:
    """Our NmpcController (any solver path of the settings) as a Stepper answering with Samples."""

    def __init__(self, settings: ControllerSettings, model: Model | None = None) -> None:
        self.controller = NmpcController(settings, model)

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None,
             time: float | None = None) -> Sample:
        begin = clock.perf_counter()
        res = self.controller.step(x, y_t, regions, time=time)
        step_time = clock.perf_counter() - begin
        return Sample(res.u, res.solve_time, res.iterations, failed=not StepStatus(res.status).is_usable,
                      fallback=res.is_fallback, budget_exhausted=res.budget_exhausted, step_time=step_time)
