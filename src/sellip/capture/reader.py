"""Reading a capture folder (:func:`read_capture` -> :class:`Capture`) and its raw frames (DNG and
camera RAW with rawpy, 16-bit TIFF/PNG as they are) as (H, W) mosaics in raw units; a raw file's recorded
exposure time (:func:`exposure_time`) and whether its flash fired (:func:`flash_fired`), with tifffile.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from sellip.capture.capture_yaml import validate_config
from sellip.capture.files import (
    CAPTURE_YAML,
    FRAMES_CSV,
    PNG_SUFFIXES,
    POSES_CSV,
    RAWPY_SUFFIXES,
    TIFF_SUFFIXES,
    ConfigError,
    FramesError,
    MissingFileError,
    RawFrameError,
    ViewWithoutFramesError,
)
from sellip.capture.mosaic import MosaicLayout, mosaic_layout
from sellip.capture.tables import read_csv, validate_frames, validate_poses
from sellip.yaml_files import DuplicateKeyError, load_yaml_file

# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Capture:
    """A validated capture folder.

    root: the folder. config: capture.yaml with defaults filled in (see validate_config).
    frames: frames.csv (columns of docs/design.md §3, flash_level/exposure_s float).
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
        """The mosaic period of the sensor (sellip.capture.mosaic)."""
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
        from sellip.model.conventions import quaternion_to_rotation

        row = self.poses.set_index("view_id").loc[view_id]
        q = row[["qw", "qx", "qy", "qz"]].to_numpy(dtype=np.float64)
        t = row[["tx", "ty", "tz"]].to_numpy(dtype=np.float64)
        return quaternion_to_rotation(q), t


def read_capture(path: str | Path, check_raw: bool = False, check_files: bool = True) -> Capture:
    """Read and validate a capture folder (docs/design.md §3).

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
            raise MissingFileError(str(needed), None, "missing; every capture folder needs it (docs/design.md §3)")
    try:
        raw_config = load_yaml_file(yaml_path)
    except DuplicateKeyError as exc:
        raise ConfigError(str(yaml_path), f"key '{exc.key}'", exc.what) from None
    except yaml.YAMLError as exc:
        raise ConfigError(str(yaml_path), None, f"not valid YAML ({exc})") from None
    config = validate_config(raw_config, str(yaml_path))
    frames = validate_frames(read_csv(frames_path, str(frames_path)), str(frames_path))
    poses = None
    if poses_path.is_file():
        poses = validate_poses(read_csv(poses_path, str(poses_path)), str(poses_path))
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


EXPOSURE_TIME_TAG = 33434
"""TIFF/EP and EXIF ExposureTime (0x829A): a RATIONAL, seconds."""

FLASH_TAG = 37385
"""TIFF/EP and EXIF Flash (0x9209): a SHORT whose bit 0 says the flash fired."""


def _recorded(path: str | Path, tag_id: int, exif_name: str) -> list:
    """The values of TIFF tag ``tag_id`` in a raw file's first IFD and of ``exif_name`` in its EXIF IFD (absent ones
    left out), read with tifffile; [] when the file is not TIFF-based."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            tag = tags.get(tag_id)
            values = [] if tag is None else [tag.value]
            exif = tags.get(34665)  # ExifTag: tifffile reads the EXIF IFD into a dict
            if exif is not None and isinstance(exif.value, dict) and exif.value.get(exif_name) is not None:
                values.append(exif.value[exif_name])
    except (tifffile.TiffFileError, OSError, ValueError, KeyError, IndexError):
        return []
    return values


def exposure_time(path: str | Path) -> float | None:
    """The exposure time (s) a camera recorded in a raw file: the ExposureTime tag (0x829A) of the first IFD or
    of its EXIF IFD, read with tifffile (DNG and the TIFF-based camera raws: NEF, ARW, CR2, ...). None when the
    file has no such tag or is not TIFF-based (PNG, CR3)."""
    for value in _recorded(path, EXPOSURE_TIME_TAG, "ExposureTime"):
        if isinstance(value, (tuple, list)) and len(value) == 2:
            value = value[0] / value[1] if value[1] else None
        if value is not None and float(value) > 0:
            return float(value)
    return None


def flash_fired(path: str | Path) -> bool | None:
    """Whether the camera recorded its flash as fired for a raw file: bit 0 of the Flash tag (0x9209) of the first
    IFD or of its EXIF IFD. None when the file does not say (no tag, or not TIFF-based). Cameras record the flash's
    power only in their maker notes, which are not read."""
    for value in _recorded(path, FLASH_TAG, "Flash"):
        try:
            return bool(int(value) & 1)
        except (TypeError, ValueError):
            continue
    return None


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
    except Exception as exc:  # noqa: BLE001 - rawpy/tifffile/imageio raise many unrelated types for corrupt files
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


