"""Calibration accuracy on synthetic frames with known truth, drawn by sellip's renderer and/or Mitsuba 3.

    python benchmarks/calibration_accuracy.py [--folder DIR] [--width 2448 --height 2048 --seed 0]
                                              [--renderer sellip mitsuba] [--wrong-square K]

Writes the calibration folder with ``sellip synth-calibration`` (unless it already holds one) in the protocol
docs/calibration.md recommends: 96 poses of a 14x10-corner, 10 mm board; 6 layouts of 3 glossy spheres before a
light panel; 6 pairs of the board alone and with 3 spheres resting on it; a ColorChecker, then runs each step of
``sellip calibrate`` as a library call, the flash and the polarization check with the CALIBRATED intrinsics (the
colour step with the chart's true corners and found without them), and prints the error of each against
truth.yaml and the targets it misses (sellip.calibrate.targets), one line each.

``--renderer``: who draws the frames, one or more of ``sellip`` (its own analytic renderer, the default) and
``mitsuba`` (Mitsuba 3, an independent renderer: its spheres mirror their surroundings, a pinhole camera). With
one renderer the set is ``--folder`` itself; with several, ``--folder/<renderer>``. Then a table puts the
renderers side by side: each step's error against the truth targets of issue #51 (fx, fy 0.1 %; cx, cy 0.5 px
at 2448 px wide, scaled to the set's width; flash 2 mm; the right polarizer layout and its angle within 0.5°;
ΔE2000 mean 1.5), whether the step passed its own gate (its targets in sellip.calibrate.targets, as the command
line would with its defaults) and, the worst case, **WRONG, PASSED**: a step that is off the truth yet passes its
gate (the command would write a wrong number and exit 0). A JSON summary is the last line (docs/calibration.md
records the figures).

The spheres before the panel mirror it unless ``--no-panel-reflection`` (sellip's renderer only). The flash is
measured with both protocols: ``flash_outline`` (spheres before the light panel, centres from their outlines) and
``flash_board`` (spheres resting on the board, centres from its pose), each with its error, its 1-sigma (and the
sphere centres' part of it), whether the error is within 3 sigma on every axis, and the targets it misses.
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
from sellip.calibrate.synthetic import BoardSpec
from sellip.calibrate.synthetic_set import synthesize_calibration
from sellip.capture import reader

TRUTH_TARGETS = {"f_pct": 0.1, "c_px_full": 0.5, "flash_mm": 2.0, "polarizer_deg": 0.5, "delta_e": 1.5}
"""Issue #51's targets against the truth (cx, cy: raw pixels of the 2448-pixel-wide sensor)."""


class _WrongSquare:
    """Fault injection for the board protocol (``--wrong-square K``): while active, the first sphere found in the
    K-th pair (spheres_K, in name order) is put one square off (+y) the square it rests on -- what a black ball on
    black squares once did on a Mitsuba frame (its silhouette too faint there), which put the flash 175 mm off
    before outlier highlights were dropped."""

    def __init__(self, pair: int | None, square_m: float):
        self.pair, self.square_m, self.calls = pair, square_m, 0
        self.original = board_spheres.board_sphere_marks

    def __enter__(self):
        if self.pair is not None:
            board_spheres.board_sphere_marks = self
        return self

    def __exit__(self, *exc):
        board_spheres.board_sphere_marks = self.original

    def __call__(self, *args, **kwargs):
        marks, left_out = self.original(*args, **kwargs)
        if self.calls == self.pair and marks:
            marks[0] = marks[0] + np.array([0.0, self.square_m])
        self.calls += 1
        return marks, left_out


def measure(folder: Path, flash_only: bool = False, wrong_square: int | None = None) -> dict:
    """Every step on the set in ``folder`` against its truth.yaml: {step: figures}. Long: one block per step,
    each the library call the command makes, its error against the truth and the targets it misses.
    ``wrong_square``: put one sphere of that pair on the wrong square (:class:`_WrongSquare`)."""
    truth = yaml.safe_load((folder / "truth.yaml").read_text())
    true = truth["device"]
    sensor = true["sensor"]
    frames = lambda sub: {p.name: reader.read_raw_file(p, sensor) for p in sorted((folder / sub).iterdir())}
    summary = {"renderer": truth.get("renderer", "sellip"), "width": sensor["width"], "height": sensor["height"]}

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
    if (folder / "board_spheres").is_dir():  # sets written before 2026-11-28 have no spheres on the board
        protocols["flash_board"] = ("board_spheres", (spec.cols, spec.rows, spec.square_m))
    for key, (sub, on_board) in protocols.items():
        started = time.perf_counter()
        try:
            with _WrongSquare(wrong_square if on_board else None, spec.square_m):
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
                        "dropped": f.dropped, "left_out": f.left_out,
                        "missed_targets": targets.check("flash", f.uncertainty()), "causes": f.causes(),
                        "position_m": f.position_m.tolist()}
        print(f"{key}:", json.dumps(summary[key]), flush=True)

    best = summary.get("flash_board", {}).get("position_m") or summary["flash_outline"].get("position_m")
    device["light"]["position_m"] = best or true["light"]["position_m"]
    if flash_only:
        return summary
    try:
        exposures = {p.name: reader.exposure_time(p) for p in (folder / "spheres").iterdir()}
        report = polarization.check_polarization(frames("spheres"), device, radius, exposures=exposures)
        summary["polarization"] = {"layout_ok": report.layout_ok, "best_layout": report.best_layout,
                                   "layout_right": bool(np.array_equal(report.best_layout,
                                                                       true["sensor"]["polarizer_layout"])),
                                   "score": report.best_score, "next_score": report.second_score,
                                   "rim_score": report.rim_score, "polarizer_error_deg": report.polarizer_error_deg,
                                   "polarizer_std_deg": report.polarizer_std_deg, "ok": report.ok,
                                   "long_frames": report.long_frames, "diffuse_level": report.diffuse_level,
                                   "missed_targets": targets.check("polarization", report.uncertainty())}
    except CalibrationError as exc:
        summary["polarization"] = {"failed": str(exc)}
    print("polarization:", json.dumps(summary["polarization"]), flush=True)

    raw = reader.read_raw_file(folder / "chart" / truth["chart"]["file"], sensor)
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
            "falloff_range": [float(c.falloff.min()), float(c.falloff.max())], "sheen_max": float(np.nanmax(c.sheen)),
            "matrix_max_rel_error": float(np.abs(c.matrix - m_true).max() / np.abs(m_true).max()),
            "missed_targets": targets.check("color", {"delta_e_mean": float(np.nanmean(c.delta_e))})}
    print("color:", json.dumps(summary["color"]), flush=True)
    return summary


def _gate(record: dict, extra_failure: str | None = None) -> tuple[bool, str]:
    """(passed, why) of a step's own gate: it raised (its message), missed targets (them), or passed."""
    if "failed" in record:
        return False, "failed: " + record["failed"].splitlines()[0][:160]
    missed = list(record.get("missed_targets", []))
    if extra_failure:
        missed.append(extra_failure)
    return (not missed), ("passed" if not missed else "failed: " + "; ".join(m[:120] for m in missed))


def verdicts(summary: dict) -> list[dict]:
    """One row per step: {step, result (figures), right (within the truth targets), gate (passed?), why}; a step
    that is not right yet passed its gate is the finding the table marks WRONG, PASSED."""
    rows = []
    k = summary["intrinsics"]
    c_target = TRUTH_TARGETS["c_px_full"] * summary["width"] / 2448
    right = (max(abs(k["fx_rel"]), abs(k["fy_rel"])) * 100 <= TRUTH_TARGETS["f_pct"]
             and max(abs(k["cx_px"]), abs(k["cy_px"])) <= c_target)
    rows.append({"step": "intrinsics", "right": right, "gate": _gate(k),
                 "result": f"fx {k['fx_rel'] * 100:+.3f} %, fy {k['fy_rel'] * 100:+.3f} %; cx {k['cx_px']:+.2f}, "
                           f"cy {k['cy_px']:+.2f} px (1σ {k['std_px']['cx']:.2f}, {k['std_px']['cy']:.2f}; "
                           f"truth target {c_target:.2g} px here)"})
    for key in ("flash_board", "flash_outline"):
        f = summary.get(key)
        if f is None:
            continue
        if "failed" in f:
            rows.append({"step": key, "right": None, "gate": _gate(f), "result": "no result"})
            continue
        rows.append({"step": key, "right": f["error_norm_mm"] <= TRUTH_TARGETS["flash_mm"], "gate": _gate(f),
                     "result": f"{f['error_norm_mm']:.2f} mm off ({', '.join(f'{v:+.2f}' for v in f['error_mm'])}), "
                               f"1σ ({', '.join(f'{v:.2f}' for v in f['std_mm'])}) mm, {f['highlights']} highlights, "
                               f"{f.get('dropped', 0)} dropped as outliers"})
    p = summary.get("polarization")
    if p is not None:
        if "failed" in p:
            rows.append({"step": "polarization", "right": None, "gate": _gate(p), "result": "no result"})
        else:
            extra = None if p["ok"] else "the layout or the flash polarizer does not fit (exit 3)"
            layout = "right" if p["layout_right"] else f"WRONG {p['best_layout']}"
            rows.append({"step": "polarization", "gate": _gate(p, extra),
                         "right": p["layout_right"] and abs(p["polarizer_error_deg"]) <= TRUTH_TARGETS["polarizer_deg"],
                         "result": f"layout {layout} (score {p['score']:+.3f}, next {p['next_score']:+.3f}, limb "
                                   f"{p['rim_score']:+.3f}; {p.get('long_frames', 0)} long exposures, diffuse "
                                   f"{100 * p.get('diffuse_level', float('nan')):.2g} % of full scale); flash "
                                   f"polarizer {p['polarizer_error_deg']:+.2f}° "
                                   f"(1σ {p['polarizer_std_deg']:.2f}°)"})
    for how, c in summary.get("color", {}).items():
        if "failed" in c:
            rows.append({"step": f"color ({how})", "right": None, "gate": _gate(c), "result": "no result"})
            continue
        rows.append({"step": f"color ({how})", "right": c["delta_e2000_mean"] <= TRUTH_TARGETS["delta_e"],
                     "gate": _gate(c), "result": f"ΔE2000 mean {c['delta_e2000_mean']:.2f} (max "
                                                 f"{c['delta_e2000_max']:.2f}), corners {c['corner_error_px']:.1f} px "
                                                 f"off, sheen {c['sheen_max']:.2f}"})
    return rows


def _cell(row: dict) -> str:
    passed, why = row["gate"]
    right = {True: "right", False: "WRONG", None: "-"}[row["right"]]
    flag = " **WRONG, PASSED**" if row["right"] is False and passed else ""
    return f"{row['result']}; {right}; gate {why}{flag}"


def table(summaries: dict[str, dict]) -> str:
    """A markdown table: one row per step, one column per renderer (result; right/WRONG vs the truth; gate)."""
    per = {name: {row["step"]: row for row in verdicts(s)} for name, s in summaries.items()}
    steps = list(dict.fromkeys(step for rows in per.values() for step in rows))
    lines = ["| step | " + " | ".join(summaries) + " |", "|---|" + "---|" * len(summaries)]
    for step in steps:
        lines.append(f"| {step} | " + " | ".join(_cell(per[n][step]) if step in per[n] else "-" for n in per) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=Path("results/calibration_synthetic"))
    parser.add_argument("--renderer", nargs="+", choices=["sellip", "mitsuba"], default=["sellip"],
                        help="who draws the frames (several: side by side, each in --folder/<renderer>)")
    parser.add_argument("--width", type=int, default=2448)
    parser.add_argument("--height", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--board-frames", type=int, default=96, help="board poses (the recommended protocol: 96)")
    parser.add_argument("--sphere-frames", type=int, default=6, help="sphere layouts, 3 spheres each (6)")
    parser.add_argument("--burst", type=int, default=1, help="frames per pose and layout (default 1)")
    parser.add_argument("--flash-only", action="store_true", help="stop after the flash (skip polarization, colour)")
    parser.add_argument("--wrong-square", type=int, metavar="K",
                        help="fault injection: one sphere of the K-th board pair put one square off (flash_board)")
    parser.add_argument("--no-panel-reflection", action="store_true",
                        help="spheres that do not mirror the light panel (sellip's renderer before 2026-11-27)")
    args = parser.parse_args()
    summaries = {}
    for renderer in args.renderer:
        folder = args.folder if len(args.renderer) == 1 else args.folder / renderer
        if not (folder / "truth.yaml").is_file():
            started = time.perf_counter()
            synthesize_calibration(folder, args.width, args.height, seed=args.seed, board_frames=args.board_frames,
                                   sphere_frames=args.sphere_frames, burst=args.burst, progress=True,
                                   reflect_panel=not args.no_panel_reflection, renderer=renderer)
            print(f"synthesized {folder} in {time.perf_counter() - started:.0f} s", flush=True)
        print(f"== {renderer}: {folder}", flush=True)
        summaries[renderer] = measure(folder, args.flash_only, args.wrong_square)
    print(table(summaries), flush=True)
    print(json.dumps(summaries))


if __name__ == "__main__":
    main()
