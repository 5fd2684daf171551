"""Scenario loading: named scenarios, anchors, overrides, and one clear error per mistake."""

import textwrap

import pytest

from drake_rus.scenario import (
    DEFAULT_SCENARIOS_FILE,
    ApplyOverrides,
    ListScenarios,
    LoadScenario,
    Scenario,
    ScenarioError,
)


def test_default_file_scenarios_load():
    names = ListScenarios()
    assert {"default", "point_contact", "hardware"} <= set(names)
    for name in names:
        scenario = LoadScenario(scenario_name=name)
        assert isinstance(scenario, Scenario)
    assert LoadScenario(scenario_name="point_contact").contact.model == "point"
    assert LoadScenario(scenario_name="hardware").hardware is True
    # The anchor carries the probe calibration into the derived scenario.
    assert list(LoadScenario(scenario_name="point_contact").probe.X_FP.translation) == [0, 0, 0.2]


def _write(tmp_path, text):
    path = tmp_path / "s.scenarios.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def test_anchors_and_merges(tmp_path):
    path = _write(
        tmp_path,
        """
        base: &base
          probe: &probe
            mass: 0.8
          contact: {model: point}
        derived:
          <<: *base
          probe:
            <<: *probe
            p_FCm: [0.0, 0.0, 0.1]
        """,
    )
    derived = LoadScenario(filename=path, scenario_name="derived")
    assert derived.probe.mass == 0.8
    assert derived.probe.p_FCm == [0.0, 0.0, 0.1]
    assert derived.contact.model == "point"
    # Unspecified fields keep their defaults.
    assert derived.contact.time_step == Scenario().contact.time_step


@pytest.mark.parametrize(
    "text, field, expected",
    [
        ("contact: {modle: point}", "contact.modle", "not a known field of ContactConfig"),
        ("contact: {model: pointy}", "contact.model", "expected one of 'hydroelastic', 'point'"),
        ("contact: {time_step: fast}", "contact.time_step", "expected a number"),
        ("contact: {time_step: -0.001}", "contact.time_step", "> 0"),
        ("hardware: 3", "hardware", "expected true or false"),
        (
            "robot: {initial_joint_positions: [0, 0, 0]}",
            "robot.initial_joint_positions",
            "list of 7 values",
        ),
        (
            "robot: {initial_joint_positions: [0, 0, 0, -2, 0, 2, 9]}",
            "robot.initial_joint_positions[6]",
            "outside the FR3 joint 7 limits",
        ),
        ("robot: {driver_kp: [1, 1, 1, 1, 1, 1, 0]}", "robot.driver_kp[6]", "> 0"),
        ("probe: {X_FP: {translation: [0, 0]}}", "probe.X_FP.translation", "3 finite numbers"),
        (
            "probe: {X_FP: {rotation: !Rpy {deg: [0, 0]}}}",
            "probe.X_FP.rotation.deg",
            "3 finite numbers",
        ),
        ("probe: {X_FP: {shift: [0, 0, 1]}}", "probe.X_FP.shift", "not a known field"),
        ("probe: {mass: .nan}", "probe.mass", "finite"),
        ("patient: {side: middle}", "patient.side", "expected one of"),
        ("probe: 3", "probe", "expected a mapping"),
        ("robott: {}", "robott", "not a known field of Scenario"),
    ],
)
def test_bad_field_names_the_field(tmp_path, text, field, expected):
    path = _write(tmp_path, f"bad:\n  {text}\n")
    with pytest.raises(ScenarioError) as info:
        LoadScenario(filename=path, scenario_name="bad")
    message = str(info.value)
    assert f"'{field}'" in message, message
    assert expected in message, message
    assert str(path) in message and "'bad'" in message


def test_missing_file_and_scenario(tmp_path):
    with pytest.raises(ScenarioError, match="scenario file not found: .*nope.yaml"):
        LoadScenario(filename=tmp_path / "nope.yaml")
    with pytest.raises(ScenarioError, match="scenario 'nope' is not in .*available: default"):
        LoadScenario(scenario_name="nope")


def test_invalid_yaml_and_empty_file(tmp_path):
    bad = tmp_path / "broken.yaml"
    bad.write_text("default: {robot: [\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        LoadScenario(filename=bad)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(ScenarioError, match="must map scenario names"):
        LoadScenario(filename=empty)


def test_overrides():
    scenario = LoadScenario(scenario_text="{contact: {model: point, friction: 0.4}}")
    assert scenario.contact.model == "point" and scenario.contact.friction == 0.4
    again = ApplyOverrides(scenario, "{probe: {mass: 0.7}}")
    assert again.probe.mass == 0.7 and again.contact.model == "point"
    with pytest.raises(ScenarioError, match="'contact.frction'"):
        ApplyOverrides(scenario, "{contact: {frction: 0.4}}")
    assert DEFAULT_SCENARIOS_FILE.is_file()


def _leaves(node, path=""):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, f"{path}.{k}" if path else k)
    else:
        yield path, node


def test_the_dataclasses_are_the_default_scenario():
    """Every default is stated once: ``Scenario()`` is what ``--scenario default`` runs."""
    from pydrake.common.yaml import yaml_dump_typed

    from drake_rus.scenario import Scenario

    assert yaml_dump_typed(Scenario()) == yaml_dump_typed(LoadScenario())


def test_named_scenarios_state_only_their_differences():
    """A value a named scenario writes must differ from the default it overrides (else it is
    a second statement of the default, free to drift from it)."""
    import yaml

    from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, Scenario

    raw = yaml.safe_load(DEFAULT_SCENARIOS_FILE.read_text())
    default = Scenario()
    repeated = []
    for name, node in raw.items():
        for path, value in _leaves(node or {}):
            obj = default
            for part in path.split("."):
                obj = getattr(obj, part)
            if obj == value:
                repeated.append(f"{name}: {path} = {value!r}")
    assert not repeated, f"named scenarios repeat defaults: {repeated}"
