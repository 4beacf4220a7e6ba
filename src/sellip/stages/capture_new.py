"""``sellip capture new``: a capture folder (docs/design.md §3) for a folder of raw frames and a calibrated device.

    sellip capture new FRAMES_DIR --device device.yaml --distance-m 0.9 --pattern '{view}_f{level}.dng' \
        [--exposure-s 0.005] [--out CAPTURE] [--accept-failed-calibration]
    sellip capture new FRAMES_DIR --device device.yaml --distance-m 0.9 --csv frames_in.csv [--out CAPTURE]

Writes capture.yaml (the device's sensor, camera and light sections, scene.distance_m, the calibration record)
and frames.csv into the capture folder (default: the parent of a folder named ``raw``, else FRAMES_DIR) after
checking every frame (a capture.yaml or frames.csv already there that differs from what it would write, e.g.
edited by the user, stops it unless --force); then the folder runs with ``snakemake --config capture=CAPTURE
name=NAME``. The library is :mod:`sellip.capture.assemble`.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.capture import files, reader

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=["new"], help="new: write capture.yaml and frames.csv for a frame folder")
    parser.add_argument("frames_dir", type=Path, help="folder of raw frames (DNG, 16-bit TIFF/PNG)")
    parser.add_argument("--device", required=True, type=Path, help="calibrated device.yaml (sellip calibrate)")
    parser.add_argument("--distance-m", required=True, type=float, help="typical camera-object distance (m)")
    parser.add_argument("--pattern", help="file-name pattern with {view} and {level}, e.g. '{view}_f{level}.dng' "
                                          "(level: a flash level in (0, 1], or N of a '1/N power' setting)")
    parser.add_argument("--csv", type=Path, help="CSV with columns file, view_id, flash_level[, frame_id, "
                                                 "exposure_s] instead of --pattern")
    parser.add_argument("--exposure-s", type=float, help="exposure time (s) of every frame (default: the one each "
                                                         "raw file records, its ExposureTime tag)")
    parser.add_argument("--accept-failed-calibration", action="store_true",
                        help="use a device.yaml whose calibration records a failed step (ok: false)")
    parser.add_argument("--out", type=Path, help="capture folder (default: see above)")
    parser.add_argument("--force", action="store_true",
                        help="replace a capture.yaml or frames.csv already there that differs from what would be "
                             "written")
    parser.add_argument("--no-check-raw", action="store_true", help="do not open every frame to check it")


def main(args: argparse.Namespace) -> int:
    from sellip.calibrate.device import read_device
    from sellip.capture.assemble import assemble_capture

    try:
        device = read_device(args.device, complete=True)
        out = assemble_capture(args.frames_dir, device, args.distance_m, out=args.out, pattern=args.pattern,
                               csv=args.csv, exposure_s=args.exposure_s, check_raw=not args.no_check_raw,
                               accept_failed_calibration=args.accept_failed_calibration,
                               device_label=str(args.device), force=args.force)
    except files.CaptureError as exc:
        raise SystemExit(f"sellip capture new: {exc}") from None
    capture = reader.read_capture(out)
    log.info("wrote %s: %d frames of %d views", out, len(capture.frames), len(capture.view_ids))
    return 0
