"""Writing a capture folder (synthetic captures, tests): raw frames as DNG/TIFF/PNG, frames.csv,
capture.yaml, poses.csv, under a temporary name and then renamed.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from sellip.capture.capture_yaml import validate_config
from sellip.capture.files import (
    CAPTURE_YAML,
    FRAME_COLUMNS,
    FRAMES_CSV,
    PNG_SUFFIXES,
    POSE_COLUMNS,
    POSES_CSV,
    RAW_DIR,
    TIFF_SUFFIXES,
    RawFrameError,
    ViewWithoutFramesError,
)
from sellip.capture.tables import validate_frames, validate_poses

# --------------------------------------------------------------------------- writing


def _shot_tags(exposure_s: float | None, flash_fired: bool | None) -> list:
    """The ExposureTime tag (33434, one RATIONAL, seconds) and the Flash tag (37385, one SHORT, bit 0: fired) for
    tifffile's extratags; each left out when not given."""
    tags = []
    if exposure_s is not None:
        from fractions import Fraction

        ratio = Fraction(float(exposure_s)).limit_denominator(1_000_000)
        tags.append((33434, "2I", 1, (ratio.numerator, ratio.denominator), True))
    if flash_fired is not None:
        tags.append((37385, "H", 1, int(bool(flash_fired)), True))
    return tags


def write_raw_file(path: str | Path, raw: np.ndarray, sensor: Mapping, exposure_s: float | None = None,
                   flash_fired: bool | None = None) -> None:
    """Write one (H, W) uint16 mosaic; the format follows the suffix (.dng, .tif/.tiff, .png).

    DNG: uncompressed CFA DNG with a dummy 2x2 RGGB pattern, BlackLevel and
    WhiteLevel tags from ``sensor``; rawpy's ``raw_image`` returns it bit-exact.
    LibRaw needs DNGs of at least DNG_MIN_SIZE pixels a side. ``exposure_s``: written as the TIFF/EP
    ExposureTime tag (33434) of a DNG or TIFF, as a camera records it (:func:`sellip.capture.reader.exposure_time`);
    ``flash_fired``: its Flash tag (37385, :func:`sellip.capture.reader.flash_fired`).
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
        ] + _shot_tags(exposure_s, flash_fired)
        tifffile.imwrite(path, raw, photometric=32803, compression=None, subfiletype=0,
                         extratags=tags, metadata=None)
    elif suffix in TIFF_SUFFIXES:
        import tifffile

        tifffile.imwrite(path, raw, photometric="minisblack", compression=None, metadata=None,
                         extratags=_shot_tags(exposure_s, flash_fired))
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
        write_raw_file(self._tmp / rel, raw, sensor, exposure_s=exposure_s, flash_fired=True)
        self._frames.append({"frame_id": frame_id, "view_id": view_id, "file": rel,
                             "flash_level": flash_level, "exposure_s": exposure_s})

    def add_pose(self, view_id: str, rotation: np.ndarray, translation: np.ndarray) -> None:
        """Record a cam_from_world pose for poses.csv: rotation as R (3, 3) or quaternion (qw, qx, qy, qz),
        translation t (3,) in metres."""
        from sellip.model.conventions import rotation_to_quaternion

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
            yaml.safe_dump(yaml_safe(self.config), f, sort_keys=False, default_flow_style=None)
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


def yaml_safe(value):
    """YAML-safe copy: numpy scalars and arrays to Python numbers and lists, keys to strings."""
    if isinstance(value, Mapping):
        return {str(k): yaml_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [yaml_safe(v) for v in (value.tolist() if isinstance(value, np.ndarray) else value)]
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


