"""Settings records: each setting declared once, and everything else derived from that declaration.

A settings record is a frozen dataclass whose fields are declared with :func:`setting`: the field's name, its
type (the annotation), its default, its range or choices, its unit and one line of meaning. From the record

- :func:`record_schema` derives the JSON schema of its config section (config/config.schema.yaml is written from
  it by ``sellip config-schema``; unknown keys are rejected there, ``additionalProperties: false``);
- :func:`record_from_mapping` builds the record from a config section (a job's ``--settings`` JSON): missing keys
  take the declared default, an unknown key is an error naming the nearest valid one;
- :func:`add_settings_argument` gives a stage the one command-line argument that carries the section.

The workflow passes each job only the keys a user (or config/config.yaml) set; the record's default is the only
place a default is written. :func:`nearest` is the "did you mean" of every unknown-key message.

This module imports no other sellip module and nothing heavy: the Snakemake process imports it.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import json
import re
from collections.abc import Iterable, Mapping
from typing import Any


def setting(default: Any, doc: str, *, unit: str | None = None, minimum: float | None = None,
            maximum: float | None = None, exclusive_minimum: float | None = None,
            exclusive_maximum: float | None = None, choices: Iterable | None = None, per_iteration: bool = False,
            min_items: int | None = None, multiple_of: int | None = None) -> Any:
    """A dataclass field declaring one setting: its ``default``, one line of meaning (``doc``), its ``unit``, its
    range (``minimum``/``maximum`` inclusive, ``exclusive_*`` exclusive; for a tuple, of each item), a whole
    number's ``multiple_of`` or its ``choices``, and whether the workflow takes a list of values, one per iteration
    (``per_iteration``).
    Records built directly in Python are not range-checked here (their ``__post_init__`` checks what the numerics
    need); :func:`record_from_mapping` and the config schema check the declared ranges."""
    meta = {"doc": doc, "unit": unit, "minimum": minimum, "maximum": maximum, "exclusiveMinimum": exclusive_minimum,
            "exclusiveMaximum": exclusive_maximum, "enum": list(choices) if choices is not None else None,
            "per_iteration": per_iteration, "minItems": min_items, "multipleOf": multiple_of}
    return dataclasses.field(default=default, metadata={"setting": meta})


def nearest(name: str, valid: Iterable[str]) -> str | None:
    """The valid name closest to ``name`` (difflib), or None when none is close."""
    found = difflib.get_close_matches(str(name), sorted(valid), n=1, cutoff=0.6)
    return found[0] if found else None


def unknown_key_message(path: str, valid: Iterable[str]) -> str:
    """``path`` (dotted: ``fit.shard``) is not a setting: the message names it, the nearest valid key of its
    section and the valid keys."""
    *section, key = path.split(".")
    valid = sorted(valid)
    guess = nearest(key, valid)
    where = f" of {'.'.join(section)}" if section else ""
    hint = f"; did you mean '{'.'.join([*section, guess])}'?" if guess else ""
    return (f"unknown setting '{path}'{hint} (the settings{where}: {', '.join(valid)}). Correct or remove the key; "
            "config/config.schema.yaml lists every setting")


class SettingsError(ValueError):
    """A settings mapping has an unknown key or a value of the wrong type or out of its declared range."""


def _declared(record: type) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(record) if "setting" in f.metadata]


_SCALARS = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}


def _annotation(field: dataclasses.Field) -> str:
    text = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", str(field.type))
    return text.replace(" ", "")


def _value_schema(field: dataclasses.Field) -> dict:
    """The JSON schema of one value of ``field`` (its annotation and declared range)."""
    meta = field.metadata["setting"]
    text = _annotation(field)
    nullable = text.endswith("|None")
    text = text.removesuffix("|None")
    bounds = {k: meta[k] for k in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "multipleOf")
              if meta[k] is not None}
    if meta["enum"] is not None:
        bounds["enum"] = meta["enum"]
    tuple_of = re.fullmatch(r"tuple\[(\w+),\.\.\.\]", text)
    if tuple_of:
        schema = {"type": "array", "items": {"type": _SCALARS[tuple_of.group(1)], **bounds}}
        if meta["minItems"] is not None:
            schema["minItems"] = meta["minItems"]
    elif text in _SCALARS:
        schema = {"type": _SCALARS[text], **bounds}
    else:
        raise TypeError(f"setting {field.name}: annotation {field.type!r} has no JSON-schema type")
    if nullable:
        schema["type"] = [schema["type"], "null"]
    return schema


def describe(field: dataclasses.Field) -> str:
    """One line for ``field``: its meaning, its unit and its declared default (the schema's description; the schema
    carries no JSON-schema ``default``, which Snakemake's validation would write into the config)."""
    meta = field.metadata["setting"]
    default = list(field.default) if isinstance(field.default, tuple) else field.default
    return meta["doc"] + (f" [{meta['unit']}]" if meta["unit"] else "") + f" (default: {json.dumps(default)})"


def record_schema(record: type, *, per_iteration: bool = True) -> dict:
    """The JSON schema of a config section holding (some of) ``record``'s settings: each declared field a property
    of its type, range and description; no other key (``additionalProperties: false``); none required (a missing
    key takes the declared default, which ``x-default`` states for the workflow's planning: a JSON-schema ``default``
    would be written into the config by Snakemake's validation). ``per_iteration``: the fields declared so also take
    a list of values."""
    properties = {}
    for field in _declared(record):
        value = _value_schema(field)
        if per_iteration and field.metadata["setting"]["per_iteration"]:
            value = {"oneOf": [value, {"type": "array", "items": value, "minItems": 1}]}
        default = list(field.default) if isinstance(field.default, tuple) else field.default
        properties[field.name] = {**value, "description": describe(field), "x-default": default}
    return {"type": "object", "x-record": f"{record.__module__}:{record.__qualname__}", "properties": properties,
            "additionalProperties": False}


def _check_value(field: dataclasses.Field, value: Any, where: str) -> Any:
    """``value`` for ``field`` (lists as tuples), or SettingsError naming ``where`` and what was expected."""
    schema = _value_schema(field)

    def fits(item, spec) -> bool:
        kinds = spec["type"] if isinstance(spec["type"], list) else [spec["type"]]
        if item is None:
            return "null" in kinds
        if isinstance(item, bool):
            ok = "boolean" in kinds
        elif isinstance(item, int):
            ok = "integer" in kinds or "number" in kinds
        elif isinstance(item, float):
            ok = "number" in kinds
        elif isinstance(item, str):
            ok = "string" in kinds
        elif isinstance(item, (list, tuple)):
            return "array" in kinds and all(fits(x, spec["items"]) for x in item) \
                and len(item) >= spec.get("minItems", 0)
        else:
            ok = False
        if not ok:
            return False
        if "enum" in spec and item not in spec["enum"]:
            return False
        return not (("minimum" in spec and item < spec["minimum"]) or ("maximum" in spec and item > spec["maximum"])
                    or ("exclusiveMinimum" in spec and item <= spec["exclusiveMinimum"])
                    or ("exclusiveMaximum" in spec and item >= spec["exclusiveMaximum"])
                    or ("multipleOf" in spec and item % spec["multipleOf"] != 0))

    if not fits(value, schema):
        raise SettingsError(f"setting '{where}': {value!r} is not {json.dumps(schema)} ({describe(field)})")
    if isinstance(value, list):
        return tuple(value)
    if isinstance(value, int) and not isinstance(value, bool) and "number" in str(schema["type"]) \
            and "integer" not in str(schema["type"]):
        return float(value)
    return value


def record_from_mapping(record: type, mapping: Mapping | None, section: str = "", base: Any = None):
    """``record`` (or ``base``, a record to start from) with the settings of ``mapping`` (a config section; keys
    missing take the declared default). An unknown key, a value of the wrong type or out of range: SettingsError
    naming ``section.key`` (and for an unknown key the nearest valid one)."""
    fields = {f.name: f for f in _declared(record)}
    values = {}
    for key, value in (mapping or {}).items():
        path = f"{section}.{key}" if section else str(key)
        if key not in fields:
            raise SettingsError(unknown_key_message(path, fields))
        values[key] = _check_value(fields[key], value, path)
    try:
        return dataclasses.replace(base, **values) if base is not None else record(**values)
    except (TypeError, ValueError) as error:
        raise SettingsError(f"settings of {section or record.__name__}: {error}") from None


def as_mapping(settings: Any) -> dict:
    """A settings record as a plain mapping (tuples as lists): what ``--settings`` and a job's log carry."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(settings).items()}


def add_settings_argument(parser: argparse.ArgumentParser, record: type, flag: str = "--settings",
                          section: str = "") -> None:
    """Give ``parser`` the argument ``flag`` that carries ``record``'s settings as one JSON object (the workflow's
    config section; keys left out take the declared defaults). ``args.<flag>`` is the record itself."""
    names = ", ".join(f.name for f in _declared(record))

    def parse(text: str):
        try:
            mapping = json.loads(text)
        except json.JSONDecodeError as error:
            raise argparse.ArgumentTypeError(f"not a JSON object: {error}") from None
        if not isinstance(mapping, dict):
            raise argparse.ArgumentTypeError(f"expected a JSON object of settings, got {text!r}")
        try:
            return record_from_mapping(record, mapping, section)
        except SettingsError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    parser.add_argument(flag, type=parse, default=record(), metavar="JSON",
                        help=f"{record.__name__} as one JSON object (config {section or 'section'}; keys left out take "
                             f"their declared defaults): {names}")


def add_renamed_argument(parser: argparse.ArgumentParser, old: str, new: str) -> None:
    """``old``, an option that was renamed or replaced: given, it is an argument error naming ``new``."""

    class Renamed(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            parser.error(f"{old} was replaced by {new}")

    parser.add_argument(old, action=Renamed, nargs="*", help=argparse.SUPPRESS)
