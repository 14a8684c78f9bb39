"""Steady-state maps, discretisations, settings validation and the params file."""

from __future__ import annotations

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import max_abs_product, settling_step
from nmpc_avoid_ros.core.problem.models import MODELS, make_model


@pytest.mark.parametrize("name", sorted(MODELS))
def test_steady_state_maps_are_equilibria_with_the_right_output(name):
    model = make_model(name)
    rng = np.random.default_rng(1)
    for _ in range(5):
        y = rng.uniform(-3, 3, model.p)
        if model.steady_state is None:  # no closed form (unicycle): the guess near a state must be one
            x_s, u_s = model.steady_guess(y, rng.uniform(-3, 3, model.n))
        else:
            x_s, u_s = (np.asarray(v, float).ravel() for v in model.steady_state(y))
        np.testing.assert_allclose(np.asarray(model.dynamics(x_s, u_s)).ravel(), 0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(model.output(x_s, u_s)).ravel(), y, atol=1e-12)
        for method in ("euler", "rk4"):
            np.testing.assert_allclose(np.asarray(model.discrete(0.5, method)(x_s, u_s)).ravel(), x_s, atol=1e-12)


def test_van_der_pol_euler_map_is_the_papers():
    f = make_model("van_der_pol").discrete(0.5, "euler")
    x, u = np.array([1.5, -0.7]), 2.0
    expected = x + 0.5 * np.array([x[1], 0.2 * (1 - x[0] ** 2) * x[1] - x[0] + u])
    np.testing.assert_allclose(np.asarray(f(x, u)).ravel(), expected)


def test_rk4_is_more_accurate_than_euler():
    from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant

    model = make_model("van_der_pol")
    x, u = np.array([1.0, 0.5]), np.array([0.3])
    exact = ContinuousPlant(model).advance(x, u, 0.1)
    err = {m: np.linalg.norm(np.asarray(model.discrete(0.1, m)(x, u)).ravel() - exact) for m in ("euler", "rk4")}
    assert err["rk4"] < 1e-5 < err["euler"]


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"horizon": 0}, "horizon"),
        ({"mu": -1.0}, "mu"),
        ({"kappa": float("nan")}, "kappa"),
        ({"sample_time": 0.0}, "sample_time"),
        ({"model": "pendulum"}, "unknown"),
        ({"discretization": "trapezoid"}, "discretization"),
        ({"state_min": (1.0, -2.0)}, "state_min"),
        ({"steady_state_scale": 1.5}, "lambda"),
        ({"plane": (0, 0)}, "plane"),
        ({"state_weights": "1,1"}, "list"),
    ],
)
def test_invalid_settings_are_refused_with_the_setting_named(changes, message):
    with pytest.raises(ConfigError, match=message):
        ControllerSettings(**changes)


def test_shipped_config_is_the_papers_example():
    params = load_params_file(default_config_path())
    settings = ControllerSettings.from_params(params.section("controller"))
    # the paper's problem; the budget, the passage mode's horizon (never triggered by the paper's loops)
    # and the real-time path (FATROP, compiled, one escape guess per sample, ellipse tiers) are ours
    assert settings.escape_horizon == 10
    assert settings == ControllerSettings(max_solve_time=settings.max_solve_time, escape_horizon=10, solver="fatrop",
                                          codegen=True, escape_guesses_per_sample=1, ellipse_tiers=(0, 2, 4))
    assert params.section("plant")["initial_state"] == [-5.0, 0.0]
    assert params.section("scenario")["target"] == [5.0]


def test_params_file_errors_are_clear(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("controller: [1, 2")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params_file(bad)
    bad.write_text("controller:\n  mu: 1\n")
    with pytest.raises(ConfigError, match="ros__parameters"):
        load_params_file(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_params_file(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="unknown controller parameter"):
        ControllerSettings.from_params({"muu": 1.0})


@pytest.mark.parametrize("mu,plant,settling,max_product", [
    (0.0, "euler", 18, 10.0), (1e8, "euler", 33, 2.0002), (0.0, "continuous", 22, 6.3445),
    (1e8, "continuous", 38, 1.8363)])
def test_the_shipped_real_time_path_keeps_the_papers_four_loops(paper, shipped_paper, mu, plant, settling, max_product):
    """The shipped config solves with FATROP; its loops are the IPOPT reference's to the solvers' tolerance."""
    fast, reference = shipped_paper(mu, plant), paper(mu, plant)
    np.testing.assert_allclose(fast.x, reference.x, atol=1e-4)
    assert settling_step(fast.x[:, 0], 5.0, 0.05) == settling_step(reference.x[:, 0], 5.0, 0.05) == settling
    assert max_abs_product(fast.x) == pytest.approx(max_product, abs=1e-4)
    assert set(fast.status) == {"ok"}
