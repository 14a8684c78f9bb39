"""The controller's verdicts on its latched inputs (`target`, `goal_pose`, `obstacles`), as data.

Per input the node counts the messages it received and keeps its verdict on the last one: accepted,
or refused with the reason. /diagnostics carries them under structured keys, three per input:
`<input>_received` (count since configure), `<input>_verdict` (`none` before any message, `accepted`,
`refused`) and `<input>_reason` (why the last one was refused; empty otherwise); for the targets
(`target`, `goal_pose`) also `<input>_applied`, the last APPLIED_HISTORY values applied, oldest first (a
JSON list of lists). A MarkerArray with a refused marker is refused (the reasons of its refused markers,
`; `-joined); the others in it still apply. `send` (tools/send.py) reads these keys to tell its user what
became of its message.

The last issue with an obstacle (a refused marker, a reset velocity estimate, a stored region a view could
not move) is an ObstacleIssue: diagnostics `last_obstacle_kind`, `last_obstacle_marker`,
`last_obstacle_reason`, and rendered for people as `last_obstacle_issue`.
"""

from __future__ import annotations

import enum
import json
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

from ..core.errors import InputError
from ..ros.markers import ApplyReport


class Verdict(enum.StrEnum):
    """What the controller made of the last message of an input."""

    NONE = "none"  # no message yet
    ACCEPTED = "accepted"
    REFUSED = "refused"


#: how many applied values of an input diagnostics keep (`<input>_applied`)
APPLIED_HISTORY = 16


@dataclass
class InputRecord:
    received: int = 0
    verdict: Verdict = Verdict.NONE
    reason: str = ""
    applied: deque[list[float]] | None = None  # None: an input whose values are not kept (obstacles)


class ObstacleKind(enum.StrEnum):
    """What the last issue with an obstacle was."""

    NONE = "none"
    REFUSED = "refused"  # a marker was refused (the last good region under its key stays)
    RESET = "reset"  # a marker was accepted, its velocity estimate reset (a jump, a skewed stamp)
    REGION = "region"  # a stored region a view or the certificate could not move to another time


@dataclass(frozen=True)
class ObstacleIssue:
    kind: ObstacleKind = ObstacleKind.NONE
    marker: str = ""  # "ns/id", or what was being done for a REGION issue
    reason: str = ""

    @property
    def text(self) -> str:
        """The issue for people: '<kind> <marker>: <reason>' (empty for none)."""
        if self.kind is ObstacleKind.NONE:
            return ""
        return f"{self.marker}: {self.reason}" if self.kind is ObstacleKind.REGION else \
            f"{self.kind.value} {self.marker}: {self.reason}"

    def values(self) -> dict[str, str]:
        """Its diagnostics keys (module doc)."""
        return {"last_obstacle_issue": self.text, "last_obstacle_kind": self.kind.value,
                "last_obstacle_marker": self.marker, "last_obstacle_reason": self.reason}


class InputLedger:
    """Messages received and the verdict on the last one, per latched input."""

    def __init__(self, names: Iterable[str], kept: Iterable[str] = ()) -> None:
        """`kept`: the inputs whose applied values are kept (`<input>_applied`)."""
        kept = set(kept)
        self.records = {name: InputRecord(applied=deque(maxlen=APPLIED_HISTORY) if name in kept else None)
                        for name in names}

    def received(self, name: str) -> None:
        """One more message on `name`, accepted unless `refused` follows."""
        record = self.records[name]
        record.received += 1
        record.verdict, record.reason = Verdict.ACCEPTED, ""

    def refused(self, name: str, reasons: str | Iterable[str]) -> None:
        """The last message on `name` was refused, for `reasons` (one, or several: a marker each)."""
        reasons = [reasons] if isinstance(reasons, str) else list(reasons)
        self.records[name].verdict, self.records[name].reason = Verdict.REFUSED, "; ".join(reasons)

    def applied(self, name: str, value: Sequence[float]) -> None:
        """The value of the last message on `name` is now in force."""
        record = self.records[name]
        if record.applied is not None:
            record.applied.append([float(v) for v in value])

    def values(self) -> dict[str, str]:
        """The diagnostics keys (module doc)."""
        values = {}
        for name, record in self.records.items():
            values.update({f"{name}_received": str(record.received), f"{name}_verdict": record.verdict.value,
                           f"{name}_reason": record.reason})
            if record.applied is not None:
                values[f"{name}_applied"] = json.dumps(list(record.applied))
        return values


class JudgedInputs:
    """ControllerNode's side (a mixin, as controller_threads.AlwaysAnswers): `reject` logs and counts a
    refused input; `judging(name)` counts a message on a latched input and refuses it on an InputError."""

    def note_obstacles(self, report: ApplyReport) -> None:
        """Count, log and keep the refused markers and reset estimates of one applied MarkerArray."""
        self.ledger.received("obstacles")
        if report.rejected:
            self.ledger.refused("obstacles", [f"marker {ns}/{i}: {reason}" for ns, i, reason in report.rejected])
        for ns, marker_id, reason in report.rejected:
            self.reject(f"marker {ns}/{marker_id}", reason)
            self.obstacle_issue = ObstacleIssue(ObstacleKind.REFUSED, f"{ns}/{marker_id}", reason)
        for ns, marker_id, reason in report.resets:
            self.counts["obstacle_resets"] += 1
            self.obstacle_issue = ObstacleIssue(ObstacleKind.RESET, f"{ns}/{marker_id}", reason)
            self.log_throttled("obstacle_reset", "warning", f"marker {ns}/{marker_id}: {reason}")

    def reject(self, what: str, reason: str) -> None:
        self.counts["rejected_inputs"] += 1
        self.last_rejected = f"{what}: {reason}"
        self.log_throttled("rejected", "warning", f"rejected {what}: {reason}")

    @contextmanager
    def judging(self, name: str) -> Iterator[None]:
        """The body converts and applies one message of the latched input `name`; an InputError refuses it."""
        self.ledger.received(name)
        try:
            yield
        except InputError as exc:
            self.reject(name, str(exc))
            self.ledger.refused(name, str(exc))
