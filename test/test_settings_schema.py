"""One declaration per setting: validation, read-only set, ROS descriptors and the reference's tables derive from it."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import pytest
from rcl_interfaces.msg import ParameterType

from nmpc_avoid_ros.core.config.schema import schema, setting
from nmpc_avoid_ros.core.config.settings import (
    NODE_ONLY_PARAMETERS,
    NODE_SETTINGS,
    RUNTIME_FIELDS,
    SETTINGS,
    ControllerSettings,
    NodeSettings,
)
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.ros.parameters import (
    markdown_table,
    node_settings_from_values,
    settings_from_values,
    settings_specs,
    spec_of,
)
from nmpc_avoid_ros.tools.readme_tables import README, REFERENCE, expected_tables, parameter_rows, reference_tables


def test_reference_parameter_tables_are_the_declared_ones_and_the_readme_has_none():
    """Fails while docs/reference.md and the declarations differ (`make readme` rewrites the tables)."""
    assert reference_tables(REFERENCE.read_text()) == expected_tables()
    assert parameter_rows(README.read_text()) == []


def test_every_field_is_declared_and_the_derived_sets_follow_the_declarations():
    assert list(SETTINGS) == [f.name for f in dataclasses.fields(ControllerSettings)]
    assert RUNTIME_FIELDS == {"state_weights", "input_weights", "kappa", "mu", "feasibility_tolerance",
                              "predict_obstacles", "region_margin", "mismatch_gain", "mismatch_window",
                              "max_mismatch_margin", "max_obstacle_speed", "max_obstacle_stamp_skew",
                              "certificate_tolerance", "certificate_error_after", "escape_guesses_per_sample",
                              "solve_domain_margin", "input_delay", "footprint_radius", "footprint", "command_budget"}
    # the solver budgets are options of the CasADi solver Function, fixed at construction
    assert not {"max_iterations", "max_solve_time", "tolerance", "acceptable_tolerance"} & RUNTIME_FIELDS
    assert NODE_ONLY_PARAMETERS == set(NODE_SETTINGS) | {"use_sim_time"}
    specs = {spec.name: spec for spec in settings_specs()}
    for name, declared in SETTINGS.items():
        descriptor = specs[name].descriptor()
        assert descriptor.read_only == (not declared.runtime), name
        assert declared.description in descriptor.description, name
    key_fields = [name for name in SETTINGS if name not in RUNTIME_FIELDS]
    assert ControllerSettings().structure_key() == tuple(getattr(ControllerSettings(), n) for n in key_fields)
    assert ControllerSettings(mu=0.0).structure_key() == ControllerSettings().structure_key()
    assert ControllerSettings(tolerance=1e-6).structure_key() != ControllerSettings().structure_key()


def test_descriptors_carry_type_range_and_choices():
    horizon = spec_of(SETTINGS["horizon"]).descriptor()
    assert horizon.type == ParameterType.PARAMETER_INTEGER and horizon.read_only
    assert (horizon.integer_range[0].from_value, horizon.integer_range[0].to_value) == (1, 2000)
    mu = spec_of(SETTINGS["mu"]).descriptor()
    assert mu.type == ParameterType.PARAMETER_DOUBLE and not mu.read_only
    assert mu.floating_point_range[0].from_value == 0.0 and "finite number >= 0" in mu.additional_constraints
    weights = spec_of(SETTINGS["state_weights"])
    assert weights.type_ == ParameterType.PARAMETER_DOUBLE_ARRAY and weights.default == [1.0, 1.0]
    assert spec_of(SETTINGS["constraints"]).default is None  # an empty list is declared typed and unset
    behaviour = spec_of(NODE_SETTINGS["stale_behavior"]).descriptor()
    assert "safe_input" in behaviour.description and not behaviour.read_only


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_each_declared_limit_is_enforced(name):
    declared = SETTINGS[name]
    default = ControllerSettings()
    if declared.choices:
        with pytest.raises(ConfigError, match=name):
            default.replace(**{name: "no_such_choice"})
    if declared.kind in ("float", "int") and declared.low is not None:
        below = declared.low if declared.low_open else declared.low - 1
        with pytest.raises(ConfigError, match=name):
            default.replace(**{name: below})
    if declared.kind in ("float", "int") and declared.high is not None:
        with pytest.raises(ConfigError, match=name):
            default.replace(**{name: declared.high + 1})
    if declared.kind == "float" and declared.finite:
        with pytest.raises(ConfigError, match=name):
            default.replace(**{name: math.nan})
    if declared.is_array:
        with pytest.raises(ConfigError, match=name):
            default.replace(**{name: "1, 2"})
    with pytest.raises(ConfigError, match=name):
        default.replace(**{name: {"a": 1}})  # no setting takes a mapping


def test_values_are_normalised_and_refused_alike_from_python_yaml_and_ros():
    s = ControllerSettings(mu=1, state_weights=[2, 3], plane=[1, 0])
    assert isinstance(s.mu, float) and s.state_weights == (2.0, 3.0) and s.plane == (1, 0)
    assert ControllerSettings.from_params({"kappa": "1.0e4"}).kappa == 1e4  # PyYAML reads 1.0e4 as text
    with pytest.raises(ConfigError, match="horizon"):
        ControllerSettings.from_params({"horizon": 5.5})
    with pytest.raises(ConfigError, match="lockstep"):
        NodeSettings(lockstep="yes")
    values = {"mu": 0.0, "stale_behavior": "zero", "target": [5.0], "constraints": None, "use_sim_time": False}
    settings, options = settings_from_values(values), node_settings_from_values(values)
    assert settings.mu == 0.0 and options.stale_behavior == "zero" and options.target == (5.0,)
    with pytest.raises(ConfigError, match="stale_behavior"):
        node_settings_from_values({"stale_behavior": "panic"})


def test_a_new_setting_is_one_declaration():
    """Everything downstream of a declaration comes from it: kind, validation, descriptor, reference row."""

    @dataclass(frozen=True)
    class Extra:
        gain: float = setting(2.0, "a new gain, 1/s", runtime=True, low=0.0, high=10.0)
        names: tuple[str, ...] | None = setting(None, "optional names")

    declared = schema(Extra)
    assert declared["gain"].kind == "float" and declared["names"].kind == "str[]" and declared["names"].optional
    assert declared["gain"].coerce(3) == 3.0
    with pytest.raises(ConfigError, match="gain must be a finite number in \\[0, 10\\]"):
        declared["gain"].coerce(11.0)
    spec = spec_of(declared["gain"])
    assert not spec.read_only and spec.float_range == (0.0, 10.0)
    row = markdown_table([spec]).splitlines()[-1]
    assert row == "| `gain` | `2.0` | run time | a new gain, 1/s. Allowed: a finite number in [0, 10]. |"


def test_make_readme_rewrites_a_stale_table_and_check_reports_it(tmp_path, capsys):
    from nmpc_avoid_ros.tools.readme_tables import main

    stale = tmp_path / "reference.md"
    declared = REFERENCE.read_text()
    stale.write_text(declared.replace("| `mu` | `100000000.0` | run time |", "| `mu` | `1.0` | run time |"))
    assert main([str(stale), "--check"]) == 1 and "`mu`" in capsys.readouterr().out
    assert main([str(stale)]) == 0 and stale.read_text() == declared
    assert main([str(stale), "--check"]) == 0
    assert main([str(tmp_path / "missing.md")]) == 2
    # a parameter table in the README fails both modes (the front door lists none)
    readme = tmp_path / "README.md"
    row = next(line for line in declared.splitlines() if line.startswith("| `mu` |"))
    readme.write_text(f"{README.read_text()}\n| parameter | default | change | meaning |\n|---|---|---|---|\n{row}\n")
    assert main([str(stale), "--check", "--readme", str(readme)]) == 1
    assert main([str(stale), "--readme", str(readme)]) == 1 and "`mu`" in capsys.readouterr().err
