"""A capture folder (DESIGN §3) from a folder of raw frames and a calibrated device.yaml (``sellip capture new``).

Public API::

    parse_pattern(pattern) -> re.Pattern           # '{view}_f{level}.dng' -> a regex with groups view, level
    flash_level(text, file_label) -> float         # '0.25' -> 0.25; '4' (a divisor, "1/4 power") -> 0.25
    frames_from_pattern(files, pattern, exposure_s) -> DataFrame   # frames.csv rows
    frames_from_csv(path, exposure_s=None) -> DataFrame
    assemble_capture(frames_dir, device, out=None, pattern=None, csv=None, distance_m, exposure_s=None) -> Path

The frames stay where they are: frames.csv names them relative to the capture folder (``out``, by default
the parent of a frames folder called ``raw``, else the frames folder itself). capture.yaml is the device's
sensor, camera and light sections, ``scene.distance_m`` from the user, and the device's ``calibration``
record. Everything is validated as :func:`sellip.io.read_capture` does (every raw frame opened and checked)
before anything is written; frames.csv and then capture.yaml (the file that marks a capture complete) are
written to temporary names and renamed.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import pandas as pd
import yaml

from sellip.capture import capture_yaml, reader, tables, writer
from sellip.capture import files as capture_files

RAW_SUFFIXES = capture_files.RAWPY_SUFFIXES + capture_files.TIFF_SUFFIXES + capture_files.PNG_SUFFIXES
FIELDS = {"view": r"(?P<view>[A-Za-z0-9._-]+?)", "level": r"(?P<level>[0-9]+(?:[.][0-9]+)?)"}


class AssembleError(capture_files.CaptureError):
    """A frame folder, pattern or CSV that does not say what a capture needs; names the file and what is missing."""


def parse_pattern(pattern: str) -> re.Pattern:
    """Compile a file-name pattern with the fields ``{view}`` and ``{level}`` (each exactly once; everything
    else literal, ``*`` any characters) into a regex matched against whole file names."""
    fields = re.findall(r"\{([^{}]*)\}", pattern)
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
        raise AssembleError("--pattern", None, f"unknown field {{{unknown[0]}}} in {pattern!r}; "
                                               f"expected {{view}} and {{level}}")
    for name in FIELDS:
        if fields.count(name) != 1:
            raise AssembleError("--pattern", None, f"{{{name}}} must appear exactly once in {pattern!r}")
    regex = ""
    for literal, field in re.findall(r"([^{]*)(?:\{([^{}]*)\})?", pattern):
        regex += ".*".join(re.escape(part) for part in literal.split("*"))
        if field:
            regex += FIELDS[field]
    return re.compile(regex + r"\Z")


def flash_level(text: str, file_label: str) -> float:
    """A flash level from a file name's ``{level}``: a number in (0, 1] is the level itself; a number above 1 is
    the divisor of a flash's "1/N power" setting (4 -> 0.25)."""
    value = float(text)
    if value <= 0:
        raise AssembleError(file_label, "{level}", f"expected a flash level in (0, 1] or a divisor > 1, got {text!r}")
    return value if value <= 1 else 1.0 / value


def frames_from_pattern(files: Iterable[str], pattern: str, exposure_s: float | None) -> pd.DataFrame:
    """frames.csv rows (frame_id = the file's stem) for file names matched by ``pattern``; every raw file must match."""
    regex = parse_pattern(pattern)
    if exposure_s is None:
        raise AssembleError("--exposure-s", None, "missing; the file-name pattern gives view and flash level, "
                                                  "the exposure time must be given (seconds)")
    rows, unmatched = [], []
    for name in sorted(files):
        match = regex.match(name)
        if match is None:
            unmatched.append(name)
            continue
        rows.append({"frame_id": Path(name).stem, "view_id": match["view"], "file": name,
                     "flash_level": flash_level(match["level"], name), "exposure_s": float(exposure_s)})
    if unmatched:
        raise AssembleError(unmatched[0], None, f"does not match --pattern {pattern!r} ({len(unmatched)} file(s) do "
                                                f"not: {unmatched[:3]}); rename them, or give a CSV with --csv")
    if not rows:
        raise AssembleError("--pattern", None, f"no raw frame matches {pattern!r}")
    return pd.DataFrame(rows, columns=capture_files.FRAME_COLUMNS)


def frames_from_csv(path: str | Path, exposure_s: float | None = None) -> pd.DataFrame:
    """frames.csv rows from a user's CSV with columns ``file``, ``view_id``, ``flash_level`` and optionally
    ``frame_id`` (default: the file's stem) and ``exposure_s`` (default: ``exposure_s``)."""
    path = Path(path)
    table = pd.read_csv(path, dtype={"file": str, "view_id": str, "frame_id": str})
    for column in ("file", "view_id", "flash_level"):
        if column not in table:
            raise AssembleError(str(path), f"column '{column}'", "missing; expected columns file, view_id, "
                                                                 "flash_level[, frame_id, exposure_s]")
    if "frame_id" not in table:
        table["frame_id"] = [Path(f).stem for f in table["file"]]
    if "exposure_s" not in table:
        if exposure_s is None:
            raise AssembleError(str(path), "column 'exposure_s'", "missing; add it or give --exposure-s")
        table["exposure_s"] = float(exposure_s)
    return table[list(capture_files.FRAME_COLUMNS)]


def _relative(frames_dir: Path, out: Path) -> str:
    return os.path.relpath(frames_dir.resolve(), out.resolve())


def assemble_capture(frames_dir: str | Path, device: Mapping, distance_m: float, out: str | Path | None = None,
                     pattern: str | None = None, csv: str | Path | None = None,
                     exposure_s: float | None = None, check_raw: bool = True) -> Path:
    """Write capture.yaml and frames.csv for the raw frames in ``frames_dir`` (module docstring); returns the
    capture folder. ``device``: a complete device (:func:`sellip.calibrate.device.read_device`, complete=True).
    Exactly one of ``pattern`` and ``csv``. Raises a CaptureError naming what is wrong; writes nothing then."""
    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        raise AssembleError(str(frames_dir), None, "not a folder; expected the folder of raw frames")
    if (pattern is None) == (csv is None):
        raise AssembleError("sellip capture new", None, "give exactly one of --pattern and --csv")
    if out is None:
        out = frames_dir.parent if frames_dir.name == capture_files.RAW_DIR else frames_dir
    out = Path(out)
    if not distance_m > 0:
        raise AssembleError("--distance-m", None, f"expected the typical camera-object distance in metres (> 0), "
                                                  f"got {distance_m}")
    files = sorted(p.name for p in frames_dir.iterdir() if p.is_file() and p.suffix.lower() in RAW_SUFFIXES)
    if not files:
        raise AssembleError(str(frames_dir), None, f"no raw frames (expected files ending in {list(RAW_SUFFIXES)})")
    frames = frames_from_pattern(files, pattern, exposure_s) if pattern else frames_from_csv(csv, exposure_s)
    prefix = _relative(frames_dir, out)
    frames["file"] = [f if prefix == "." else f"{prefix}/{f}" for f in frames["file"]]
    config = {section: dict(device[section]) for section in ("sensor", "camera", "light")}
    config["scene"] = {"distance_m": float(distance_m)}
    if device.get("calibration"):
        config["calibration"] = device["calibration"]
    checked = capture_yaml.validate_config(config, str(out / capture_files.CAPTURE_YAML))
    frames = tables.validate_frames(frames, str(out / capture_files.FRAMES_CSV))
    for row in frames.itertuples(index=False):
        path = Path(os.path.normpath(out / row.file))  # `out` itself may not exist yet
        if not path.is_file():
            raise capture_files.MissingFileError(str(out / capture_files.FRAMES_CSV), f"frame {row.frame_id!r}",
                                                 f"file {path} missing")
        if check_raw:
            reader.read_raw_file(path, checked["sensor"], file_label=f"{path} (frame {row.frame_id!r})")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        for name, write in ((capture_files.FRAMES_CSV, lambda f: frames.to_csv(f, index=False, float_format="%.10g")),
                            (capture_files.CAPTURE_YAML, lambda f: yaml.safe_dump(writer.yaml_safe(checked), f,
                                                                                  sort_keys=False,
                                                                                  default_flow_style=None))):
            tmp = out / f".{name}.tmp-{os.getpid()}"
            written.append(tmp)
            with open(tmp, "w") as f:
                write(f)
        for tmp, name in zip(written, (capture_files.FRAMES_CSV, capture_files.CAPTURE_YAML)):
            tmp.replace(out / name)
    finally:
        for tmp in written:
            tmp.unlink(missing_ok=True)
    reader.read_capture(out)  # the folder as every stage will see it
    return out
