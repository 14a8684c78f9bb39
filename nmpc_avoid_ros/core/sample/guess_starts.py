"""The escape's and the passage's guesses as search starts: which of them a sample solves, each as the NLP's w, and
what the escape admits (core/sample/candidates.py makes the guesses; core/sample/search_phases.py runs them)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np

from ..nlp.search import Candidate, Start
from ..nlp.tracking import NlpBase
from .candidates import MANOEUVRE, STALL_TOLERANCE, Guess

T = TypeVar("T")  # a guess, or a passage's turn (core/sample/passage.py)


def guess_batch(guesses: Sequence[T], start: int, per_sample: int) -> tuple[list[T], int]:
    """The guesses to solve this sample: `per_sample` of them from index `start` (all if per_sample is 0),
    and how many remain after them. A start past the end (the list shrank) starts over."""
    if per_sample <= 0:
        return list(guesses), 0
    start = start if start < len(guesses) else 0
    batch = list(guesses[start:start + per_sample])
    return batch, len(guesses) - start - len(batch)


def guess_w(nlp: NlpBase, x: np.ndarray, par: np.ndarray, guess: Guess) -> np.ndarray:
    """The guess as the NLP's w [n_w] for the state x [n], slacks filled at `par`."""
    layout = nlp.layout
    rest = None if layout.closed_form else np.concatenate([guess.states[-1], guess.inputs[-1]])
    return nlp.fill_slacks(layout.join_w(guess.inputs, guess.states, guess.y_a, rest, x0=x), par)


def guess_start(nlp: NlpBase, x: np.ndarray, par: np.ndarray, guess: Guess, label: str | None = None,
                budget: int | None = None, cold: bool = False) -> Start:
    """The guess as a search Start of `nlp` (zero multipliers; iteration budget: the regular one unless given)."""
    return Start(label or guess.label, nlp, guess_w(nlp, x, par, guess), np.zeros(nlp.layout.n_w),
                 np.zeros(nlp.lbg.size), budget or nlp.settings.max_iterations, cold)


#: an escape candidate may predict at most this much penetration beyond the base plan's (region g units)
DEPTH_ALLOWANCE = 1e-4


def escape_admission(base: Candidate) -> Callable[[Candidate], str]:
    """The escape's admission rule for `search`: a candidate may not buy progress with penetration (no
    more predicted depth than the base plan's + DEPTH_ALLOWANCE, unless it is clear by the sample's tolerance:
    campaign vdp-0188 rested for good before a guess 3.5e-4 deep was admitted against a stall 1.5e-4 deep); a
    manoeuvre must move y_a (by at least STALL_TOLERANCE): one that came back to the base's rest is the base again,
    and kept on a cost lower by rounding it ended the escape without its wait, so that it ran again every sample
    (measured in the campaign)."""
    y_base = base.nlp.layout.y_a(base.w)

    def admit(candidate: Candidate) -> str:
        if candidate.depth > base.depth + DEPTH_ALLOWANCE and not candidate.clear:
            return "penetrates more"
        moved = np.max(np.abs(candidate.nlp.layout.y_a(candidate.w) - y_base)) >= STALL_TOLERANCE
        return "" if moved or not candidate.label.startswith(MANOEUVRE) else "back at the rest"
    return admit
