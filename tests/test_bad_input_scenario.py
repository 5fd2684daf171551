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
    (
        "colon_without_space",
        "s: {controller: {scan_speed:-1}}",
        ["controller.scan_speed:-1", "space after each colon", "scan_speed: ..."],
    ),
    ("string_for_number", "s: {contact: {time_step: fast}}", ["contact.time_step", "number"]),
    ("negative_time_step", "s: {contact: {time_step: -0.001}}", ["contact.time_step", "> 0"]),
    ("zero_time_step", "s: {contact: {time_step: 0}}", ["contact.time_step"]),
    (
        "nan_modulus",
        "s: {contact: {hydroelastic_modulus: .nan}}",
        ["contact.hydroelastic_modulus", "finite"],
    ),
    (
        "inf_modulus",
        "s: {contact: {hydroelastic_modulus: .inf}}",
        ["contact.hydroelastic_modulus", "finite"],
    ),
    ("bad_choice", "s: {contact: {model: jelly}}", ["contact.model", "jelly"]),
    ("bad_side", "s: {patient: {side: middle}}", ["patient.side", "middle"]),
    ("bad_posture", "s: {patient: {posture: standing}}", ["patient.posture"]),
    (
        "short_joint_list",
        "s: {robot: {initial_joint_positions: [0, 0, 0, -2, 0, 2]}}",
        ["robot.initial_joint_positions", "7"],
    ),
    (
        "joint_string",
        "s: {robot: {initial_joint_positions: [0, 0, 0, x, 0, 2, 0]}}",
        ["robot.initial_joint_positions[3]"],
    ),
    (
        "joint_out_of_limits",
        "s: {robot: {initial_joint_positions: [0, 0, 0, 0.5, 0, 2, 0]}}",
        ["robot.initial_joint_positions[3]", "limits"],
    ),
    ("bool_for_number", "s: {safety: {force_ceiling: true}}", ["safety.force_ceiling"]),
    ("zero_force_ceiling", "s: {safety: {force_ceiling: 0}}", ["safety.force_ceiling"]),
    ("number_for_bool", "s: {hardware: 1}", ["hardware", "true or false"]),
    ("scalar_for_section", "s: {robot: 3}", ["robot", "mapping"]),
    ("list_for_section", "s: {contact: [1, 2]}", ["contact"]),
    ("float_for_int", "s: {random_seed: 1.5}", ["random_seed", "integer"]),
    ("negative_seed", "s: {random_seed: -1}", ["random_seed"]),
    (
        "bad_translation",
        "s: {patient: {X_BPt: {translation: [0.5, 0]}}}",
        ["patient.X_BPt.translation"],
    ),
    (
        "nan_translation",
        "s: {probe: {X_FP: {translation: [0, 0, .nan]}}}",
        ["probe.X_FP.translation"],
    ),
    ("bad_rotation", "s: {probe: {X_FP: {rotation: 45}}}", ["probe.X_FP.rotation"]),
    (
        "bad_rpy_length",
        "s: {probe: {X_FP: {rotation: !Rpy {deg: [0, 0]}}}}",
        ["probe.X_FP.rotation.deg"],
    ),
    ("unknown_transform_key", "s: {probe: {X_FP: {scale: 2}}}", ["probe.X_FP.scale"]),
    # Rotations Drake builds but cannot evaluate (a NaN angle, a random rotation), or refuses
    # without naming the field.
    (
        "nan_angle",
        "s: {patient: {X_BPt: {rotation: !AngleAxis {angle_deg: .nan, axis: [0, 0, 1]}}}}",
        ["patient.X_BPt.rotation.angle_deg", "finite"],
    ),
    (
        "inf_angle_probe",
        "s: {probe: {X_FP: {rotation: !AngleAxis {angle_deg: .inf, axis: [0, 0, 1]}}}}",
        ["probe.X_FP.rotation.angle_deg"],
    ),
    (
        "string_angle",
        "s: {probe: {X_FP: {rotation: !AngleAxis {angle_deg: ten, axis: [0, 0, 1]}}}}",
        ["probe.X_FP.rotation.angle_deg"],
    ),
    (
        "zero_axis",
        "s: {probe: {X_FP: {rotation: !AngleAxis {angle_deg: 10, axis: [0, 0, 0]}}}}",
        ["probe.X_FP.rotation.axis", "non-zero"],
    ),
    (
        "random_rotation",
        "s: {patient: {X_BPt: {rotation: !Uniform {}}}}",
        ["patient.X_BPt.rotation", "!Rpy", "fixed"],
    ),
    (
        "untagged_rpy",
        "s: {probe: {X_FP: {rotation: {deg: [0, 0, 90]}}}}",
        ["probe.X_FP.rotation.deg", "!Rpy"],
    ),
    (
        "rpy_in_radians",
        "s: {probe: {X_FP: {rotation: !Rpy {rad: [0, 0, 1]}}}}",
        ["probe.X_FP.rotation.rad", "deg"],
    ),
    ("negative_probe_mass", "s: {probe: {mass: -0.5}}", ["probe.mass"]),
    (
        "negative_inertia",
        "s: {probe: {inertia_diagonal: [0.001, -0.001, 0.001]}}",
        ["probe.inertia_diagonal[1]"],
    ),
    ("bad_segmenter_type", "s: {imaging: {segmenter: 3}}", ["imaging.segmenter"]),
    ("fault_kind", "s: {faults: {sensor: [{kind: gremlins}]}}", ["faults.sensor[0].kind"]),
    ("fault_not_list", "s: {faults: {sensor: {kind: force_spike}}}", ["faults.sensor"]),
    (
        "fault_unknown_key",
        "s: {faults: {sensor: [{kind: force_spike, strength: 3}]}}",
        ["faults.sensor[0].strength"],
    ),
    (
        "fault_negative_start",
        "s: {faults: {sensor: [{kind: force_bias, start: -1}]}}",
        ["faults.sensor[0].start"],
    ),
    (
        "breathing_amplitude",
        "s: {patient: {motion: {breathing: {enabled: true, amplitude: 0.2}}}}",
        ["patient.motion.breathing.amplitude"],
    ),
    (
        "breathing_rate",
        "s: {patient: {motion: {breathing: {rate_per_min: 90}}}}",
        ["patient.motion.breathing.rate_per_min"],
    ),
    (
        "shift_too_big",
        "s: {patient: {motion: {shift: {offset: [0, 0.05, 0]}}}}",
        ["patient.motion.shift.offset[1]"],
    ),
    (
        "shift_wrong_length",
        "s: {patient: {motion: {shift: {offset: [0, 0.01]}}}}",
        ["patient.motion.shift.offset"],
    ),
    ("old_breathing_place", "s: {faults: {breathing: {enabled: true}}}", ["faults.breathing"]),
    ("random_seed_negative", "s: {random_seed: -1}", ["random_seed"]),
    # Seeds: 0 to 2**32 - 1 (config_schema.SEED_MAX); a 400-digit one overflowed float().
    ("random_seed_2_32", "s: {random_seed: 4294967296}", ["random_seed", "0-4294967295"]),
    (
        "random_seed_400_digits",
        "s: {random_seed: 1%s}" % ("0" * 400),
        ["random_seed", "0-4294967295"],
    ),
    (
        "placement_seed_2_64",
        "s: {start: {placement_seed: 18446744073709551616}}",
        ["start.placement_seed", "0-4294967295"],
    ),
    ("motion_seed_2_32", "s: {patient: {motion: {seed: 4294967296}}}", ["patient.motion.seed"]),
    ("faults_seed_2_32", "s: {faults: {seed: 4294967296}}", ["faults.seed", "0-4294967295"]),
    ("workspace_length", "s: {safety: {workspace_min: [0, 0]}}", ["safety.workspace_min"]),
    ("null_field_name", "s: {controller: {null: 1}}", ["null or empty", "in 'controller'"]),
    ("start_xy_length", "s: {controller: {start_xy: [0.5]}}", ["controller.start_xy", "[x (m)"]),
    # Physical ranges (each field's metadata, config_schema.physical), issue 17.
    ("probe_1000_kg", "s: {probe: {mass: 1000}}", ["probe.mass", "0.05-3 kg"]),
    ("probe_feather", "s: {probe: {mass: 0.001}}", ["probe.mass", "physical range"]),
    ("time_step_10_s", "s: {contact: {time_step: 10}}", ["contact.time_step", "0.01 s"]),
    ("time_step_too_fine", "s: {contact: {time_step: 1e-7}}", ["contact.time_step"]),
    ("frame_rate_1e9", "s: {imaging: {frame_rate_hz: 1e9}}", ["imaging.frame_rate_hz", "Hz"]),
    ("frame_rate_tiny", "s: {imaging: {frame_rate_hz: 0.01}}", ["imaging.frame_rate_hz"]),
    ("depth_2_m", "s: {imaging: {depth: 2.0}}", ["imaging.depth", "0.03-0.4 m"]),
    ("depth_1_mm", "s: {imaging: {depth: 0.001}}", ["imaging.depth"]),
    ("preset_1_mm", "s: {imaging: {depth_presets: [0.001, 0.15]}}", ["imaging.depth_presets[0]"]),
    ("probe_radius_1_m", "s: {imaging: {probe_radius: 1.0}}", ["imaging.probe_radius"]),
    (
        "inertia_1000",
        "s: {probe: {inertia_diagonal: [1000, 0.001, 0.001]}}",
        ["probe.inertia_diagonal[0]"],
    ),
    ("com_2_m", "s: {probe: {p_FCm: [0, 0, 2.0]}}", ["probe.p_FCm[2]"]),
    ("modulus_1_pa", "s: {contact: {hydroelastic_modulus: 1}}", ["contact.hydroelastic_modulus"]),
    ("friction_5", "s: {contact: {friction: 5}}", ["contact.friction"]),
    ("controller_rate_1_hz", "s: {controller: {rate_hz: 1}}", ["controller.rate_hz"]),
    ("force_ceiling_500", "s: {safety: {force_ceiling: 500}}", ["safety.force_ceiling"]),
    (
        "command_rate_5_hz",
        "s: {hardware_interface: {command_rate_hz: 5}}",
        ["hardware_interface.command_rate_hz"],
    ),
    (
        "frequency_100_mhz",
        "s: {imaging: {center_frequency_mhz: 100}}",
        ["imaging.center_frequency_mhz"],
    ),
    # Cross-field rules (config_schema.CROSS_FIELD_RULES).
    (
        "force_above_ceiling",
        "s: {controller: {desired_force: 25}}",
        ["controller.desired_force", "safety.force_ceiling = 20"],
    ),
    (
        "force_equal_ceiling",
        "s: {controller: {desired_force: 12}, safety: {force_ceiling: 12}}",
        ["controller.desired_force", "below"],
    ),
    (
        "time_step_slower_than_controller",
        "s: {contact: {time_step: 0.008}, controller: {rate_hz: 200}}",
        ["contact.time_step", "controller.rate_hz = 200"],
    ),
    (
        "frames_faster_than_plant",
        "s: {contact: {time_step: 0.01}, imaging: {frame_rate_hz: 150}}",
        ["imaging.frame_rate_hz", "contact.time_step"],
    ),
    (
        "tip_speed_above_clamp",
        "s: {controller: {max_tip_speed: 0.1}}",
        ["controller.max_tip_speed", "safety.command_tip_speed"],
    ),
    (
        "clamp_above_stop",
        "s: {safety: {command_tip_speed: 0.2}}",
        ["safety.command_tip_speed", "safety.max_tip_speed"],
    ),
    (
        "workspace_inverted",
        "s: {safety: {workspace_min: [0.9, -0.5, -0.05]}}",
        ["safety.workspace_min", "below its maximum"],
    ),
    (
        "command_rate_below_controller",
        "s: {hardware_interface: {command_rate_hz: 50}}",
        ["hardware_interface.command_rate_hz", "controller.rate_hz"],
    ),
    (
        "left_kidney_against_the_bed",
        "s: {patient: {side: left, posture: left_lateral_decubitus}}",
        [
            "patient.side",
            "left kidney against the bed",
            "patient.posture = 'left_lateral_decubitus'",
        ],
    ),
    (
        "patient_100_m_away",
        "s: {patient: {X_BPt: {translation: [100, 0, 0]}}}",
        ["patient.X_BPt.translation", "1.5 m"],
    ),
    (
        "patient_below_floor",
        "s: {patient: {X_BPt: {translation: [0.5, 0, -3]}}}",
        ["patient.X_BPt.translation"],
    ),
    # Duplicate keys: YAML loaders keep the last one silently.
    (
        "duplicate_top_key",
        "s: {contact: {model: point}, contact: {model: hydroelastic}}",
        ["'contact'", "twice"],
    ),
    (
        "duplicate_nested_key",
        "s:\n  probe:\n    mass: 0.5\n    mass: 0.6\n",
        ["probe.mass", "twice", "lines 3 and 4"],
    ),
    (
        "duplicate_in_list_item",
        "s: {faults: {sensor: [{kind: force_spike, kind: force_bias}]}}",
        ["faults.sensor[0].kind", "twice"],
    ),
]


@pytest.mark.parametrize("case_id,text,words", FIELD_CASES, ids=[c[0] for c in FIELD_CASES])
def test_bad_scenario_field_is_named(tmp_path, case_id, text, words):
    with pytest.raises(ScenarioError) as e:
        _load(tmp_path, text)
    message = str(e.value)
    assert "bad.scenarios.yaml" in message, message
    assert "'s'" in message or "twice" in message, message
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
    path.write_text(text, errors="surrogateescape") if "\x00" not in text else path.write_bytes(
        text.encode("latin-1")
    )
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
    ("contact", "time_step", "range"),
    ("contact", "hydroelastic_modulus", "range"),
    ("contact", "friction", "range"),
    ("safety", "force_ceiling", "range"),
    ("safety", "image_timeout", "positive"),
    ("probe", "mass", "range"),
    ("faults", "seed", "nonneg_int"),
]


def _in_range(section, name, value) -> bool:
    """Whether the default scenario with ``section.name = value`` is acceptable: the
    physical range of its field (config_schema.physical_ranges) and the cross-field rules it
    enters."""
    from drake_rus.config_schema import physical_ranges

    lo, hi, _, _ = physical_ranges(Scenario)[f"{section}.{name}"]
    ok = lo <= value <= hi
    if (section, name) == ("contact", "time_step"):  # <= 1 / controller.rate_hz, and
        ok = ok and value <= 0.01 and 20.0 <= 1.0 / value + 1e-9  # one frame per step
    if (section, name) == ("safety", "force_ceiling"):  # above the desired 9 N
        ok = ok and value > 9.0
    return ok


_bad_scalar = st.one_of(
    st.text(
        st.characters(whitelist_categories=("L", "N", "P", "Zs")), min_size=1, max_size=8
    ).filter(lambda s: s.strip() and s.strip()[0].isalpha()),
    st.just(float("nan")),
    st.just(float("inf")),
    st.just(float("-inf")),
    st.lists(st.integers(), max_size=3),
    st.booleans(),
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
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


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    field=st.sampled_from(NUMERIC_FIELDS),
    value=st.floats(min_value=-1e6, max_value=1e6, allow_nan=False),
)
def test_property_numbers_accepted_iff_in_range(tmp_path, field, value):
    section, name, rule = field
    if rule == "nonneg_int":
        value = int(value)
    ok = {
        "positive": value > 0,
        "nonneg_int": value >= 0,
        "range": rule == "range" and _in_range(section, name, value),
    }[rule]
    if ok:
        scenario, _ = _load(tmp_path, f"s: {{{section}: {{{name}: {value!r}}}}}")
        assert getattr(getattr(scenario, section), name) == pytest.approx(value)
    else:
        with pytest.raises(ScenarioError, match=f"{section}.{name}"):
            _load(tmp_path, f"s: {{{section}: {{{name}: {value!r}}}}}")


_identifier = st.from_regex(r"[a-z][a-z_]{0,12}", fullmatch=True)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    section=st.sampled_from(
        [
            "robot",
            "probe",
            "patient",
            "contact",
            "imaging",
            "localization",
            "controller",
            "safety",
            "faults",
        ]
    ),
    key=_identifier,
)
def test_property_unknown_keys_are_named(tmp_path, section, key):
    import dataclasses

    known = {f.name for f in dataclasses.fields(getattr(Scenario(), section))}
    if key in known:
        return
    with pytest.raises(ScenarioError) as e:
        _load(tmp_path, f"s: {{{section}: {{{key}: 1}}}}")
    assert f"{section}.{key}" in str(e.value)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.recursive(
        st.one_of(st.none(), st.booleans(), st.integers(), st.text(max_size=5)),
        lambda c: st.one_of(st.lists(c, max_size=3), st.dictionaries(_identifier, c, max_size=3)),
        max_leaves=8,
    )
)
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
    scenario, _ = _load(
        tmp_path, "s: {contact: {time_step: 1e-3}, probe: {inertia_diagonal: [1e-3, 2e-3, 1e-4]}}"
    )
    assert scenario.contact.time_step == 0.001
    assert scenario.probe.inertia_diagonal == [0.001, 0.002, 0.0001]
    with pytest.raises(ScenarioError, match=r"contact\.time_step.*> 0"):
        _load(tmp_path, "s: {contact: {time_step: -1e-3}}")


# ---------------------------------------------------------------- issue 17: physics and YAML
def test_duplicate_key_in_overrides_is_named():
    with pytest.raises(ScenarioError, match=r"overrides.*'contact\.time_step' is given twice"):
        ApplyOverrides(Scenario(), "{contact: {time_step: 0.001, time_step: 0.002}}")


def test_merge_keys_may_be_overridden(tmp_path):
    """`<<: *anchor` then the same key is YAML's override, not a duplicate."""
    scenario, _ = _load(
        tmp_path,
        "a: &a\n  contact: &c\n    model: point\n"
        "s:\n  <<: *a\n  contact:\n    <<: *c\n    model: hydroelastic\n",
    )
    assert scenario.contact.model == "hydroelastic"


def test_shipped_scenarios_pass_every_rule():
    from drake_rus.scenario import ListScenarios

    for name in ListScenarios():
        LoadScenario(scenario_name=name)


def test_every_physical_range_names_a_real_field_and_holds_by_default():
    from drake_rus.config_schema import CROSS_FIELD_RULES, _get, physical_ranges

    s = Scenario()
    ranges = physical_ranges(Scenario)
    assert len(ranges) >= 21
    for path, (lo, hi, unit, why) in ranges.items():
        value = _get(s, path)
        for v in value if isinstance(value, list) else [value]:
            assert lo <= v <= hi, (path, v)
        assert lo < hi and why
    for fields, holds, what in CROSS_FIELD_RULES:
        assert holds(s), fields
        for f in fields:
            if not f.endswith("translation"):
                _get(s, f)


def test_scenario_file_that_is_a_folder_is_named(tmp_path):
    with pytest.raises(ScenarioError, match="is a folder"):
        LoadScenario(filename=tmp_path)


def test_duplicate_scenario_name_is_named(tmp_path):
    with pytest.raises(ScenarioError, match=r"scenario 's' is given twice \(lines 1 and 2\)"):
        _load(tmp_path, "s: {}\ns: {contact: {model: point}}\n")
