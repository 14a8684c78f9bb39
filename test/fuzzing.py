"""Shared pieces of the property-based (hypothesis) fuzz tests: settings, a hang guard, the
"only documented errors" check, and strategies for hostile values and visualization markers."""

from __future__ import annotations

import contextlib
import math
import signal
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from nmpc_avoid_ros.core.errors import NmpcError

T = TypeVar("T")

def fuzz_settings(examples: int) -> settings:
    """Hypothesis settings of the fuzz tests: `examples` derandomized examples, no deadline."""
    return settings(max_examples=examples, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much])


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Turn a hang into a TimeoutError after `seconds` (main thread, POSIX)."""

    def on_alarm(signum, frame):  # noqa: ARG001 - signal handler signature
        raise TimeoutError(f"took longer than {seconds} s: a hang on hostile input")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome(fn: Callable[[], T], allowed: tuple[type[BaseException], ...] = (NmpcError,)) -> T | BaseException:
    """fn() or the documented exception it raised (with a non-empty message); anything else propagates."""
    try:
        return fn()
    except allowed as exc:
        assert str(exc).strip(), f"{type(exc).__name__} without a message"
        return exc


# --- hostile plain values ---------------------------------------------------------------------

any_float = st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True)
huge_int = st.integers(min_value=-(10**400), max_value=10**400)
scalar = st.one_of(any_float, huge_int, st.booleans(), st.none(), st.text(max_size=8), st.binary(max_size=4),
                   st.complex_numbers(allow_nan=True))
#: nested garbage of lists, tuples and dicts over hostile scalars
garbage = st.recursive(scalar, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.tuples(inner, inner),
                                                       st.dictionaries(st.text(max_size=4), inner, max_size=3)),
                       max_leaves=12)


def is_exc(value: Any) -> bool:
    return isinstance(value, BaseException)


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)
