"""``sellip linearize``: every raw frame of a capture -> linear analyzer images (rule ``linearize_frames``).

    sellip linearize --capture CAPTURE --output results/NAME/ingest/linear.zarr [--threads 2]
                     [--settings '{"bad_frames": "skip", "saturation": 0.98}']

``--settings``: :class:`sellip.capture.ingest.IngestSettings` (config ``ingest``) as one JSON object; a key left out
takes its declared default.

Per frame (:func:`sellip.capture.ingest.process_frame`): black level, white level,
saturated/dead pixels, demosaic, colour matrix, undistortion, on the output
grid of one pixel per polarizer cell. Written store (read by ``sellip merge-hdr``):

``linear``
    (F, H/2, W/2, 4, C) float32, frames in frames.csv order, one frame per
    chunk, NaN where invalid; C = 3 (linear sRGB) or 1 (mono).
attrs
    ``frame_id``, ``view_id``, ``flash_level``, ``exposure_s`` (lists, frames.csv
    order), ``intrinsics`` (output grid, :func:`sellip.capture.ingest.output_intrinsics`),
    ``analyzer_angles_deg``, ``channels``, ``raw_shape``, ``capture``, ``saturation``,
    ``black_level_from``, ``bad_frames`` and ``skipped`` (per frame: null, or why it was left out).

Bad frames (missing, unreadable, wrong size, type or bit depth): ``bad_frames: error`` (default)
stops with the file and its frames.csv row; ``skip`` leaves the frame out (all NaN in the store,
``skipped`` says why) with a warning naming both, and ``sellip merge-hdr`` merges the view from its
other frames (a view with none left is dropped).

Frames are processed in a pool of ``--threads`` threads (numpy releases the
GIL), one frame per task, so memory stays at a few frames. The store is
written under a temporary name and renamed when complete: a failure leaves
no output.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.capture import ingest
from sellip.capture.files import CaptureError
from sellip.capture.linearize import linearize_capture
from sellip.settings import add_settings_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (docs/design.md §3)")
    parser.add_argument("--output", required=True, type=Path, help="zarr store to write (a directory)")
    parser.add_argument("--threads", type=int, default=1, help="frames processed in parallel (default: 1)")
    add_settings_argument(parser, ingest.IngestSettings, section="ingest")


def main(args: argparse.Namespace) -> int:
    try:
        linearize_capture(args.capture, args.output, threads=args.threads, settings=args.settings)
    except (CaptureError, ingest.IngestError) as exc:
        log.error("%s", exc)
        return 1
    return 0
