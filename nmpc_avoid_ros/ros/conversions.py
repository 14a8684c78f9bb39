"""Conversions between std_msgs / builtin_interfaces messages and numpy / float seconds.

Vectors travel as std_msgs/msg/Float64MultiArray (ros2_control's forward-command convention):
only `data` carries values; the layout is informative and ignored on input.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Duration, Time
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from ..core.errors import InputError
from ..core.sample.step_result import validate_vector

_NS_PER_S = 1_000_000_000
#: s: a message's DDS stamp further than this before now (or after it) is not trusted
DDS_STAMP_SKEW = 0.5


def dds_stamp_age_ns(info: dict | None, key: str, now_ns: int) -> int | None:
    """ns from a message's DDS stamp `key` in its rclpy message info (`source_timestamp`: its publisher's write;
    `received_timestamp`: its reception, by the middleware's thread) to `now_ns` (system clock), or None when
    the stamp is missing or more than DDS_STAMP_SKEW off."""
    age = now_ns - int((info or {}).get(key, 0))
    return age if 0 <= age <= DDS_STAMP_SKEW * _NS_PER_S else None


def array_to_vector(msg: Float64MultiArray, size: int, name: str) -> np.ndarray:
    """Validated copy of `msg.data` as a float array of shape [size].

    Raises InputError naming `name` when the length differs from `size` or a value is NaN/inf or
    beyond +-1e12 (finite but absurd, it would overflow the NLP's costs),
    so the caller can log it and keep the last good value.
    """
    data = getattr(msg, "data", None)
    if data is None:
        raise InputError(f"{name}: message has no data field")
    # validate_vector copies (the message buffer may be reused) and names what is wrong
    return validate_vector(name, data, size)


def vector_to_array(values: Sequence[float] | np.ndarray, label: str | None = None) -> Float64MultiArray:
    """A 1-d vector of n values -> Float64MultiArray with one layout dim (label, size n, stride n).

    Values are not checked for finiteness (a recorder may legitimately publish NaN for "missing");
    raises InputError for values that are not a 1-d sequence of numbers.
    """
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float range
        raise InputError("vector_to_array: values are not numbers") from None
    if arr.ndim > 1:
        raise InputError(f"vector_to_array: expected a 1-d vector, got shape {arr.shape}")
    arr = arr.reshape(-1)
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label or "", size=arr.size, stride=arr.size)]
    msg.layout.data_offset = 0
    msg.data = arr.tolist()
    return msg


def stamp_to_seconds(stamp: Time | Duration) -> float:
    """builtin_interfaces Time or Duration (or an rclpy Time/Duration) -> seconds as a float."""
    nanoseconds = getattr(stamp, "nanoseconds", None)
    if nanoseconds is not None:  # rclpy.time.Time / rclpy.duration.Duration
        return nanoseconds / _NS_PER_S
    return float(stamp.sec) + float(stamp.nanosec) / _NS_PER_S


def _split_seconds(seconds: float) -> tuple[int, int]:
    if not math.isfinite(seconds):
        raise InputError(f"time must be finite, got {seconds}")
    total_ns = round(seconds * _NS_PER_S)
    sec, nanosec = divmod(total_ns, _NS_PER_S)  # floor division keeps 0 <= nanosec < 1e9 for negatives
    if not -(2**31) <= sec < 2**31:
        raise InputError(f"time {seconds} s does not fit a builtin_interfaces stamp")
    return int(sec), int(nanosec)


def seconds_to_time(seconds: float) -> Time:
    """Seconds (>= 0) -> builtin_interfaces/Time; raises InputError if negative or not finite."""
    if seconds < 0:
        raise InputError(f"a time stamp must not be negative, got {seconds}")
    sec, nanosec = _split_seconds(seconds)
    return Time(sec=sec, nanosec=nanosec)


def seconds_to_duration(seconds: float) -> Duration:
    """Seconds -> builtin_interfaces/Duration (negative durations keep 0 <= nanosec < 1e9)."""
    sec, nanosec = _split_seconds(seconds)
    return Duration(sec=sec, nanosec=nanosec)
