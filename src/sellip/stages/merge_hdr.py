"""``sellip merge-hdr``: the linear frames of each view -> one HDR analyzer image per view (rule ``merge_hdr``).

    sellip merge-hdr --linear results/NAME/ingest/linear.zarr --output results/NAME/hdr.zarr [--threads 2]
                     [--settings '{"flash_ratio_tolerance": 1.5}']

``--settings``: :class:`sellip.capture.ingest.IngestSettings` (config ``ingest``; merge-hdr reads its
``flash_ratio_tolerance``) as one JSON object; a key left out takes its declared default.

Written store (read lazily by later stages with :func:`read_hdr`):

``analyzers``
    (V, H, W, 4, C) float32, one view per chunk: I0, I45, I90, I135
    (:data:`sellip.model.conventions.ANALYZER_ANGLES_DEG`) in linear sRGB (C = 3) or
    mono (C = 1). Units: relative radiance, ``linear / (flash_level * exposure_s)``
    where linear is 1 at the sensor's full scale (white - black). 0 where no frame is valid.
``valid``
    (V, H, W) bool: every analyzer and channel has at least one valid frame.
attrs
    ``view_id`` (list, order of first appearance in frames.csv), ``frames_per_view``,
    ``intrinsics`` (fx, fy, cx, cy, width, height, distortion of the output grid:
    undistorted, one pixel per polarizer cell), ``analyzer_angles_deg``,
    ``channels``, ``units``, ``capture``, ``dropped_views`` (views whose every frame was left out).

Frames that ``sellip linearize`` left out with ``bad_frames: skip`` (its ``skipped`` attr) are not merged: the
view is merged from its other frames, and a view with none left is dropped with a warning.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.capture import ingest
from sellip.capture.hdr import merge_capture
from sellip.settings import add_settings_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--linear", required=True, type=Path, help="store written by `sellip linearize`")
    parser.add_argument("--output", required=True, type=Path, help="hdr.zarr store to write (a directory)")
    parser.add_argument("--threads", type=int, default=1, help="views merged in parallel (default: 1)")
    add_settings_argument(parser, ingest.IngestSettings, section="ingest")


def main(args: argparse.Namespace) -> int:
    try:
        merge_capture(args.linear, args.output, threads=args.threads, settings=args.settings)
    except ingest.IngestError as exc:
        log.error("%s", exc)
        return 1
    return 0
