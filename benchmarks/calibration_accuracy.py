"""Calibration accuracy on synthetic frames with known truth, at the device's size (2448x2048, real sensor noise).

    python benchmarks/calibration_accuracy.py [--folder DIR] [--width 2448 --height 2048 --seed 0]

Writes the calibration folder with ``sellip synth-calibration`` (unless ``--folder`` already holds one) in the
protocol docs/calibration.md recommends: 48 poses of a 14x10-corner, 10 mm board; 6 layouts of 3 glossy 40 mm
spheres before a light panel; every pose a burst of 4 frames (192 board frames, 24 sphere frames); a
ColorChecker, then runs each step of ``sellip calibrate`` as a library call, the flash and the polarization
check with the CALIBRATED intrinsics (the colour step with the chart's true corners and found without
them), and prints the error of each against truth.yaml and the targets it misses (sellip.calibrate.targets),
one line each, and a JSON summary on the last line (docs/calibration.md records the figures). The spheres mirror
their light panel unless ``--no-panel-reflection``. The flash is measured with both protocols: ``flash_outline``
(spheres before the light panel, centres from their outlines) and ``flash_board`` (spheres resting on the board,
centres from its pose; the folder's ``board_spheres``), each with its error, its 1-sigma (and the sphere centres'
part of it), whether the error is within 3 sigma on every axis, and the targets it misses.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np
import yaml

from sellip.calibrate import board_spheres, color, flash, intrinsics, polarization, targets
from sellip.calibrate.intrinsics import CalibrationError
from sellip.calibrate.synthetic import BoardSpec, synthesize_calibration
from sellip.capture import reader


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=Path("results/calibration_synthetic"))
    parser.add_argument("--width", type=int, default=2448)
    parser.add_argument("--height", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--board-frames", type=int, default=96, help="board poses (the recommended protocol: 96)")
    parser.add_argument("--sphere-frames", type=int, default=6, help="sphere layouts, 3 spheres each (6)")
    parser.add_argument("--burst", type=int, default=1, help="frames per pose and layout (default 1)")
    parser.add_argument("--flash-only", action="store_true", help="stop after the flash (skip polarization, colour)")
    parser.add_argument("--no-panel-reflection", action="store_true",
                        help="spheres that do not mirror the light panel (the simulator before 2026-11-27)")
    args = parser.parse_args()
    if not (args.folder / "truth.yaml").is_file():
        started = time.perf_counter()
        synthesize_calibration(args.folder, args.width, args.height, seed=args.seed, board_frames=args.board_frames,
                               sphere_frames=args.sphere_frames, burst=args.burst, progress=True,
                               reflect_panel=not args.no_panel_reflection)
        print(f"synthesized {args.folder} in {time.perf_counter() - started:.0f} s", flush=True)
    truth = yaml.safe_load((args.folder / "truth.yaml").read_text())
    true = truth["device"]
    sensor = true["sensor"]
    frames = lambda sub: {p.name: reader.read_raw_file(p, sensor) for p in sorted((args.folder / sub).iterdir())}
    summary = {}

    board = truth["board"]
    spec = BoardSpec(board["cols"], board["rows"], board["square_m"])
    started = time.perf_counter()
    k = intrinsics.calibrate_intrinsics(frames("board"), sensor, spec.cols, spec.rows, spec.square_m)
    cam = true["camera"]
    summary["intrinsics"] = {
        "frames": len(k.per_frame), "fx_rel": k.fx / cam["fx"] - 1, "fy_rel": k.fy / cam["fy"] - 1,
        "cx_px": k.cx - cam["cx"], "cy_px": k.cy - cam["cy"], "std_px": k.std, "rms_px": k.rms_px,
        "distortion": k.distortion, "distortion_true": cam["distortion"], "seconds": time.perf_counter() - started}
    measured, _ = intrinsics.intrinsics_uncertainty(k)
    summary["intrinsics"]["missed_targets"] = targets.check("intrinsics", measured)
    print("intrinsics:", json.dumps(summary["intrinsics"]), flush=True)

    device = copy.deepcopy(true)
    device["camera"].update(k.camera())
    device["calibration"] = {"intrinsics": {"std_px": k.std}}  # the flash's 1-sigma includes the intrinsics'
    radius = truth["spheres"]["radius_m"]
    protocols = {"flash_outline": ("spheres", None)}
    if (args.folder / "board_spheres").is_dir():  # sets written before 2026-11-28 have no spheres on the board
        protocols["flash_board"] = ("board_spheres", (spec.cols, spec.rows, spec.square_m))
    for key, (sub, on_board) in protocols.items():
        started = time.perf_counter()
        try:
            f = (board_spheres.calibrate_flash_on_board(frames(sub), device, radius, *on_board) if on_board
                 else flash.calibrate_flash(frames(sub), device, radius))
        except CalibrationError as exc:
            summary[key] = {"failed": str(exc)}
            print(f"{key}:", json.dumps(summary[key]), flush=True)
            continue
        error = f.position_m - np.asarray(true["light"]["position_m"])
        summary[key] = {"highlights": len(f.highlights), "error_mm": (error * 1e3).tolist(),
                        "error_norm_mm": float(np.linalg.norm(error) * 1e3), "std_mm": (f.std_m * 1e3).tolist(),
                        "centre_std_mm": (f.centre_std_m * 1e3).tolist(), "rms_mm": f.rms_mm,
                        "within_3_sigma": bool(np.all(np.abs(error) <= 3 * f.std_m)),
                        "seconds": time.perf_counter() - started,
                        "missed_targets": targets.check("flash", f.uncertainty()), "causes": f.causes(),
                        "position_m": f.position_m.tolist()}
        print(f"{key}:", json.dumps(summary[key]), flush=True)

    best = summary.get("flash_board", {}).get("position_m") or summary["flash_outline"].get("position_m")
    device["light"]["position_m"] = best or true["light"]["position_m"]
    if args.flash_only:
        print(json.dumps(summary))
        return
    try:
        report = polarization.check_polarization(frames("spheres"), device, radius)
        summary["polarization"] = {"layout_ok": report.layout_ok, "score": report.best_score,
                                   "next_score": report.second_score, "rim_score": report.rim_score,
                                   "polarizer_error_deg": report.polarizer_error_deg,
                                   "polarizer_std_deg": report.polarizer_std_deg,
                                   "missed_targets": targets.check("polarization", report.uncertainty())}
    except CalibrationError as exc:
        summary["polarization"] = {"failed": str(exc)}
    print("polarization:", json.dumps(summary["polarization"]), flush=True)

    raw = reader.read_raw_file(args.folder / "chart" / truth["chart"]["file"], sensor)
    m_true = np.asarray(cam["color_matrix"])
    true_corners = np.asarray(truth["chart"]["corners_px"])
    summary["color"] = {}
    for how, corners in (("given_corners", true_corners), ("found", None)):
        try:
            c = color.calibrate_color(raw, device, corners)
        except CalibrationError as exc:
            summary["color"][how] = {"failed": str(exc)}
            continue
        summary["color"][how] = {
            "delta_e2000_mean": float(np.nanmean(c.delta_e)), "delta_e2000_max": float(np.nanmax(c.delta_e)),
            "corner_error_px": float(np.linalg.norm(c.corners_px - true_corners, axis=1).max()),
            "falloff_range": [float(c.falloff.min()), float(c.falloff.max())],
            "matrix_max_rel_error": float(np.abs(c.matrix - m_true).max() / np.abs(m_true).max()),
            "missed_targets": targets.check("color", {"delta_e_mean": float(np.nanmean(c.delta_e))})}
    print("color:", json.dumps(summary["color"]), flush=True)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
