"""capture.yaml (docs/design.md §3): its JSON schema and :func:`validate_config`, which names the key,
what was expected and what was found.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import jsonschema
import numpy as np

from sellip.capture.files import (
    CAPTURE_YAML,
    ConfigError,
    UnknownLayoutError,
    more_problems,
)
from sellip.capture.mosaic import MosaicError, mosaic_layout

# --------------------------------------------------------------------------- capture.yaml

_NUMBER = {"type": "number"}
_VECTOR3 = {"type": "array", "items": _NUMBER, "minItems": 3, "maxItems": 3}
_MATRIX3 = {"type": "array", "items": _VECTOR3, "minItems": 3, "maxItems": 3}

CONFIG_SCHEMA: dict = {
    "type": "object",
    "required": ["sensor", "camera", "light", "scene"],
    # Like the sections' keys, a top-level key must be known (a misspelt `scene:` must not pass silently): the four
    # sections, `synthetic` (sellip synth's record), `calibration` (the device's, copied by sellip capture new),
    # `notes`, and any key starting with `x_` (the user's own).
    "additionalProperties": False,
    "patternProperties": {"^x_": {}},
    "properties": {
        "synthetic": {"type": "object"},
        "calibration": {"type": "object"},
        "notes": {},
        "sensor": {
            "type": "object",
            "additionalProperties": False,
            "required": ["width", "height", "bit_depth", "black_level", "white_level",
                         "polarizer_layout", "color_layout"],
            "properties": {
                "width": {"type": "integer", "minimum": 4},
                "height": {"type": "integer", "minimum": 4},
                "bit_depth": {"type": "integer", "minimum": 8, "maximum": 16},
                "black_level": {"oneOf": [
                    {"type": "number", "minimum": 0},
                    {"type": "array", "items": {"type": "array", "items": {"type": "number", "minimum": 0}}},
                ]},
                "white_level": {"type": "number", "exclusiveMinimum": 0},
                "polarizer_layout": {"type": "array", "minItems": 2, "maxItems": 2,
                                     "items": {"type": "array", "minItems": 2, "maxItems": 2,
                                               "items": {"type": "number"}}},
                "color_layout": {"type": "string"},
            },
        },
        "camera": {
            "type": "object",
            "additionalProperties": False,
            "required": ["fx", "fy", "cx", "cy"],
            "properties": {
                "fx": {"type": "number", "exclusiveMinimum": 0},
                "fy": {"type": "number", "exclusiveMinimum": 0},
                "cx": _NUMBER,
                "cy": _NUMBER,
                "distortion": {"type": "array", "items": _NUMBER, "minItems": 4, "maxItems": 5},
                "color_matrix": _MATRIX3,
            },
        },
        "light": {
            "type": "object",
            "additionalProperties": False,
            "required": ["position_m", "polarizer_deg"],
            "properties": {"position_m": _VECTOR3, "polarizer_deg": _NUMBER},
        },
        "scene": {
            "type": "object",
            "additionalProperties": False,
            "required": ["distance_m"],
            "properties": {"distance_m": {"type": "number", "exclusiveMinimum": 0}},
        },
    },
}
"""JSON schema of capture.yaml (docs/design.md §3). ``synthetic``, ``calibration``, ``notes`` and ``x_*`` sections are
kept as they are;
another top-level key is an error, as inside the sections."""


MAX_FIELD_DEG = 150.0
"""A camera.fx (fy) whose field of view over the sensor's width (height) is wider than this is not in raw pixels
(a focal length in millimetres gives ~170 deg); the method's lenses see 10-60 deg."""


def _key_path(parts) -> str:
    return ".".join(str(p) for p in parts) or "(top level)"


def schema_problem(error: jsonschema.ValidationError) -> tuple[str, str]:
    """(key, what was expected) for one jsonschema error."""
    path = list(error.absolute_path)
    if error.validator == "required":
        missing = error.message.split("'")[1] if "'" in error.message else error.message
        return _key_path(path + [missing]), "missing; this key is required"
    if error.validator == "additionalProperties":
        patterns = error.schema.get("patternProperties", {})
        unknown = sorted(key for key in set(error.instance) - set(error.schema["properties"])
                         if not any(re.match(pattern, str(key)) for pattern in patterns))
        allowed = sorted(error.schema["properties"]) + [f"{p.lstrip('^')}..." for p in error.schema.get(
            "patternProperties", {})]
        return _key_path(path + unknown[:1]), f"unknown key; expected only {allowed}"
    if error.validator == "oneOf":
        return _key_path(path), f"expected a number >= 0 or a nested list of numbers >= 0, got {error.instance!r}"
    expected = {
        "type": f"expected a value of type {error.validator_value}",
        "minimum": f"expected >= {error.validator_value}",
        "maximum": f"expected <= {error.validator_value}",
        "exclusiveMinimum": f"expected > {error.validator_value}",
        "minItems": f"expected at least {error.validator_value} items",
        "maxItems": f"expected at most {error.validator_value} items",
    }.get(error.validator, error.message)
    return _key_path(path), f"{expected}, got {error.instance!r}"


def validate_config(config: Mapping, file_label: str = CAPTURE_YAML) -> dict:
    """Check a capture.yaml mapping and return a copy with defaults filled in.

    Defaults: camera.distortion = [0, 0, 0, 0, 0], camera.color_matrix = identity.
    Raises ConfigError (UnknownLayoutError for layouts) naming the key and the expectation.
    """
    if not isinstance(config, Mapping):
        raise ConfigError(file_label, None, f"expected a mapping with sections sensor/camera/light/scene, "
                                            f"got {type(config).__name__}")
    errors = sorted(jsonschema.Draft7Validator(CONFIG_SCHEMA).iter_errors(config),
                    key=lambda e: [str(p) for p in e.absolute_path])
    if errors:
        key, problem = schema_problem(errors[0])
        others = [f"key '{k}': {p}" for k, p in map(schema_problem, errors[1:])]
        raise ConfigError(file_label, f"key '{key}'", problem + more_problems(others))

    cfg = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in config.items()}
    sensor, camera = cfg["sensor"], cfg["camera"]
    for key in ("width", "height", "bit_depth"):
        sensor[key] = int(sensor[key])
    try:
        layout = mosaic_layout(sensor["polarizer_layout"], sensor["color_layout"])
    except MosaicError as exc:
        key = "sensor.color_layout" if "color_layout" in str(exc) else "sensor.polarizer_layout"
        raise UnknownLayoutError(file_label, f"key '{key}'", str(exc)) from None
    for key in ("width", "height"):
        if sensor[key] % layout.period:
            raise ConfigError(file_label, f"key 'sensor.{key}'",
                              f"expected a multiple of the mosaic period {layout.period}, got {sensor[key]}")
    max_code = 2 ** sensor["bit_depth"] - 1
    if sensor["white_level"] > max_code:
        raise ConfigError(file_label, "key 'sensor.white_level'",
                          f"expected at most {max_code} for bit_depth {sensor['bit_depth']}, "
                          f"got {sensor['white_level']}")
    black = np.asarray(sensor["black_level"], dtype=np.float64)
    if black.ndim and black.shape != (layout.period, layout.period):
        raise ConfigError(file_label, "key 'sensor.black_level'",
                          f"expected a number or a {layout.period}x{layout.period} list (one per mosaic position), "
                          f"got shape {black.shape}")
    if np.any(black >= sensor["white_level"]):
        raise ConfigError(file_label, "key 'sensor.black_level'",
                          f"expected below white_level {sensor['white_level']}, got {sensor['black_level']}")
    for key, size in (("fx", sensor["width"]), ("fy", sensor["height"])):
        field_deg = 2 * np.degrees(np.arctan(size / 2 / float(camera[key])))
        if field_deg > MAX_FIELD_DEG:
            raise ConfigError(file_label, f"key 'camera.{key}'",
                              f"{camera[key]} gives a {field_deg:.0f} deg field of view over the {size} raw pixels: "
                              f"wrong units? It is in raw pixels: the focal length over the pixel pitch (e.g. 25 mm / "
                              f"3.45 um = 7246), not millimetres")
    camera.setdefault("distortion", [0.0] * 5)
    camera.setdefault("color_matrix", np.eye(3).tolist())
    if abs(np.linalg.det(np.asarray(camera["color_matrix"], dtype=np.float64))) < 1e-9:
        raise ConfigError(file_label, "key 'camera.color_matrix'", "expected an invertible 3x3 matrix")
    return cfg


