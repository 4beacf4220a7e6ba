"""Calibration of a real device (docs/design.md §3, paper §6): what ``sellip calibrate`` computes.

Public API (raw frames are (H, W) uint16 mosaics; a device is device.yaml's mapping)::

    intrinsics.calibrate_intrinsics(frames, sensor, cols, rows, square_m) -> IntrinsicsResult  # OpenCV Zhang
    intrinsics.linear_mosaic(raw, sensor) -> (H, W)             # linear, saturated samples NaN
    intrinsics.intensity_image(linear, sensor) -> (H/2, W/2)   # s0 per polarizer cell
    intrinsics.half_to_raw(p) = 2 p + 0.5                       # half-resolution -> raw pixel centres
    intrinsics.flat_mosaic(linear, sensor) -> (H, W)            # full resolution, each filter's gain divided out
    flash.calibrate_flash(frames, device, radius_m) -> FlashResult   # spheres -> mirror rays -> nearest point
    board_spheres.calibrate_flash_on_board(frames, device, radius_m, cols, rows, square_m) -> FlashResult
                                                                  # spheres resting on the board: its pose
    flash_fit.nearest_point / solve_flash / drop_outliers         # the flash from mirror lines; outliers dropped
    polarization.check_polarization(frames, device, radius_m, exposures) -> PolarizationReport
                                                                  # layout, flash polarizer; NAME_long brackets
    color.calibrate_color(raw, device, corners_px=None) -> ColorResult   # 3x3 camera RGB -> sRGB, dE2000
    report.intrinsics_report / flash_report / polarization_report / color_report -> StepReport
                                                                  # each step's log lines, sections and record
    device.read_device / write_device / update_device            # device.yaml, validated, atomic
    targets.TARGETS / check(step, measured, targets) -> [missed]  # each step's 1-sigma and residual targets
    synthetic_set.synthesize_calibration(out, width, height, seed, renderer="sellip")   # frames with known truth
    renderers.frame_renderer("sellip" | "mitsuba")                # who draws them (Mitsuba 3: independent)
    CalibrationError                                              # names the frames and what is wrong
"""

from sellip.calibrate.intrinsics import CalibrationError

__all__ = ["CalibrationError"]
