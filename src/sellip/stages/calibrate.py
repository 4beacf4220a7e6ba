"""``sellip calibrate``: describe a real device once (docs/design.md §3), step by step, into device.yaml.

    sellip calibrate intrinsics FRAME... --device device.yaml --board 9x7 --square-mm 15 [--k3]
    sellip calibrate flash FRAME... --device device.yaml --sphere-radius-mm 20 [--board 9x7 --square-mm 15]
                                    [--max-flash-std-mm 2 ...]
    sellip calibrate polarization FRAME... --device device.yaml --sphere-radius-mm 20 [--write]
    sellip calibrate color FRAME --device device.yaml [--corners X,Y X,Y X,Y X,Y]

device.yaml must exist with at least its ``sensor`` section (docs/calibration.md); each step reads raw frames
(DNG / 16-bit TIFF / PNG, checked against the sensor), logs every frame it leaves out with why, gates on its own
uncertainty (:mod:`sellip.calibrate.targets`: each target an option ``--max-...``; a step that misses one exits
non-zero naming the causes it sees and writes nothing), and writes its result, residuals, 1-sigma and targets
into device.yaml (:mod:`sellip.calibrate.device`). The library is
:mod:`sellip.calibrate`; what each step logs and writes: :mod:`sellip.calibrate.report`.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from sellip.calibrate import device as devices
from sellip.calibrate import targets as gates
from sellip.calibrate.intrinsics import CalibrationError
from sellip.calibrate.report import StepReport
from sellip.capture import files, reader

log = logging.getLogger(__name__)


def _existing(path: Path) -> Path:
    """``path`` if it is a file; else a CalibrationError that says a shell glob matched nothing (the shell passes
    an unmatched pattern through as it is) or that the file is missing."""
    if path.is_file():
        return path
    if any(c in str(path) for c in "*?["):
        raise CalibrationError(f"no file matches {str(path)!r}: expected raw frames there (check the folder and "
                               "the pattern)")
    raise CalibrationError(f"{path}: no such file; expected a raw frame (DNG, 16-bit TIFF or PNG)")


def _frames(paths: list[Path], sensor: dict) -> dict[str, np.ndarray]:
    out = {}
    for path in paths:
        out[path.name] = reader.read_raw_file(_existing(path), sensor)
    return out


def _board(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners (e.g. 9x7), got {text!r}") from None
    if cols < 3 or rows < 3:
        raise argparse.ArgumentTypeError(f"a board needs at least 3x3 inner corners, got {text!r}")
    return cols, rows


def _point(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in raw pixels, got {text!r}") from None
    return x, y


def configure_parser(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="step", required=True, metavar="STEP")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--device", required=True, type=Path,
                        help="device.yaml to read and update (at least its sensor section)")
    p = sub.add_parser("intrinsics", parents=[common], help="fx, fy, cx, cy and distortion from checkerboard frames")
    p.add_argument("frames", nargs="+", type=Path, help="raw frames of the board")
    p.add_argument("--board", required=True, type=_board, help="inner corners COLSxROWS, e.g. 9x7")
    p.add_argument("--square-mm", required=True, type=float, help="side of a square (mm)")
    p.add_argument("--k3", action="store_true", help="also fit k3 (wide-angle lenses; default: k3 = 0)")
    _add_targets(p, "intrinsics")
    p = sub.add_parser("flash", parents=[common], help="the flash position from mirror highlights on spheres")
    p.add_argument("frames", nargs="+", type=Path,
                   help="raw frames of glossy spheres: with --board, pairs NAME.dng (spheres resting on the board) "
                        "and NAME_board.dng (the board alone, same camera position); else spheres before a bright "
                        "background")
    p.add_argument("--sphere-radius-mm", required=True, type=float, help="the spheres' radius (mm)")
    p.add_argument("--board", type=_board, help="the spheres rest on this board's squares: inner corners COLSxROWS")
    p.add_argument("--square-mm", type=float, help="with --board: side of a square (mm)")
    _add_targets(p, "flash")
    p = sub.add_parser("polarization", parents=[common],
                       help="check the polarizer layout and the flash polarizer on the sphere frames")
    p.add_argument("frames", nargs="+", type=Path, help="raw frames of glossy dielectric spheres")
    p.add_argument("--sphere-radius-mm", required=True, type=float, help="the spheres' radius (mm)")
    p.add_argument("--write", action="store_true", help="write the layout and polarizer angle that fit")
    _add_targets(p, "polarization")
    p = sub.add_parser("color", parents=[common], help="3x3 colour matrix from a ColorChecker under the flash")
    p.add_argument("frame", type=Path, help="raw frame of the chart")
    p.add_argument("--corners", type=_point, nargs=4, metavar="X,Y",
                   help="the patch area's corners in raw pixels: dark skin's outer corner first, then clockwise "
                        "(bluish green's, black's, white's); default: the chart is found and its order checked")
    _add_targets(p, "color")


def _add_targets(parser: argparse.ArgumentParser, step: str) -> None:
    for target in gates.for_step(step):
        parser.add_argument(target.option, dest=f"target_{target.name}", type=float, default=target.default,
                            metavar=target.unit.replace(" ", "_").upper(),
                            help=f"target: {target.help} ({target.unit}; default {target.default:g})"
                            .replace("%", "%%"))  # argparse expands %-formats: the unit may be "%"


def _targets(args, step: str) -> dict[str, float]:
    return {t.name: getattr(args, f"target_{t.name}") for t in gates.for_step(step)}


def _gate(args, step: str, measured: dict, causes: list[str]) -> dict:
    """The step's targets from the command line; a CalibrationError naming every target missed and the causes
    seen in the frames when one is missed (device.yaml is then not touched)."""
    targets = _targets(args, step)
    missed = gates.check(step, measured, targets)
    if missed:
        why = "".join(f"\n  {line}" for line in missed)
        seen = "".join(f"\n  {line}" for line in causes) or "\n  none that the frames show"
        raise CalibrationError(f"the {step} step cannot give a trustworthy result; device.yaml is unchanged. "
                               f"Missed:{why}\nCauses seen in the frames:{seen}")
    return targets


def _apply(args, step: str, report, targets: dict | None = None) -> None:
    """Log the step's lines and write its sections and record (with the targets it met) into device.yaml."""
    for level, line in report.lines:
        log.log(level, line)
    record = dict(report.record)
    if targets is not None:
        record = {"ok": record.get("ok", True), **record, "targets": targets}
    devices.update_device(args.device, report.sections, step, record)


def _intrinsics(args, device) -> int:
    from sellip.calibrate.intrinsics import calibrate_intrinsics, intrinsics_uncertainty
    from sellip.calibrate.report import intrinsics_report

    cols, rows = args.board
    result = calibrate_intrinsics(_frames(args.frames, device["sensor"]), device["sensor"], cols, rows,
                                  args.square_mm / 1000, fix_k3=not args.k3, log=log.info)
    measured, causes = intrinsics_uncertainty(result, _targets(args, "intrinsics")["c_std_px"])
    targets = _gate(args, "intrinsics", measured, causes)
    _apply(args, "intrinsics", intrinsics_report(result, args.board, args.square_mm), targets)
    return 0


def _flash(args, device) -> int:
    from sellip.calibrate.board_spheres import calibrate_flash_on_board
    from sellip.calibrate.flash import calibrate_flash
    from sellip.calibrate.report import flash_report

    frames, radius = _frames(args.frames, device["sensor"]), args.sphere_radius_mm / 1000
    if args.board is not None:
        if args.square_mm is None:
            raise CalibrationError("--board needs --square-mm (the side of the board's squares, mm)")
        result = calibrate_flash_on_board(frames, device, radius, *args.board, args.square_mm / 1000, log=log.info)
    else:
        result = calibrate_flash(frames, device, radius, log=log.info)
    report = flash_report(result, device, args.sphere_radius_mm)
    for level, line in report.lines:
        log.log(level, line)
    targets = _gate(args, "flash", result.uncertainty(), result.causes())
    _apply(args, "flash", StepReport([], report.sections, report.record), targets)
    return 0


def _polarization(args, device) -> int:
    from sellip.calibrate.polarization import check_polarization
    from sellip.calibrate.report import polarization_report

    exposures = {path.name: reader.exposure_time(path) for path in map(_existing, args.frames)}
    report = check_polarization(_frames(args.frames, device["sensor"]), device, args.sphere_radius_mm / 1000,
                                log=log.info, exposures=exposures)
    targets = _gate(args, "polarization", report.uncertainty(), report.causes())
    _apply(args, "polarization", polarization_report(report, device, args.write), targets)
    return 0 if report.ok or args.write else 3


def _color(args, device) -> int:
    from sellip.calibrate.color import calibrate_color, corner_order_causes
    from sellip.calibrate.report import color_report

    raw = reader.read_raw_file(_existing(args.frame), device["sensor"])
    corners = None if args.corners is None else np.asarray(args.corners, np.float64)
    result = calibrate_color(raw, device, corners)
    measured = {"delta_e_mean": float(np.nanmean(result.delta_e))}
    limit = _targets(args, "color")["delta_e_mean"]
    causes = (corner_order_causes(raw, device, result.corners_px, limit)
              if not measured["delta_e_mean"] <= limit else [])
    targets = _gate(args, "color", measured, causes)
    _apply(args, "color", color_report(result), targets)
    return 0


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
    try:
        device = devices.read_device(args.device)
        if args.step != "intrinsics" and "camera" not in device:
            raise devices.DeviceError(str(args.device), "key 'camera'",
                                      "missing; run `sellip calibrate intrinsics` first")
        step = {"intrinsics": _intrinsics, "flash": _flash, "polarization": _polarization, "color": _color}
        return step[args.step](args, device)
    except (CalibrationError, files.CaptureError) as exc:
        raise SystemExit(f"sellip calibrate {args.step}: {exc}") from None
