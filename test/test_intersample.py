"""Between the samples: sub-stepped prediction, avoidance at the sub-step states, the dense clearance check.

The scene is the README's obstacle sequence offline (config/scenes/readme_obstacle.yaml): from rest at
x = (5, 0) to the target -3 past the ellipse centred (2, -0.5), semi-axes 0.4 x 0.2, on the continuous
plant. The paper's Euler prediction enters the ellipse there; the live config must not, at the samples
or between them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant
from nmpc_avoid_ros.core.loop.intersample import clearance_between_samples, dense_states
from nmpc_avoid_ros.core.loop.scene import load_scene
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.tools.simulate import scene_scenario, simulate

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "config" / "scenes" / "readme_obstacle.yaml"
#: the issue's bound on penetration, at the samples and between them
BOUND = 1e-3
#: offline: no machine-dependent budget cuts, no compile (the same NLP, interpreted)
OFFLINE = dict(codegen=False, max_solve_time=2.0)


def test_sub_steps_end_where_the_one_sample_map_ends_and_approach_the_plant() -> None:
    model = make_model("van_der_pol")
    x, u = np.array([3.0, -1.0]), np.array([1.5])
    exact = ContinuousPlant(model).advance(x, u, 0.5)
    errors = []
    for steps in (1, 2, 8):
        path = np.asarray(model.discrete_path(0.5, "rk4", steps)(x, u))
        assert path.shape == (2, steps)
        np.testing.assert_allclose(path[:, -1], np.asarray(model.discrete(0.5, "rk4", steps)(x, u)).ravel())
        errors.append(np.linalg.norm(path[:, -1] - exact))
    assert errors[0] > 10 * errors[1] > 10 * errors[2]  # RK4: error ~ h^4
    with pytest.raises(ConfigError, match="integration_steps"):
        model.discrete_path(0.5, "rk4", 0)


def test_dense_states_follow_the_continuous_plant_from_each_recorded_state() -> None:
    model = make_model("van_der_pol")
    plant = ContinuousPlant(model)
    x = np.array([[3.0, -1.0], [0.0, 1.0], [-2.0, 0.5]])  # not a trajectory: each sample starts afresh
    u = np.array([[1.5], [-2.0]])
    dense = dense_states(model, x, u, 0.5, per_sample=5)
    assert dense.shape == (11, 2)
    for k in range(2):
        np.testing.assert_array_equal(dense[5 * k], x[k])
        for j in range(1, 5):
            np.testing.assert_allclose(dense[5 * k + j], plant.advance(x[k], u[k], 0.1 * j), atol=1e-8)
    np.testing.assert_array_equal(dense[-1], x[-1])


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


def test_the_live_config_clears_the_readme_ellipse_at_and_between_the_samples(scene) -> None:
    scenario = scene_scenario(scene, **OFFLINE)
    assert scenario.settings.discretization == "rk4" and scenario.settings.integration_steps > 1
    run, summary = simulate(scenario)
    assert summary["min_clearance"]["readme"] >= -BOUND
    between = summary["between_samples"]
    assert between["min_clearance_obstacles"] >= -BOUND
    assert between["max_penetration_keep_in"] <= BOUND  # |x1 x2| <= 2 between the samples too
    assert summary["settling_step"] is not None and summary["fallbacks"] == 0


def test_the_paper_config_enters_it_between_the_samples_and_the_check_sees_it(scene) -> None:
    """The same scene predicted with the paper's Euler map (as van_der_pol.yaml): the dense check finds
    what the samples hide."""
    paper = scene_scenario(scene, **OFFLINE)
    paper.settings = paper.settings.replace(discretization="euler", integration_steps=1, region_margin=0.0)
    run, summary = simulate(paper)
    assert summary["between_samples"]["min_clearance_obstacles"] < summary["min_clearance"]["readme"] - 0.1
    assert summary["between_samples"]["min_clearance_obstacles"] < -0.1
    direct = clearance_between_samples(paper.settings, make_model("van_der_pol"), run.x, run.u, run.regions)
    assert direct["min_clearance_obstacles"] == summary["between_samples"]["min_clearance_obstacles"]


def test_a_chord_row_flags_a_chord_that_cuts_a_thin_ellipse_and_clears_every_chord_it_passes() -> None:
    """core/nlp/between.py: g along a chord <= (1 - t) g(a) + t g(b) + t (1 - t) c^2 (c normalised): rows
    g(a) <= 0 and g(b) + c^2 <= 0 keep the whole chord out; the sampled ends alone do not."""
    from nmpc_avoid_ros.core.problem.regions import ellipse_chord_sq

    thin = Ellipse((0.0, 0.0), (1.2, 0.15), 0.4, "state")
    slot = thin.slot_values()
    a, b = np.array([0.974, 0.52]), np.array([1.052, 0.336])  # both outside (g -0.29), the chord crosses the tip
    line = [a + t * (b - a) for t in np.linspace(0, 1, 201)]
    c2 = float(ellipse_chord_sq(a, None, b, None, slot, 0.0, 0.0))
    assert thin.depth(a) < 0 and thin.depth(b) < 0 and max(thin.depth(p) for p in line) > 0.05
    assert thin.depth(b) + c2 > 0  # the row sees it
    rng = np.random.default_rng(0)
    cleared = 0
    for _ in range(4000):
        a, b = rng.uniform(-1.6, 1.6, 2), rng.uniform(-1.6, 1.6, 2)
        c2 = float(ellipse_chord_sq(a, None, b, None, slot, 0.0, 0.0))
        if thin.depth(a) <= 0 and thin.depth(b) + c2 <= 0:
            cleared += 1
            assert max(thin.depth(a + t * (b - a)) for t in np.linspace(0, 1, 51)) <= 1e-12
    assert cleared > 500


def test_a_campaign_scene_with_a_thin_ellipse_is_clear_between_the_samples() -> None:
    """Campaign vdp-0274 (seed 0) with the live config on the continuous plant: with the sub-step points
    alone the motion clipped the 1.17 x 0.15 ellipse's tip between them by 0.24 in g; the chord rows keep
    it clear, and |x1 x2| <= 2 within the bound."""
    from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
    from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
    from nmpc_avoid_ros.core.sample.controller import NmpcController

    params = load_params_file(ROOT / "config" / "van_der_pol_live.yaml").section("controller")
    settings = ControllerSettings.from_params(params).replace(**OFFLINE)
    regions = [Ellipse((-1.151396057570926, -1.0583246575245728), (1.1686191696092787, 0.15245754836960676),
                       0.8624660125850363, "state"),
               Ellipse((-2.0017692162609215, 1.1126558358904948), (0.4029768032437231, 0.3155308428301835),
                       1.8190574338544054, "state")]
    run = run_closed_loop(NmpcController(settings), [1.0346166655733864, -1.6059259800145278],
                          [-4.655908510752598], 80, "continuous", regions=lambda k: regions)
    between = clearance_between_samples(settings, make_model("van_der_pol"), run.x[2:], run.u[2:], run.regions[2:])
    assert between["min_clearance_obstacles"] >= -BOUND
    assert between["max_penetration_keep_in"] <= BOUND


def test_keep_in_margin_plans_the_keep_in_set_tightened_by_it() -> None:
    """keep_in_margin: the paper's loop (Euler plant: the prediction is exact) presses against |x1 x2| = 2;
    with the margin its states ride that much inside (the penalty's own optimum up to ~3e-4 beyond)."""
    from nmpc_avoid_ros.core.config.settings import ControllerSettings, load_params_file
    from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
    from nmpc_avoid_ros.core.sample.controller import NmpcController

    params = load_params_file(ROOT / "config" / "van_der_pol.yaml").section("controller")
    settings = ControllerSettings.from_params(params).replace(codegen=False)
    worst = {}
    for margin in (0.0, 0.05):
        run = run_closed_loop(NmpcController(settings.replace(keep_in_margin=margin)), [-5.0, 0.0], [5.0], 30,
                              "euler")
        worst[margin] = float(np.max(np.abs(run.x[:, 0] * run.x[:, 1])))
        assert abs(run.x[-1, 0] - 5.0) < 0.2  # still on its way to the target
    assert worst[0.0] > 2.0 - 1e-3
    assert 2.0 - 0.05 - 0.01 < worst[0.05] <= 2.0 - 0.05 + 1e-3
    with pytest.raises(ConfigError, match="keep_in_margin"):
        settings.replace(keep_in_margin=-0.1)
