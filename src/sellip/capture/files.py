"""The capture folder's file names and columns (docs/design.md §3), and the errors every reader raises
(:class:`CaptureError` and its kinds: each names the file, and where it applies the row, column or key).
"""

from __future__ import annotations

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
    """A capture folder that does not follow docs/design.md §3. The message names file, place and expectation."""

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


GROUND_TRUTH_MESH = f"{GROUND_TRUTH_DIR}/model.ply"


MAX_LISTED_PROBLEMS = 10
"""A file with several problems: the first in detail, then up to this many more listed, then a count."""


def more_problems(others: list[str]) -> str:
    """The problems after the first, listed (at most MAX_LISTED_PROBLEMS) and counted beyond that."""
    if not others:
        return ""
    listed = "; ".join(others[:MAX_LISTED_PROBLEMS])
    rest = f"; and {len(others) - MAX_LISTED_PROBLEMS} more" if len(others) > MAX_LISTED_PROBLEMS else ""
    return f" (and {len(others)} more problem(s): {listed}{rest})"
