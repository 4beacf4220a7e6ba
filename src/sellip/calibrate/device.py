"""device.yaml: a calibrated device (docs/design.md §3) -- the sensor, camera and light sections of capture.yaml, plus
a ``calibration`` section with each step's residuals and date.

Public API::

    read_device(path, complete=False) -> dict          # validated; complete=True needs sensor, camera and light
    validate_device(device, file_label, complete=False) -> dict
    write_device(path, device) -> Path                 # validated, atomic (temporary file, then rename)
    update_device(path, sections: dict, step: str, record: dict) -> dict   # merge a calibration step's result
    DeviceError

A device.yaml starts with the ``sensor`` section (the datasheet: size, bit depth, black and white level,
polarizer and colour layout); each ``sellip calibrate`` step fills in its part: ``intrinsics`` ->
camera.fx/fy/cx/cy/distortion, ``flash`` -> light.position_m, ``polarization`` -> sensor.polarizer_layout and
light.polarizer_deg (checked; rewritten only when asked), ``color`` -> camera.color_matrix. Each step writes
``calibration.<step>``: its date (UTC, ISO 8601), its inputs and residuals.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Mapping
from pathlib import Path

import jsonschema
import yaml

from sellip.capture import capture_yaml, files
from sellip.capture.writer import yaml_safe
from sellip.yaml_files import DuplicateKeyError, load_yaml_file

DEVICE_SECTIONS = ("sensor", "camera", "light")
STEPS = ("intrinsics", "flash", "polarization", "color")


class DeviceError(files.ConfigError):
    """device.yaml that is not valid: the message names the file, the key and what was expected."""


def validate_device(device: Mapping, file_label: str = "device.yaml", complete: bool = False) -> dict:
    """Check a device mapping: sections sensor (required), camera and light (required when ``complete``),
    calibration (free-form); each section as in capture.yaml (:func:`sellip.io.validate_config`). Returns a
    copy; with ``complete`` the camera's defaults (distortion, color_matrix) are filled in."""
    if not isinstance(device, Mapping):
        raise DeviceError(file_label, None, f"expected a mapping with sections {list(DEVICE_SECTIONS)}, "
                                            f"got {type(device).__name__}")
    unknown = sorted(set(device) - set(DEVICE_SECTIONS) - {"calibration"})
    if unknown:
        raise DeviceError(file_label, f"key '{unknown[0]}'",
                          f"unknown section; expected {list(DEVICE_SECTIONS)} and 'calibration'")
    needed = DEVICE_SECTIONS if complete else ("sensor",)
    for section in needed:
        if section not in device:
            hint = {"camera": "run `sellip calibrate intrinsics` first",
                    "light": "run `sellip calibrate flash` first"}.get(section, "copy it from the camera's datasheet")
            raise DeviceError(file_label, f"key '{section}'", f"missing; {hint}")
    schema = capture_yaml.CONFIG_SCHEMA["properties"]
    for section in DEVICE_SECTIONS:
        if section in device:
            errors = list(jsonschema.Draft7Validator(schema[section]).iter_errors(device[section]))
            if errors:
                error = min(errors, key=lambda e: list(map(str, e.absolute_path)))
                error.path.appendleft(section)
                key, problem = capture_yaml.schema_problem(error)
                raise DeviceError(file_label, f"key '{key}'", problem)
    # The sensor and camera checks of capture.yaml (layouts, levels, an invertible colour matrix), with
    # stand-ins for what a partial device does not have yet.
    stand_in = {"sensor": device["sensor"],
                "camera": device.get("camera", {"fx": float(device["sensor"].get("width", 1)),  # a 53 deg stand-in
                                                "fy": float(device["sensor"].get("width", 1)), "cx": 0.0, "cy": 0.0}),
                "light": device.get("light", {"position_m": [0.0, 0.0, 0.0], "polarizer_deg": 0.0}),
                "scene": {"distance_m": 1.0}}
    try:
        checked = capture_yaml.validate_config(stand_in, file_label)
    except files.ConfigError as exc:
        raise DeviceError(exc.file, exc.where, exc.problem) from None
    out = {"sensor": checked["sensor"]}
    if "camera" in device:
        out["camera"] = checked["camera"] if complete else dict(device["camera"])
    if "light" in device:
        out["light"] = dict(device["light"])
    if "calibration" in device:
        out["calibration"] = dict(device["calibration"] or {})
    return out


def read_device(path: str | Path, complete: bool = False) -> dict:
    """Read and validate device.yaml (see :func:`validate_device`)."""
    path = Path(path)
    if not path.is_file():
        raise files.MissingFileError(str(path), None, "missing; start from the sensor section of your camera's "
                                                   "datasheet (docs/calibration.md)")
    try:
        device = load_yaml_file(path)
    except DuplicateKeyError as exc:
        raise DeviceError(str(path), f"key '{exc.key}'", exc.what) from None
    except yaml.YAMLError as exc:
        raise DeviceError(str(path), None, f"not valid YAML ({exc})") from None
    return validate_device(device, str(path), complete=complete)


def write_device(path: str | Path, device: Mapping) -> Path:
    """Validate and write device.yaml atomically (a temporary sibling renamed into place)."""
    path = Path(path)
    checked = validate_device(device, f"{path} (to be written)")
    ordered = {k: checked[k] for k in (*DEVICE_SECTIONS, "calibration") if k in checked}
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}"
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "w") as f:
            yaml.safe_dump(yaml_safe(ordered), f, sort_keys=False, default_flow_style=None)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def update_device(path: str | Path, sections: Mapping[str, Mapping], step: str, record: Mapping) -> dict:
    """Merge ``sections`` ({section: {key: value}}) into device.yaml at ``path``, record ``calibration.<step>``
    (``record`` plus the date), write it atomically and return the new device."""
    if step not in STEPS:
        raise ValueError(f"step must be one of {STEPS}, got {step!r}")
    device = read_device(path)
    for section, values in sections.items():
        device.setdefault(section, {}).update(yaml_safe(dict(values)))
    calibration = device.setdefault("calibration", {})
    calibration[step] = {"date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                         **yaml_safe(dict(record))}
    write_device(path, device)
    return device
