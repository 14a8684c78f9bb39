"""Plan.shifted: the one shift of a plan (warm start, fallback, result, passage hand-back, the bench's peers)."""

from __future__ import annotations

import numpy as np
import pytest

from nmpc_avoid_ros.core.sample.step_result import Plan, shifted_rows


def plan(age: int = 0) -> Plan:
    N = 3
    return Plan(np.arange(N, dtype=float)[:, None], np.arange(2 * N + 2, dtype=float).reshape(N + 1, 2),
                np.array([9.0]), np.array([7.0, 8.0]), np.array([6.0]), np.zeros(1), np.zeros(1), age)


def test_a_prepared_plan_shifted_by_its_age_plus_one_is_unchanged():
    p = plan(age=-1)
    inputs, states = p.shifted(p.age + 1)
    np.testing.assert_array_equal(inputs, p.inputs)
    np.testing.assert_array_equal(states, p.states)
    assert inputs is not p.inputs and states is not p.states  # copies: the plan is kept as it was


def test_a_shift_drops_the_first_rows_and_pads_with_the_steady_state():
    inputs, states = plan().shifted(2)
    np.testing.assert_array_equal(inputs, [[2.0], [6.0], [6.0]])
    np.testing.assert_array_equal(states, [[4.0, 5.0], [6.0, 7.0], [7.0, 8.0], [7.0, 8.0]])
    inputs, states = plan().shifted(10)  # past the horizon: the steady state only, shapes kept
    assert inputs.shape == (3, 1) and states.shape == (4, 2)
    assert np.all(inputs == 6.0) and np.all(states == [7.0, 8.0])


def test_a_negative_shift_is_refused():
    with pytest.raises(ValueError):
        shifted_rows(np.zeros((3, 1)), np.zeros(1), -1)
