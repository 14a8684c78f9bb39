"""Models declared as data (core/problem/model_files.py): the shipped files, a user's file by path, a model
registered by another package's entry point, and malformed files refused in one line naming file and line."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from fuzzing import fuzz_settings
from hypothesis import given
from hypothesis import strategies as st

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.closed_loop import run_closed_loop
from nmpc_avoid_ros.core.loop.intersample import dense_run
from nmpc_avoid_ros.core.problem.model_files import ModelFileError, load_model_file
from nmpc_avoid_ros.core.problem.models import MODEL_DIR, MODELS, make_model, model_names
from nmpc_avoid_ros.core.problem.shapes import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController

#: a damped pendulum driven by a torque: not shipped, written as a user would
PENDULUM = textwrap.dedent("""\
    name: pendulum
    parameters: {g: 9.81, l: 1.0, b: 0.5}
    states: [theta, omega]
    inputs: [torque]
    outputs: [angle]
    dynamics:
      theta: omega
      omega: -g/l*sin(theta) - b*omega + torque
    output:
      angle: theta
    steady_state:
      states: {theta: angle, omega: 0*angle}
      inputs: {torque: g/l*sin(angle)}
    bounds: {state_min: [-3.0, -4.0], state_max: [3.0, 4.0], input_min: [-12.0], input_max: [12.0]}
    """)


def write(tmp_path: Path, text: str, name: str = "model.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_every_shipped_model_is_a_model_file_and_loads():
    files = sorted(p.stem for p in MODEL_DIR.glob("*.yaml"))
    assert files == sorted(MODELS)
    assert {"van_der_pol", "double_integrator_2d", "unicycle", "unicycle_pose"} <= set(files)
    for name in files:
        model = make_model(name)
        assert model.name == name and model.source.endswith(f"{name}.yaml")
        assert set(model.bounds) == {"state_min", "state_max", "input_min", "input_max"}


def test_the_shipped_van_der_pol_file_is_the_papers_oscillator():
    model = make_model("van_der_pol")
    x, u = np.array([1.5, -0.7]), np.array([2.0])
    np.testing.assert_array_equal(np.asarray(model.dynamics(x, u)).ravel(),
                                  [x[1], 0.2 * (1 - x[0] ** 2) * x[1] - x[0] + u[0]])
    x_s, u_s = model.steady_state(np.array([3.0]))
    np.testing.assert_array_equal(np.asarray(x_s).ravel(), [3.0, 0.0])
    np.testing.assert_array_equal(np.asarray(u_s).ravel(), [3.0])


def test_a_users_model_file_named_by_its_path_runs_a_closed_loop_with_the_bounds_it_declares(tmp_path):
    path = write(tmp_path, PENDULUM, "pendulum.yaml")
    settings = ControllerSettings.from_params({"model": str(path), "horizon": 10, "sample_time": 0.1,
                                               "discretization": "rk4", "mu": 0.0, "keep_in": [],
                                               "state_weights": [1.0, 0.1], "input_weights": [0.01]})
    assert settings.state_min == (-3.0, -4.0) and settings.input_max == (12.0,)  # Z from the model file
    run = run_closed_loop(NmpcController(settings), [0.0, 0.0], [1.0], 60, "continuous")
    assert abs(run.x[-1, 0] - 1.0) < 1e-3 and abs(run.x[-1, 1]) < 1e-3
    assert np.all(np.abs(run.u) <= 12.0 + 1e-9)


def test_a_model_registered_by_another_packages_entry_point_is_found_by_name(tmp_path, monkeypatch):
    """A real distribution on sys.path: its dist-info declares the entry point, its module returns the file."""
    (tmp_path / "my_pendulum").mkdir()
    write(tmp_path / "my_pendulum", PENDULUM, "pendulum.yaml")
    (tmp_path / "my_pendulum" / "__init__.py").write_text(
        "from pathlib import Path\n\n\ndef pendulum():\n    return Path(__file__).parent / 'pendulum.yaml'\n")
    info = tmp_path / "my_pendulum-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-pendulum\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[nmpc_avoid_ros.models]\npendulum = my_pendulum:pendulum\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "pendulum" in model_names()
    model = make_model("pendulum")
    assert model.name == "pendulum" and model.n == 2
    settings = ControllerSettings(model="pendulum")  # Z from the registered model's file, as from a params file
    assert (settings.state_min, settings.input_max) == ((-3.0, -4.0), (12.0,))
    sys.modules.pop("my_pendulum", None)


def test_an_unknown_model_name_lists_the_known_ones():
    with pytest.raises(ConfigError, match="unknown model 'van_der_poll'.*van_der_pol"):
        ControllerSettings(model="van_der_poll")
    with pytest.raises(ConfigError, match="does not exist"):
        ControllerSettings(model="no/such/model.yaml")


BROKEN = {
    "unknown symbol": (PENDULUM.replace("b*omega", "b*omgea"), 8, "unknown name 'omgea'"),
    "missing key": (PENDULUM.replace("outputs: [angle]\n", ""), 0, "missing key(s): outputs"),
    "unknown key": (PENDULUM + "dynamic: {}\n", 15, "unknown key 'dynamic'"),
    "a state without dynamics": (PENDULUM.replace("  theta: omega\n", "", 1), 6, "missing ['theta']"),
    "dynamics of an undeclared state": (PENDULUM.replace("  theta: omega\n", "  theta: omega\n  phi: 0\n", 1),
                                        8, "unknown ['phi']"),
    "NaN bound": (PENDULUM.replace("input_min: [-12.0]", "input_min: [.nan]"), 14, "not NaN"),
    "bound of the wrong size": (PENDULUM.replace("input_min: [-12.0]", "input_min: [-12.0, 1]"), 14, "list 1 numbers"),
    "not an equilibrium": (PENDULUM.replace("torque: g/l*sin(angle)", "torque: g/l*cos(angle)"), 11,
                           "not an equilibrium"),
    "a name used twice": (PENDULUM.replace("outputs: [angle]", "outputs: [theta]"), 0, "used twice"),
    "eval in an expression": (PENDULUM.replace("theta: omega", "theta: __import__('os')"), 7, "not allowed"),
    "not YAML": ("name: [unclosed\n", 2, "not YAML"),
    "not a mapping": ("- 1\n- 2\n", 0, "a model file is a mapping"),
    "both dynamics and a map": (PENDULUM + "sample_time: 0.1\ndiscrete: {theta: theta, omega: omega}\n", 0,
                                "not both or neither"),
    "a map without its sample time": (PENDULUM.replace("dynamics:", "discrete:"), 6, "goes with a `discrete` map"),
    "a parameter that is not a number": (PENDULUM.replace("g: 9.81", "g: heavy"), 2, "finite number"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_a_malformed_model_file_is_refused_in_one_line_naming_file_line_and_cause(tmp_path, case):
    text, line, cause = BROKEN[case]
    path = write(tmp_path, text)
    with pytest.raises(ModelFileError) as info:
        load_model_file(path)
    message = str(info.value)
    assert "\n" not in message and cause in message
    assert message.startswith(f"{path}:{line}: " if line else f"{path}: ")
    with pytest.raises(ConfigError):  # the controller refuses it the same way, before building anything
        NmpcController(ControllerSettings(model=str(path), state_min=(-3.0, -4.0), state_max=(3.0, 4.0),
                                          input_min=(-12.0,), input_max=(12.0,)))


KEYS = ["name", "parameters", "states", "inputs", "outputs", "dynamics", "output", "steady_state", "bounds",
        "planar", "rest", "units", "plane", "angle_outputs"]
YAML_VALUES = st.recursive(st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers() |
                           st.text(max_size=12), lambda inner: st.lists(inner, max_size=3) |
                           st.dictionaries(st.text(max_size=6), inner, max_size=3), max_leaves=8)


@fuzz_settings(150)
@given(st.sampled_from(KEYS), YAML_VALUES)
def test_a_model_file_with_any_key_replaced_by_junk_is_refused_cleanly_or_loads(tmp_path_factory, key, junk):
    data = yaml.safe_load(PENDULUM)
    data[key] = junk
    path = write(tmp_path_factory.mktemp("fuzz"), yaml.safe_dump(data))
    try:
        model = load_model_file(path)
    except ModelFileError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(path))
    else:  # junk that happens to be valid (an empty `units`, a `plane` of two states): a complete model
        assert model.n == 2 and model.m == 1 and model.p == 1


#: the pendulum as a discrete map: one explicit Euler step of 0.1 s, written out
PENDULUM_MAP = PENDULUM.replace("""dynamics:
  theta: omega
  omega: -g/l*sin(theta) - b*omega + torque""", """sample_time: 0.1
discrete:
  theta: theta + 0.1*omega
  omega: omega + 0.1*(-g/l*sin(theta) - b*omega + torque)""")


def test_a_model_declared_as_a_discrete_map_runs_the_loop_its_euler_twin_runs(tmp_path):
    """The map is the continuous pendulum's Euler step: the same closed loop on the prediction model's own plant."""
    assert "discrete:" in PENDULUM_MAP
    mapped, continuous = write(tmp_path, PENDULUM_MAP, "map.yaml"), write(tmp_path, PENDULUM, "ode.yaml")
    base = {"horizon": 10, "sample_time": 0.1, "mu": 0.0, "keep_in": [], "state_weights": [1.0, 0.1],
            "input_weights": [0.01]}
    runs = [run_closed_loop(NmpcController(ControllerSettings.from_params({**base, "model": str(path)})),
                            [0.0, 0.0], [1.0], 40, "euler") for path in (mapped, continuous)]
    np.testing.assert_allclose(runs[0].x, runs[1].x, atol=1e-6)
    assert abs(runs[0].x[-1, 0] - 1.0) < 1e-3
    model = load_model_file(mapped)
    with pytest.raises(ConfigError, match="discrete map over 0.1 s"):
        model.discrete(0.2)
    with pytest.raises(ConfigError, match="integration_steps must be 1"):
        model.discrete(0.1, "rk4", 4)
    with pytest.raises(ConfigError, match="no continuous plant"):
        run_closed_loop(NmpcController(ControllerSettings.from_params({**base, "model": str(mapped)})),
                        [0.0, 0.0], [1.0], 2, "continuous")
    flow = model.flow()  # the straight line between the samples, exact at the sample
    np.testing.assert_allclose(np.asarray(flow([0.2, 0.5], [1.0], 0.1)).ravel(),
                               np.asarray(model.discrete(0.1)([0.2, 0.5], [1.0])).ravel())


@pytest.mark.parametrize("solver", ["ipopt", "fatrop", "sqp", "sqp_hpipm"])
def test_every_solver_path_runs_a_declared_model_past_a_region_between_the_samples(tmp_path, solver):
    """A user's file on each solver path, with sub-step rows and an ellipse in its (theta, omega) plane: it swings
    to the target clear of the ellipse at and between the samples."""
    path = write(tmp_path, PENDULUM, "pendulum.yaml")
    settings = ControllerSettings.from_params({
        "model": str(path), "horizon": 15, "sample_time": 0.1, "discretization": "rk4", "integration_steps": 2,
        "mu": 1e6, "kappa": 100.0, "keep_in": [], "state_weights": [1.0, 0.1], "input_weights": [0.01],
        "solver": solver, "max_solve_time": 30.0, "ellipse_tiers": []})
    ellipse = Ellipse((0.5, 1.5), (0.1, 0.4), frame="state")  # across the swing mu = 0 takes (omega 1.6 at 0.5)
    run = run_closed_loop(NmpcController(settings), [0.0, 0.0], [1.0], 60, "continuous",
                          regions=lambda k: (ellipse,) if k == 0 else None)
    assert abs(run.x[-1, 0] - 1.0) < 1e-2
    dense = dense_run(settings, make_model(str(path)), run.x, run.u, run.regions)[0]
    scaled = (dense[:, :2] - ellipse.center) / ellipse.semi_axes
    assert np.min(np.sum(scaled**2, axis=1)) > 1.0 - 1e-2


def test_a_configs_model_parameters_override_the_files_defaults_and_bad_ones_are_refused_in_one_line(tmp_path):
    path = str(write(tmp_path, PENDULUM))
    x, u = [0.5, 0.0], [0.0]
    default = np.array(ControllerSettings(model=path).build_model().dynamics(x, u)).ravel()
    longer = ControllerSettings(model=path, model_parameters=("l=2.0", "b = 0"))
    assert longer.build_model().parameters == {"g": 9.81, "l": 2.0, "b": 0.0}
    changed = np.array(longer.build_model().dynamics(x, u)).ravel()
    assert changed[1] == pytest.approx(default[1] / 2) and default[1] == pytest.approx(-9.81 * np.sin(0.5))
    # the steady-state map reads them too: the torque holding the pendulum at 0.5 rad halves with l = 2
    x_s, u_s = longer.build_model().steady_state(np.array([0.5]))
    assert float(u_s) == pytest.approx(9.81 / 2 * np.sin(0.5))
    with pytest.raises(ModelFileError, match=r"model\.yaml:2: parameter 'length' is not declared"):
        ControllerSettings(model=path, model_parameters=("length=2.0",))  # refused at construction, not at a build
    for bad in ("l", "l=nan", "l=two", "1l=2", "=2"):
        with pytest.raises(ConfigError, match="model_parameters: .* is not 'name=value' with a finite number"):
            ControllerSettings(model=path, model_parameters=(bad,))
    with pytest.raises(ConfigError, match="'l' given twice"):
        ControllerSettings(model=path, model_parameters=("l=1", "l=2"))
    shipped = ControllerSettings(model="bicycle", model_parameters=("wheelbase=1.0",)).build_model()
    assert shipped.parameters["wheelbase"] == 1.0  # a shipped model is a model file like any other
