"""Capture folders (DESIGN §3): read, validate and write them.

Public API::

    read_capture(path: str | Path, check_raw: bool = False, check_files: bool = True) -> Capture
    read_raw_frame(capture: Capture, row: str | Mapping | pandas.Series) -> np.ndarray  # (H, W) uint16
    read_raw_file(path: str | Path, sensor: Mapping, file_label: str | None = None) -> np.ndarray
    validate_config(config: Mapping, file_label: str = "capture.yaml") -> dict
    validate_frames(frames: pandas.DataFrame, file_label: str = "frames.csv") -> pandas.DataFrame
    validate_poses(poses: pandas.DataFrame, file_label: str = "poses.csv") -> pandas.DataFrame
    write_raw_file(path: str | Path, raw: np.ndarray, sensor: Mapping) -> None   # .dng / .tif / .png
    CaptureWriter(path, config)  # add_frame, add_pose, path_in_capture, finish (atomic)
    write_capture(path, config, frames, raw_frames, poses=None, raw_format="dng") -> Path
    write_ply(path, vertex: dict, faces) / read_ply(path) -> (dict, faces)
    write_param_mesh(path, mesh: ParamMesh) / read_param_mesh(path) -> ParamMesh   # DESIGN §4 vertex properties

A capture is written into a temporary sibling folder and renamed into place
by :meth:`CaptureWriter.finish`, so a failed run leaves nothing half-written
(capture.yaml, the file that marks a capture complete, never exists alone).

Every validation problem raises a :class:`CaptureError` subclass whose
message names the file, the key or the row and column, and what was expected.
Rows are numbered from 0 as in the DataFrame; the CSV line is row + 2.

Raw frames: DNG and camera RAW files are read with rawpy and only
``raw_image`` is used (the polarization mosaic is not a Bayer pattern; DNGs
written here declare a dummy 2x2 CFA). 16-bit TIFF/PNG files are read as
they are. A frame must be (sensor.height, sensor.width), unsigned integer,
with no value above ``2**bit_depth - 1``.
"""

from __future__ import annotations

import math
import os
import re
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import jsonschema
import numpy as np
import pandas as pd
import pandera.pandas as pa
import yaml

from sellip.mosaic import MosaicError, MosaicLayout, mosaic_layout

CAPTURE_YAML = "capture.yaml"
FRAMES_CSV = "frames.csv"
POSES_CSV = "poses.csv"
RAW_DIR = "raw"
GROUND_TRUTH_DIR = "ground_truth"

RAWPY_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw")
TIFF_SUFFIXES = (".tif", ".tiff")
PNG_SUFFIXES = (".png",)

FRAME_COLUMNS = ("frame_id", "view_id", "file", "flash_level", "exposure_s")
POSE_COLUMNS = ("view_id", "qw", "qx", "qy", "qz", "tx", "ty", "tz")


# --------------------------------------------------------------------------- errors


class CaptureError(ValueError):
    """A capture folder that does not follow DESIGN §3. The message names file, place and expectation."""

    def __init__(self, file: str, where: str | None, problem: str):
        self.file = str(file)
        self.where = where
        self.problem = problem
        super().__init__(f"{self.file}: {where}: {problem}" if where else f"{self.file}: {problem}")


class MissingFileError(CaptureError):
    """A file the capture needs (capture.yaml, frames.csv, a raw frame) does not exist."""


class ConfigError(CaptureError):
    """capture.yaml: a missing, unknown or out-of-range key."""


class UnknownLayoutError(ConfigError):
    """capture.yaml: a polarizer_layout or color_layout that sellip cannot interpret."""


class FramesError(CaptureError):
    """frames.csv: a bad column or row."""


class DuplicateFrameError(FramesError):
    """frames.csv: the same frame_id on more than one row."""


class FlashLevelError(FramesError):
    """frames.csv: a flash_level outside (0, 1]."""


class PosesError(CaptureError):
    """poses.csv: a bad column or row."""


class ViewWithoutFramesError(CaptureError):
    """A view named in poses.csv has no frame in frames.csv."""


class RawFrameError(CaptureError):
    """A raw frame that cannot be read, or has the wrong size, type or bit depth."""


# --------------------------------------------------------------------------- capture.yaml

_NUMBER = {"type": "number"}
_VECTOR3 = {"type": "array", "items": _NUMBER, "minItems": 3, "maxItems": 3}
_MATRIX3 = {"type": "array", "items": _VECTOR3, "minItems": 3, "maxItems": 3}

CONFIG_SCHEMA: dict = {
    "type": "object",
    "required": ["sensor", "camera", "light", "scene"],
    # Like the sections' keys, a top-level key must be known (a misspelt `scene:` must not pass silently): the four
    # sections, `synthetic` (sellip synth's record), `notes`, and any key starting with `x_` (the user's own).
    "additionalProperties": False,
    "patternProperties": {"^x_": {}},
    "properties": {
        "synthetic": {"type": "object"},
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
"""JSON schema of capture.yaml (DESIGN §3). ``synthetic``, ``notes`` and ``x_*`` sections are kept as they are;
another top-level key is an error, as inside the sections."""


def _key_path(parts) -> str:
    return ".".join(str(p) for p in parts) or "(top level)"


def _schema_problem(error: jsonschema.ValidationError) -> tuple[str, str]:
    """(key, what was expected) for one jsonschema error."""
    path = list(error.absolute_path)
    if error.validator == "required":
        missing = error.message.split("'")[1] if "'" in error.message else error.message
        return _key_path(path + [missing]), "missing; this key is required"
    if error.validator == "additionalProperties":
        unknown = sorted(key for key in set(error.instance) - set(error.schema["properties"])
                         if not any(re.match(pattern, str(key)) for pattern in error.schema.get("patternProperties", {})))
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


MAX_LISTED_PROBLEMS = 10
"""A file with several problems: the first in detail, then up to this many more listed, then a count."""


def _more(others: list[str]) -> str:
    """The problems after the first, listed (at most MAX_LISTED_PROBLEMS) and counted beyond that."""
    if not others:
        return ""
    listed = "; ".join(others[:MAX_LISTED_PROBLEMS])
    rest = f"; and {len(others) - MAX_LISTED_PROBLEMS} more" if len(others) > MAX_LISTED_PROBLEMS else ""
    return f" (and {len(others)} more problem(s): {listed}{rest})"


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
        key, problem = _schema_problem(errors[0])
        others = [f"key '{k}': {p}" for k, p in map(_schema_problem, errors[1:])]
        raise ConfigError(file_label, f"key '{key}'", problem + _more(others))

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
    camera.setdefault("distortion", [0.0] * 5)
    camera.setdefault("color_matrix", np.eye(3).tolist())
    if abs(np.linalg.det(np.asarray(camera["color_matrix"], dtype=np.float64))) < 1e-9:
        raise ConfigError(file_label, "key 'camera.color_matrix'", "expected an invertible 3x3 matrix")
    return cfg


# --------------------------------------------------------------------------- tables

FRAMES_SCHEMA = pa.DataFrameSchema(
    {
        "frame_id": pa.Column(str, pa.Check.str_length(min_value=1), unique=True,
                              description="a non-empty string, unique in the file"),
        "view_id": pa.Column(str, pa.Check.str_length(min_value=1), description="a non-empty string"),
        "file": pa.Column(str, pa.Check.str_length(min_value=1),
                          description="a path relative to the capture folder"),
        "flash_level": pa.Column(float, [pa.Check.gt(0), pa.Check.le(1)], coerce=True,
                                 description="a number in (0, 1]"),
        "exposure_s": pa.Column(float, [pa.Check.gt(0), pa.Check(np.isfinite, element_wise=True)], coerce=True,
                                description="a finite number > 0 (seconds)"),
    },
    name="frames.csv",
)
"""pandera schema of frames.csv (DESIGN §3)."""

POSES_SCHEMA = pa.DataFrameSchema(
    {
        "view_id": pa.Column(str, pa.Check.str_length(min_value=1), unique=True,
                             description="a non-empty string, unique in the file"),
        **{name: pa.Column(float, pa.Check(np.isfinite, element_wise=True), coerce=True,
                           description="a finite number") for name in POSE_COLUMNS[1:]},
    },
    name="poses.csv",
)
"""pandera schema of poses.csv: COLMAP cam_from_world quaternion (qw, qx, qy, qz) and translation (metres)."""


def _table_error(exc: pa.errors.SchemaErrors, schema: pa.DataFrameSchema, file_label: str,
                 base: type[CaptureError]) -> CaptureError:
    """One CaptureError for pandera's failure cases: the first problem in detail, a count of the rest."""
    cases = exc.failure_cases
    messages, kinds = [], []
    for case in cases.itertuples(index=False):
        column, check, index, value = case.column, str(case.check), case.index, case.failure_case
        if check == "column_in_dataframe":
            messages.append((f"column '{value}'", f"missing; expected columns {list(schema.columns)}"))
            kinds.append(base)
            continue
        if index is None or (isinstance(index, float) and math.isnan(index)):
            continue  # a follow-up of a failed coercion, already reported per row
        description = schema.columns[column].description
        where = f"row {int(index)} (line {int(index) + 2}), column '{column}'"
        if check == "field_uniqueness":
            messages.append((where, f"duplicate {column} {value!r}; expected {description}"))
            kinds.append(DuplicateFrameError if base is FramesError else base)
        else:
            messages.append((where, f"expected {description}, got {value!r}"))
            kinds.append(FlashLevelError if column == "flash_level" else base)
    if not messages:
        return base(file_label, None, str(exc))
    unique = list(dict.fromkeys(zip(messages, kinds)))  # pandera reports a failed coercion twice
    messages, kinds = [m for m, _ in unique], [k for _, k in unique]
    order = sorted(range(len(messages)), key=lambda i: (kinds[i] is base, i))
    first = order[0]
    more = _more([f"{messages[i][0]}: {messages[i][1]}" for i in order[1:]])
    return kinds[first](file_label, messages[first][0], messages[first][1] + more)


def _validate_table(table: pd.DataFrame, schema: pa.DataFrameSchema, file_label: str,
                    base: type[CaptureError]) -> pd.DataFrame:
    if len(table) == 0:
        raise base(file_label, None, "no rows; expected at least one")
    try:
        out = schema.validate(table, lazy=True)
    except pa.errors.SchemaErrors as exc:
        raise _table_error(exc, schema, file_label, base) from None
    return out.reset_index(drop=True)


def validate_frames(frames: pd.DataFrame, file_label: str = FRAMES_CSV) -> pd.DataFrame:
    """Check a frames table (DESIGN §3); returns it with float columns coerced.

    Raises FramesError, DuplicateFrameError or FlashLevelError naming row and column.
    """
    return _validate_table(frames, FRAMES_SCHEMA, file_label, FramesError)


def validate_poses(poses: pd.DataFrame, file_label: str = POSES_CSV) -> pd.DataFrame:
    """Check a poses table; quaternions must have unit norm (to 1e-3). Raises PosesError."""
    poses = _validate_table(poses, POSES_SCHEMA, file_label, PosesError)
    norms = np.linalg.norm(poses[["qw", "qx", "qy", "qz"]].to_numpy(), axis=1)
    bad = np.flatnonzero(np.abs(norms - 1) > 1e-3)
    if bad.size:
        i = int(bad[0])
        raise PosesError(file_label, f"row {i} (line {i + 2}), columns qw..qz",
                         f"expected a unit quaternion, got norm {norms[i]:.6g}")
    return poses


def _read_csv(path: Path, label: str) -> pd.DataFrame:
    try:
        return pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise (FramesError if label.endswith(FRAMES_CSV) else PosesError)(
            label, None, f"not a readable CSV file ({exc})") from None


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Capture:
    """A validated capture folder.

    root: the folder. config: capture.yaml with defaults filled in (see validate_config).
    frames: frames.csv (columns of DESIGN §3, flash_level/exposure_s float).
    poses: poses.csv or None.
    """

    root: Path
    config: dict
    frames: pd.DataFrame
    poses: pd.DataFrame | None

    @property
    def sensor(self) -> dict:
        return self.config["sensor"]

    @property
    def layout(self) -> MosaicLayout:
        """The mosaic period of the sensor (sellip.mosaic)."""
        return mosaic_layout(self.sensor["polarizer_layout"], self.sensor["color_layout"])

    @property
    def view_ids(self) -> list[str]:
        """View ids in order of first appearance in frames.csv."""
        return list(dict.fromkeys(self.frames["view_id"]))

    def frames_of(self, view_id: str) -> pd.DataFrame:
        """The frames of one view, in file order."""
        return self.frames[self.frames["view_id"] == view_id]

    def intrinsics(self) -> np.ndarray:
        """(3, 3) OpenCV camera matrix K in raw-pixel units."""
        cam = self.config["camera"]
        return np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])

    def pose(self, view_id: str) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3), t (3,)) cam_from_world of a view from poses.csv; KeyError if the capture has none."""
        if self.poses is None:
            raise KeyError(f"{self.root / POSES_CSV} does not exist")
        from sellip.conventions import quaternion_to_rotation

        row = self.poses.set_index("view_id").loc[view_id]
        q = row[["qw", "qx", "qy", "qz"]].to_numpy(dtype=np.float64)
        t = row[["tx", "ty", "tz"]].to_numpy(dtype=np.float64)
        return quaternion_to_rotation(q), t


def read_capture(path: str | Path, check_raw: bool = False, check_files: bool = True) -> Capture:
    """Read and validate a capture folder (DESIGN §3).

    Checks capture.yaml, frames.csv (and poses.csv if present), that every raw
    file exists (unless ``check_files`` is False: for stages that never read a
    raw frame, and for ingest with ``bad_frames: skip``) and that every view in
    poses.csv has frames. With ``check_raw`` every raw frame is also opened and
    checked (slow). Raises a CaptureError subclass on the first problem.
    """
    root = Path(path)
    yaml_path, frames_path, poses_path = root / CAPTURE_YAML, root / FRAMES_CSV, root / POSES_CSV
    for needed in (yaml_path, frames_path):
        if not needed.is_file():
            raise MissingFileError(str(needed), None, "missing; every capture folder needs it (DESIGN §3)")
    try:
        raw_config = yaml.safe_load(yaml_path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(str(yaml_path), None, f"not valid YAML ({exc})") from None
    config = validate_config(raw_config, str(yaml_path))
    frames = validate_frames(_read_csv(frames_path, str(frames_path)), str(frames_path))
    poses = None
    if poses_path.is_file():
        poses = validate_poses(_read_csv(poses_path, str(poses_path)), str(poses_path))
        framed = set(frames["view_id"])
        for i, view in enumerate(poses["view_id"]):
            if view not in framed:
                raise ViewWithoutFramesError(str(poses_path), f"row {i} (line {i + 2}), view_id {view!r}",
                                             f"this view has no frame in {frames_path}; "
                                             "expected every view to have at least one frame")
    for i, rel in enumerate(frames["file"]):
        if check_files and not (root / rel).is_file():
            raise MissingFileError(str(frames_path), f"row {i} (line {i + 2}), column 'file'",
                                   f"raw frame {str(root / rel)!r} does not exist")
    capture = Capture(root=root, config=config, frames=frames, poses=poses)
    if check_raw:
        for _, row in frames.iterrows():
            read_raw_frame(capture, row)
    return capture


def read_raw_file(path: str | Path, sensor: Mapping, file_label: str | None = None) -> np.ndarray:
    """One raw mosaic frame as (height, width) uint16, checked against capture.yaml's ``sensor``.

    DNG/camera RAW: rawpy's ``raw_image``; TIFF: tifffile; PNG: imageio.
    Raises RawFrameError (unreadable, unknown format, wrong size, type or bit depth).
    """
    path = Path(path)
    label = file_label or str(path)
    suffix = path.suffix.lower()
    try:
        if suffix in RAWPY_SUFFIXES:
            import rawpy

            with rawpy.imread(str(path)) as raw:
                image = np.array(raw.raw_image, copy=True)
        elif suffix in TIFF_SUFFIXES:
            import tifffile

            image = tifffile.imread(path)
        elif suffix in PNG_SUFFIXES:
            import imageio.v3 as iio

            image = iio.imread(path)
        else:
            raise RawFrameError(label, None, f"unknown raw format {suffix!r}; expected one of "
                                             f"{list(RAWPY_SUFFIXES + TIFF_SUFFIXES + PNG_SUFFIXES)}")
    except RawFrameError:
        raise
    except FileNotFoundError:
        raise MissingFileError(label, None, "raw frame does not exist") from None
    except Exception as exc:  # rawpy/tifffile/imageio raise many unrelated types for corrupt files
        raise RawFrameError(label, None, f"cannot be read as a raw frame ({type(exc).__name__}: {exc})") from None
    expected = (int(sensor["height"]), int(sensor["width"]))
    if image.shape != expected:
        raise RawFrameError(label, None, f"expected a single-channel image of (height, width) = {expected} "
                                         f"(capture.yaml sensor), got shape {image.shape}")
    bit_depth = int(sensor["bit_depth"])
    if image.dtype.kind != "u" or image.dtype.itemsize * 8 < bit_depth:
        raise RawFrameError(label, None, f"expected unsigned integers holding {bit_depth}-bit data, "
                                         f"got dtype {image.dtype}")
    peak = int(image.max())
    if peak > 2 ** bit_depth - 1:
        raise RawFrameError(label, None, f"expected {bit_depth}-bit values (at most {2 ** bit_depth - 1}), got "
                                         f"a maximum of {peak}; is the data MSB-aligned (declare bit_depth 16)?")
    return image.astype(np.uint16, copy=False)


def read_raw_frame(capture: Capture, row: str | Mapping | pd.Series) -> np.ndarray:
    """The raw mosaic of one frame, (height, width) uint16. ``row`` is a frames.csv row or a frame_id."""
    if isinstance(row, str):
        match = capture.frames[capture.frames["frame_id"] == row]
        if match.empty:
            raise FramesError(str(capture.root / FRAMES_CSV), f"frame_id {row!r}", "no such frame")
        row = match.iloc[0]
    path = capture.root / row["file"]
    return read_raw_file(path, capture.sensor, file_label=str(path))


# --------------------------------------------------------------------------- writing


def write_raw_file(path: str | Path, raw: np.ndarray, sensor: Mapping) -> None:
    """Write one (H, W) uint16 mosaic; the format follows the suffix (.dng, .tif/.tiff, .png).

    DNG: uncompressed CFA DNG with a dummy 2x2 RGGB pattern, BlackLevel and
    WhiteLevel tags from ``sensor``; rawpy's ``raw_image`` returns it bit-exact.
    LibRaw needs DNGs of at least DNG_MIN_SIZE pixels a side.
    """
    path = Path(path)
    raw = np.ascontiguousarray(raw)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise ValueError(f"{path}: expected a 2-D uint16 mosaic, got {raw.dtype} {raw.shape}")
    suffix = path.suffix.lower()
    if suffix == ".dng":
        import tifffile

        if min(raw.shape) < DNG_MIN_SIZE:
            raise ValueError(f"{path}: LibRaw cannot read DNGs smaller than {DNG_MIN_SIZE} px a side, got {raw.shape}; "
                             "write TIFF or PNG frames instead")

        black = int(round(float(np.mean(sensor["black_level"]))))
        identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)  # 3x3 SRATIONAL identity
        tags = [
            (50706, "B", 4, (1, 4, 0, 0), True),        # DNGVersion
            (50707, "B", 4, (1, 1, 0, 0), True),        # DNGBackwardVersion
            (50708, "s", 0, "sellip polarization mosaic", True),  # UniqueCameraModel
            (33421, "H", 2, (2, 2), True),              # CFARepeatPatternDim (dummy)
            (33422, "B", 4, (0, 1, 1, 2), True),        # CFAPattern (dummy RGGB)
            (50710, "B", 3, (0, 1, 2), True),           # CFAPlaneColor
            (50711, "H", 1, 1, True),                   # CFALayout
            (50714, "H", 1, black, True),               # BlackLevel
            (50717, "H", 1, int(sensor["white_level"]), True),  # WhiteLevel
            (50721, "2i", 9, identity, True),            # ColorMatrix1 (required by the DNG spec)
        ]
        tifffile.imwrite(path, raw, photometric=32803, compression=None, subfiletype=0,
                         extratags=tags, metadata=None)
    elif suffix in TIFF_SUFFIXES:
        import tifffile

        tifffile.imwrite(path, raw, photometric="minisblack", compression=None, metadata=None)
    elif suffix in PNG_SUFFIXES:
        import imageio.v3 as iio

        iio.imwrite(path, raw)
    else:
        raise ValueError(f"{path}: unknown raw format {suffix!r}; expected .dng, .tif, .tiff or .png")


RAW_FORMATS = {"dng": ".dng", "tiff": ".tiff", "png": ".png"}
DNG_MIN_SIZE = 22
"""LibRaw (rawpy) rejects raw images narrower or shorter than this."""


class CaptureWriter:
    """Write a capture folder atomically: everything goes to a temporary sibling, renamed by finish().

    Use as a context manager; on an exception the temporary folder is removed
    and an existing capture at ``path`` is left untouched::

        with CaptureWriter(out, config) as writer:
            writer.add_frame("v000_f0", "v000", raw, flash_level=0.25, exposure_s=0.01)
            writer.add_pose("v000", rotation, translation)
            ...  # extra files under writer.path_in_capture("ground_truth/...")
            writer.finish()
    """

    def __init__(self, path: str | Path, config: Mapping, raw_format: str = "dng"):
        if raw_format not in RAW_FORMATS:
            raise ValueError(f"raw_format must be one of {list(RAW_FORMATS)}, got {raw_format!r}")
        self.path = Path(path)
        self.config = validate_config(config, f"{self.path / CAPTURE_YAML} (to be written)")
        self.raw_format = raw_format
        self._tmp = self.path.parent / f".{self.path.name}.tmp-{os.getpid()}"
        if self._tmp.exists():
            shutil.rmtree(self._tmp)
        (self._tmp / RAW_DIR).mkdir(parents=True)
        self._frames: list[dict] = []
        self._poses: list[dict] = []
        self._done = False

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._done:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def path_in_capture(self, relative: str | Path) -> Path:
        """Where a file at ``relative`` inside the capture is written now (parents created)."""
        target = self._tmp / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def add_frame(self, frame_id: str, view_id: str, raw: np.ndarray, flash_level: float,
                  exposure_s: float) -> None:
        """Write one raw frame to raw/<frame_id>.<ext> and record its frames.csv row."""
        sensor = self.config["sensor"]
        if raw.shape != (sensor["height"], sensor["width"]) or int(raw.max()) > 2 ** sensor["bit_depth"] - 1:
            raise RawFrameError(f"frame {frame_id!r} (to be written)", None,
                                f"expected ({sensor['height']}, {sensor['width']}) with {sensor['bit_depth']}-bit "
                                f"values, got {raw.shape} with maximum {int(raw.max())}")
        rel = f"{RAW_DIR}/{frame_id}{RAW_FORMATS[self.raw_format]}"
        write_raw_file(self._tmp / rel, raw, sensor)
        self._frames.append({"frame_id": frame_id, "view_id": view_id, "file": rel,
                             "flash_level": flash_level, "exposure_s": exposure_s})

    def add_pose(self, view_id: str, rotation: np.ndarray, translation: np.ndarray) -> None:
        """Record a cam_from_world pose for poses.csv: rotation as R (3, 3) or quaternion (qw, qx, qy, qz),
        translation t (3,) in metres."""
        from sellip.conventions import rotation_to_quaternion

        rotation = np.asarray(rotation, dtype=np.float64)
        q = rotation if rotation.shape == (4,) else rotation_to_quaternion(rotation)
        t = np.asarray(translation, dtype=np.float64)
        self._poses.append(dict(zip(POSE_COLUMNS, [view_id, *map(float, q), *map(float, t)])))

    def finish(self) -> Path:
        """Validate and write the tables, then capture.yaml, then move the folder into place."""
        frames = validate_frames(pd.DataFrame(self._frames, columns=FRAME_COLUMNS),
                                 f"{self.path / FRAMES_CSV} (to be written)")
        frames.to_csv(self._tmp / FRAMES_CSV, index=False, float_format="%.10g")
        if self._poses:
            poses = validate_poses(pd.DataFrame(self._poses, columns=POSE_COLUMNS),
                                   f"{self.path / POSES_CSV} (to be written)")
            missing = sorted(set(poses["view_id"]) - set(frames["view_id"]))
            if missing:
                raise ViewWithoutFramesError(f"{self.path / POSES_CSV} (to be written)", f"view_id {missing[0]!r}",
                                             "this view has no frame; expected every view to have frames")
            poses.to_csv(self._tmp / POSES_CSV, index=False, float_format="%.17g")
        with open(self._tmp / CAPTURE_YAML, "w") as f:
            yaml.safe_dump(_plain(self.config), f, sort_keys=False, default_flow_style=None)
        if self.path.exists():
            old = self.path.parent / f".{self.path.name}.old-{os.getpid()}"
            self.path.rename(old)
            self._tmp.rename(self.path)
            shutil.rmtree(old)
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp.rename(self.path)
        self._done = True
        return self.path


def _plain(value):
    """YAML-safe copy: numpy scalars and arrays to Python numbers and lists."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in (value.tolist() if isinstance(value, np.ndarray) else value)]
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_capture(path: str | Path, config: Mapping, frames: pd.DataFrame, raw_frames: Mapping[str, np.ndarray],
                  poses: pd.DataFrame | None = None, raw_format: str = "dng") -> Path:
    """Write a whole capture at once: ``frames`` rows (frame_id, view_id, flash_level, exposure_s; ``file`` is
    ignored and rewritten as raw/<frame_id>.<ext>), ``raw_frames[frame_id]`` (H, W) uint16, optional poses
    table (POSE_COLUMNS). Atomic, see CaptureWriter."""
    with CaptureWriter(path, config, raw_format=raw_format) as writer:
        for row in frames.itertuples(index=False):
            writer.add_frame(row.frame_id, row.view_id, raw_frames[row.frame_id], row.flash_level, row.exposure_s)
        if poses is not None:
            for row in poses.itertuples(index=False):
                writer.add_pose(row.view_id, np.array([row.qw, row.qx, row.qy, row.qz]),
                                np.array([row.tx, row.ty, row.tz]))
        return writer.finish()


# --------------------------------------------------------------------------- PLY meshes with per-vertex parameters

GROUND_TRUTH_MESH = f"{GROUND_TRUTH_DIR}/model.ply"

MODEL_VERTEX_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "eta", "rho_d_r", "rho_d_g", "rho_d_b", "rho_s",
                           "sigma_s", "rho_ss_r", "rho_ss_g", "rho_ss_b", "sigma_ss")
"""Vertex properties of a model PLY (DESIGN §4), all float32, in this order."""

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}


def write_ply(path: str | Path, vertex: Mapping[str, np.ndarray], faces: np.ndarray | None = None) -> None:
    """Binary little-endian PLY: one vertex property per entry of ``vertex`` ((V,) arrays, their own dtype,
    in the mapping's order) and triangles ``faces`` (F, 3) as ``vertex_indices`` lists."""
    names = list(vertex)
    count = len(next(iter(vertex.values())))
    dtype = np.dtype([(name, np.asarray(vertex[name]).dtype.newbyteorder("<")) for name in names])
    table = np.empty(count, dtype)
    for name in names:
        table[name] = vertex[name]
    header = ["ply", "format binary_little_endian 1.0", "comment written by sellip", f"element vertex {count}"]
    header += [f"property {_PLY_NAMES[dtype[name].str[1:]]} {name}" for name in names]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(table.tobytes())
        if faces is not None:
            face_table = np.empty(len(faces), np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
            face_table["n"] = 3
            face_table["v"] = faces
            f.write(face_table.tobytes())


def read_ply(path: str | Path) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Read a binary little-endian PLY with triangle faces: ({property: (V,) array}, faces (F, 3) int64 or None).

    Raises CaptureError naming the file for formats this reader does not handle.
    """
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise CaptureError(str(path), None, "not a PLY file")
        elements: list[list] = []
        fmt = None
        while True:
            line = f.readline()
            if not line:
                raise CaptureError(str(path), None, "PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append([words[1], int(words[2]), []])
            elif words[0] == "property":
                elements[-1][2].append(words[1:])
        if fmt != "binary_little_endian":
            raise CaptureError(str(path), "format", f"expected binary_little_endian, got {fmt}")
        vertex, faces = {}, None
        for name, count, props in elements:
            if name == "face":
                if len(props) != 1 or props[0][0] != "list":
                    raise CaptureError(str(path), "element face", "expected one vertex_indices list property")
                row = np.dtype([("n", _PLY_TYPES[props[0][1]]), ("v", "<" + _PLY_TYPES[props[0][2]], (3,))])
                table = np.frombuffer(f.read(row.itemsize * count), row, count)
                if count and np.any(table["n"] != 3):
                    raise CaptureError(str(path), "element face", "expected triangles only")
                faces = table["v"].astype(np.int64)
            else:
                if any(p[0] == "list" for p in props):
                    raise CaptureError(str(path), f"element {name}", "list properties are only read on faces")
                row = np.dtype([(p[1], "<" + _PLY_TYPES[p[0]]) for p in props])
                table = np.frombuffer(f.read(row.itemsize * count), row, count)
                if name == "vertex":
                    vertex = {p[1]: table[p[1]].copy() for p in props}
    return vertex, faces


def write_param_mesh(path: str | Path, mesh, extra: Mapping[str, np.ndarray] | None = None) -> None:
    """Write a :class:`sellip.render.ParamMesh` as a model PLY (MODEL_VERTEX_PROPERTIES, float32; plus an
    int32 ``material`` property when the mesh has region labels, and the (V,) arrays of ``extra``
    in their own dtype, e.g. ``confidence`` float32 and ``model`` uint8)."""
    p = mesh.params
    columns = [mesh.vertices, mesh.normals, np.asarray(p.eta)[:, None], p.rho_d, np.asarray(p.rho_s)[:, None],
               np.asarray(p.sigma_s)[:, None], p.rho_ss, np.asarray(p.sigma_ss)[:, None]]
    table = np.concatenate([np.asarray(c, np.float64).reshape(mesh.num_vertices, -1) for c in columns], axis=1)
    vertex = {name: table[:, k].astype(np.float32) for k, name in enumerate(MODEL_VERTEX_PROPERTIES)}
    if mesh.material is not None:
        vertex["material"] = np.asarray(mesh.material, np.int32)
    for name, values in (extra or {}).items():
        values = np.asarray(values)
        if values.shape != (mesh.num_vertices,):
            raise ValueError(f"{path}: extra property {name!r} has shape {values.shape}, expected ({mesh.num_vertices},)")
        vertex[name] = values
    write_ply(path, vertex, np.asarray(mesh.faces))


def read_param_mesh(path: str | Path):
    """Read a model PLY into a :class:`sellip.render.ParamMesh` (float64 arrays)."""
    from sellip.pbrdf import PBRDFParams
    from sellip.render import ParamMesh

    vertex, faces = read_ply(path)
    missing = [name for name in MODEL_VERTEX_PROPERTIES if name not in vertex]
    if missing:
        raise CaptureError(str(path), "element vertex", f"missing properties {missing}; "
                                                        f"expected {list(MODEL_VERTEX_PROPERTIES)}")

    def stack(*names):
        return np.stack([vertex[n].astype(np.float64) for n in names], axis=-1)

    params = PBRDFParams(eta=vertex["eta"].astype(np.float64), rho_d=stack("rho_d_r", "rho_d_g", "rho_d_b"),
                         rho_s=vertex["rho_s"].astype(np.float64), sigma_s=vertex["sigma_s"].astype(np.float64),
                         rho_ss=stack("rho_ss_r", "rho_ss_g", "rho_ss_b"),
                         sigma_ss=vertex["sigma_ss"].astype(np.float64))
    return ParamMesh(vertices=stack("x", "y", "z"), faces=faces, normals=stack("nx", "ny", "nz"), params=params,
                     material=vertex["material"].astype(np.int64) if "material" in vertex else None)
