"""Moving regions in the core: stage k sees c + v (t_k - stamp), as parameters, for both formulations."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.errors import RegionError
from nmpc_avoid_ros.core.loop.closed_loop import make_plant
from nmpc_avoid_ros.core.problem.regions import Ellipse, SlotLayout, rotated_box
from nmpc_avoid_ros.core.sample.controller import NmpcController

LAYOUT = SlotLayout(max_ellipses=1, max_polygons=1, max_polygon_vertices=4)
ROBOT = default_config_path().with_name("mobile_robot.yaml")


def stage_depths() -> ca.Function:
    """depths(point, slots, elapsed) as the NLP builds them at a stage `elapsed` s after x(0)."""
    point, slots, elapsed = ca.SX.sym("p", 2), ca.SX.sym("s", LAYOUT.size), ca.SX.sym("t")
    return ca.Function("d", [point, slots, elapsed], [LAYOUT.depths(slots, point, None, elapsed)])


finite = st.floats(-5.0, 5.0)


@settings(max_examples=60, deadline=None)
@given(cx=finite, cy=finite, vx=finite, vy=finite, stamp=st.floats(-3.0, 3.0), now=st.floats(-3.0, 3.0),
       k=st.integers(0, 20), px=finite, py=finite)
def test_stage_k_sees_the_region_where_it_will_be(cx, cy, vx, vy, stamp, now, k, px, py):
    """The symbolic slot depth at stage k equals the numeric depth of the region moved to now + k Ts."""
    ts = 0.25
    ellipse = Ellipse((cx, cy), (0.7, 0.4), 0.3, velocity=(vx, vy), stamp=stamp)
    box = rotated_box((cy, cx), (1.0, 0.6), -0.2, velocity=(vy, vx), stamp=stamp)
    fn = stage_depths()
    got = np.asarray(fn((px, py), LAYOUT.pack([ellipse, box], now=now), k * ts)).ravel()
    t_k = now + k * ts
    assert got[0] == pytest.approx(ellipse.at(t_k).depth((px, py)), abs=1e-9)
    assert got[1] == pytest.approx(box.at(t_k).depth((px, py)), abs=1e-9)
    # prediction off: the region stays where it was at its stamp, at every stage
    frozen = np.asarray(fn((px, py), LAYOUT.pack([ellipse, box], now=now, predict=False), k * ts)).ravel()
    assert frozen[0] == pytest.approx(ellipse.depth((px, py)), abs=1e-9)
    assert frozen[1] == pytest.approx(box.depth((px, py)), abs=1e-9)


def test_static_region_slots_do_not_depend_on_time():
    """v = 0: the motion entries are exact zeros whatever the stamp and the sample time."""
    ellipse = Ellipse((1.0, 2.0), (0.5, 0.3), 0.4, stamp=123.0)
    box = rotated_box((0.0, 0.0), (1.0, 2.0), 0.1, stamp=-7.0)
    reference = LAYOUT.pack([ellipse, box])
    for now in (0.0, 5.5, 1e6):
        assert np.array_equal(LAYOUT.pack([ellipse, box], now=now), reference)
    assert np.all(reference[8:11] == 0.0) and np.all(reference[11 + 2:11 + 5] == 0.0)


def test_moved_region_keeps_shape_and_velocity():
    e = Ellipse((0.0, -4.0), (0.6, 0.6), 0.2, "output", velocity=(0.1, 0.5), stamp=2.0)
    later = e.at(6.0)
    assert later.center == pytest.approx((0.4, -2.0)) and later.stamp == 6.0
    assert (later.semi_axes, later.yaw, later.velocity, later.frame) == (e.semi_axes, e.yaw, e.velocity, e.frame)
    box = rotated_box((1.0, 1.0), (2.0, 2.0), velocity=(-1.0, 0.0), stamp=0.0)
    assert np.mean(box.at(3.0).vertices, axis=0) == pytest.approx((-2.0, 1.0))


@pytest.mark.parametrize("velocity, stamp", [((math.nan, 0.0), 0.0), ((0.0, math.inf), 0.0), ((1.0,), 0.0),
                                             ((0.0, 0.0), math.nan), ((0.0, 0.0), "soon")])
def test_bad_motion_is_refused(velocity, stamp):
    with pytest.raises(RegionError):
        Ellipse((0.0, 0.0), (1.0, 1.0), velocity=velocity, stamp=stamp)


def robot_settings(solver: str, predict: bool) -> ControllerSettings:
    params = load_params_file(ROBOT).section("controller")
    return ControllerSettings.from_params(params).replace(solver=solver, predict_obstacles=predict, horizon=16,
                                                          max_solve_time=30.0)


def crossing(controller: NmpcController, steps: int = 56) -> float:
    """A walker crosses the straight path of the robot; returns the deepest penetration (g = 1 - r^2)."""
    plant = make_plant("continuous", controller.model, controller.settings)
    walker = Ellipse((0.0, -4.0), (0.6, 0.6), 0.0, "output", velocity=(0.0, 0.5), stamp=0.0)
    x, deepest, ts = np.array([-8.0, 0.0, 0.0, 0.0]), -math.inf, controller.settings.sample_time
    for k in range(steps):
        # the walker as a tracker reports it at each sample: where it is now, and its velocity
        result = controller.step(x, [8.0, 0.0], [walker.at(k * ts)], time=k * ts)
        x = plant.advance(x, result.u, ts)
        deepest = max(deepest, walker.at((k + 1) * ts).depth(x[:2]))
    return deepest


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["ipopt", "fatrop"])
def test_prediction_avoids_a_crossing_walker_that_the_static_assumption_hits(solver):
    """Both formulations; the same NLP object throughout: toggling prediction and moving regions never rebuild."""
    controller = NmpcController(robot_settings(solver, True))
    solver_object, builds = controller.nlp.solver, controller.nlp_builds
    predicted = crossing(controller)
    controller.reset()
    controller.update_settings(predict_obstacles=False)
    static = crossing(controller)
    assert controller.nlp_builds == builds and controller.nlp.solver is solver_object
    assert predicted <= 1e-3, f"penetration {predicted} with prediction"
    assert static > 0.3, f"the static assumption should walk into the walker (depth {static})"


def test_counterfactual_penetration_counts_a_moving_region_where_it_is_at_each_sample() -> None:
    """replay --closed-loop's metrics: sample k is at k Ts, so a walker stamped at 0 is moved there."""
    from nmpc_avoid_ros.core.loop.closed_loop import ClosedLoopRun
    from nmpc_avoid_ros.evaluation.counterfactual import loop_metrics

    settings = ControllerSettings(mu=0.0, keep_in=())
    # the walker starts at (0, -4) and moves up at 1 /s; the state sits at (0, -2), reached by the walker at t = 2
    walker = Ellipse((0.0, -4.0), (0.5, 0.5), 0.0, "state", velocity=(0.0, 1.0), stamp=0.0)
    K, ts = 6, 0.5
    run = ClosedLoopRun(
        x=np.tile([0.0, -2.0], (K + 1, 1)), u=np.zeros((K, 1)), y_a=np.zeros((K, 1)), targets=np.zeros((K, 1)),
        solve_time=np.full(K, 1e-3), iterations=np.ones(K, int), status=["ok"] * K, solver_status=["0"] * K,
        costs=np.zeros((K, 3)), sample_time=ts, regions=[(walker,)] * K)
    # at its stamp the walker is 2 away (no penetration); at sample 4 (t = 2) its centre is on the state
    assert walker.depth((0.0, -2.0)) < 0
    assert loop_metrics(run, settings)["max_penetration"] == pytest.approx(1.0)


@pytest.mark.slow
def test_a_region_margin_keeps_the_robot_that_far_from_the_walker_and_changes_at_run_time():
    """region_margin (m): the plan avoids the walker grown by it; the sampled states keep at least the
    margin from the real walker (a circle grows by exactly the margin), the regions as set stay the
    real ones, and a new margin takes effect at the next step without a rebuild."""
    controller = NmpcController(robot_settings("fatrop", True))
    builds = controller.nlp_builds
    without = crossing(controller)
    controller.reset()
    controller.update_settings(region_margin=0.15)
    plant = make_plant("continuous", controller.model, controller.settings)
    walker = Ellipse((0.0, -4.0), (0.6, 0.6), 0.0, "output", velocity=(0.0, 0.5), stamp=0.0)
    x, nearest, ts = np.array([-8.0, 0.0, 0.0, 0.0]), math.inf, controller.settings.sample_time
    for k in range(56):
        result = controller.step(x, [8.0, 0.0], [walker.at(k * ts)], time=k * ts)
        assert controller.regions[0].semi_axes == (0.6, 0.6)  # as set
        x = plant.advance(x, result.u, ts)
        nearest = min(nearest, float(np.hypot(*(x[:2] - walker.at((k + 1) * ts).center))) - 0.6)
    assert nearest >= 0.15 - 0.01, f"closest approach {nearest} m to the walker's edge with a 0.15 m margin"
    assert without > -0.01  # without it the robot grazes the walker's edge (depth g = 1 - (d / r)^2)
    assert controller.nlp_builds == builds
