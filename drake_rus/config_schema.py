"""Validation of raw scenario YAML against the typed scenario dataclasses.

Drake's ``yaml_load_typed`` builds the dataclasses but its errors do not say *where* in a
nested scenario a value went wrong ("could not convert string to float: 'foo'"). This module
walks the raw YAML next to the schema first and raises one :class:`ScenarioError` that names
the field path (``contact.hydroelastic_modulus``), the expected form and what was found.

Field constraints are declared on the dataclass fields themselves with ``metadata``:

- ``choices``: the allowed values of a string field;
- ``length``: the exact length of a list field;
- ``min_length``: the least length of a list field (e.g. a list that must not be empty);
- ``min`` / ``max``: bounds of a number (or of every element of a list of numbers);
- ``positive``: the number (or every element) must be > 0;
- ``seed``: a seed, 0 to :data:`SEED_MAX` (:func:`seed_metadata`).
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing

import numpy as np
from pydrake.common.schema import Transform


def schema_transform(*, xyz=(0.0, 0.0, 0.0), rpy_deg=(0.0, 0.0, 0.0)) -> Transform:
    """A schema ``Transform`` (the YAML form ``{translation: [x, y, z], rotation: !Rpy
    {deg: [r, p, y]}}``) from a translation (m) and roll-pitch-yaw angles (deg): the one
    helper for dataclass defaults, keyword arguments only so the order cannot be mixed up."""
    t = Transform()
    t.translation = list(xyz)
    t.set_rotation_rpy_deg(list(rpy_deg))
    return t


# The seeds a run accepts (``--seed`` options and the scenario's seed fields): 0 to 2**32 - 1.
# The emulator seeds its speckle with 32 bits, so a larger seed would silently repeat a
# smaller one's pictures, and PyTorch's generator refuses 2**64 and above.
SEED_MAX = 2**32 - 1
SEED_RANGE = f"an integer 0-{SEED_MAX}"


def seed_metadata() -> dict:
    """Field metadata of a seed: 0 to :data:`SEED_MAX` (see there); loading refuses any
    other integer in one line with the range."""
    return {"min": 0, "max": SEED_MAX, "seed": True}


class ScenarioError(ValueError):
    """A scenario file, name or field is invalid. The message names which one."""


def _type_name(tp) -> str:
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    if dataclasses.is_dataclass(tp):
        return f"a mapping ({tp.__name__})"
    origin = typing.get_origin(tp)
    if origin is list:
        (arg,) = typing.get_args(tp)
        return f"a list of {_type_name(arg).removeprefix('a ').removeprefix('an ')}s"
    if tp is Transform:
        return "a transform {translation: [x, y, z], rotation: !Rpy {deg: [r, p, y]}}"
    return getattr(tp, "__name__", str(tp))


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# YAML 1.2 (and Drake's typed loader) read 1e-3 as a number; PyYAML's YAML 1.1 rules give
# the string '1e-3'. Such strings are accepted where a float is expected.
_YAML12_FLOAT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)[eE][-+]?[0-9]+")


def _yaml12_float(value):
    if isinstance(value, str) and _YAML12_FLOAT.fullmatch(value.strip()):
        return float(value)
    return value


def physical(lo: float, hi: float, unit: str, why: str, **schema) -> dict:
    """Field metadata of a number (or of every number of a list) with a physical range: the
    bounds, the unit and the reason, stated once, beside the field. Loading refuses a value
    outside with the field, the range and the reason. ``schema``: other metadata (``length``,
    ``positive``, ...)."""
    if not lo < hi:
        raise ValueError(f"physical range: expected lo < hi, got {lo}, {hi}")
    return {**schema, "min": lo, "max": hi, "unit": unit, "why": why}


def _check_number(path: str, value, meta: dict, integer: bool = False) -> None:
    if integer:
        if not isinstance(value, int) or isinstance(value, bool):
            raise ScenarioError(f"field '{path}': expected an integer, got {value!r}")
    elif not _is_number(value):
        raise ScenarioError(f"field '{path}': expected a number, got {value!r}")
    # An int is finite (and float() of a 400-digit one overflows).
    if not isinstance(value, int) and not math.isfinite(float(value)):
        raise ScenarioError(f"field '{path}': expected a finite number, got {value!r}")
    if meta.get("seed") and not 0 <= value <= SEED_MAX:
        raise ScenarioError(f"field '{path}': expected a seed, {SEED_RANGE}, got {value!r}")
    if meta.get("positive") and not value > 0:
        raise ScenarioError(f"field '{path}': expected a number > 0, got {value!r}")
    if "why" in meta and "min" in meta and not meta["min"] <= value <= meta["max"]:
        unit = meta["unit"]
        raise ScenarioError(
            f"field '{path}': {value:g} {unit} is outside the physical range "
            f"{meta['min']:g}-{meta['max']:g} {unit} ({meta['why']})".replace("  ", " ")
        )
    if "min" in meta and value < meta["min"]:
        raise ScenarioError(f"field '{path}': expected a number >= {meta['min']}, got {value!r}")
    if "max" in meta and value > meta["max"]:
        raise ScenarioError(f"field '{path}': expected a number <= {meta['max']}, got {value!r}")


def _check_min_length(where: str, values, meta: dict) -> None:
    n = meta.get("min_length")
    if n is not None and len(values) < n:
        raise ScenarioError(
            f"field '{where}': expected a list of at least {n} value"
            f"{'s' if n > 1 else ''}, got {len(values)}"
        )


# The fixed rotations a scenario's transform may have: Drake's YAML tag (None: untagged, the
# identity) -> its fields. A random rotation (!Uniform) has no single value to build with.
_ROTATION_FIELDS = {
    None: (),
    "!Identity": (),
    "!Rpy": ("deg",),
    "!AngleAxis": ("angle_deg", "axis"),
}
_ROTATION_FORMS = "!Rpy {deg: [r, p, y]} or !AngleAxis {angle_deg: a, axis: [x, y, z]}"


def _check_rotation(where: str, rotation: dict) -> None:
    """Raises ScenarioError naming ``where`` unless the raw rotation mapping is a fixed
    rotation of :data:`_ROTATION_FIELDS` with a finite angle and a non-zero axis."""
    tag = rotation.get("_tag")
    if tag not in _ROTATION_FIELDS:
        random = " (a scenario's transforms are fixed, not random)" if tag == "!Uniform" else ""
        raise ScenarioError(f"field '{where}': expected {_ROTATION_FORMS}, got {tag}{random}")
    known = _ROTATION_FIELDS[tag]
    for key in rotation:
        if key != "_tag" and key not in known:
            if tag is None:
                raise ScenarioError(
                    f"field '{where}.{key}': an untagged rotation is the identity; expected "
                    f"{_ROTATION_FORMS}"
                )
            raise ScenarioError(
                f"field '{where}.{key}' is not a known field of {tag}; known fields: "
                f"{', '.join(known)}"
            )
    if "angle_deg" in rotation:
        angle = _yaml12_float(rotation["angle_deg"])
        if not (_is_number(angle) and math.isfinite(angle)):
            raise ScenarioError(
                f"field '{where}.angle_deg': expected a finite angle in deg, got {angle!r}"
            )
    axis = rotation.get("axis")
    if (
        tag == "!AngleAxis"
        and isinstance(axis, list)
        and all(_is_number(x) for x in axis)
        and not any(axis)
    ):
        raise ScenarioError(f"field '{where}.axis': expected a non-zero axis, got {axis!r}")


def validate(schema, data, path: str = "", meta: dict | None = None) -> None:
    """Raises ScenarioError if ``data`` (raw YAML) does not fit ``schema`` at ``path``."""
    meta = meta or {}
    where = path or "<scenario>"
    origin = typing.get_origin(schema)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(schema) if a is not type(None)]
        if data is None:
            return
        if len(args) == 1:
            return validate(args[0], data, path, meta)
        return  # Drake's own variants; leave to yaml_load_typed.
    if dataclasses.is_dataclass(schema):
        if not isinstance(data, dict):
            raise ScenarioError(f"field '{where}': expected {_type_name(schema)}, got {data!r}")
        fields = {f.name: f for f in dataclasses.fields(schema)}
        for key, value in data.items():
            if key not in fields:
                name = f"{path + '.' if path else ''}{key}"
                head = str(key).split(":")[0].strip()
                if ":" in str(key) and head in fields:
                    # YAML reads {a:{b:1}} as one key "a:{b:1}": a colon needs a space.
                    raise ScenarioError(
                        f"field '{name}': YAML needs a space after each colon: write "
                        f"'{head}: ...', e.g. {{controller: {{scan_speed: 0.01}}}}"
                    )
                known = ", ".join(sorted(fields))
                raise ScenarioError(
                    f"field '{name}' is not a known field of "
                    f"{schema.__name__}; known fields: {known}"
                )
            f = fields[key]
            hint = typing.get_type_hints(schema)[key]
            validate(hint, value, f"{path}.{key}" if path else key, dict(f.metadata))
        return
    if schema is Transform:
        if not isinstance(data, dict):
            raise ScenarioError(f"field '{where}': expected {_type_name(schema)}, got {data!r}")
        allowed = {"base_frame", "translation", "rotation"}
        extra = set(data) - allowed
        if extra:
            raise ScenarioError(
                f"field '{where}.{sorted(extra)[0]}' is not a known field of Transform; "
                f"known fields: {', '.join(sorted(allowed))}"
            )
        if "translation" in data:
            t = data["translation"]
            if (
                not isinstance(t, list)
                or len(t) != 3
                or not all(_is_number(v) and math.isfinite(v) for v in t)
            ):
                raise ScenarioError(
                    f"field '{where}.translation': expected a list of 3 finite numbers (m), "
                    f"got {t!r}"
                )
        rotation = data.get("rotation")
        if isinstance(rotation, dict):
            for key, n in (("deg", 3), ("axis", 3)):
                if key in rotation:
                    v = rotation[key]
                    if (
                        not isinstance(v, list)
                        or len(v) != n
                        or not all(_is_number(x) and math.isfinite(x) for x in v)
                    ):
                        raise ScenarioError(
                            f"field '{where}.rotation.{key}': expected a list of {n} finite "
                            f"numbers, got {v!r}"
                        )
            _check_rotation(f"{where}.rotation", rotation)
        elif rotation is not None:
            raise ScenarioError(
                f"field '{where}.rotation': expected !Rpy {{deg: [r, p, y]}} or "
                f"!AngleAxis {{angle_deg: a, axis: [x, y, z]}}, got {rotation!r}"
            )
        return
    if schema is bool:
        if not isinstance(data, bool):
            raise ScenarioError(f"field '{where}': expected true or false, got {data!r}")
        return
    if schema is float:
        _check_number(where, _yaml12_float(data), meta)
        return
    if schema is int:
        _check_number(where, data, meta, integer=True)
        return
    if schema is str:
        if not isinstance(data, str):
            raise ScenarioError(f"field '{where}': expected a string, got {data!r}")
        choices = meta.get("choices")
        if choices and data not in choices:
            raise ScenarioError(
                f"field '{where}': expected one of {', '.join(map(repr, choices))}, got {data!r}"
            )
        return
    if origin is list:
        (item,) = typing.get_args(schema)
        if not isinstance(data, list):
            raise ScenarioError(f"field '{where}': expected {_type_name(schema)}, got {data!r}")
        if "length" in meta and len(data) != meta["length"]:
            raise ScenarioError(
                f"field '{where}': expected a list of {meta['length']} values, got {len(data)}"
            )
        _check_min_length(where, data, meta)
        for i, value in enumerate(data):
            validate(item, value, f"{where}[{i}]", meta)
        return
    if origin is dict:
        if not isinstance(data, dict):
            raise ScenarioError(f"field '{where}': expected a mapping, got {data!r}")
        _, value_type = typing.get_args(schema)
        for key, value in data.items():
            validate(value_type, value, f"{where}.{key}", meta)
        return
    if schema is np.ndarray:
        return


def check_dataclass_values(obj, path: str = "") -> None:
    """Checks constraints on a constructed scenario (for scenarios built in code)."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        where = f"{path}.{f.name}" if path else f.name
        meta = dict(f.metadata)
        if dataclasses.is_dataclass(value):
            check_dataclass_values(value, where)
        elif isinstance(value, bool):
            continue
        elif _is_number(value):
            _check_number(
                where, value, meta, integer=isinstance(value, int) and f.type in (int, "int")
            )
        elif isinstance(value, str) and meta.get("choices") and value not in meta["choices"]:
            raise ScenarioError(
                f"field '{where}': expected one of {', '.join(map(repr, meta['choices']))}, "
                f"got {value!r}"
            )
        elif isinstance(value, (list, tuple)):
            if "length" in meta and len(value) != meta["length"]:
                raise ScenarioError(
                    f"field '{where}': expected a list of {meta['length']} values, got {len(value)}"
                )
            _check_min_length(where, value, meta)
            for i, v in enumerate(value):
                if _is_number(v):
                    _check_number(f"{where}[{i}]", v, meta)
                    if "element_min" in meta:
                        lo, hi = meta["element_min"][i], meta["element_max"][i]
                        if not lo <= v <= hi:
                            raise ScenarioError(
                                f"field '{where}[{i}]': {v:g} {meta['unit']} is outside "
                                f"{meta['element_label']} {i + 1} limits [{lo}, {hi}] "
                                f"({meta['why']})"
                            )


# ------------------------------------------------------------------ physical ranges and rules
# Each field's physical range, unit and reason are its metadata (:func:`physical`, beside the
# field); the rules between fields are CROSS_FIELD_RULES below. Each is stated once.
# Breathing rates a patient can have (breaths/min): the cross-field rule on the holds needs
# the fastest, the field's range both.
BREATHING_RATE_MIN = 6.0
BREATHING_RATE_MAX = 30.0
# The patient's bed surface faces up: z_Pt within this angle (deg) of the base's z (the
# simulated patient lies on a level bed under gravity along -z_B; the probe comes from above).
MAX_BED_TILT_DEG = 5.0


def physical_ranges(obj, path: str = "") -> dict:
    """{field path: (min, max, unit, why)} of every field with a physical range in the
    dataclass (instance or class) ``obj``, nested sections included."""
    out = {}
    for f in dataclasses.fields(obj):
        where = f"{path}.{f.name}" if path else f.name
        meta = f.metadata
        if "why" in meta and "min" in meta:
            out[where] = (meta["min"], meta["max"], meta["unit"], meta["why"])
        hint = typing.get_type_hints(obj if isinstance(obj, type) else type(obj))[f.name]
        if dataclasses.is_dataclass(hint):
            out.update(physical_ranges(hint, where))
    return out


# Patient placement: the bed lies within this distance (m) of the robot base (the FR3
# reaches 0.855 m; the bed is beside it).
MAX_PATIENT_DISTANCE = 1.5


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, (int, float)) else repr(v)


# Rules between fields: (fields, holds(scenario) -> bool, what must hold). The first field
# is the one named in the error.
CROSS_FIELD_RULES = [
    (
        ("controller.desired_force", "safety.force_ceiling"),
        lambda s: s.controller.desired_force < s.safety.force_ceiling,
        "the desired force must be below the safety force ceiling (or every scan ends in a "
        "safety stop)",
    ),
    (
        ("contact.time_step", "controller.rate_hz"),
        lambda s: s.contact.time_step <= 1.0 / s.controller.rate_hz + 1e-12,
        "the plant must step at least once per controller period",
    ),
    (
        ("imaging.frame_rate_hz", "contact.time_step"),
        lambda s: s.imaging.frame_rate_hz <= 1.0 / s.contact.time_step + 1e-9,
        "at most one ultrasound frame per plant step",
    ),
    (
        ("controller.max_tip_speed", "safety.command_tip_speed"),
        lambda s: s.controller.max_tip_speed <= s.safety.command_tip_speed,
        "the controller's tip speed must fit within the safety layer's command clamp",
    ),
    (
        ("safety.command_tip_speed", "safety.max_tip_speed"),
        lambda s: s.safety.command_tip_speed <= s.safety.max_tip_speed,
        "the commanded tip speed must be below the speed that stops the robot",
    ),
    (
        ("safety.workspace_min", "safety.workspace_max"),
        lambda s: all(lo < hi for lo, hi in zip(s.safety.workspace_min, s.safety.workspace_max)),
        "every workspace minimum must be below its maximum",
    ),
    (
        ("hardware_interface.command_rate_hz", "controller.rate_hz"),
        lambda s: s.hardware_interface.command_rate_hz >= s.controller.rate_hz - 1e-9,
        "velocity targets must be sent at least as often as the controller computes them",
    ),
    (
        ("controller.start_xy",),
        lambda s: len(s.controller.start_xy) in (0, 2),
        "the landing point is [x (m), y (m)] of the probe tip in the base frame; [] lands "
        "straight down from the start pose",
    ),
    (
        ("controller.pivot_pose",),
        lambda s: len(s.controller.pivot_pose) in (0, 3),
        "a given pivot pose is [x (m), y (m), yaw (rad)]; [] pivots at T* of the registered "
        "kidney pose",
    ),
    (
        ("controller.pivot_pose", "controller.pivot_strategy"),
        lambda s: not (s.controller.pivot_pose and s.controller.pivot_strategy == "predicted_end"),
        "the predicted_end pivot predicts the kidney's ends from the registered pose, which a "
        "scan with a given pivot pose does not make; use pivot_strategy two_leg",
    ),
    (
        ("controller.pivot_pose", "controller.sweep"),
        lambda s: not (s.controller.pivot_pose and s.controller.sweep == "line"),
        "a line sweep has no pivot; give pivot_pose [] or sweep pivot",
    ),
    (
        ("patient.side", "patient.posture"),
        lambda s: not (s.patient.side == "left" and s.patient.posture == "left_lateral_decubitus"),
        "left lateral decubitus lays the left kidney against the bed (it turns the right flank "
        "up for the right kidney); scan the left kidney supine (right lateral decubitus is not "
        "modelled)",
    ),
    (
        ("patient.X_BPt.rotation",),
        lambda s: _bed_tilt_deg(s) <= MAX_BED_TILT_DEG,
        f"the bed's surface must face up: z of the patient frame (the bed's normal) within "
        f"{MAX_BED_TILT_DEG:g} deg of the robot base's z (a patient lies on a level bed, the "
        f"probe comes from above)",
    ),
    (
        ("patient.motion.breathing.hold_duration", "patient.motion.breathing.hold_period"),
        lambda s: (
            not _holds(s)
            or s.patient.motion.breathing.hold_duration < s.patient.motion.breathing.hold_period
        ),
        "a breath-hold must end before the next one starts (hold_duration < hold_period; "
        "hold_period 0 for free breathing only)",
    ),
    (
        ("patient.motion.breathing.hold_duration", "patient.motion.breathing.hold_period"),
        lambda s: (
            not _holds(s)
            or s.patient.motion.breathing.hold_period - s.patient.motion.breathing.hold_duration
            >= 60.0 / BREATHING_RATE_MAX - 1e-9
        ),
        f"between breath-holds the patient must breathe at least once: hold_period - "
        f"hold_duration >= {60.0 / BREATHING_RATE_MAX:g} s (one breath at "
        f"{BREATHING_RATE_MAX:g} breaths/min, the fastest rate modelled)",
    ),
    (
        ("patient.motion.breathing.first_hold",),
        lambda s: (
            not _holds(s)
            or s.patient.motion.breathing.first_hold == 0.0
            or s.patient.motion.breathing.first_hold >= 60.0 / BREATHING_RATE_MAX - 1e-9
        ),
        f"the free breathing before the first hold is at least one breath: first_hold 0 or "
        f">= {60.0 / BREATHING_RATE_MAX:g} s",
    ),
    (
        ("patient.X_BPt.translation",),
        lambda s: (
            float(np.linalg.norm(s.patient.X_BPt.GetDeterministicValue().translation()))
            <= MAX_PATIENT_DISTANCE
        ),
        f"the patient must lie within {MAX_PATIENT_DISTANCE:g} m of the robot base (the FR3 "
        "reaches 0.855 m)",
    ),
]


def _bed_tilt_deg(scenario) -> float:
    """Angle (deg) between the patient frame's z (the bed's normal) and the base's z."""
    R = scenario.patient.X_BPt.GetDeterministicValue().rotation().matrix()
    return float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))


def _holds(scenario) -> bool:
    """The breathing model has breath-holds (hold_period and hold_duration > 0)."""
    b = scenario.patient.motion.breathing
    return b.hold_period > 0.0 and b.hold_duration > 0.0


def check_physical(scenario) -> None:
    """Checks ``CROSS_FIELD_RULES`` on a constructed scenario (each field's own range is
    checked with its metadata, :func:`check_dataclass_values`)."""
    for fields, holds, what in CROSS_FIELD_RULES:
        try:
            ok = holds(scenario)
        except AttributeError:
            continue
        if not ok:
            values = []
            for f in fields:
                try:
                    v = _value_for_message(scenario, f)
                    values.append(f"{f} = {v if isinstance(v, _Text) else _fmt(v)}")
                except AttributeError:
                    pass
            raise ScenarioError(f"field '{fields[0]}': {what}; got {', '.join(values)}")


class _Text(str):
    """A value already written for a message (shown without quotes)."""


def _value_for_message(scenario, path: str):
    if path.endswith("X_BPt.rotation"):
        return _Text(f"z_Pt at {_bed_tilt_deg(scenario):.1f} deg from z_B")
    if path.endswith("X_BPt.translation"):
        return [
            round(float(x), 3) for x in scenario.patient.X_BPt.GetDeterministicValue().translation()
        ]
    return _get(scenario, path)


# ------------------------------------------------------------------------ nesting depth
# How deep scenario YAML may nest (mappings and lists): the schema's deepest field is 5
# levels (patient.X_BPt.rotation.deg[i]), a scenarios file adds the scenario's name, YAML
# anchors one more. Deeper text is not a scenario, and parsing it recurses (Python's YAML
# composer, Drake's loader) until the interpreter's recursion limit.
MAX_YAML_DEPTH = 16


def yaml_depth(text: str) -> tuple[int, int]:
    """(deepest nesting of mappings and lists, its line) of YAML ``text``, counted on the
    token stream (no recursion, whatever the depth). Text that does not scan as YAML gives
    the depth reached before the error (the loader names the error)."""
    import yaml

    opening = (
        yaml.BlockMappingStartToken,
        yaml.BlockSequenceStartToken,
        yaml.FlowMappingStartToken,
        yaml.FlowSequenceStartToken,
    )
    closing = (yaml.BlockEndToken, yaml.FlowMappingEndToken, yaml.FlowSequenceEndToken)
    depth = deepest = line = 0
    try:
        for token in yaml.scan(text, Loader=yaml.SafeLoader):
            if isinstance(token, opening):
                depth += 1
                if depth > deepest:
                    deepest, line = depth, token.start_mark.line + 1
                if deepest > 10 * MAX_YAML_DEPTH:
                    break
            elif isinstance(token, closing):
                depth -= 1
    except yaml.YAMLError:
        pass
    return deepest, line


def check_nesting_depth(text: str, where: str, limit: int = MAX_YAML_DEPTH) -> None:
    """Raises ScenarioError naming ``where`` (``--set``, a file) when YAML ``text`` nests
    deeper than ``limit`` levels."""
    if not text:
        return
    depth, line = yaml_depth(text)
    if depth > limit:
        shown = f"more than {10 * limit}" if depth > 10 * limit else f"{depth}"
        raise ScenarioError(
            f"{where}: the YAML nests {shown} levels deep (line {line}); "
            f"scenario fields nest at most {limit} levels"
        )


# ------------------------------------------------------------------------ YAML errors
def yaml_error_text(error: Exception) -> str:
    """One line for a YAML parse error: the problem, where (line, column) and what the parser
    was doing; PyYAML's own text spans four lines with the source quoted."""
    import yaml

    if isinstance(error, yaml.MarkedYAMLError) and error.problem:
        mark = error.problem_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        context = f" ({error.context})" if error.context else ""
        return f"{error.problem}{where}{context}"
    return " ".join(str(error).split())


# ------------------------------------------------------------------------ duplicate keys
def check_duplicate_keys(text: str, scenarios_file: bool = False) -> None:
    """Raises ScenarioError naming the field path and line of the first key written twice in
    one mapping of the YAML ``text`` (YAML loaders keep the last silently); in a
    ``scenarios_file`` the top-level keys are scenario names. Merge keys
    (``<<: *anchor``) and what they bring in may be overridden, as YAML intends. A null or
    empty key is refused too (the loader fails on it without naming it). Text that is not
    YAML is left to the loader's own error."""
    import yaml

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return
    seen_nodes = set()

    def walk(node, path: str) -> None:
        if node is None or id(node) in seen_nodes:
            return
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            keys = {}
            for key_node, value_node in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge" or key_node.value == "<<":
                    continue
                if key_node.tag == "tag:yaml.org,2002:null":  # `null: 1`, `~: 1`, `: 1`
                    line = key_node.start_mark.line + 1
                    if scenarios_file and not path:
                        raise ScenarioError(f"a scenario name is null or empty (line {line})")
                    scenario, inside = "", path
                    if scenarios_file:
                        name, _, inside = path.partition(".")
                        scenario = f"scenario '{name}': "
                    inside = f" in '{inside}'" if inside else ""
                    raise ScenarioError(
                        f"{scenario}a field name{inside} is null or empty (line {line}); "
                        "expected a field name such as controller or exploration_ratio"
                    )
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                if key is not None:
                    where = f"{path}.{key}" if path else key
                    if key in keys:
                        lines = f"lines {keys[key]} and {key_node.start_mark.line + 1}"
                        if scenarios_file and not path:
                            raise ScenarioError(f"scenario '{key}' is given twice ({lines})")
                        if scenarios_file:
                            name, _, field = where.partition(".")
                            raise ScenarioError(
                                f"scenario '{name}': field '{field}' is "
                                f"given twice ({lines}); remove one"
                            )
                        raise ScenarioError(f"field '{where}' is given twice ({lines}); remove one")
                    keys[key] = key_node.start_mark.line + 1
                    walk(value_node, where)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                walk(item, f"{path}[{i}]")

    walk(root, "")
