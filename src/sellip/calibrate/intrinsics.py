"""Camera intrinsics from checkerboard frames: Zhang's method (OpenCV); the board found on the polarization mosaic's
intensity image, its corners refined on the full-resolution mosaic.

Public API::

    linear_mosaic(raw, sensor) -> (H, W) float32            # linear, 1 = full scale, saturated samples NaN
    intensity_image(linear, sensor) -> (H/2, W/2) float32   # s0 per polarizer cell, 1 = full scale
    half_to_raw(points) / raw_to_half(points)                # the half-resolution <-> raw pixel mapping
    flat_mosaic(linear, sensor) -> (H, W) float32            # the linear mosaic with each filter's gain divided out
    detect_board(raw, sensor, cols, rows, max_edge_px=...) -> BoardDetection   # corners in raw pixels, or why not
    refine_corners(mosaic, corners, cols, rows) -> (N, 2)    # cv2.cornerSubPix on flat_mosaic, raw pixels
    calibrate_intrinsics(frames: {name: raw}, sensor, cols, rows, square_m, ...) -> IntrinsicsResult
    opencv_single_threaded()                                 # context: OpenCV on one thread (deterministic)
    MIN_BOARD_FRAMES

The intensity image
    Every 2x2 polarizer cell holds the four analyzers 0/45/90/135; their sum is 2 s0 whatever the
    polarization, so the cell-grid image of s0 sees a board's edges without the polarization's pattern. It is
    made with the ingest chain (:func:`sellip.ingest.linearize`, :func:`sellip.ingest.demosaic`: every analyzer
    and colour on the cell grid), averaged over the four analyzers and the colour channels (camera RGB; a grey
    board needs no colour matrix). It is NOT undistorted: the lens is what is calibrated.

The full-resolution mosaic
    On the half-resolution intensity image cv2.cornerSubPix pulls a corner towards the image's pixel centres: its
    error swings by +-0.05 raw px with the corner's position within a cell, which left the principal point's
    1-sigma at 0.4-0.6 px with 96 board poses at 2448x2048. The board's paper is grey, so every raw pixel sees the
    same scene through its own analyzer and colour filter: :func:`flat_mosaic` divides each of the mosaic's
    positions by its gain (measured on the frame's bright paper) and smooths the result by a Gaussian of
    :data:`CORNER_BLUR_PX`; refined there, the corners scatter 2-3 times less (0.02-0.03 raw px per axis on
    Mitsuba's and sellip's full-size frames) and the 1-sigma is 0.15-0.22 px (docs/calibration.md).

Half-resolution pixel centres (stated once, tested in tests/test_calibrate.py)
    The demosaiced analyzer k sits at raw (2j + dx_k, 2i + dy_k) for cell (i, j); the four analyzers' mean
    sits at the cell's centre, raw (x, y) = (2j + 0.5, 2i + 0.5), with pixel centres at integer coordinates
    (OpenCV). So a position (x', y') on the intensity image is raw (2x' + 0.5, 2y' + 0.5) (:func:`half_to_raw`),
    the inverse of :func:`sellip.ingest.output_intrinsics` (f' = f / 2, c' = (c - 0.5) / 2). Corners are mapped
    to raw pixels before OpenCV calibrates, so fx, fy, cx, cy come out in raw-pixel units (docs/design.md §3) and
    the distortion coefficients (normalized coordinates) need no conversion.

Deterministic
    OpenCV's parallel loops (findChessboardCornersSB, calibrateCameraExtended) sum in an order that depends on
    how the work was split between threads: with its thread pool the same frames gave intrinsics differing in the
    12th digit from run to run (and within one process), which a reconstruction then amplified. Every OpenCV call
    here runs inside :func:`opencv_single_threaded`, so the same frames give bit-identical results
    (``test_intrinsics_are_bit_identical_between_runs``); it costs nothing measurable (the demosaicing dominates).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from sellip.capture import ingest
from sellip.capture.mosaic import mosaic_layout

MIN_BOARD_FRAMES = 6
"""Usable board frames needed: Zhang's method needs 3 for a solution; with five distortion coefficients and a
narrow lens, 6 well-spread tilted views are the least that meets 0.1 % on fx (docs/calibration.md)."""

MAX_EDGE_WIDTH_PX = 2.5
"""A board whose edges are wider than this (OpenCV's estimateChessboardSharpness, intensity-image pixels, the
10-90 % rise) is blurred: its corners are left out (a sharp board measures about 2 at 2448x2048)."""

MAX_FRAME_RMS_PX = 1.0
"""A frame whose corners reproject worse than this (raw pixels RMS) after the fit is left out and the fit redone."""


@contextmanager
def opencv_single_threaded() -> Iterator[None]:
    """Run the enclosed OpenCV calls on one thread (cv2.setNumThreads(1)), restoring the previous setting after:
    OpenCV's multithreaded reductions are not bit-reproducible (module docstring, "Deterministic")."""
    import cv2

    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(previous)


class CalibrationError(ValueError):
    """Calibration inputs that cannot give a trustworthy result; the message names the frames and what is wrong."""


def linear_mosaic(raw: np.ndarray, sensor: Mapping) -> np.ndarray:
    """(H, W) float32 linear intensities (1 = full scale, the black level map subtracted) of a raw mosaic (H, W);
    saturated samples are NaN. What :func:`intensity_image` and :func:`flat_mosaic` are made from."""
    height, width = raw.shape
    linear, invalid = ingest.linearize(raw, ingest.black_level_map(sensor["black_level"], height, width),
                                       float(sensor["white_level"]))
    linear[invalid] = np.nan
    return linear


def intensity_image(linear: np.ndarray, sensor: Mapping) -> np.ndarray:
    """s0 / 2 per polarizer cell (H/2, W/2) float32 from a linear mosaic (H, W) (:func:`linear_mosaic`): the
    mean over the four analyzers and the colour channels; saturated samples are NaN (see module docstring
    for where each pixel sits on the raw grid)."""
    layout = mosaic_layout(sensor["polarizer_layout"], sensor["color_layout"])
    height, width = linear.shape
    plan = ingest.make_demosaic_plan(layout, height, width)
    images = ingest.demosaic(linear, plan)  # (4, Hc, Wc, C)
    return images.mean(axis=(0, 3)).astype(np.float32)


def half_to_raw(points: np.ndarray) -> np.ndarray:
    """Raw-pixel positions (..., 2) of intensity-image (half-resolution) positions (..., 2): 2 p + 0.5."""
    return 2.0 * np.asarray(points, np.float64) + 0.5


def raw_to_half(points: np.ndarray) -> np.ndarray:
    """Inverse of :func:`half_to_raw`: (p - 0.5) / 2."""
    return (np.asarray(points, np.float64) - 0.5) / 2.0


@dataclass
class BoardDetection:
    """One frame's board: ``corners`` (rows * cols, 2) raw pixels (None if not usable), ``edge_width_px``
    (OpenCV's sharpness, intensity-image pixels; NaN if not found) and ``problem`` (None, or what is wrong)."""

    corners: np.ndarray | None
    edge_width_px: float = float("nan")
    problem: str | None = None


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """Intensity image -> 8-bit, stretched between its 0.5th and 99.5th percentiles (NaN = saturated = white)."""
    finite = np.isfinite(image)
    lo, hi = np.percentile(image[finite], [0.5, 99.5]) if finite.any() else (0.0, 1.0)
    scaled = np.where(finite, (image - lo) / max(hi - lo, 1e-9), 1.0)
    return np.clip(np.rint(scaled * 255), 0, 255).astype(np.uint8)


def flat_mosaic(linear: np.ndarray, sensor: Mapping) -> np.ndarray:
    """The linear mosaic (H, W) (:func:`linear_mosaic`) at full resolution as one grey image (H, W) float32 for
    corner refinement: each position of the mosaic's period divided by its gain (the median ratio of its pixels to
    their period's mean, over the brightest 30 % of blocks: the analyzer's and colour filter's response to the
    board's paper), then smoothed by a Gaussian of :data:`CORNER_BLUR_PX`. Saturated samples (NaN) take the
    image's largest value."""
    from scipy import ndimage

    period = mosaic_layout(sensor["polarizer_layout"], sensor["color_layout"]).period
    linear = np.asarray(linear, np.float64)
    blocks = ndimage.uniform_filter(np.nan_to_num(linear), period, mode="nearest")
    bright = np.isfinite(linear) & (blocks > np.percentile(blocks, 70))
    flat = np.empty_like(linear)
    for i in range(period):
        for j in range(period):
            cell = (slice(i, None, period), slice(j, None, period))
            flat[cell] = linear[cell] / np.median(linear[cell][bright[cell]] / blocks[cell][bright[cell]])
    flat = np.nan_to_num(flat, nan=float(np.nanmax(flat)))
    return ndimage.gaussian_filter(flat, CORNER_BLUR_PX).astype(np.float32)


def detect_board(raw: np.ndarray, sensor: Mapping, cols: int, rows: int,
                 max_edge_px: float = MAX_EDGE_WIDTH_PX) -> BoardDetection:
    """Find the cols x rows inner corners of a raw frame (H, W): OpenCV's sector-based detector
    (findChessboardCornersSB, accuracy mode) on the intensity image (:func:`intensity_image`), then each corner
    refined on the full-resolution mosaic (:func:`refine_corners`); corners in raw pixels."""
    import cv2

    linear = linear_mosaic(raw, sensor)
    image = intensity_image(linear, sensor)
    gray = _to_uint8(image)
    if np.mean(np.isnan(image)) > 0.01:
        return BoardDetection(None, problem=f"{100 * np.mean(np.isnan(image)):.1f} % of the image is saturated; "
                                            "expected a board exposed below the white level (lower the flash)")
    with opencv_single_threaded():
        found, corners = cv2.findChessboardCornersSB(gray, (cols, rows),
                                                     flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not found:
        return BoardDetection(None, problem=f"board not found: all {cols}x{rows} inner corners must be visible "
                                            "(is the whole board in the frame, in focus, and --board right?)")
    corners = corners.reshape(-1, 2).astype(np.float64)
    with opencv_single_threaded():
        sharpness = cv2.estimateChessboardSharpness(gray, (cols, rows),
                                                    corners.reshape(-1, 1, 2).astype(np.float32))
    width = float(sharpness[0][0])
    if width > max_edge_px:
        return BoardDetection(None, width, f"board blurred: edges {width:.2f} px wide on the intensity image, "
                                           f"expected at most {max_edge_px} (focus, or hold still)")
    return BoardDetection(refine_corners(flat_mosaic(linear, sensor), half_to_raw(corners), cols, rows), width)


CORNER_BLUR_PX = 1.5
"""Standard deviation (raw pixels) of the Gaussian that smooths :func:`flat_mosaic` before corners are refined on
it: it removes what is left of the mosaic's pattern and the refinement's pull towards pixel centres (0.5-2
measured, docs/calibration.md "Corners on the full-resolution mosaic")."""

SUBPIX_WINDOW_FRACTION = 0.35
"""cv2.cornerSubPix's half window as a share of the board's square (raw pixels, 4 to 32 pixels)."""


def refine_corners(mosaic: np.ndarray, corners: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """The (cols * rows, 2) corners (raw pixels) refined by ``cv2.cornerSubPix`` on the full-resolution mosaic
    (:func:`flat_mosaic`, (H, W)), in a half window of :data:`SUBPIX_WINDOW_FRACTION` of the median square (4-32
    raw px). On the half-resolution intensity image the corners were pulled towards its pixel centres by up to
    0.06 raw px, which left the principal point's 1-sigma at 0.4-0.6 px with 96 board poses at 2448x2048; here
    the pull is below 0.01 px and the corners' scatter 2-3 times smaller (docs/calibration.md)."""
    import cv2

    grid = corners.reshape(rows, cols, 2)
    square = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    half_window = int(np.clip(round(SUBPIX_WINDOW_FRACTION * square), 4, 32))
    with opencv_single_threaded():
        refined = cv2.cornerSubPix(np.ascontiguousarray(mosaic, np.float32),
                                   corners.astype(np.float32).reshape(-1, 1, 2), (half_window, half_window),
                                   (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
    return refined.reshape(-1, 2).astype(np.float64)


@dataclass
class IntrinsicsResult:
    """fx, fy, cx, cy (raw pixels), distortion (k1, k2, p1, p2, k3); rms_px: the fit's RMS reprojection error
    (raw pixels); per_frame: {name: RMS px} of the frames used; left_out: {name: why};
    std: one-sigma uncertainties of fx, fy, cx, cy from OpenCV's covariance (raw pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: list[float]
    rms_px: float
    per_frame: dict[str, float]
    left_out: dict[str, str] = field(default_factory=dict)
    std: dict[str, float] = field(default_factory=dict)
    field_coverage: float = float("nan")

    def camera(self) -> dict:
        """The intrinsics part of capture.yaml's ``camera`` section."""
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "distortion": list(self.distortion)}


COVERAGE_GRID = 8
"""The field is cut into this many x this many cells to say how much of it the board's corners covered."""

RECOMMENDED_POSES = 96
"""Board poses of the recommended protocol (docs/calibration.md): the principal point's 1-sigma 0.15-0.22 px at
2448x2048."""


def intrinsics_uncertainty(result: IntrinsicsResult, c_std_target_px: float | None = None
                           ) -> tuple[dict[str, float], list[str]]:
    """What :mod:`sellip.calibrate.targets` gates the intrinsics on ({f_std_pct, c_std_px, reprojection_rms_px})
    and the causes of a large uncertainty the frames show (too few poses, the field's corners not covered). With
    ``c_std_target_px`` (the gate on the principal point's 1-sigma) the poses to add are those that bring the
    1-sigma, falling as 1/sqrt(poses), to it; without, those up to :data:`RECOMMENDED_POSES`."""
    std = result.std
    measured = {"f_std_pct": 100 * max(std.get("fx", np.nan) / result.fx, std.get("fy", np.nan) / result.fy),
                "c_std_px": max(std.get("cx", np.nan), std.get("cy", np.nan)),
                "reprojection_rms_px": result.rms_px}
    causes = []
    used = len(result.per_frame)
    needed = RECOMMENDED_POSES
    if c_std_target_px and measured["c_std_px"] > c_std_target_px:
        needed = max(needed, int(np.ceil(used * (measured["c_std_px"] / c_std_target_px) ** 2)))
    if used < needed:
        causes.append(f"{used} board poses used: the principal point's 1-sigma falls only as 1/sqrt(poses); take "
                      f"about {needed - used} more, each another pose, tilted 20-50 deg")
    if result.field_coverage < 0.8:
        causes.append(f"the board's corners covered {100 * result.field_coverage:.0f} % of the field "
                      f"({COVERAGE_GRID}x{COVERAGE_GRID} cells): put the board in the image corners too")
    if result.left_out:
        causes.append(f"{len(result.left_out)} frame(s) left out (named above)")
    return measured, causes


def _too_few(usable: int, needed: int, left_out: Mapping[str, str]) -> CalibrationError:
    lines = "".join(f"\n  {name}: {why}" for name, why in left_out.items())
    return CalibrationError(f"{usable} usable board frame(s), at least {needed} needed: take {needed - usable} more "
                            f"(the board tilted 15-40 deg, over the whole field).{lines}")


def calibrate_intrinsics(frames: Mapping[str, np.ndarray], sensor: Mapping, cols: int, rows: int, square_m: float,
                         fix_k3: bool = True, min_frames: int = MIN_BOARD_FRAMES,
                         max_edge_px: float = MAX_EDGE_WIDTH_PX, max_frame_rms_px: float = MAX_FRAME_RMS_PX,
                         log=None) -> IntrinsicsResult:
    """Zhang's calibration (cv2.calibrateCameraExtended) from raw board frames {name: (H, W) raw}.

    A frame whose board is not found, blurred or saturated is left out and named in ``left_out``; so is a frame
    that reprojects worse than ``max_frame_rms_px`` (then the fit is redone without it). Raises
    CalibrationError when fewer than ``min_frames`` frames remain, saying how many more are needed.
    ``fix_k3``: keep k3 = 0 (a narrow lens cannot separate it from k1, k2). Bit-identical for the same frames
    (OpenCV on one thread, module docstring).
    """
    import cv2

    height, width = int(sensor["height"]), int(sensor["width"])
    objp = np.zeros((rows * cols, 3), np.float32)
    objp[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    corners, left_out = {}, {}
    for name, raw in frames.items():
        if raw.shape != (height, width):
            left_out[name] = f"size {raw.shape[1]}x{raw.shape[0]}, expected the sensor's {width}x{height}"
            continue
        found = detect_board(raw, sensor, cols, rows, max_edge_px)
        if found.problem:
            left_out[name] = found.problem
        else:
            corners[name] = found.corners
        if log:
            log(f"{name}: {found.problem or f'{rows * cols} corners, edge width {found.edge_width_px:.2f} px'}")
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    while True:
        if len(corners) < min_frames:
            raise _too_few(len(corners), min_frames, left_out)
        names = list(corners)
        with opencv_single_threaded():
            rms, k, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(
                [objp] * len(names), [corners[n].astype(np.float32).reshape(-1, 1, 2) for n in names],
                (width, height), None, None, flags=flags, criteria=criteria)
        per_view = per_view.ravel()
        worst = int(np.argmax(per_view))
        if per_view[worst] <= max_frame_rms_px:
            break
        left_out[names[worst]] = (f"corners reproject at {per_view[worst]:.2f} px RMS, expected at most "
                                  f"{max_frame_rms_px} (board bent or moved during the exposure?)")
        del corners[names[worst]]
    dist = dist.ravel().tolist() + [0.0] * (5 - dist.size)
    std = std.ravel()
    cells = np.zeros((COVERAGE_GRID, COVERAGE_GRID), bool)
    for n in names:
        ij = np.floor(corners[n] / [width, height] * COVERAGE_GRID).astype(int).clip(0, COVERAGE_GRID - 1)
        cells[ij[:, 1], ij[:, 0]] = True
    return IntrinsicsResult(field_coverage=float(cells.mean()), fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]),
                            cy=float(k[1, 2]), distortion=[float(c) for c in dist[:5]], rms_px=float(rms),
                            per_frame={n: float(e) for n, e in zip(names, per_view)}, left_out=left_out,
                            std={"fx": float(std[0]), "fy": float(std[1]), "cx": float(std[2]), "cy": float(std[3])})
