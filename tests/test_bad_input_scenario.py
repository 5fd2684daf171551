"""Bad-input corpus, scenario files: every malformed or adversarial scenario gives one
ScenarioError whose message names the file and the offending field (or scenario)."""

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drake_rus.config_schema import ScenarioError
from drake_rus.scenario import ApplyOverrides, LoadScenario, Scenario


def _load(tmp_path, text, name="s"):
    path = tmp_path / "bad.scenarios.yaml"
    path.write_text(text)
    return LoadScenario(filename=path, scenario_name=name), path


# (case id, YAML body of scenario 's', words the message must contain)
FIELD_CASES = [
    ("unknown_top_field", "s: {robott: {}}", ["robott"]),
    ("unknown_nested_field", "s: {contact: {modell: point}}", ["contact.modell"]),
    ("string_for_number", "s: {contact: {time_step: fast}}", ["contact.time_step", "number"]),
    ("negative_time_step", "s: {contact: {time_step: -0.001}}", ["contact.time_step", "> 0"]),
    ("zero_time_step", "s: {contact: {time_step: 0}}", ["contact.time_step"]),
    ("nan_modulus", "s: {contact: {hydroelastic_modulus: .nan}}",
     ["contact.hydroelastic_modulus", "finite"]),
    ("inf_modulus", "s: {contact: {hydroelastic_modulus: .inf}}",
     ["contact.hydroelastic_modulus", "finite"]),
    ("bad_choice", "s: {contact: {model: jelly}}", ["contact.model", "jelly"]),
    ("bad_side", "s: {patient: {side: middle}}", ["patient.side", "middle"]),
    ("bad_posture", "s: {patient: {posture: standing}}", ["patient.posture"]),
    ("short_joint_list", "s: {robot: {initial_joint_positions: [0, 0, 0, -2, 0, 2]}}",
     ["robot.initial_joint_positions", "7"]),
    ("joint_string", "s: {robot: {initial_joint_positions: [0, 0, 0, x, 0, 2, 0]}}",
     ["robot.initial_joint_positions[3]"]),
    ("joint_out_of_limits", "s: {robot: {initial_joint_positions: [0, 0, 0, 0.5, 0, 2, 0]}}",
     ["robot.initial_joint_positions[3]", "limits"]),
    ("bool_for_number", "s: {safety: {force_ceiling: true}}", ["safety.force_ceiling"]),
    ("zero_force_ceiling", "s: {safety: {force_ceiling: 0}}", ["safety.force_ceiling"]),
    ("number_for_bool", "s: {hardware: 1}", ["hardware", "true or false"]),
    ("scalar_for_section", "s: {robot: 3}", ["robot", "mapping"]),
    ("list_for_section", "s: {contact: [1, 2]}", ["contact"]),
    ("float_for_int", "s: {random_seed: 1.5}", ["random_seed", "integer"]),
    ("negative_seed", "s: {random_seed: -1}", ["random_seed"]),
    ("bad_translation", "s: {patient: {X_BPt: {translation: [0.5, 0]}}}",
     ["patient.X_BPt.translation"]),
    ("nan_translation", "s: {probe: {X_FP: {translation: [0, 0, .nan]}}}",
     ["probe.X_FP.translation"]),
    ("bad_rotation", "s: {probe: {X_FP: {rotation: 45}}}", ["probe.X_FP.rotation"]),
    ("bad_rpy_length", "s: {probe: {X_FP: {rotation: !Rpy {deg: [0, 0]}}}}",
     ["probe.X_FP.rotation.deg"]),
    ("unknown_transform_key", "s: {probe: {X_FP: {scale: 2}}}", ["probe.X_FP.scale"]),
    ("negative_probe_mass", "s: {probe: {mass: -0.5}}", ["probe.mass"]),
    ("negative_inertia", "s: {probe: {inertia_diagonal: [0.001, -0.001, 0.001]}}",
     ["probe.inertia_diagonal[1]"]),
    ("bad_segmenter_type", "s: {imaging: {segmenter: 3}}", ["imaging.segmenter"]),
    ("fault_kind", "s: {faults: {sensor: [{kind: gremlins}]}}", ["faults.sensor[0].kind"]),
    ("fault_not_list", "s: {faults: {sensor: {kind: force_spike}}}", ["faults.sensor"]),
    ("fault_unknown_key", "s: {faults: {sensor: [{kind: force_spike, strength: 3}]}}",
     ["faults.sensor[0].strength"]),
    ("fault_negative_start", "s: {faults: {sensor: [{kind: force_bias, start: -1}]}}",
     ["faults.sensor[0].start"]),
    ("breathing_amplitude",
     "s: {patient: {motion: {breathing: {enabled: true, amplitude: 0.2}}}}",
     ["patient.motion.breathing.amplitude"]),
    ("breathing_rate", "s: {patient: {motion: {breathing: {rate_per_min: 90}}}}",
     ["patient.motion.breathing.rate_per_min"]),
    ("shift_too_big", "s: {patient: {motion: {shift: {offset: [0, 0.05, 0]}}}}",
     ["patient.motion.shift.offset[1]"]),
    ("shift_wrong_length", "s: {patient: {motion: {shift: {offset: [0, 0.01]}}}}",
     ["patient.motion.shift.offset"]),
    ("old_breathing_place", "s: {faults: {breathing: {enabled: true}}}",
     ["faults.breathing"]),
    ("random_seed_negative", "s: {random_seed: -1}", ["random_seed"]),
    ("workspace_length", "s: {safety: {workspace_min: [0, 0]}}", ["safety.workspace_min"]),
]


@pytest.mark.parametrize("case_id,text,words", FIELD_CASES, ids=[c[0] for c in FIELD_CASES])
def test_bad_scenario_field_is_named(tmp_path, case_id, text, words):
    with pytest.raises(ScenarioError) as e:
        _load(tmp_path, text)
    message = str(e.value)
    assert "bad.scenarios.yaml" in message and "'s'" in message, message
    for word in words:
        assert word in message, message
    assert "Traceback" not in message


FILE_CASES = [
    ("empty_file", "", ["bad.scenarios.yaml"]),
    ("top_level_list", "- a\n- b\n", ["bad.scenarios.yaml", "map"]),
    ("top_level_scalar", "42\n", ["bad.scenarios.yaml"]),
    ("yaml_syntax", "s: {contact: [\n", ["bad.scenarios.yaml", "YAML"]),
    ("tab_indent", "s:\n\tcontact: {}\n", ["bad.scenarios.yaml"]),
    ("binary_garbage", "\x00\x01\x02\xff", ["bad.scenarios.yaml"]),
]


@pytest.mark.parametrize("case_id,text,words", FILE_CASES, ids=[c[0] for c in FILE_CASES])
def test_bad_scenario_file_is_named(tmp_path, case_id, text, words):
    path = tmp_path / "bad.scenarios.yaml"
    path.write_text(text, errors="surrogateescape") if "\x00" not in text else \
        path.write_bytes(text.encode("latin-1"))
    with pytest.raises(ScenarioError) as e:
        LoadScenario(filename=path, scenario_name="s")
    for word in words:
        assert word in str(e.value), str(e.value)


def test_missing_scenario_file_is_named(tmp_path):
    with pytest.raises(ScenarioError, match="nope.yaml"):
        LoadScenario(filename=tmp_path / "nope.yaml")


def test_unknown_scenario_name_lists_available(tmp_path):
    with pytest.raises(ScenarioError) as e:
        _load(tmp_path, "a: {}\nb: {}\n", name="c")
    assert "'c'" in str(e.value) and "a, b" in str(e.value)


def test_bad_overrides_name_the_field():
    with pytest.raises(ScenarioError, match=r"contact\.time_step"):
        ApplyOverrides(Scenario(), "{contact: {time_step: -1}}")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        ApplyOverrides(Scenario(), "{contact: [")
    with pytest.raises(ScenarioError, match=r"faults\.sensor\[0\]\.kind"):
        ApplyOverrides(Scenario(), "{faults: {sensor: [{kind: 7}]}}")


# ------------------------------------------------------------------ property-based (Hypothesis)
# Numeric leaf fields of the scenario with their constraint; any value outside it must be
# rejected with the field named, any value inside accepted.
NUMERIC_FIELDS = [
    ("contact", "time_step", "positive"), ("contact", "hydroelastic_modulus", "positive"),
    ("contact", "friction", "nonneg"), ("safety", "force_ceiling", "positive"),
    ("safety", "image_timeout", "positive"), ("probe", "mass", "positive"),
    ("faults", "seed", "nonneg_int"),
]

_bad_scalar = st.one_of(
    st.text(st.characters(whitelist_categories=("L", "N", "P", "Zs")), min_size=1, max_size=8)
    .filter(lambda s: s.strip() and s.strip()[0].isalpha()),
    st.just(float("nan")), st.just(float("inf")), st.just(float("-inf")),
    st.lists(st.integers(), max_size=3), st.booleans())


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(NUMERIC_FIELDS), value=_bad_scalar)
def test_property_bad_numeric_value_names_field(tmp_path, field, value):
    section, name, _ = field
    if isinstance(value, float):
        text = {math.isnan(value): ".nan"}.get(True, ".inf" if value > 0 else "-.inf")
    elif isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, list):
        text = str(value)
    else:
        text = '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    with pytest.raises(ScenarioError) as e:
        _load(tmp_path, f"s: {{{section}: {{{name}: {text}}}}}")
    assert f"{section}.{name}" in str(e.value), str(e.value)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(NUMERIC_FIELDS),
       value=st.floats(min_value=-1e6, max_value=1e6, allow_nan=False))
def test_property_numbers_accepted_iff_in_range(tmp_path, field, value):
    section, name, rule = field
    if rule == "nonneg_int":
        value = int(value)
    ok = {"positive": value > 0, "nonneg": value >= 0, "nonneg_int": value >= 0}[rule]
    if ok:
        scenario, _ = _load(tmp_path, f"s: {{{section}: {{{name}: {value!r}}}}}")
        assert getattr(getattr(scenario, section), name) == pytest.approx(value)
    else:
        with pytest.raises(ScenarioError, match=f"{section}.{name}"):
            _load(tmp_path, f"s: {{{section}: {{{name}: {value!r}}}}}")


_identifier = st.from_regex(r"[a-z][a-z_]{0,12}", fullmatch=True)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(section=st.sampled_from(["robot", "probe", "patient", "contact", "imaging",
                                "localization", "controller", "safety", "faults"]),
       key=_identifier)
def test_property_unknown_keys_are_named(tmp_path, section, key):
    import dataclasses
    known = {f.name for f in dataclasses.fields(getattr(Scenario(), section))}
    if key in known:
        return
    with pytest.raises(ScenarioError) as e:
        _load(tmp_path, f"s: {{{section}: {{{key}: 1}}}}")
    assert f"{section}.{key}" in str(e.value)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.recursive(st.one_of(st.none(), st.booleans(), st.integers(), st.text(max_size=5)),
                    lambda c: st.one_of(st.lists(c, max_size=3),
                                        st.dictionaries(_identifier, c, max_size=3)),
                    max_leaves=8))
def test_property_adversarial_structures_never_crash(tmp_path, node):
    """Arbitrary nested YAML as a whole scenario: a valid Scenario or a ScenarioError; never
    another exception."""
    import yaml
    path = tmp_path / "adv.scenarios.yaml"
    path.write_text(yaml.safe_dump({"s": node}))
    try:
        LoadScenario(filename=path, scenario_name="s")
    except ScenarioError as e:
        assert "adv.scenarios.yaml" in str(e)


def test_scientific_notation_without_dot_is_a_number(tmp_path):
    """1e-3 is a number in YAML 1.2 and for Drake's loader (it used to be rejected as the
    string '1e-3'); a negative one is still checked against the field's bound."""
    scenario, _ = _load(tmp_path, "s: {contact: {time_step: 1e-3}, "
                                  "probe: {inertia_diagonal: [1e-3, 2e-3, 1e-4]}}")
    assert scenario.contact.time_step == 0.001
    assert scenario.probe.inertia_diagonal == [0.001, 0.002, 0.0001]
    with pytest.raises(ScenarioError, match=r"contact\.time_step.*> 0"):
        _load(tmp_path, "s: {contact: {time_step: -1e-3}}")
