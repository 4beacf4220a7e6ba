"""What each ``sellip calibrate`` step logs and writes into device.yaml (sellip.calibrate.report), from results
built by hand: the lines and their levels, the sections (what changes in device.yaml, what is kept) and the record."""

from __future__ import annotations

import logging

import numpy as np

from sellip.calibrate import report
from sellip.calibrate.color import PATCH_NAMES, ColorResult
from sellip.calibrate.flash import FlashResult
from sellip.calibrate.intrinsics import IntrinsicsResult
from sellip.calibrate.polarization import PolarizationReport

LAYOUT = [[90, 45], [135, 0]]


def test_intrinsics_report():
    result = IntrinsicsResult(fx=1811.5, fy=1812.25, cx=309.4, cy=253.7, distortion=[-0.12, 0.25, 4e-4, -3e-4, 0.0],
                              rms_px=0.0734, per_frame={"a.dng": 0.07, "b.dng": 0.08},
                              left_out={"c.dng": "board not found"},
                              std={"fx": 1.5, "fy": 1.4, "cx": 0.9, "cy": 0.6})
    step = report.intrinsics_report(result, (14, 10), 10.0)
    assert step.lines[0] == (logging.WARNING, "left out c.dng: board not found")
    level, summary = step.lines[1]
    assert level == logging.INFO and "fx 1811.50 fy 1812.25 cx 309.40 cy 253.70" in summary
    assert "(1-sigma 1.50 1.40 0.90 0.60 px)" in summary and "RMS 0.073 px over 2 frames" in summary
    assert step.sections == {"camera": {"fx": 1811.5, "fy": 1812.25, "cx": 309.4, "cy": 253.7,
                                        "distortion": [-0.12, 0.25, 4e-4, -3e-4, 0.0]}}
    assert step.record["board"] == "14x10" and step.record["per_frame_rms_px"] == {"a.dng": 0.07, "b.dng": 0.08}
    assert step.record["left_out"] == {"c.dng": "board not found"}


def test_flash_report_keeps_the_polarizer_angle():
    result = FlashResult(position_m=np.array([0.0001, 0.0502, 0.0013]), std_m=np.array([2e-4, 2e-4, 8e-4]),
                         rms_mm=0.4, highlights=[{"frame": "s0.dng", "sphere": 1, "residual_mm": 0.25}],
                         left_out={"s1.dng#0": "highlight saturated"})
    step = report.flash_report(result, {"light": {"polarizer_deg": 12.0, "position_m": [0, 0, 0]}}, 20.0)
    assert step.lines[0] == (logging.WARNING, "left out s1.dng#0: highlight saturated")
    assert step.lines[1] == (logging.INFO, "s0.dng sphere 1: highlight residual 0.250 mm")
    assert step.lines[2][1].startswith("flash at [0.1, 50.2, 1.3] mm (1-sigma [0.2, 0.2, 0.8] mm, of which the "
                                       "sphere centres' [0.0, 0.0, 0.0] mm)")
    assert step.sections == {"light": {"polarizer_deg": 12.0, "position_m": [0.0001, 0.0502, 0.0013]}}
    assert np.allclose(step.record["std_mm"], [0.2, 0.2, 0.8]) and step.record["sphere_radius_mm"] == 20.0
    assert step.record["protocol"] == "outline" and step.record["centre_std_mm"] == [0.0, 0.0, 0.0]
    # a device without a light section yet: the polarizer at 0
    assert report.flash_report(result, {}, 20.0).sections["light"]["polarizer_deg"] == 0.0


def _polarization(best, measured_deg):
    return PolarizationReport(claimed_layout=LAYOUT, best_layout=best, claimed_score=0.85, best_score=0.85,
                              second_score=0.01, polarizer_deg=measured_deg, polarizer_std_deg=0.3,
                              claimed_polarizer_deg=0.0, limb_pixels=5000, highlights=6)


def test_polarization_report_warns_and_writes_only_when_asked():
    fits = report.polarization_report(_polarization(LAYOUT, 0.2), {"light": {"position_m": [0, 0.05, 0]}}, False)
    assert [level for level, _ in fits.lines] == [logging.INFO, logging.INFO] and fits.sections == {}
    assert fits.record["ok"] and "fits" in fits.lines[0][1]
    off = report.polarization_report(_polarization(LAYOUT, 19.5), {"light": {"position_m": [0, 0.05, 0]}}, True)
    assert [level for level, _ in off.lines] == [logging.WARNING, logging.WARNING] and not off.record["ok"]
    assert off.sections == {"sensor": {"polarizer_layout": LAYOUT},
                            "light": {"position_m": [0, 0.05, 0], "polarizer_deg": 19.5}}


def test_color_report_names_the_worst_patch_and_ignores_left_out_ones():
    delta_e = np.full(24, 0.5)
    delta_e[3], delta_e[18] = 1.75, np.nan  # foliage worst; white left out
    step = report.color_report(ColorResult(matrix=np.eye(3) * 1.5, delta_e=delta_e,
                                           left_out={PATCH_NAMES[18]: "clipped"}))
    (level, line), = step.lines
    assert level == logging.INFO and f"max 1.75 (patch {PATCH_NAMES[3]})" in line and "mean 0.55" in line
    assert step.sections == {"camera": {"color_matrix": (np.eye(3) * 1.5).tolist()}}
    assert step.record["patches_used"] == 23 and step.record["left_out"] == {PATCH_NAMES[18]: "clipped"}


def test_targets_are_declared_once_and_a_missing_value_misses():
    """Every target has one option and one step; check() names each target missed with its value, limit and
    option, and a value not measured (NaN) misses rather than passes."""
    from sellip.calibrate import targets

    options = [t.option for t in targets.TARGETS]
    assert len(set(options)) == len(options) and {t.step for t in targets.TARGETS} == {
        "intrinsics", "flash", "polarization", "color"}
    assert targets.check("color", {"delta_e_mean": 1.2}) == []
    assert targets.check("color", {"delta_e_mean": 1.2}, {"delta_e_mean": 1.0}) == [
        "mean CIEDE2000 of the chart's patches after the fit is 1.2 ΔE2000, target <= 1 ΔE2000 (--max-delta-e-mean)"]
    missed = targets.check("polarization", {"polarizer_std_deg": float("nan")})
    assert len(missed) == 1 and "is nan deg" in missed[0]
