"""Validation of raw scenario YAML against the typed scenario dataclasses.

Drake's ``yaml_load_typed`` builds the dataclasses but its errors do not say *where* in a
nested scenario a value went wrong ("could not convert string to float: 'foo'"). This module
walks the raw YAML next to the schema first and raises one :class:`ScenarioError` that names
the field path (``contact.hydroelastic_modulus``), the expected form and what was found.

Field constraints are declared on the dataclass fields themselves with ``metadata``:

- ``choices``: the allowed values of a string field;
- ``length``: the exact length of a list field;
- ``min`` / ``max``: bounds of a number (or of every element of a list of numbers);
- ``positive``: the number (or every element) must be > 0.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing

import numpy as np

from pydrake.common.schema import Transform


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


def _check_number(path: str, value, meta: dict, integer: bool = False) -> None:
    if integer:
        if not isinstance(value, int) or isinstance(value, bool):
            raise ScenarioError(f"field '{path}': expected an integer, got {value!r}")
    elif not _is_number(value):
        raise ScenarioError(f"field '{path}': expected a number, got {value!r}")
    if not math.isfinite(float(value)):
        raise ScenarioError(f"field '{path}': expected a finite number, got {value!r}")
    if meta.get("positive") and not value > 0:
        raise ScenarioError(f"field '{path}': expected a number > 0, got {value!r}")
    if "min" in meta and value < meta["min"]:
        raise ScenarioError(f"field '{path}': expected a number >= {meta['min']}, got {value!r}")
    if "max" in meta and value > meta["max"]:
        raise ScenarioError(f"field '{path}': expected a number <= {meta['max']}, got {value!r}")


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
            raise ScenarioError(
                f"field '{where}': expected {_type_name(schema)}, got {data!r}")
        fields = {f.name: f for f in dataclasses.fields(schema)}
        for key, value in data.items():
            if key not in fields:
                known = ", ".join(sorted(fields))
                raise ScenarioError(
                    f"field '{path + '.' if path else ''}{key}' is not a known field of "
                    f"{schema.__name__}; known fields: {known}")
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
                f"known fields: {', '.join(sorted(allowed))}")
        if "translation" in data:
            t = data["translation"]
            if (not isinstance(t, list) or len(t) != 3
                    or not all(_is_number(v) and math.isfinite(v) for v in t)):
                raise ScenarioError(
                    f"field '{where}.translation': expected a list of 3 finite numbers (m), "
                    f"got {t!r}")
        rotation = data.get("rotation")
        if isinstance(rotation, dict):
            for key, n in (("deg", 3), ("axis", 3)):
                if key in rotation:
                    v = rotation[key]
                    if (not isinstance(v, list) or len(v) != n
                            or not all(_is_number(x) and math.isfinite(x) for x in v)):
                        raise ScenarioError(
                            f"field '{where}.rotation.{key}': expected a list of {n} finite "
                            f"numbers, got {v!r}")
        elif rotation is not None:
            raise ScenarioError(
                f"field '{where}.rotation': expected !Rpy {{deg: [r, p, y]}} or "
                f"!AngleAxis {{angle_deg: a, axis: [x, y, z]}}, got {rotation!r}")
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
                f"field '{where}': expected one of {', '.join(map(repr, choices))}, got {data!r}")
        return
    if origin is list:
        (item,) = typing.get_args(schema)
        if not isinstance(data, list):
            raise ScenarioError(f"field '{where}': expected {_type_name(schema)}, got {data!r}")
        if "length" in meta and len(data) != meta["length"]:
            raise ScenarioError(
                f"field '{where}': expected a list of {meta['length']} values, got {len(data)}")
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
            _check_number(where, value, meta, integer=isinstance(value, int) and f.type in (int, "int"))
        elif isinstance(value, str) and meta.get("choices") and value not in meta["choices"]:
            raise ScenarioError(
                f"field '{where}': expected one of {', '.join(map(repr, meta['choices']))}, "
                f"got {value!r}")
        elif isinstance(value, (list, tuple)):
            if "length" in meta and len(value) != meta["length"]:
                raise ScenarioError(
                    f"field '{where}': expected a list of {meta['length']} values, got {len(value)}")
            for i, v in enumerate(value):
                if _is_number(v):
                    _check_number(f"{where}[{i}]", v, meta)
