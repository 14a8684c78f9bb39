"""The status of one controller sample: the one definition of the strings in results, JSON and bags.

`StepStatus` is a StrEnum: each member is its string ('ok', 'fallback_shift', ...), so it compares
equal to the text read back from a JSON file or a diagnostics message, and `json.dumps` and the
ROS messages carry the plain string. Read a recorded string back with `StepStatus(text)`.

A new fallback is added as one member named FALLBACK_<NAME> with the value 'fallback_<name>':
`is_fallback` recognises it by that prefix (diagnostics then report it as a WARN and count it).
"""

from __future__ import annotations

from enum import StrEnum


class StepStatus(StrEnum):
    """What one sample applied."""

    #: solved: the solver's solution is applied
    OK = "ok"
    #: the iteration or time budget cut the solve; its iterate is applied because it is feasible
    TRUNCATED = "truncated"
    #: the solver stopped without converging and without a budget cut (e.g. FATROP's line search gave up:
    #: the result's solver_status says why); its iterate is applied because it is feasible
    UNCONVERGED = "unconverged"
    #: no usable solve: the next input of the shifted previous plan (the paper's feasibility candidate)
    FALLBACK_SHIFT = "fallback_shift"
    #: no usable solve and the previous plan is used up: its steady input u_a
    FALLBACK_STEADY = "fallback_steady"
    #: no usable solve and no plan at all: the safe input (zero clipped to the input box)
    FALLBACK_SAFE = "fallback_safe"
    #: every other candidate predicts a violation: a short solve minimising it (core/sample/fallback.py)
    FALLBACK_RECOVERY = "fallback_recovery"

    @property
    def is_fallback(self) -> bool:
        """The sample did not apply a solve of this sample's problem."""
        return self.value.startswith("fallback_")

    @property
    def is_usable(self) -> bool:
        """The sample applied a solve (converged, or a feasible budget-cut iterate)."""
        return not self.is_fallback


class FeedbackOutcome(StrEnum):
    """What became of a prepared plan at the sample it was prepared for (StepResult.feedback)."""

    #: the prepared plan, moved to the state that arrived, gave the command
    ANSWERED = "answered"
    #: its law's active set changed, and one QP on the prepared linearisation moved it (core/sample/feedback_qp.py)
    ANSWERED_QP = "answered_qp"
    #: the preparation's plan has no law (it penetrates a region, or its KKT conditions do not hold to the
    #: tolerance of core/nlp/sensitivity.py)
    NO_LAW = "no_law"
    #: the target, a weight, the region set or a margin changed since the preparation
    INPUTS_CHANGED = "inputs_changed"
    #: an active constraint would leave its active set for this state: a new active set, searched
    ACTIVE_SET_CHANGED = "active_set_changed"
    #: the moved plan violates a constraint beyond feasibility_tolerance, or a slack beyond
    #: VIOLATION_TOLERANCE (the state is too far from the predicted one for the first-order law)
    INFEASIBLE = "infeasible"

    @property
    def answered(self) -> bool:
        """The prepared plan gave the command (by its law, or by the QP): no search ran in the sample."""
        return self in (FeedbackOutcome.ANSWERED, FeedbackOutcome.ANSWERED_QP)
