"""What each step of ``sellip calibrate`` reports and writes into device.yaml, from its result: the lines it logs
(each with its level), the device.yaml sections it changes and its ``calibration.<step>`` record.

Public API::

    StepReport(lines, sections, record)     # lines: [(logging level, text)]; sections and record for update_device
    intrinsics_report(result, board, square_mm) -> StepReport
    flash_report(result, device, sphere_radius_mm) -> StepReport
    polarization_report(report, device, write) -> StepReport
    color_report(result) -> StepReport

The stage adapter (``sellip.stages.calibrate``) logs ``lines`` and passes ``sections`` and ``record`` to
:func:`sellip.calibrate.device.update_device`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np


@dataclass
class StepReport:
    """lines: [(logging level, text)] in the order they are logged; sections: device.yaml sections to update;
    record: the step's ``calibration.<step>`` record."""

    lines: list[tuple[int, str]] = field(default_factory=list)
    sections: dict = field(default_factory=dict)
    record: dict = field(default_factory=dict)


def _left_out(left_out: Mapping[str, str]) -> list[tuple[int, str]]:
    return [(logging.WARNING, f"left out {name}: {why}") for name, why in left_out.items()]


def intrinsics_report(result, board: tuple[int, int], square_mm: float) -> StepReport:
    """The intrinsics step (:class:`sellip.calibrate.intrinsics.IntrinsicsResult`, the board's inner corners
    (cols, rows) and square side): the frames left out, fx fy cx cy with their one-sigma, the distortion and the
    RMS; ``camera`` (fx, fy, cx, cy, distortion); the record with every frame's RMS."""
    cols, rows = board
    std = [result.std.get(key, float("nan")) for key in ("fx", "fy", "cx", "cy")]
    summary = (f"fx {result.fx:.2f} fy {result.fy:.2f} cx {result.cx:.2f} cy {result.cy:.2f} (1-sigma "
               f"{std[0]:.2f} {std[1]:.2f} {std[2]:.2f} {std[3]:.2f} px) distortion "
               f"{np.round(result.distortion, 5).tolist()}; RMS {result.rms_px:.3f} px over {len(result.per_frame)} "
               "frames")
    return StepReport(_left_out(result.left_out) + [(logging.INFO, summary)], {"camera": result.camera()}, {
        "board": f"{cols}x{rows}", "square_mm": square_mm, "rms_px": result.rms_px, "std_px": result.std,
        "per_frame_rms_px": result.per_frame, "left_out": result.left_out})


def flash_report(result, device: Mapping, sphere_radius_mm: float) -> StepReport:
    """The flash step (:class:`sellip.calibrate.flash.FlashResult`): the highlights left out, each highlight's
    residual, the position (mm) with its one-sigma and the RMS; ``light`` with the new position (the polarizer
    angle kept, 0 when the device has none yet); the record with every highlight."""
    lines = _left_out(result.left_out)
    lines += [(logging.INFO, f"{h['frame']} sphere {h['sphere']}: highlight residual {h['residual_mm']:.3f} mm")
              for h in result.highlights]
    summary = (f"flash at {np.round(np.asarray(result.position_m) * 1e3, 2).tolist()} mm (1-sigma "
               f"{np.round(np.asarray(result.std_m) * 1e3, 2).tolist()} mm, of which the sphere centres' "
               f"{np.round(np.asarray(result.centre_std_m) * 1e3, 2).tolist()} mm), RMS residual "
               f"{result.rms_mm:.3f} mm over {len(result.highlights)} highlights ({result.protocol} protocol; "
               f"{result.dropped} dropped as outliers)")
    lines.append((logging.INFO, summary))
    light = dict(device.get("light", {"polarizer_deg": 0.0}))
    light["position_m"] = np.asarray(result.position_m, np.float64).tolist()
    return StepReport(lines, {"light": light}, {
        "sphere_radius_mm": sphere_radius_mm, "protocol": result.protocol,
        "std_mm": (np.asarray(result.std_m) * 1e3).tolist(),
        "centre_std_mm": (np.asarray(result.centre_std_m) * 1e3).tolist(),
        "rms_mm": result.rms_mm, "highlights": result.highlights, "dropped": result.dropped,
        "left_out": result.left_out})


def polarization_report(report, device: Mapping, write: bool) -> StepReport:
    """The polarization check (:class:`sellip.calibrate.polarization.PolarizationReport`): its messages (warnings
    when something does not fit); with ``write``, the layout and the flash polarizer angle that fit (``sensor`` and
    ``light``), else no section; the record."""
    level = logging.INFO if report.ok else logging.WARNING
    sections = {}
    if write:
        sections = {"sensor": {"polarizer_layout": report.best_layout},
                    "light": {**device.get("light", {}), "polarizer_deg": report.polarizer_deg}}
    return StepReport([(level, line) for line in report.messages()], sections, report.record())


def color_report(result) -> StepReport:
    """The colour step (:class:`sellip.calibrate.color.ColorResult`): the matrix, the mean and worst ΔE2000 with the
    worst patch; ``camera.color_matrix``; the record."""
    worst = int(np.nanargmax(result.delta_e))
    line = (f"colour matrix {np.round(result.matrix, 4).tolist()}; dE2000 mean {np.nanmean(result.delta_e):.2f}, "
            f"max {result.delta_e[worst]:.2f} (patch {result.patch_names[worst]})")
    return StepReport([(logging.INFO, line)], {"camera": {"color_matrix": np.asarray(result.matrix).tolist()}},
                      result.record())
