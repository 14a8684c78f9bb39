"""Tests of nmpc_avoid_ros.ros.conversions (Float64MultiArray <-> numpy, stamps <-> seconds)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from builtin_interfaces.msg import Duration, Time
from hypothesis import given
from hypothesis import strategies as st
from rclpy.duration import Duration as RclpyDuration
from rclpy.time import Time as RclpyTime
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.core.errors import InputError
from nmpc_avoid_ros.ros.conversions import (
    array_to_vector,
    seconds_to_duration,
    seconds_to_time,
    stamp_to_seconds,
    vector_to_array,
)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def make_array(values: list[float]) -> Float64MultiArray:
    msg = Float64MultiArray()
    msg.data = values
    return msg


def test_array_to_vector_returns_a_float_copy() -> None:
    msg = make_array([1.0, -2.5, 3.0])
    vec = array_to_vector(msg, 3, "state")
    assert vec.shape == (3,) and vec.dtype == float
    np.testing.assert_array_equal(vec, [1.0, -2.5, 3.0])
    vec[0] = 99.0  # the message must not alias the returned array
    assert msg.data[0] == 1.0


def test_wrong_length_names_the_vector_and_both_sizes() -> None:
    with pytest.raises(InputError, match=r"^state: expected 2 values, got 3$"):
        array_to_vector(make_array([1.0, 2.0, 3.0]), 2, "state")
    with pytest.raises(InputError, match=r"^target: expected 1 values, got 0$"):
        array_to_vector(make_array([]), 1, "target")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_rejected(bad: float) -> None:
    with pytest.raises(InputError, match=r"^target: contains NaN or infinite values$"):
        array_to_vector(make_array([0.0, bad]), 2, "target")


def test_layout_is_ignored_on_input() -> None:
    # ros2_control's forward-command convention: only data counts
    msg = vector_to_array([1.0, 2.0], label="something else")
    msg.layout.dim[0].size = 7
    np.testing.assert_array_equal(array_to_vector(msg, 2, "command"), [1.0, 2.0])


def test_garbage_message_raises_input_error_not_something_else() -> None:
    with pytest.raises(InputError, match="state"):
        array_to_vector(object(), 2, "state")  # type: ignore[arg-type]


def test_vector_to_array_sets_one_labelled_dim() -> None:
    msg = vector_to_array(np.array([0.5, 1.5, 2.5]), label="u")
    assert list(msg.data) == [0.5, 1.5, 2.5]
    assert len(msg.layout.dim) == 1
    dim = msg.layout.dim[0]
    assert (dim.label, dim.size, dim.stride) == ("u", 3, 3)
    assert msg.layout.data_offset == 0
    assert vector_to_array([1.0]).layout.dim[0].label == ""


def test_vector_to_array_rejects_a_matrix() -> None:
    with pytest.raises(InputError, match="1-d"):
        vector_to_array(np.zeros((2, 2)))


@given(st.lists(st.floats(-1e12, 1e12), max_size=20))  # validate_vector bounds |v| <= 1e12
def test_vector_round_trip(values: list[float]) -> None:
    back = array_to_vector(vector_to_array(values), len(values), "v")
    np.testing.assert_array_equal(back, np.array(values, dtype=float))


def test_stamp_to_seconds_reads_time_duration_and_rclpy_types() -> None:
    assert stamp_to_seconds(Time(sec=12, nanosec=500_000_000)) == pytest.approx(12.5)
    assert stamp_to_seconds(Duration(sec=0, nanosec=250_000_000)) == pytest.approx(0.25)
    assert stamp_to_seconds(Duration(sec=-1, nanosec=500_000_000)) == pytest.approx(-0.5)
    assert stamp_to_seconds(RclpyTime(seconds=3, nanoseconds=1_000_000)) == pytest.approx(3.001)
    assert stamp_to_seconds(RclpyDuration(seconds=2.5)) == pytest.approx(2.5)


@given(st.floats(min_value=0.0, max_value=2e9))
def test_seconds_to_time_round_trip(seconds: float) -> None:
    stamp = seconds_to_time(seconds)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert stamp_to_seconds(stamp) == pytest.approx(seconds, abs=1e-9, rel=1e-15)


@given(st.floats(min_value=-2e9, max_value=2e9))
def test_seconds_to_duration_round_trip(seconds: float) -> None:
    duration = seconds_to_duration(seconds)
    assert 0 <= duration.nanosec < 1_000_000_000
    assert stamp_to_seconds(duration) == pytest.approx(seconds, abs=1e-9, rel=1e-15)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, 1e12])
def test_seconds_to_time_rejects_unrepresentable(bad: float) -> None:
    with pytest.raises(InputError):
        seconds_to_time(bad)
