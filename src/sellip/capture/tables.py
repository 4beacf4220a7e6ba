"""frames.csv and poses.csv (docs/design.md §3): pandera schemas and validation that names the file, row
and column of every problem.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pandera.pandas as pa

from sellip.capture.files import (
    FRAMES_CSV,
    POSE_COLUMNS,
    POSES_CSV,
    CaptureError,
    DuplicateFrameError,
    FlashLevelError,
    FramesError,
    PosesError,
    more_problems,
)

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
"""pandera schema of frames.csv (docs/design.md §3)."""

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
    more = more_problems([f"{messages[i][0]}: {messages[i][1]}" for i in order[1:]])
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
    """Check a frames table (docs/design.md §3); returns it with float columns coerced.

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


def read_csv(path: Path, label: str) -> pd.DataFrame:
    try:
        return pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise (FramesError if label.endswith(FRAMES_CSV) else PosesError)(
            label, None, f"not a readable CSV file ({exc})") from None


