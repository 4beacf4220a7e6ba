"""The colour matrix (camera RGB -> linear sRGB) from a ColorChecker photographed under the flash.

Public API::

    reference_srgb() -> (24, 3)                       # linear sRGB (D65) of the ColorChecker 24 (colour-science)
    PATCH_NAMES                                       # the 24 names, row by row
    patch_means(camera_rgb, corners_px) -> (means (24, 3), spread (24,))   # camera RGB per patch
    fit_color_matrix(camera (24, 3), reference (24, 3)) -> (M (3, 3), scale)
    delta_e_2000(srgb_a, srgb_b) -> (N,)              # CIEDE2000 between linear sRGB colours (colour-science)
    calibrate_color(raw, device, corners_px) -> ColorResult
    corner_orders(corners_px) -> [(words, (4, 2))]    # the 7 other orders of four corners around the chart
    corner_order_causes(raw, device, corners_px, max_delta_e) -> [str]   # why ΔE is high: the order that fits, sheen

The chart: the four corners of its patch area in raw pixels, dark skin's outer corner first, then clockwise
(along the top row to bluish green, down to black, back to white). Each patch is sampled in its central
40 % (a homography from the corners places it; lens distortion moves a patch centre by far less than that
margin). Camera RGB is the demosaiced mean of the four analyzers (s0 / 2 per colour), without any colour
matrix. The matrix M minimizes sum |M c_i - k r_i|^2 over patches i with the flash's unknown level k (the
chart's white reads what it reads); it is then scaled so that the neutral patches keep their green level
(albedos are relative anyway, docs/design.md §4). Patches darker than 2 % of full scale in green, or with a clipped
sample, are left out and named (a chart in shadow: all of them).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from sellip.calibrate.intrinsics import CalibrationError
from sellip.capture import ingest
from sellip.capture.mosaic import mosaic_layout

MIN_PATCH_LEVEL = 0.02
"""A patch's green below this (linear, 1 = full scale): too dark for a colour (a chart in shadow)."""

MIN_PATCHES = 12
"""Patches needed for a 3x3 matrix and a trustworthy residual."""

NEUTRALS = slice(18, 24)


def _checker():
    import colour

    return colour.CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"]


PATCH_NAMES: tuple[str, ...] = ("dark skin", "light skin", "blue sky", "foliage", "blue flower", "bluish green",
                                "orange", "purplish blue", "moderate red", "purple", "yellow green", "orange yellow",
                                "blue", "green", "red", "yellow", "magenta", "cyan",
                                "white 9.5 (.05 D)", "neutral 8 (.23 D)", "neutral 6.5 (.44 D)", "neutral 5 (.70 D)",
                                "neutral 3.5 (1.05 D)", "black 2 (1.5 D)")


def reference_srgb() -> np.ndarray:
    """(24, 3) linear sRGB (D65) of the ColorChecker 24 ('After November 2014', colour-science, Bradford from D50)."""
    import colour

    checker = _checker()
    xyz = colour.xyY_to_XYZ(np.array(list(checker.data.values())))
    return colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], illuminant=checker.illuminant,
                             chromatic_adaptation_transform="Bradford", apply_cctf_encoding=False)


def delta_e_2000(srgb_a: np.ndarray, srgb_b: np.ndarray) -> np.ndarray:
    """CIEDE2000 (N,) between linear sRGB colours (N, 3) (D65, Y of white = 1), with colour-science."""
    import colour

    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]

    def lab(rgb):
        xyz = colour.RGB_to_XYZ(np.asarray(rgb, np.float64), colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
        return colour.XYZ_to_Lab(xyz, d65)

    return np.asarray(colour.delta_E(lab(srgb_a), lab(srgb_b), method="CIE 2000"))


def patch_centres(corners_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homography (3, 3) from chart units (patch pitch 1; 6 x 4) to raw pixels, and the 24 patch centres (24, 2)."""
    import cv2

    chart = np.array([[0, 0], [6, 0], [6, 4], [0, 4]], np.float64)
    homography = cv2.getPerspectiveTransform(chart.astype(np.float32), np.asarray(corners_px, np.float32))
    i, j = np.divmod(np.arange(24), 6)
    centres = np.stack([j + 0.5, i + 0.5, np.ones(24)], axis=-1) @ homography.T
    return homography, centres[:, :2] / centres[:, 2:]


def patch_means(camera_rgb: np.ndarray, corners_px: np.ndarray, fraction: float = 0.4
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean camera RGB (24, 3) of each patch's central ``fraction`` on the cell-grid image (H/2, W/2, 3) (raw
    pixel p sits at cell (p - 0.5) / 2), its relative spread (24,), and whether a sample was clipped (24,)."""
    homography, _ = patch_centres(corners_px)
    offsets = (np.linspace(-0.5, 0.5, 9) * fraction)
    du, dv = np.meshgrid(offsets, offsets)
    means, spread, clipped = np.zeros((24, 3)), np.zeros(24), np.zeros(24, bool)
    height, width = camera_rgb.shape[:2]
    for k in range(24):
        i, j = divmod(k, 6)
        pts = np.stack([j + 0.5 + du.ravel(), i + 0.5 + dv.ravel(), np.ones(du.size)], axis=-1) @ homography.T
        raw_xy = pts[:, :2] / pts[:, 2:]
        cell = np.rint((raw_xy - 0.5) / 2).astype(int)
        if (cell < 0).any() or (cell[:, 0] >= width).any() or (cell[:, 1] >= height).any():
            raise CalibrationError(f"patch {k + 1} ({PATCH_NAMES[k]}) lies outside the frame: check --corners")
        # every cell of the patch's central area (the grid above spans it; take its bounding box)
        x0, y0 = cell.min(axis=0)
        x1, y1 = cell.max(axis=0) + 1
        values = camera_rgb[y0:y1, x0:x1].reshape(-1, 3)
        clipped[k] = bool(np.isnan(values).any())
        values = values[np.all(np.isfinite(values), axis=-1)]
        means[k] = values.mean(axis=0) if len(values) else np.nan
        spread[k] = float(np.std(values[:, 1]) / max(abs(means[k, 1]), 1e-9)) if len(values) else np.nan
    return means, spread, clipped


def fit_color_matrix(camera: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """M (3, 3) with M camera_i ~ reference_i in least squares (camera, reference (N, 3)); the flash level is
    absorbed in M."""
    solution, *_ = np.linalg.lstsq(camera, reference, rcond=None)
    return solution.T


@dataclass
class ColorResult:
    """matrix (3, 3) camera RGB -> linear sRGB (scaled to keep the neutrals' green); delta_e (24,) CIEDE2000 per
    patch (NaN for patches left out) of the fitted (unscaled) matrix against the reference; left_out {patch: why}."""

    matrix: np.ndarray
    delta_e: np.ndarray
    patch_names: tuple[str, ...] = PATCH_NAMES
    left_out: dict = field(default_factory=dict)

    def record(self) -> dict:
        used = np.isfinite(self.delta_e)
        return {"delta_e2000_mean": float(np.nanmean(self.delta_e)), "delta_e2000_max": float(np.nanmax(self.delta_e)),
                "delta_e2000": {n: (float(e) if np.isfinite(e) else None)
                                for n, e in zip(self.patch_names, self.delta_e)},
                "patches_used": int(used.sum()), "left_out": self.left_out}


def camera_rgb_image(raw: np.ndarray, sensor: Mapping) -> np.ndarray:
    """Demosaiced camera RGB (H/2, W/2, 3) (mean of the four analyzers), NaN where saturated; no colour matrix."""
    layout = mosaic_layout(sensor["polarizer_layout"], sensor["color_layout"])
    if layout.channels != 3:
        raise CalibrationError("a mono sensor (color_layout: mono) has no colour matrix to calibrate")
    height, width = raw.shape
    black = ingest.black_level_map(sensor["black_level"], height, width)
    linear, invalid = ingest.linearize(raw, black, float(sensor["white_level"]))
    linear[invalid] = np.nan
    return ingest.demosaic(linear, ingest.make_demosaic_plan(layout, height, width)).mean(axis=0)


def calibrate_color(raw: np.ndarray, device: Mapping, corners_px: np.ndarray,
                    min_patches: int = MIN_PATCHES) -> ColorResult:
    """The colour matrix from one raw frame of a ColorChecker with its patch area's ``corners_px`` (4, 2) (module
    docstring). Raises CalibrationError naming the patches when fewer than ``min_patches`` are usable."""
    camera, _spread, clipped = patch_means(camera_rgb_image(raw, device["sensor"]), np.asarray(corners_px))
    reference = reference_srgb()
    left_out = {}
    for k in range(24):
        if clipped[k]:
            left_out[PATCH_NAMES[k]] = "clipped (saturated samples): lower the flash"
        elif not camera[k, 1] >= MIN_PATCH_LEVEL:
            left_out[PATCH_NAMES[k]] = (f"too dark: green {camera[k, 1]:.4f} of full scale, expected at least "
                                        f"{MIN_PATCH_LEVEL} (chart in shadow, or the flash too weak)")
    used = np.array([PATCH_NAMES[k] not in left_out for k in range(24)])
    if used.sum() < min_patches:
        lines = "".join(f"\n  {k}: {v}" for k, v in left_out.items())
        raise CalibrationError(f"{int(used.sum())} usable ColorChecker patches, at least {min_patches} needed "
                               f"({min_patches - int(used.sum())} more): light the whole chart with the flash, "
                               f"below the white level.{lines}")
    fitted = fit_color_matrix(camera[used], reference[used])
    delta_e = np.full(24, np.nan)
    delta_e[used] = delta_e_2000(camera[used] @ fitted.T, reference[used])
    neutral = used[NEUTRALS]
    if neutral.any():
        grey = camera[NEUTRALS][neutral]
        scale = float(np.sum(grey[:, 1]) / np.sum((grey @ fitted.T)[:, 1]))
    else:
        scale = float(np.mean(camera[used, 1]) / np.mean((camera[used] @ fitted.T)[:, 1]))
    return ColorResult(matrix=fitted * scale, delta_e=delta_e, left_out=left_out)


def corner_orders(corners_px: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The 8 ways four corners (4, 2) can be listed around a quadrilateral: (how it differs from the given order,
    the corners in the documented order if that is how they were really given)."""
    corners = np.asarray(corners_px, np.float64)
    out = []
    for reverse in (False, True):
        ring = corners[::-1] if reverse else corners
        for shift in range(4):
            if not reverse and shift == 0:
                continue
            start = int(np.flatnonzero(np.all(corners == ring[shift], axis=1))[0]) + 1
            words = f"{'counter-clockwise' if reverse else 'clockwise'}, dark skin's corner given as number {start}"
            out.append((words, np.roll(ring, -shift, axis=0)))
    return out


def corner_order_causes(raw: np.ndarray, device: Mapping, corners_px: np.ndarray, max_delta_e: float) -> list[str]:
    """Why a chart's ΔE2000 is far above its target, as far as the frame shows it: the corners given in another
    order (all 8 orders around the patch area are tried; the one that fits is named with the --corners to give),
    patches left out, patches whose samples spread (uneven light, sheen)."""
    causes = []
    image = camera_rgb_image(raw, device["sensor"])
    best = None
    for words, order in corner_orders(corners_px):
        try:
            result = calibrate_color(raw, device, order)
        except CalibrationError:
            continue
        mean = float(np.nanmean(result.delta_e))
        if best is None or mean < best[0]:
            best = (mean, words, order)
    if best is not None and best[0] <= max_delta_e:
        given = " ".join(f"{x:.1f},{y:.1f}" for x, y in best[2])
        causes.append(f"the corners were given in another order ({best[1]}): in that order the chart fits with "
                      f"ΔE2000 mean {best[0]:.2f}; give --corners {given} (dark skin's outer corner first, then "
                      "clockwise)")
    _, spread, clipped = patch_means(image, np.asarray(corners_px))
    uneven = [PATCH_NAMES[k] for k in range(24) if spread[k] > 0.05 and not clipped[k]]
    if uneven and not causes:
        causes.append(f"{len(uneven)} patch(es) vary by more than 5 % across their centre ({', '.join(uneven[:4])}"
                      f"{' ...' if len(uneven) > 4 else ''}): sheen or uneven light; tilt the chart away from the "
                      "flash's mirror direction")
    return causes
