"""Velocities on `obstacles`: estimated from stamped updates or explicit in `text`; bad input refused or reset."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from hypothesis import given, settings
from hypothesis import strategies as st
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.bag.analysis import load_run, run_metrics
from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter
from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
from nmpc_avoid_ros.core.problem.motion import VelocityEstimator
from nmpc_avoid_ros.core.problem.regions import Ellipse, rotated_box
from nmpc_avoid_ros.ros.conversions import seconds_to_time
from nmpc_avoid_ros.ros.markers import RegionStore, region_marker, regions_to_markers, velocity_from_text

MAX_SPEED = 2.0
ROBOT = Path(__file__).resolve().parents[1] / "config" / "mobile_robot.yaml"


def store() -> RegionStore:
    return RegionStore(max_speed=MAX_SPEED, max_stamp_skew=1.0)


def send(target: RegionStore, region, stamp: float, now: float | None = None, text: str | None = None):
    marker = region_marker(region, 7, "tracker", stamp)
    if text is not None:
        marker.text = text
    return target.apply(MarkerArray(markers=[marker]), stamp if now is None else now)


@settings(max_examples=80, deadline=None)
@given(vx=st.floats(-1.4, 1.4), vy=st.floats(-1.4, 1.4), period=st.floats(0.02, 1.0), start=st.floats(1.0, 1e5),
       updates=st.integers(2, 8))
def test_constant_velocity_is_estimated_exactly(vx, vy, period, start, updates):
    """Stamped updates of a region moving at constant velocity: the estimate is that velocity."""
    s = store()
    for i in range(updates):
        t = start + i * period
        report = send(s, Ellipse((1.0 + vx * (t - start), -2.0 + vy * (t - start)), (0.5, 0.5)), t)
        assert report.rejected == [] and report.resets == []
    (region,) = s.active(t)
    # stamps go through integer nanoseconds: the estimate is exact up to that rounding
    assert region.velocity == pytest.approx((vx, vy), abs=1e-5 / period + 1e-9) or (vx, vy) == (0.0, 0.0)
    assert region.at(t).center == pytest.approx((1.0 + vx * (t - start), -2.0 + vy * (t - start)), abs=1e-6)


def test_explicit_velocity_round_trips_through_the_marker_text():
    walker = Ellipse((0.0, -4.0), (0.6, 0.6), 0.0, "output", velocity=(0.0, 0.5), stamp=10.0)
    box = rotated_box((2.0, 2.0), (1.0, 0.5), 0.3, "output", velocity=(-0.3, 0.1), stamp=10.0)
    msg = regions_to_markers([walker, box], stamp=12.0)
    assert msg.markers[1].text == "velocity=0.0,0.5"
    s = store()
    report = s.apply(msg, now=12.1)
    assert report.rejected == [] and report.applied == 2
    got_walker, got_box = s.active(12.1)
    assert got_walker.velocity == (0.0, 0.5) and got_walker.at(13.0).center == pytest.approx(walker.at(13.0).center)
    assert got_box.velocity == pytest.approx((-0.3, 0.1))
    for (ax, ay), (bx, by) in zip(got_box.at(13.0).vertices, box.at(13.0).vertices):
        assert (ax, ay) == pytest.approx((bx, by), abs=1e-9)


@pytest.mark.parametrize("text, reason", [
    ("velocity=nan,0", "NaN or infinite"), ("velocity=0,inf", "NaN or infinite"), ("velocity=3,0", "exceeds"),
    ("velocity=1", "two numbers"), ("label velocity=a,b", "two numbers"),
])
def test_bad_explicit_velocity_is_refused_and_the_last_good_region_stays(text, reason):
    s = store()
    good = Ellipse((0.0, 0.0), (0.5, 0.5))
    send(s, good, 5.0, text="velocity=0.5,0")
    report = send(s, Ellipse((9.0, 9.0), (0.5, 0.5)), 5.5, text=text)
    assert report.applied == 0 and len(report.rejected) == 1 and reason in report.rejected[0][2]
    (kept,) = s.active(5.5)
    assert kept.center == (0.0, 0.0) and kept.velocity == (0.5, 0.0)


@pytest.mark.parametrize("stamp, now", [(100.0, 10.0), (10.0, 100.0)])
def test_stamp_far_from_receipt_is_refused_for_a_moving_region(stamp, now):
    s = store()
    report = send(s, Ellipse((0.0, 0.0), (0.5, 0.5)), stamp, now=now, text="velocity=0.5,0")
    assert report.applied == 0 and "receipt" in report.rejected[0][2]
    assert s.active(now) == ()


def test_estimate_with_a_skewed_stamp_is_reset_with_a_reason():
    s = store()
    send(s, Ellipse((0.0, 0.0), (0.5, 0.5)), 100.0, now=10.0)
    report = send(s, Ellipse((0.5, 0.0), (0.5, 0.5)), 101.0, now=11.0)
    assert report.applied == 1 and "ahead of its receipt" in report.resets[0][2]
    (region,) = s.active(11.0)
    assert region.velocity == (0.0, 0.0) and region.center == (0.5, 0.0)


def test_a_jump_across_the_map_resets_the_estimate():
    s = store()
    for i in range(3):
        send(s, Ellipse((0.5 * i, 0.0), (0.5, 0.5)), 1.0 + i)
    assert s.active(3.0)[0].velocity == pytest.approx((0.5, 0.0))
    report = send(s, Ellipse((50.0, 50.0), (0.5, 0.5)), 4.0)
    assert report.applied == 1 and "jumped" in report.resets[0][2]
    (region,) = s.active(4.0)
    assert region.center == (50.0, 50.0) and region.velocity == (0.0, 0.0)


def test_stamp_going_backwards_resets_and_a_repeat_keeps_the_estimate():
    s = store()
    send(s, Ellipse((0.0, 0.0), (0.5, 0.5)), 1.0)
    send(s, Ellipse((0.5, 0.0), (0.5, 0.5)), 2.0)
    assert send(s, Ellipse((0.5, 0.0), (0.5, 0.5)), 2.0).resets == []  # latched repeat
    assert s.active(2.0)[0].velocity == (0.5, 0.0)
    report = send(s, Ellipse((0.4, 0.0), (0.5, 0.5)), 1.5, now=2.0)
    assert "stamp went from" in report.resets[0][2] and s.active(2.0)[0].velocity == (0.0, 0.0)


def test_replacing_the_whole_set_keeps_the_estimates_but_delete_forgets_them():
    s = store()
    for i in range(2):
        s.apply(regions_to_markers([Ellipse((0.2 * i, 0.0), (0.5, 0.5))], stamp=1.0 + i), now=1.0 + i)
    assert s.active(2.0)[0].velocity == pytest.approx((0.2, 0.0))  # DELETEALL + ADD in one message
    assert len(s.motion) == 1
    s.apply(MarkerArray(markers=[regions_to_markers([]).markers[0]]), now=2.5)
    assert len(s.motion) == 0


def test_unstamped_markers_stay_static():
    s = store()
    for i in range(3):
        s.apply(regions_to_markers([Ellipse((0.3 * i, 0.0), (0.5, 0.5))]), now=float(i))
    assert s.active(2.0)[0].velocity == (0.0, 0.0)


def test_velocity_text_ignores_other_tokens():
    assert velocity_from_text("walker; velocity=0.25,-1e-3 id=4") == (0.25, -1e-3)
    assert velocity_from_text("just a label") is None


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e3, 1e3))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(numbers, numbers, numbers, numbers, st.one_of(st.none(), st.tuples(numbers, numbers))),
                min_size=1, max_size=12))
def test_any_update_sequence_leaves_finite_bounded_motion(updates):
    """Whatever arrives (NaN, inf, huge stamps, jumps, fast velocities): the store never raises and every
    region it holds moves at a finite speed within the bound, from a finite stamp."""
    s = RegionStore(max_speed=MAX_SPEED, max_stamp_skew=1.0)
    now = 0.0
    for x, y, stamp, dt, velocity in updates:
        now += min(abs(dt), 10.0) if math.isfinite(dt) else 0.1
        marker = region_marker(Ellipse((0.0, 0.0), (0.5, 0.5)), 1, "fuzz")
        marker.pose.position.x, marker.pose.position.y = x, y
        if math.isfinite(stamp) and 0 <= stamp < 2**31:
            marker.header.stamp = seconds_to_time(stamp)
        if velocity is not None:
            marker.text = f"velocity={velocity[0]!r},{velocity[1]!r}"
        s.apply(MarkerArray(markers=[marker]), now)
        for region in s.active(now):
            assert math.isfinite(region.stamp)
            assert all(math.isfinite(v) for v in region.velocity)
            assert math.hypot(*region.velocity) <= MAX_SPEED * (1 + 1e-12)


def test_estimator_refuses_bad_bounds():
    with pytest.raises(Exception, match="max_speed"):
        VelocityEstimator(max_speed=math.nan)


def _diagnostic(state: list[float], state_time: float) -> DiagnosticArray:
    values = {"state": json.dumps(state), "command": "[0.0, 0.0]", "y_a": "[nan, nan]", "solve_time_ms": "1.0",
              "status": "ok", "state_time": repr(state_time), "samples": "1", "fallbacks": "0",
              "rejected_inputs": "0", "deadline_overruns": "0", "stale": "0"}
    status = DiagnosticStatus(name="/controller: nmpc", values=[KeyValue(key=k, value=v) for k, v in values.items()])
    return DiagnosticArray(status=[status])


@pytest.mark.parametrize("explicit", [True, False])
def test_analyze_evaluates_a_recorded_moving_region_at_each_sample_time(tmp_path, explicit):
    """A walker recorded as stamped markers (velocity in text, or estimated from the stamps): analysis
    places it where it was at each state's time. The robot sits where the walker passes at t = 10 s."""
    settings = ControllerSettings.from_params(load_params_file(ROBOT).section("controller"))
    walker = Ellipse((0.0, -5.0), (0.5, 0.5), 0.0, "output", velocity=(0.0, 0.5), stamp=100.0)
    path = tmp_path / "walker.mcap"
    with Ros2McapWriter(path) as bag:
        for k in range(120):  # markers at 10 Hz, samples at 4 Hz, from t = 100 s
            t = 100.0 + 0.1 * k
            marker = region_marker(walker.at(t), 0, "tracker", t)
            if not explicit:
                marker.text = ""
            bag.write_message("/obstacles", MarkerArray(markers=[marker]), int(t * 1e9))
        for k in range(48):
            t = 100.0 + 0.25 * k + 0.02
            bag.write_message("/diagnostics", _diagnostic([0.0, 0.0, 0.0, 0.0], t), int((t + 0.01) * 1e9))
    run = load_run(path, settings=settings)
    metrics = run_metrics(run, settings)
    # deepest when the walker's centre passes the origin (t = 110 s, 10 s after its stamp)
    worst = max(range(len(run.x)), key=lambda k: run.regions_at(k)[0].depth((0.0, 0.0)) if run.regions_at(k) else -9)
    assert run.times[worst] == pytest.approx(110.0, abs=0.13)
    assert metrics["max_penetration_obstacles"] == pytest.approx(1.0, abs=0.01)
    assert metrics["min_clearance_obstacles"] == pytest.approx(-1.0, abs=0.01)
    # the store's last update alone (no motion between updates) would be off by up to 0.1 s * 0.5 m/s
    assert all(r.moving for regions in run.regions[3:] for r in regions)


def test_republished_markers_move_to_the_new_clock_and_keep_their_velocity():
    from rclpy.serialization import serialize_message

    from nmpc_avoid_ros.tools.replay import restamped

    walker = Ellipse((0.0, -5.0), (0.5, 0.5), 0.0, "output", velocity=(0.0, 0.5), stamp=100.0)
    msg = regions_to_markers([walker], stamp=100.0)
    msg.markers.append(region_marker(Ellipse((3.0, 3.0), (1.0, 1.0)), 5, "static"))  # zero stamp: stays zero
    out = restamped(serialize_message(msg), MarkerArray, 2_500_000_000)
    assert out.markers[1].header.stamp.sec == 102 and out.markers[1].text == "velocity=0.0,0.5"
    assert (out.markers[2].header.stamp.sec, out.markers[2].header.stamp.nanosec) == (0, 0)
    store = RegionStore()
    store.apply(out, now=102.0)
    assert store.active(102.0)[0].at(103.0).center == pytest.approx(walker.at(100.5).center)  # 2.5 s earlier
