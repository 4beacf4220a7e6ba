"""A capture folder (docs/design.md §3) from a folder of raw frames and a calibrated device.yaml
(``sellip capture new``).

Public API::

    parse_pattern(pattern) -> re.Pattern           # '{view}_f{level}.dng' -> a regex with groups view, level
    flash_level(text, file_label) -> float         # '0.25' -> 0.25; '4' (a divisor, "1/4 power") -> 0.25
    frames_from_pattern(files, pattern, exposure_s) -> DataFrame   # frames.csv rows
    frames_from_csv(path, exposure_s=None) -> DataFrame
    fill_exposure(frames, frames_dir, given_by) -> DataFrame   # exposure_s from the files' ExposureTime tags
    check_flash_fired(frames, frames_dir)          # no frame whose file records that the flash did not fire
    failed_steps(device) -> {step: why}            # calibration records with ok: false
    assemble_capture(frames_dir, device, out=None, pattern=None, csv=None, distance_m, exposure_s=None,
                     accept_failed_calibration=False, force=False) -> Path

The frames stay where they are: frames.csv names them relative to the capture folder (``out``, by default
the parent of a frames folder called ``raw``, else the frames folder itself). capture.yaml is the device's
sensor, camera and light sections, ``scene.distance_m`` from the user, and the device's ``calibration``
record. Everything is validated as :func:`sellip.io.read_capture` does (every raw frame opened and checked)
before anything is written; frames.csv and then capture.yaml (the file that marks a capture complete) are
written to temporary names and renamed. Either file already there with other content (the user's edits) stops it
unless ``force``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import pandas as pd
import yaml

from sellip import jobs
from sellip.capture import capture_yaml, reader, tables, writer
from sellip.capture import files as capture_files

RAW_SUFFIXES = capture_files.RAWPY_SUFFIXES + capture_files.TIFF_SUFFIXES + capture_files.PNG_SUFFIXES
FIELDS = {"view": r"(?P<view>[A-Za-z0-9._-]+?)", "level": r"(?P<level>[0-9]+(?:[.][0-9]+)?)"}


class ExistingFileError(capture_files.CaptureError):
    """capture.yaml or frames.csv exists with other content than ``sellip capture new`` would write (no --force)."""


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
    rows, unmatched = [], []
    for name in sorted(files):
        match = regex.match(name)
        if match is None:
            unmatched.append(name)
            continue
        rows.append({"frame_id": Path(name).stem, "view_id": match["view"], "file": name,
                     "flash_level": flash_level(match["level"], name),
                     "exposure_s": float("nan") if exposure_s is None else float(exposure_s)})
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
        table["exposure_s"] = float("nan") if exposure_s is None else float(exposure_s)
    return table[list(capture_files.FRAME_COLUMNS)]


EXPOSURE_RTOL = 0.02
"""An exposure time given on the command line or in the CSV may differ from the one the file records by this
much (relative; cameras round 1/3 stops: 1/250 s is recorded as 0.004)."""


def fill_exposure(frames: pd.DataFrame, frames_dir: Path, given_by: str) -> pd.DataFrame:
    """``frames`` (its ``file`` relative to ``frames_dir``) with every frame's ``exposure_s`` from the file's metadata
    (:func:`sellip.capture.reader.exposure_time`) where none was given; a given time that disagrees with the file's
    by more than :data:`EXPOSURE_RTOL`, or a frame with neither, is an error naming the file."""
    frames = frames.copy()
    times = []
    for row in frames.itertuples(index=False):
        path = frames_dir / row.file
        recorded = reader.exposure_time(path) if path.is_file() else None
        given = float(row.exposure_s)
        if given == given:  # not NaN
            if recorded is not None and abs(given - recorded) > EXPOSURE_RTOL * recorded:
                raise AssembleError(str(path), "ExposureTime",
                                    f"the file records {recorded:g} s but {given_by} says "
                                    f"{given:g} s; leave the exposure out to use the file's, "
                                    "or correct it")
            times.append(given)
        elif recorded is not None:
            times.append(recorded)
        else:
            raise AssembleError(str(path), "ExposureTime", f"the file records no exposure time; give it with "
                                                           f"{given_by} (seconds)")
    frames["exposure_s"] = times
    return frames


def check_flash_fired(frames: pd.DataFrame, frames_dir: Path) -> None:
    """Every frame of a capture is lit by the flash (its ``flash_level`` > 0): a frame whose file records that the
    flash did not fire (:func:`sellip.capture.reader.flash_fired`) is an error naming the file and its row; a file
    that does not say passes."""
    for row_number, row in enumerate(frames.itertuples(index=False), start=1):
        path = frames_dir / row.file
        if path.is_file() and reader.flash_fired(path) is False:
            raise AssembleError(str(path), "Flash",
                                f"the file records that the flash did not fire, but frame {row.frame_id!r} (row "
                                f"{row_number}) has flash_level {row.flash_level:g}: every frame must be lit by "
                                "the flash; leave it out, or shoot it again (a flash not yet recharged?)")


def failed_steps(device: Mapping) -> dict[str, str]:
    """{step: why} for every ``calibration.<step>`` record of a device that says ``ok: false``."""
    out = {}
    for step, record in (device.get("calibration") or {}).items():
        if isinstance(record, Mapping) and record.get("ok") is False:
            messages = record.get("messages") or []
            out[step] = "; ".join(map(str, messages)) or "the step recorded ok: false"
    return out


def _relative(frames_dir: Path, out: Path) -> str:
    return os.path.relpath(frames_dir.resolve(), out.resolve())


def assemble_capture(frames_dir: str | Path, device: Mapping, distance_m: float, out: str | Path | None = None,
                     pattern: str | None = None, csv: str | Path | None = None,
                     exposure_s: float | None = None, check_raw: bool = True,
                     accept_failed_calibration: bool = False, device_label: str = "device.yaml",
                     force: bool = False) -> Path:
    """Write capture.yaml and frames.csv for the raw frames in ``frames_dir`` (module docstring); returns the
    capture folder. ``device``: a complete device (:func:`sellip.calibrate.device.read_device`, complete=True);
    one whose calibration records a failed step is refused unless ``accept_failed_calibration``. Exactly one of
    ``pattern`` and ``csv``. Each frame's exposure time is the one its file records unless given
    (:func:`fill_exposure`). Raises a CaptureError naming what is wrong; writes nothing then. A capture.yaml or
    frames.csv already there with other content (a user's edits) is an ExistingFileError unless ``force``; the
    same content is written again without a word."""
    failed = failed_steps(device)
    if failed and not accept_failed_calibration:
        step, why = next(iter(failed.items()))
        raise AssembleError(device_label, f"key 'calibration.{step}.ok'",
                            f"false: the {step} step failed ({why}); calibrate it again, or give "
                            f"--accept-failed-calibration to use the device as it is"
                            + (f" (failed too: {sorted(failed)[1:]})" if len(failed) > 1 else ""))
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
    given_by = "--exposure-s" if exposure_s is not None or pattern else f"{csv} (column exposure_s) or --exposure-s"
    frames = fill_exposure(frames, frames_dir, given_by)
    check_flash_fired(frames, frames_dir)
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
    texts = {capture_files.FRAMES_CSV: frames.to_csv(index=False, float_format="%.10g"),
             capture_files.CAPTURE_YAML: yaml.safe_dump(writer.yaml_safe(checked), sort_keys=False,
                                                        default_flow_style=None)}
    for name, text in texts.items():  # a capture.yaml or frames.csv the user has edited is never replaced silently
        try:
            jobs.refuse_to_replace(out / name, text, "sellip capture new", force=force)
        except jobs.WouldReplaceError as exc:
            raise ExistingFileError(str(out / name), None, str(exc).split(": ", 1)[1]) from None
    out.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        for name, text in texts.items():  # frames.csv first: capture.yaml marks a capture complete
            tmp = out / f".{name}.tmp-{os.getpid()}"
            written.append(tmp)
            tmp.write_text(text, encoding="utf-8")
        for tmp, name in zip(written, texts):
            tmp.replace(out / name)
    finally:
        for tmp in written:
            tmp.unlink(missing_ok=True)
    reader.read_capture(out)  # the folder as every stage will see it
    return out
