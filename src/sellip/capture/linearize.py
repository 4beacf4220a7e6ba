"""Linearize a capture's raw frames (docs/design.md §2 linearize; docs/ingest.md): black and white level,
saturation mask, demosaic into the four analyzer images, colour matrix, undistortion, one store for all
frames (:func:`linearize_capture`); a bad frame stops with its file and row, or is left out with
``bad_frames: skip``.
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sellip.capture import ingest
from sellip.capture.files import FRAMES_CSV, RAWPY_SUFFIXES, CaptureError, MissingFileError
from sellip.capture.reader import read_capture, read_raw_frame
from sellip.jobs import atomic_directory, map_in_threads, progress_logger
from sellip.model.conventions import ANALYZER_ANGLES_DEG

log = logging.getLogger(__name__)








def _frame_black(path: Path, plan: ingest.IngestPlan, black_level_from: str) -> np.ndarray | None:
    """The black level to use for one frame file: None for the plan's (capture.yaml) levels."""
    if black_level_from == "file" and path.suffix.lower() in RAWPY_SUFFIXES:
        black = ingest.rawpy_black_level(path)
        if black.shape != plan.raw_shape:
            raise CaptureError(str(path), None, f"rawpy's black-level map has shape {black.shape}, "
                                                f"expected the mosaic shape {plan.raw_shape}")
        return black
    return None



def _check_file_black_level(path: Path, plan: ingest.IngestPlan) -> None:
    """Warn when a RAW file declares black levels other than capture.yaml's (the ones used)."""
    declared = ingest.rawpy_black_level(path)
    if declared.shape == plan.raw_shape and not np.allclose(declared, plan.black, atol=0.5):
        log.warning("%s declares black levels %s (rawpy, per position) but capture.yaml gives %s; using "
                    "capture.yaml's (set ingest.black_level_from: file to use the file's)", path,
                    np.unique(declared).tolist(), np.unique(plan.black).tolist())



def _frame_row(capture, index: int) -> str:
    """'frames.csv row i (line i+2), frame_id ..., view ...': where a frame comes from, for messages."""
    row = capture.frames.iloc[index]
    return (f"{capture.root / FRAMES_CSV} row {index} (line {index + 2}), frame_id {row['frame_id']!r}, "
            f"view {row['view_id']!r}")



DARK_FLOOR = 0.002
"""A pixel whose signal (raw - black) is at most this fraction of its range (white - black) counts as dark: 8 raw
units of 4095, about 9 times the rig sensor's read noise (2.4 e- at 2.58 e-/DN: 0.93 units, SensorModel), so a black
frame's noise stays below it while a dim but real object (20 units, tests/capture/test_ingest.py's dark flat scene)
is above it."""

MIN_USABLE_FRACTION = 1e-3
"""Ingest stops when no frame of the capture has this fraction of its pixels usable (above DARK_FLOOR and below
saturation): every frame black or saturated (a lens cap, a flash that did not fire, a wrong black or white level).
An object that fills 0.1 % of the frame is far too small for the method anyway; a view whose frames are all below
it is named in a warning."""


@dataclass(frozen=True)
class FrameContent:
    """What ingest records of one raw frame: ``digest`` (BLAKE2b of its pixels), the fractions of its pixels that
    are ``usable`` (neither dark nor saturated), ``saturated`` and ``dark``."""

    digest: str
    usable: float
    saturated: float
    dark: float


def frame_content(raw: np.ndarray, plan: ingest.IngestPlan, black: np.ndarray | None = None) -> FrameContent:
    """:class:`FrameContent` of one raw mosaic (H, W) (``black``: the frame's own black level, else the plan's)."""
    black = plan.black if black is None else black
    signal = raw.astype(np.float32) - black
    headroom = np.float32(plan.white_level) - black
    saturated = signal >= np.float32(plan.saturation) * headroom
    dark = signal <= np.float32(DARK_FLOOR) * headroom
    return FrameContent(digest=hashlib.blake2b(np.ascontiguousarray(raw).tobytes(), digest_size=16).hexdigest(),
                        usable=float(1.0 - saturated.mean() - dark.mean()), saturated=float(saturated.mean()),
                        dark=float(dark.mean()))


def check_frame_contents(capture, content: list[FrameContent | None], saturation: float) -> None:
    """Stop when the photographs cannot be what frames.csv says they are: every frame black or saturated
    (:data:`MIN_USABLE_FRACTION`), or two frames with identical pixels (one photograph listed twice, under two
    file names). ``content``: per frames.csv row, None for a frame left out. Warns about a view whose every frame
    is black or saturated. Raises CaptureError naming the frames and rows."""
    frames_csv = str(capture.root / FRAMES_CSV)
    read = [(i, c) for i, c in enumerate(content) if c is not None]
    best_index, best = max(read, key=lambda item: item[1].usable)
    if best.usable < MIN_USABLE_FRACTION:
        saturated = float(np.median([c.saturated for _, c in read])) > 0.5
        what = ("saturated: raise sensor.white_level if it is below the data's, or shorten the exposure / lower the "
                "flash" if saturated else
                "black: check the lens cap and that the flash fired, and capture.yaml's sensor.black_level (at or "
                "above the data's level it leaves nothing)")
        raise CaptureError(frames_csv, None,
                           f"all {len(read)} frames are {'saturated' if saturated else 'black'}: at most "
                           f"{100 * best.usable:.2f}% of a frame's pixels are usable (above {100 * DARK_FLOOR:g}% of "
                           f"the sensor's range and below saturation at {saturation:g} of it; best frame "
                           f"{capture.frames['frame_id'].iloc[best_index]!r}), expected at least "
                           f"{100 * MIN_USABLE_FRACTION:g}%. The photographs are {what}")
    by_view: dict[str, list[float]] = {}
    for i, c in read:
        by_view.setdefault(capture.frames["view_id"].iloc[i], []).append(c.usable)
    empty = [v for v, usable in by_view.items() if max(usable) < MIN_USABLE_FRACTION]
    if empty:
        log.warning("%d view(s) have no usable pixels in any frame (all black or saturated; at most %.2f%% usable): "
                    "%s; check these photographs", len(empty), 100 * max(max(by_view[v]) for v in empty),
                    ", ".join(repr(v) for v in empty[:30]))
    seen: dict[str, int] = {}
    for j, c in read:
        if c.digest in seen:
            i = seen[c.digest]
            row = capture.frames.iloc
            raise CaptureError(frames_csv, f"rows {i} (line {i + 2}) and {j} (line {j + 2})",
                               f"frame_id {row[i]['frame_id']!r} (view {row[i]['view_id']!r}, {row[i]['file']!r}) and "
                               f"frame_id {row[j]['frame_id']!r} (view {row[j]['view_id']!r}, {row[j]['file']!r}) "
                               "have identical pixels: one photograph listed as two frames (a copied file?); "
                               "expected a photograph of its own for each frame: correct the file of the wrong row")
        seen[c.digest] = j


def linearize_capture(capture_dir: str | Path, output: str | Path, threads: int = 1,
                      settings: ingest.IngestSettings = ingest.IngestSettings()) -> Path:
    """Linearize every frame of a capture into a zarr store at ``output`` (layout in the module docstring).

    settings: config ``ingest`` (saturation, black_level_from, bad_frames). bad_frames "error" raises
    :class:`sellip.capture.files.CaptureError` naming the file and its frames.csv row for a
    bad capture or frame, and nothing is written; "skip" leaves bad frames out (module docstring). Raises
    CaptureError when every frame is bad.
    Long: the per-frame loop and its bad-frame policy share the store being written; split, they would pass it around.
    """
    saturation, black_level_from, bad_frames = settings.saturation, settings.black_level_from, settings.bad_frames
    import zarr

    started = time.perf_counter()
    skip = bad_frames == "skip"
    capture = read_capture(capture_dir, check_files=not skip)
    frames = capture.frames
    plan = ingest.make_ingest_plan(capture.sensor, capture.config["camera"], capture.layout, saturation)
    out = plan.intrinsics
    channels = plan.demosaic.channels
    paths = [capture.root / rel for rel in frames["file"]]
    raw_paths = [p for p in paths if p.suffix.lower() in RAWPY_SUFFIXES and p.is_file()]
    if black_level_from == "capture" and raw_paths:
        try:
            _check_file_black_level(raw_paths[0], plan)
        except Exception as exc:  # noqa: BLE001 -- rawpy raises many types; the frame's own read reports it
            log.debug("black-level check of %s failed: %s", raw_paths[0], exc)
    log.info("%s: %d frames of %d views, raw %dx%d -> %dx%d x 4 analyzers x %d channels, %d thread(s)",
             capture.root, len(frames), len(capture.view_ids), plan.raw_shape[1], plan.raw_shape[0],
             out["width"], out["height"], channels, threads)

    with atomic_directory(output) as tmp:
        group = zarr.open_group(str(tmp), mode="w")
        shape = (len(frames), out["height"], out["width"], len(ANALYZER_ANGLES_DEG), channels)
        linear = group.create_array("linear", shape=shape, chunks=(1,) + shape[1:], dtype="float32",
                                    fill_value=np.nan, compressors=None)

        content: list[FrameContent | None] = [None] * len(frames)

        def run(index: int) -> str | None:
            """Linearize frame ``index``; returns None, or (skip) why the frame was left out."""
            try:
                if not paths[index].is_file():  # rawpy reports a missing file as an I/O error
                    raise MissingFileError(str(paths[index]), None, "raw frame does not exist")
                raw = read_raw_frame(capture, frames.iloc[index])
                black = _frame_black(paths[index], plan, black_level_from)
            except CaptureError as exc:
                if not skip:
                    raise type(exc)(exc.file, _frame_row(capture, index),
                                    f"{exc.problem} (ingest.bad_frames: skip leaves such frames out)") from None
                log.warning("skipping %s: %s", _frame_row(capture, index), exc)
                return str(exc)
            content[index] = frame_content(raw, plan, black)
            try:
                linear[index] = ingest.process_frame(raw, plan, black)
            except ingest.IngestError as exc:
                raise ingest.IngestError(f"{paths[index]}: {exc}") from None
            return None

        skipped = map_in_threads(run, len(frames), threads, progress_logger(len(frames), "linearized frames"))
        if all(reason is not None for reason in skipped):
            raise CaptureError(str(capture.root / FRAMES_CSV), None,
                               f"none of its {len(frames)} raw frames could be read (first: {skipped[0]})")
        check_frame_contents(capture, content, plan.saturation)
        group.attrs.update({
            "frame_id": frames["frame_id"].tolist(),
            "view_id": frames["view_id"].tolist(),
            "flash_level": [float(v) for v in frames["flash_level"]],
            "exposure_s": [float(v) for v in frames["exposure_s"]],
            "intrinsics": out,
            "analyzer_angles_deg": list(ANALYZER_ANGLES_DEG),
            "channels": "RGB" if channels == 3 else "mono",
            "raw_shape": list(plan.raw_shape),
            "capture": str(capture.root),
            "saturation": float(saturation),
            "black_level_from": black_level_from,
            "bad_frames": bad_frames,
            "skipped": skipped,
        })
    left_out = [frames["frame_id"].iloc[i] for i, reason in enumerate(skipped) if reason is not None]
    if left_out:
        log.warning("left out %d of %d frames (ingest.bad_frames: skip): %s", len(left_out), len(frames),
                    ", ".join(left_out[:30]))
    log.info("wrote %s in %.1f s", output, time.perf_counter() - started)
    return Path(output)
