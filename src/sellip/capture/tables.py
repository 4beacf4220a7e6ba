"""frames.csv and poses.csv (docs/design.md §3): pandera schemas and validation that names the file, row
and column of every problem.
"""

from __future__ import annotations

import math
import posixpath
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
    frames = _validate_table(frames, FRAMES_SCHEMA, file_label, FramesError)
    _check_identifiers(frames, ("frame_id", "view_id", "file"), file_label, FramesError)
    _check_distinct_files(frames, file_label)
    return frames


def _check_identifiers(table: pd.DataFrame, columns, file_label: str, error: type[CaptureError]) -> None:
    """An identifier (or file name) with white space at either end is an error naming row, column and the value
    quoted: 'v000 ' and 'v000' are different views, and a message that prints v000 hides why."""
    for column in columns:
        values = table[column].astype(str)
        bad = np.flatnonzero((values != values.str.strip()).to_numpy())
        if bad.size:
            i = int(bad[0])
            others = [f"row {j} (line {j + 2}): {values.iloc[j]!r}" for j in bad[1:]]
            raise error(file_label, f"row {i} (line {i + 2}), column '{column}'",
                        f"{values.iloc[i]!r} starts or ends with white space; {column} values are compared exactly "
                        f"({values.iloc[i]!r} and {values.iloc[i].strip()!r} are different): remove the space"
                        + more_problems(others))


def _check_distinct_files(frames: pd.DataFrame, file_label: str) -> None:
    """Two rows that name the same raw file (after normalizing the path) are an error naming both rows and frames:
    one photograph cannot be two frames (a copy-paste slip in frames.csv)."""
    normalized = [posixpath.normpath(str(f).replace("\\", "/")) for f in frames["file"]]
    first: dict[str, int] = {}
    for j, name in enumerate(normalized):
        if name in first:
            i = first[name]
            raise DuplicateFrameError(
                file_label, f"rows {i} (line {i + 2}) and {j} (line {j + 2}), column 'file'",
                f"frame_id {frames['frame_id'].iloc[i]!r} (view {frames['view_id'].iloc[i]!r}) and frame_id "
                f"{frames['frame_id'].iloc[j]!r} (view {frames['view_id'].iloc[j]!r}) name the same raw file "
                f"{frames['file'].iloc[j]!r}; expected one photograph per frame: correct the file of the wrong row")
        first[name] = j


def validate_poses(poses: pd.DataFrame, file_label: str = POSES_CSV) -> pd.DataFrame:
    """Check a poses table; quaternions must have unit norm (to 1e-3). Raises PosesError."""
    poses = _validate_table(poses, POSES_SCHEMA, file_label, PosesError)
    _check_identifiers(poses, ("view_id",), file_label, PosesError)
    norms = np.linalg.norm(poses[["qw", "qx", "qy", "qz"]].to_numpy(), axis=1)
    bad = np.flatnonzero(np.abs(norms - 1) > 1e-3)
    if bad.size:
        i = int(bad[0])
        raise PosesError(file_label, f"row {i} (line {i + 2}), columns qw..qz",
                         f"expected a unit quaternion, got norm {norms[i]:.6g}")
    return poses


OTHER_SEPARATORS = {";": "';'", "\t": "a tab", "|": "'|'"}
"""Separators a spreadsheet may write instead of the comma (a locale with decimal commas writes ';'), named as such
rather than reported as every column missing."""


def read_csv(path: Path, label: str) -> pd.DataFrame:
    error = FramesError if label.endswith(FRAMES_CSV) else PosesError
    try:
        table = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise error(label, None, f"not a readable CSV file ({exc})") from None
    if len(table.columns) == 1:  # one column: the header was not split at commas
        header = str(table.columns[0])
        for separator, name in OTHER_SEPARATORS.items():
            if separator in header:
                raise error(label, "line 1 (the header)",
                            f"uses {name} as separator ({header!r}); expected ',' (comma-separated values): save it "
                            "as CSV with commas, and '.' as the decimal mark")
    return table


