"""``sellip synth-calibration``: a synthetic calibration folder with known truth (board, spheres, chart).

    sellip synth-calibration --out calib/ [--width 2448 --height 2048 --seed 0 --board-frames 24
                                           --sphere-frames 6 --board-sphere-frames 6 --burst 1
                                           --polarizer-deg 0 --renderer sellip|mitsuba]

See :mod:`sellip.calibrate.synthetic_set` for what is rendered and written (sensor.yaml to start a device.yaml
from, truth.yaml to compare with).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="folder to write")
    parser.add_argument("--width", type=int, default=2448, help="raw width, a multiple of 4 (default: 2448)")
    parser.add_argument("--height", type=int, default=2048, help="raw height, a multiple of 4 (default: 2048)")
    parser.add_argument("--seed", type=int, default=0, help="seed (default: 0)")
    parser.add_argument("--board-frames", type=int, default=24, help="checkerboard frames (default: 24)")
    parser.add_argument("--board", default="14x10", help="inner corners COLSxROWS (default: 14x10)")
    parser.add_argument("--square-mm", type=float, default=10.0, help="square side (mm, default: 10)")
    parser.add_argument("--sphere-frames", type=int, default=6, help="sphere frames, 3 spheres each (default: 6)")
    parser.add_argument("--board-sphere-frames", type=int, default=6,
                        help="pairs of frames (the board alone, then 3 spheres resting on it) for the flash "
                             "(default: 6)")
    parser.add_argument("--burst", type=int, default=1,
                        help="frames per board pose and sphere layout, each with its own noise (default: 1; "
                             "a burst helps the flash a little, not the board: docs/calibration.md)")
    parser.add_argument("--polarizer-deg", type=float, default=0.0, help="the flash polarizer's angle (default: 0)")
    parser.add_argument("--raw-format", choices=["dng", "tiff", "png"], default="dng", help="frame files")
    parser.add_argument("--force", action="store_true", help="replace --out even when it holds no truth.yaml")
    parser.add_argument("--renderer", choices=["sellip", "mitsuba"], default="sellip",
                        help="who draws the frames: sellip's analytic renderer (default) or Mitsuba 3 (an independent "
                             "renderer, the test extra; a pinhole camera with square pixels)")


def main(args: argparse.Namespace) -> int:
    from sellip.calibrate.synthetic import BoardSpec
    from sellip.calibrate.synthetic_set import synthesize_calibration
    from sellip.jobs import WouldReplaceError

    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
    if args.width % 4 or args.height % 4 or args.width < 64 or args.height < 64:
        raise SystemExit(f"--width and --height must be multiples of 4, at least 64, got {args.width}x{args.height}")
    cols, rows = (int(v) for v in args.board.lower().split("x"))
    started = time.perf_counter()
    try:
        out = synthesize_calibration(args.out, args.width, args.height, args.seed, board_frames=args.board_frames,
                                     sphere_frames=args.sphere_frames, board_sphere_frames=args.board_sphere_frames,
                                     spec=BoardSpec(cols, rows, args.square_mm / 1000),
                                     raw_format=args.raw_format, polarizer_deg=args.polarizer_deg, burst=args.burst,
                                     force=args.force, renderer=args.renderer)
    except (WouldReplaceError, ImportError) as exc:
        raise SystemExit(f"sellip synth-calibration: {exc}") from None
    log.info("wrote %s in %.0f s", out, time.perf_counter() - started)
    return 0
