"""The controller's verdicts on its latched inputs (`target`, `goal_pose`, `obstacles`), as data.

Per input the node counts the messages it received and keeps its verdict on the last one: accepted,
or refused with the reason. /diagnostics carries them under structured keys, three per input:
`<input>_received` (count since configure), `<input>_verdict` (`none` before any message, `accepted`,
`refused`) and `<input>_reason` (why the last one was refused; empty otherwise). A MarkerArray with
a refused marker is refused (the reasons of its refused markers, `; `-joined); the others in it
still apply. `send` (tools/send.py) reads these keys to tell its user what became of its message.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from ..core.errors import InputError


class Verdict(enum.StrEnum):
    """What the controller made of the last message of an input."""

    NONE = "none"  # no message yet
    ACCEPTED = "accepted"
    REFUSED = "refused"


@dataclass
class InputRecord:
    received: int = 0
    verdict: Verdict = Verdict.NONE
    reason: str = ""


class InputLedger:
    """Messages received and the verdict on the last one, per latched input."""

    def __init__(self, names: Iterable[str]) -> None:
        self.records = {name: InputRecord() for name in names}

    def received(self, name: str) -> None:
        """One more message on `name`, accepted unless `refused` follows."""
        record = self.records[name]
        record.received += 1
        record.verdict, record.reason = Verdict.ACCEPTED, ""

    def refused(self, name: str, reasons: str | Iterable[str]) -> None:
        """The last message on `name` was refused, for `reasons` (one, or several: a marker each)."""
        reasons = [reasons] if isinstance(reasons, str) else list(reasons)
        self.records[name].verdict, self.records[name].reason = Verdict.REFUSED, "; ".join(reasons)

    def values(self) -> dict[str, str]:
        """The diagnostics keys (module doc)."""
        values = {}
        for name, record in self.records.items():
            values.update({f"{name}_received": str(record.received), f"{name}_verdict": record.verdict.value,
                           f"{name}_reason": record.reason})
        return values


class JudgedInputs:
    """ControllerNode's side (a mixin, as controller_threads.AlwaysAnswers): `reject` logs and counts a
    refused input; `judging(name)` counts a message on a latched input and refuses it on an InputError."""

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
