"""What a child process of the controller needs so that it never outlives it (the solver worker's child,
core/nlp/worker.py; the background compile, core/nlp/background.py)."""

from __future__ import annotations

import ctypes
import signal

_PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGKILL) -> None:
    """Ask Linux to send `sig` to this (child) process when its parent (the thread that forked it) ends;
    a no-op elsewhere."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0)
    except (OSError, AttributeError):
        pass
