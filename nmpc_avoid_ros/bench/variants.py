"""What a benchmark variant is: something that, given a measured state, returns a command.

Every variant (our controller with any solver path, the paper's Opti + IPOPT formulation,
do-mpc) is driven through the same `Stepper` protocol by the same closed loop
(`run_variant`), so their solve times and closed-loop quality are comparable sample by sample.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..core.closed_loop import ContinuousPlant, DiscretePlant
from ..core.controller import NmpcController
from ..core.models import Model
from ..core.regions import Region
from ..core.settings import ControllerSettings


@dataclass
class Sample:
    """One sample of a variant.

    Attributes:
        u: command applied [m].
        solve_time: wall time of the solver call alone, s.
        iterations: solver iterations (-1 if the solver does not say).
        failed: the solver returned no usable solution (whatever the variant then applied).
        fallback: the variant applied a fallback instead of a fresh solution.
        budget_exhausted: the iteration or time budget cut the solve.
    """

    u: np.ndarray
    solve_time: float
    iterations: int
    failed: bool = False
    fallback: bool = False
    budget_exhausted: bool = False


class Stepper(Protocol):
    """A controller under test. Built once per scenario (building is not timed)."""

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None) -> Sample:
        """Command for the measured state x [n] and target y_t [p]; regions replace the current set if not None."""
        ...


#: a factory builds a fresh stepper for (settings, model); variants are named factories
StepperFactory = Callable[[ControllerSettings, Model], Stepper]


class OursStepper:
    """Our NmpcController (any solver path of the settings) as a Stepper."""

    def __init__(self, settings: ControllerSettings, model: Model | None = None) -> None:
        self.controller = NmpcController(settings, model)

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None) -> Sample:
        res = self.controller.step(x, y_t, regions)
        return Sample(res.u, res.solve_time, res.iterations, failed=res.status not in ("ok", "truncated"),
                      fallback=res.is_fallback, budget_exhausted=res.budget_exhausted)


@dataclass
class VariantRun:
    """A closed loop of one variant: x [K+1, n], u [K, m], per-sample solve time (s) and iterations."""

    x: np.ndarray
    u: np.ndarray
    targets: np.ndarray
    solve_time: np.ndarray
    iterations: np.ndarray
    failed: np.ndarray
    fallback: np.ndarray
    budget_exhausted: np.ndarray
    regions: list[tuple[Region, ...]] = field(default_factory=list)


def run_variant(stepper: Stepper, model: Model, settings: ControllerSettings, x0: Sequence[float],
                target: Sequence[float], steps: int, plant: str = "euler",
                regions: Callable[[int], Sequence[Region] | None] | None = None) -> VariantRun:
    """Closed loop of `steps` samples with the 'euler' (prediction model) or 'continuous' plant.

    `regions(k)` gives the region set of sample k (None keeps the current one); the set in force
    at each sample is kept in the result for the quality figures.
    """
    if plant == "euler":
        sim = DiscretePlant(model, settings.sample_time, settings.discretization)
    else:
        sim = ContinuousPlant(model)
    x = np.asarray(x0, float)
    y_t = np.asarray(target, float)
    xs, us, times, iters, failed, fallback, cut, in_force = [x], [], [], [], [], [], [], []
    current: tuple[Region, ...] = ()
    for k in range(steps):
        new = regions(k) if regions else None
        if new is not None:
            current = tuple(new)
        sample = stepper.step(x, y_t, new)
        x = sim.advance(x, sample.u, settings.sample_time)
        xs.append(x)
        us.append(np.asarray(sample.u, float))
        times.append(sample.solve_time)
        iters.append(sample.iterations)
        failed.append(sample.failed)
        fallback.append(sample.fallback)
        cut.append(sample.budget_exhausted)
        in_force.append(current)
    return VariantRun(np.array(xs), np.array(us), np.tile(y_t, (steps, 1)), np.array(times), np.array(iters),
                      np.array(failed), np.array(fallback), np.array(cut), in_force)
