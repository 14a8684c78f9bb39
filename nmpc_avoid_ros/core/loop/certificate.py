"""Online stability certificate: the value-function decrease of the paper's proof, checked per sample.

docs/certificate.md derives it. For the nominal model (plant = prediction model), unchanged
parameters and a solver that does at least as well as the shifted candidate,

    V_N(k+1) - V_N(k) <= -l(x(k) - x_a(k), u(k) - u_a(k)) - mu F(x(k), u(k)) + mu F(x_a(k), u_a(k))

where V_N(k) = V_o + V_a + sum l is the cost of the plan applied at sample k. The right-hand side
(`decrease_bound`) is computed at sample k+1 as J(previous plan shifted, from its x(1), under the
parameters of k+1) - V_N(k), which equals the expression above term by term (a test checks it),
needs nothing but the NLP's own cost terms whatever the regions and the model, and places moving
regions at the stage times of k+1.

In the passage mode (core/sample/passage.py) the plans come from the NLP with the longer horizon: the
same inequality holds for it, and each sample is checked with the NLP of its plan's horizon. A
sample whose horizon differs from the previous one (entering or leaving the mode) is not checked:
V_N of two horizons are different functions, and their difference bounds nothing.

A violation is `decrease > decrease_bound + tolerance`, with

    tolerance = certificate_tolerance * solver tolerance * max(1, |V_N(k)|)

(the solver stops when its scaled KKT error is below its tolerance; the objective is then known to
about that relative accuracy). A sample that is not a fresh optimum (budget-cut iterate, fallback)
is scored with the cost of the plan it applied, and says so in `cost_source`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..nlp.parts import command_index
from ..nlp.terminal import ShiftedTail
from ..problem.regions import Region
from ..sample.controller import NmpcController
from ..sample.status import StepStatus
from ..sample.step_result import StepResult

#: the per-sample vector of `~/certificate` (std_msgs/Float64MultiArray), in this order
LAYOUT = ("value_function", "decrease", "decrease_bound", "margin", "tolerance", "checked", "violated",
          "certificate_violations", "consecutive_violations", "model_mismatch")

#: where the value of V_N comes from, by step status
COST_SOURCES = {StepStatus.OK: "optimal", StepStatus.TRUNCATED: "budget-cut iterate",
                StepStatus.UNCONVERGED: "unconverged iterate",
                StepStatus.FALLBACK_SHIFT: "shifted plan (fallback)",
                StepStatus.FALLBACK_STEADY: "steady plan (fallback)",
                StepStatus.FALLBACK_RECOVERY: "recovery plan (fallback)",
                StepStatus.FALLBACK_SAFE: "safe input (fallback)"}


#: inf-norm distance (state units) within which a fallback's plan ends at its x_a (its shift is a candidate)
REST_TOLERANCE = 1e-6


def ends_at_rest(result: StepResult) -> bool:
    """Is the plan `result` applied a candidate of the NLP once shifted: a solve's (its x(N) = x_a is its
    constraint, or the terminal set's), a shift fallback's (the last plan's), or another fallback's that ends at
    its x_a (u_a held once the plan is used up: the paper's recursive-feasibility candidate)."""
    if result.status in (StepStatus.FALLBACK_RECOVERY, StepStatus.FALLBACK_SAFE, StepStatus.FALLBACK_STEADY):
        return bool(np.all(np.isfinite(result.x_a))
                    and np.max(np.abs(result.states[-1] - result.x_a)) <= REST_TOLERANCE)
    return True


@dataclass(frozen=True)
class CertificateSample:
    """The check at one sample.

    value_function: V_N of the plan applied at this sample (nan without a plan).
    decrease: V_N(k) - V_N(k-1); decrease_bound: the previous sample's bound; both nan when unchecked.
    tolerance: the allowance added to the bound; checked: whether the inequality applied here;
    reason: why not ('' when checked); violated: decrease > bound + tolerance;
    cost_source: what V_N is the cost of (see COST_SOURCES); violations: running count;
    consecutive: violations in a row up to this sample; error_after: the settings'
    certificate_error_after (that many in a row are an ERROR); model_mismatch: max |x(k) - x_pred(k)|
    between the measured state and the previous plan's x(1), the candidate's start (0 for the
    nominal model up to the solver's constraint tolerance; nan when there was no previous plan);
    changed: what changed when the check restarted for changed parameters ('target', 'regions', 'weights',
    'obstacle settings'; () otherwise), the data `reason` renders.
    """

    value_function: float
    decrease: float
    decrease_bound: float
    tolerance: float
    checked: bool
    reason: str
    violated: bool
    cost_source: str
    violations: int
    consecutive: int
    error_after: int = 3
    model_mismatch: float = math.nan
    changed: tuple[str, ...] = ()

    @property
    def margin(self) -> float:
        """decrease_bound + tolerance - decrease: negative exactly when violated (nan if unchecked)."""
        return self.decrease_bound + self.tolerance - self.decrease if self.checked else math.nan

    @property
    def level(self) -> str:
        """'ok', 'warn' (a violation) or 'error' (error_after or more in a row)."""
        if not self.violated:
            return "ok"
        return "error" if self.consecutive >= self.error_after else "warn"

    def as_vector(self) -> list[float]:
        """The values in LAYOUT order (booleans as 0/1)."""
        return [self.value_function, self.decrease, self.decrease_bound, self.margin, self.tolerance,
                float(self.checked), float(self.violated), float(self.violations), float(self.consecutive),
                self.model_mismatch]

    def as_dict(self) -> dict:
        """LAYOUT's values (nan -> None, so the JSON is strict), plus reason, changed and cost_source."""
        values = {k: (None if math.isnan(v) else v) for k, v in zip(LAYOUT, self.as_vector())}
        return {**values, "checked": self.checked, "violated": self.violated, "reason": self.reason,
                "changed": list(self.changed), "cost_source": self.cost_source, "level": self.level}


#: two poses of a region agree when their numbers do to this (relative and absolute; stamps are float
#: seconds of a ~1e9 s clock, resolved to ~2e-7 s)
POSE_TOLERANCE = 1e-6


def _numbers(value: object) -> list:
    """The numbers and strings of a nested dataclass tuple, flattened."""
    if isinstance(value, (tuple, list)):
        return [v for item in value for v in _numbers(item)]
    return [value]


def same_trajectory(a: Region, b: Region, time: float | None) -> bool:
    """The same region moving the same way: equal, or (moving) equal poses at `time` and equal velocities.

    An obstacle re-published with a new stamp and the centre it has then is the same trajectory.
    """
    if a == b:
        return True
    if type(a) is not type(b) or time is None or not (a.moving or b.moving):
        return False
    pa, pb = _numbers(dataclasses.astuple(a.at(time))), _numbers(dataclasses.astuple(b.at(time)))
    if len(pa) != len(pb) or [v for v in pa if isinstance(v, str)] != [v for v in pb if isinstance(v, str)]:
        return False
    fa = np.array([v for v in pa if not isinstance(v, str)], float)
    fb = np.array([v for v in pb if not isinstance(v, str)], float)
    return bool(np.allclose(fa, fb, rtol=POSE_TOLERANCE, atol=POSE_TOLERANCE))


def what_changed(previous: tuple, key: tuple, time: float | None, target_size: int) -> tuple[str, ...]:
    """() when Assumption P holds between two samples, else what changed ('target', 'regions', ...).

    key = (parameters but x(0) and the slots: y_t [target_size] first, then the weights; the regions;
    the prediction switch; region_margin; the mismatch margin). Equal regions are `same_trajectory`, in order."""
    changes = []
    if not np.array_equal(previous[0][:target_size], key[0][:target_size]):
        changes.append("target")
    if len(previous[1]) != len(key[1]) or not all(same_trajectory(a, b, time) for a, b in zip(previous[1], key[1])):
        changes.append("regions")
    if not np.array_equal(previous[0][target_size:], key[0][target_size:]):
        changes.append("weights")
    if previous[2:] != key[2:]:
        changes.append("obstacle settings")
    return tuple(changes)


@dataclass
class _Previous:
    """What the next sample is checked against: V_N of this one, its parameter key and its plan."""

    value: float
    key: tuple
    result: StepResult


class StabilityCertificate:
    """Checks the decrease inequality sample after sample for one controller.

    Call `observe(result, y_t, time)` right after each `controller.step` (same regions, settings and
    time as the step used), `skip(reason)` for a sample without a solve (no new state, stale state).
    """

    def __init__(self, controller: NmpcController) -> None:
        self.controller = controller
        self.violations = 0
        self.consecutive = 0
        self._previous: _Previous | None = None
        #: the candidate's last input and state: u_a, x_a (equality) or kappa(x(N)), f(x(N), kappa) (terminal set)
        self.tail = ShiftedTail(controller.settings, controller.model)

    def reset(self) -> None:
        """Forget the previous sample (the next one is not checked)."""
        self._previous = None

    def skip(self, reason: str) -> CertificateSample:
        """A sample without a solve: not checked, and the next one is not either."""
        self._previous = None
        return CertificateSample(math.nan, math.nan, math.nan, math.nan, False, reason, False, "none",
                                 self.violations, self.consecutive)

    def observe(self, result: StepResult, y_t: np.ndarray, time: float | None = None) -> CertificateSample:
        """Score the sample whose step gave `result` for target y_t [p] at `time` (s, as given to the step)."""
        source = COST_SOURCES.get(result.status, str(result.status))
        n, N = self.controller.model.n, result.inputs.shape[0]
        if not np.all(np.isfinite(result.y_a)) or result.states.shape[0] != N + 1 or \
                self.controller.nlp_of_horizon(N) is None:
            return self.skip(f"no plan of horizon {self.controller.nlp.layout.horizon} ({source})")
        # V_N of the problem the sample solved: for a y_t out of reach, that of its projection y* (result.target);
        # costed against the raw y_t, the offset of a plan settling onto y* moved V_N up and down by the solver's
        # tolerance (214 "violations" in the robot campaign, whose goals are partly outside the box)
        tracked = y_t if result.target is None else result.target
        par = self.controller.parameters(result.states[0], tracked, time)
        value = self.plan_cost(result.states, result.inputs, result.y_a, result.x_a, result.u_a, par)
        # what must stay equal (Assumption P): the parameters but x(0) and the slots' time-dependent
        # packing, and the regions themselves (a moving one is the same trajectory while its
        # stamp and velocity are)
        s = self.controller.settings
        slot_size = self.controller.nlp.slot_layout.size
        commanded = command_index(par.size, slot_size, self.controller.model.m, bool(s.input_rate_max))
        # with input_rate_max the command in force is state, as x(0) is: the plan's u(0) moves it every sample
        # (before, every sample of a rate-limited loop was "parameters changed": unchecked)
        key = (np.delete(par[n:par.size - slot_size], commanded - n), self.controller.regions, s.predict_obstacles,
               s.region_margin, self.controller.mismatch_margin)
        changed = what_changed(self._previous.key, key, time, len(tracked)) if self._previous is not None else ()
        previous, self._previous = self._previous, _Previous(value, key, result)
        if previous is None:
            return self._unchecked(value, source, "first sample")
        plan = previous.result
        mismatch = float(np.max(np.abs(result.states[0] - plan.states[1])))
        if plan.inputs.shape[0] != N:
            return self._unchecked(value, source, f"horizon switched ({plan.inputs.shape[0]} -> {N}, passage mode)",
                                   mismatch)
        if not ends_at_rest(plan):
            # the shifted plan is the bound's candidate only where it is one of the NLP (x(N) = x_a): a recovery or
            # safe fallback's inputs, or u_a held from x before the plan was used up, end elsewhere (campaign
            # vdp-0173: the sample after a first-sample recovery was "violated" by 9.1e3 in 1.6e7)
            return self._unchecked(value, source, f"after a fallback whose plan is no candidate ({plan.status})",
                                   mismatch)
        if changed:
            # the decrease holds under unchanged parameters only: the check restarts from here
            return self._unchecked(value, source, f"parameters changed ({', '.join(changed)}): check restarted",
                                   mismatch, changed)
        # the previous plan shifted (u(1..N-1), u_a; x(2..N), x_a; with the terminal set kappa(x(N)) and
        # f(x(N), kappa) in place of u_a, x_a), started at its own x(1) (the nominal successor) and costed
        # with this sample's parameters (moving regions at this sample's stage times)
        candidate_par = par.copy()
        candidate_par[:n] = plan.states[1]
        if commanded.size:
            candidate_par[commanded] = plan.inputs[0]  # the nominal successor's command in force
        last_u, last_x = self.tail(plan.states[-1], plan.y_a, plan.x_a, plan.u_a)
        candidate = self.plan_cost(np.vstack([plan.states[1:], last_x[None, :]]),
                                   np.vstack([plan.inputs[1:], last_u[None, :]]), plan.y_a, plan.x_a, plan.u_a,
                                   candidate_par)
        bound = candidate - previous.value
        if not math.isfinite(value) or not math.isfinite(bound):
            return self._unchecked(value, source, "cost not finite", mismatch)
        decrease = value - previous.value
        tolerance = s.certificate_tolerance * s.tolerance * max(1.0, abs(previous.value))
        violated = decrease > bound + tolerance
        self.consecutive = self.consecutive + 1 if violated else 0
        self.violations += int(violated)
        return CertificateSample(value, decrease, bound, tolerance, True, "", violated, source,
                                 self.violations, self.consecutive, s.certificate_error_after, mismatch)

    def _unchecked(self, value: float, source: str, reason: str, mismatch: float = math.nan,
                   changed: tuple[str, ...] = ()) -> CertificateSample:
        self.consecutive = 0
        return CertificateSample(value, math.nan, math.nan, math.nan, False, reason, False, source,
                                 self.violations, self.consecutive, model_mismatch=mismatch, changed=changed)

    def plan_cost(self, states: np.ndarray, inputs: np.ndarray, y_a: np.ndarray, x_a: np.ndarray,
                  u_a: np.ndarray, par: np.ndarray) -> float:
        """V_o + V_a + sum l of a plan: states x(0..N) [N+1, n], inputs [N, m], steady triple, parameters
        (costed by the NLP of horizon N: the regular one or the passage mode's)."""
        nlp = self.controller.nlp_of_horizon(inputs.shape[0]) or self.controller.nlp
        rest = None if nlp.layout.closed_form else np.concatenate([x_a, u_a])
        w = nlp.layout.join_w(inputs, states[1:], y_a, rest, x0=states[0])
        w = nlp.fill_slacks(w, par)
        return float(sum(float(term[0]) for term in nlp.terms(w, par)))
