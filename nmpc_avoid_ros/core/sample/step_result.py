"""What one controller sample returns (StepResult), the plan it keeps, and input validation.

Split from core/sample/controller.py so that the controller module holds the sample's logic only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..nlp.search import SearchReport
from .status import FeedbackOutcome, StepStatus

#: StepResult.terminal_inside: how far beyond the terminal set's level (relative) x(N) still counts as inside
INSIDE_TOLERANCE = 1e-6


@dataclass
class StepResult:
    """Outcome of one sample.

    Attributes:
        u: command to apply now [m].
        states: predicted states x(0..N) [N+1, n] (x(0) the measurement).
        inputs: predicted inputs u(0..N-1) [N, m].
        y_a, x_a, u_a: artificial steady output [p], state [n], input [m].
        offset_cost, avoidance_cost, tracking_cost: V_o, V_a and the stage-cost sum of the plan.
        status: what was applied (core/sample/status.py): ok (solved), truncated (budget cut, feasible
            iterate used), unconverged (the solver stopped short on its own, e.g. a failed line search;
            feasible iterate used; solver_status says why), fallback_shift, fallback_steady, fallback_safe
            or fallback_recovery (see core/sample/fallback.py).
        solver_status: the solver's own return status.
        iterations: solver iterations; solve_time: wall time of the solve in s.
        budget_exhausted: True when the iteration or time budget cut the solve.
        search: what the sample's search tried (core/nlp/search.py: phase, kept plan, one line per start);
            `escape` renders it for people.
        horizon: stages of the NLP solved (or attempted) at this sample: the regular N, or
            escape_horizon in the passage mode (0: no solve, e.g. `coast`).
        fallback_reason: for a fallback, which candidate was applied and every candidate's
            predicted violation, for people; fallback_predicted: the same as data (candidate -> predicted
            violation, region g / state units); predicted_violation: the applied one's.
        target: the output y* [p] the NLP tracked: y_t, or for a y_t out of reach its nearest
            reachable output (core/nlp/projection.py); None where no sample was solved (`coast`).
        region_unavoidable: the solved plan predicts a violation beyond VIOLATION_TOLERANCE (a
            region cannot be avoided from this state): the least-violating input was applied.
        margin_unavoidable: every candidate violates the regions as planned around (inflated by the
            margins), but one keeps clear of the regions themselves: not a region_unavoidable.
        delay: s the measured state was predicted over (core/sample/latency.py); measured_state: that
            state [n] (states[0] is the predicted one); None where no sample was solved (`coast`).
        feedback: what became of the plan prepared for this sample (core/sample/feedback.py); None: none was.
        feedback_time: s from the sample's start to its command when the prepared plan answered (0 otherwise);
        preparation_time: s the preparation of this sample took between the samples (solver calls and the law);
            solve_time counts both, with the solver time of a search the sample ran itself.
        terminal_cost, terminal_level: with `terminal: set`, V_f(x(N) - x_a, y_a) of the applied plan's last state
            states[-1] and alpha(y_a), the terminal set's level (docs/terminal_set.md); NaN with the equality or
            without y_a. `terminal_inside`: V_f <= alpha to INSIDE_TOLERANCE (None where they are NaN).
    """

    u: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    y_a: np.ndarray
    x_a: np.ndarray
    u_a: np.ndarray
    offset_cost: float
    avoidance_cost: float
    tracking_cost: float
    status: StepStatus
    solver_status: str
    iterations: int
    solve_time: float
    budget_exhausted: bool = False
    search: SearchReport = field(default_factory=SearchReport)
    fallback_reason: str = ""
    predicted_violation: float = math.nan
    region_unavoidable: bool = False
    horizon: int = 0
    target: np.ndarray | None = None
    margin_unavoidable: bool = False
    fallback_predicted: dict[str, float] = field(default_factory=dict)
    delay: float = 0.0
    measured_state: np.ndarray | None = None
    feedback: FeedbackOutcome | None = None
    feedback_time: float = 0.0
    preparation_time: float = 0.0
    terminal_cost: float = math.nan
    terminal_level: float = math.nan

    @property
    def terminal_inside(self) -> bool | None:
        """x(N) in the terminal set: the NLP's row V_f / alpha - 1 <= INSIDE_TOLERANCE (a plan on the set's boundary
        meets it to the solver's tolerance); None with the equality (no set) or without a plan."""
        if math.isnan(self.terminal_cost) or math.isnan(self.terminal_level):
            return None
        return self.terminal_cost / self.terminal_level - 1 <= INSIDE_TOLERANCE

    @property
    def escape(self) -> str:
        """The search report rendered for people (diagnostics); '' for an ordinary warm sample."""
        return self.search.render()

    @property
    def is_fallback(self) -> bool:
        return StepStatus(self.status).is_fallback

    @property
    def answered(self) -> bool:
        """Its prepared plan gave the command (the law or the QP, core/sample/feedback.py): no search ran."""
        return self.feedback is not None and self.feedback.answered


@dataclass
class Plan:
    """The last accepted solution and how many samples ago it was computed."""

    inputs: np.ndarray
    states: np.ndarray
    y_a: np.ndarray
    x_a: np.ndarray
    u_a: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    age: int = 0
    costs: tuple[float, float, float] = field(default=(math.nan, math.nan, math.nan))
    #: with `terminal: set`, the plan continued after x(N) by the local controller kappa (core/nlp/terminal.py
    #: ShiftedTail.rollout): inputs [K, m] and the states x(N+1..N+K) [K, n]; None: it rests at (u_a, x_a)
    tail: tuple[np.ndarray, np.ndarray] | None = None
    #: the slack variables as its solver left them (id of the NLP that solved it, values in that NLP's order), or
    #: None: a law rebuilds them as max(0, depth), which misses the solver's by its tolerance, and with mu = 1e8 a
    #: slack off by 5e-9 moves the cost's gradient by 1 (core/sample/feedback.py)
    slacks: tuple[int, np.ndarray] | None = None

    def shifted(self, by: int) -> tuple[np.ndarray, np.ndarray]:
        """The plan seen `by` >= 0 samples later: (inputs [N, m]: u(by..N-1), then the tail's, then u_a; states
        [N+1, n]: x(by..N), then the tail's, then x_a). by = 0 gives copies of inputs and states; the warm start
        shifts by age + 1 (a prepared plan's age is -1: core/sample/feedback.py), an applied plan by its age."""
        if self.tail is None:
            return shifted_rows(self.inputs, self.u_a, by), shifted_rows(self.states, self.x_a, by)
        N = len(self.inputs)
        return (shifted_rows(np.vstack([self.inputs, self.tail[0]]), self.u_a, by)[:N],
                shifted_rows(np.vstack([self.states, self.tail[1]]), self.x_a, by)[:N + 1])


def shifted_rows(rows: np.ndarray, last: np.ndarray, by: int) -> np.ndarray:
    """rows [K, d] shifted `by` >= 0 rows up and padded with last [d] to K rows: rows(by..K-1), then last.

    The one shift of a plan (Plan.shifted) and of a budget-cut iterate (core/sample/warm_start.py)."""
    if by < 0:
        raise ValueError(f"a plan shifts by 0 or more samples, not {by}")
    rows = np.asarray(rows, float)
    if by == 0:  # an applied plan as it is: every answered sample's (np.tile and vstack of nothing cost ~10 us)
        return rows.copy()
    kept = rows[by:]
    return np.vstack([kept, np.tile(last, (len(rows) - len(kept), 1))])


def validate_vector(name: str, values: Sequence[float] | np.ndarray, size: int, max_abs: float = 1e12) -> np.ndarray:
    """A finite float vector of exactly `size` entries, each within +-`max_abs`, else InputError naming the problem.

    The magnitude bound refuses values that are finite but absurd: a target or state of 1e300 overflows
    the NLP's squared costs, and the solver would then fail at every sample until the next good value.
    """
    if isinstance(values, (str, bytes)):  # numpy would read "1.5" as the number 1.5
        raise InputError(f"{name}: data is not a sequence of numbers (got a {type(values).__name__})")
    try:
        arr = np.array(values, dtype=float).ravel()  # a copy, never a view of the caller's buffer
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float range
        raise InputError(f"{name}: data is not a sequence of numbers") from None
    if arr.size != size:
        raise InputError(f"{name}: expected {size} values, got {arr.size}")
    # one pass that also refuses NaN (no comparison holds) and inf; for a state's few entries a Python loop is
    # ~10x cheaper than numpy's dispatch (every answered sample validates two or three vectors)
    if not all(-max_abs <= v <= max_abs for v in arr.tolist()):
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{name}: contains NaN or infinite values")
        raise InputError(f"{name}: values must be within +-{max_abs:g}, got {arr.tolist()}")
    return arr
