"""The colour matrix (camera RGB -> linear sRGB) from a ColorChecker photographed under the flash.

Public API::

    reference_srgb() -> (24, 3)                       # linear sRGB (D65) of the ColorChecker 24 (colour-science)
    PATCH_NAMES                                       # the 24 names, row by row
    analyzer_images(raw, sensor) -> (4, H/2, W/2, 3)  # demosaiced analyzers, NaN where saturated
    detect_chart(camera_rgb (H/2, W/2, 3)) -> corners_px (4, 2)   # cv2.mcc; the order is checked by the fit
    patch_stats(analyzers, corners_px) -> PatchStats  # per patch: RGB, its polarized part, spread, clipped, cells
    chart_falloff(corners_px, device, pitch_m) -> (24,)   # the flash's relative irradiance from the chart's pose
    fit_color_matrix(camera (N, 3), reference (N, 3)) -> M (3, 3)
    delta_e_2000(srgb_a, srgb_b) -> (N,)              # CIEDE2000 between linear sRGB colours (colour-science)
    calibrate_color(raw, device, corners_px=None) -> ColorResult   # None: the chart is found
    corner_orders(corners_px) -> [(words, (4, 2))]    # the 7 other orders of four corners around the chart
    corner_order_causes(raw, device, corners_px, max_delta_e) -> [str]   # why ΔE is high: the order that fits, sheen

The chart: the four corners of its patch area in raw pixels, dark skin's outer corner first, then clockwise
(along the top row to bluish green, down to black, back to white); given, or found by OpenCV's Macbeth chart
detector, the order that fits the colours best kept. Each patch is sampled in its central 40 % (a homography
from the corners places it; lens distortion moves a patch centre by far less than that margin). Camera RGB is
the demosaiced mean of the four analyzers (s0 / 2 per colour), without any colour matrix; where a patch's light
is more than :data:`SHEEN_MIN` linearly polarized, that part (the polarized flash's mirror reflection, the
sheen) is taken out. Each patch is divided by the flash's relative irradiance there (cos(incidence) /
distance^2, the chart's pose from its corners, the flash at ``light.position_m``). The matrix M minimizes
sum |M c_i - k r_i|^2 over patches i with the flash's unknown level k (the chart's white reads what it reads);
it is then scaled so that the neutral patches keep their green level (albedos are relative anyway,
docs/design.md §4). Patches darker than 2 % of full scale in green, with a clipped sample, or sampled by fewer
than :data:`MIN_PATCH_CELLS` cells are left out and named (a chart in shadow: all of them).
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

PATCH_PITCH_M = 0.04
"""Centre-to-centre distance of the chart's patches (metres); it only sets the chart's distance for the flash's
fall-off, which a few millimetres change by far less than the noise."""


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


def patch_stats(analyzers: np.ndarray, corners_px: np.ndarray, fraction: float = 0.4) -> PatchStats:
    """Each patch's central ``fraction`` on the cell grid (raw pixel p sits at cell (p - 0.5) / 2) of the analyzer
    images ``analyzers`` (4, H/2, W/2, 3) (:func:`analyzer_images`): :class:`PatchStats`."""
    homography, _ = patch_centres(corners_px)
    offsets = (np.linspace(-0.5, 0.5, 9) * fraction)
    du, dv = np.meshgrid(offsets, offsets)
    rgb, polarized = np.zeros((24, 3)), np.zeros((24, 3))
    spread, clipped, cells = np.zeros(24), np.zeros(24, bool), np.zeros(24, int)
    height, width = analyzers.shape[1:3]
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
        values = analyzers[:, y0:y1, x0:x1].reshape(4, -1, 3)
        finite = np.all(np.isfinite(values), axis=(0, 2))
        clipped[k] = not finite.all()
        cells[k] = int(finite.sum())
        if not cells[k]:
            rgb[k] = polarized[k] = spread[k] = np.nan
            continue
        mean = values[:, finite].mean(axis=1)  # (4, 3): analyzers 0, 45, 90, 135 degrees
        rgb[k] = mean.mean(axis=0)  # s0 / 2
        polarized[k] = np.hypot(mean[0] - mean[2], mean[1] - mean[3]) / 2  # |s1, s2| / 2
        green = values[:, finite, 1].mean(axis=0)
        spread[k] = float(np.std(green) / max(abs(rgb[k, 1]), 1e-9))
    return PatchStats(rgb, polarized, spread, clipped, cells)


@dataclass
class PatchStats:
    """Per patch (24 rows): ``rgb`` (24, 3) mean camera RGB (s0 / 2), ``polarized`` (24, 3) its linearly polarized
    part (|s1, s2| / 2, of the patch means), ``spread`` (24,) the green's relative spread over the cells,
    ``clipped`` (24,) a saturated sample, ``cells`` (24,) cells sampled."""

    rgb: np.ndarray
    polarized: np.ndarray
    spread: np.ndarray
    clipped: np.ndarray
    cells: np.ndarray

    @property
    def unpolarized(self) -> np.ndarray:
        """(24, 3) the patches' light without the flash's sheen (module docstring): the unpolarized part where the
        polarized part exceeds :data:`SHEEN_MIN` of it (in green), the whole light elsewhere (a patch's diffuse
        light is polarized by well under that, and removing noise's polarization would bias it)."""
        sheen = self.polarized[:, 1] > SHEEN_MIN * self.rgb[:, 1]
        return np.where(sheen[:, None], self.rgb - self.polarized, self.rgb)


def fit_color_matrix(camera: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """M (3, 3) with M camera_i ~ reference_i in least squares (camera, reference (N, 3)); the flash level is
    absorbed in M."""
    solution, *_ = np.linalg.lstsq(camera, reference, rcond=None)
    return solution.T


@dataclass
class ColorResult:
    """matrix (3, 3) camera RGB -> linear sRGB (scaled to keep the neutrals' green); delta_e (24,) CIEDE2000 per
    patch (NaN for patches left out) of the fitted (unscaled) matrix against the reference; left_out {patch: why};
    corners_px (4, 2) the patch area's corners used (given or found, documented order); falloff (24,) the
    flash's relative irradiance divided out; sheen (24,) each patch's polarized fraction taken out (green)."""

    matrix: np.ndarray
    delta_e: np.ndarray
    patch_names: tuple[str, ...] = PATCH_NAMES
    left_out: dict = field(default_factory=dict)
    corners_px: np.ndarray | None = None
    falloff: np.ndarray | None = None
    sheen: np.ndarray | None = None

    def record(self) -> dict:
        used = np.isfinite(self.delta_e)
        out = {"delta_e2000_mean": float(np.nanmean(self.delta_e)), "delta_e2000_max": float(np.nanmax(self.delta_e)),
               "delta_e2000": {n: (float(e) if np.isfinite(e) else None)
                               for n, e in zip(self.patch_names, self.delta_e)},
               "patches_used": int(used.sum()), "left_out": self.left_out}
        if self.corners_px is not None:
            out["corners_px"] = np.round(np.asarray(self.corners_px, np.float64), 2).tolist()
        if self.falloff is not None:
            out["falloff_range"] = [float(np.min(self.falloff)), float(np.max(self.falloff))]
        if self.sheen is not None:
            out["sheen_max"] = float(np.nanmax(self.sheen))
        return out


def analyzer_images(raw: np.ndarray, sensor: Mapping) -> np.ndarray:
    """Demosaiced analyzer images (4, H/2, W/2, 3) (0, 45, 90, 135 degrees), linear (1 = full scale), NaN where
    saturated; no colour matrix."""
    layout = mosaic_layout(sensor["polarizer_layout"], sensor["color_layout"])
    if layout.channels != 3:
        raise CalibrationError("a mono sensor (color_layout: mono) has no colour matrix to calibrate")
    height, width = raw.shape
    black = ingest.black_level_map(sensor["black_level"], height, width)
    linear, invalid = ingest.linearize(raw, black, float(sensor["white_level"]))
    linear[invalid] = np.nan
    return ingest.demosaic(linear, ingest.make_demosaic_plan(layout, height, width))


def camera_rgb_image(raw: np.ndarray, sensor: Mapping) -> np.ndarray:
    """Demosaiced camera RGB (H/2, W/2, 3) (mean of the four analyzers), NaN where saturated; no colour matrix."""
    return analyzer_images(raw, sensor).mean(axis=0)


def detect_chart(camera_rgb: np.ndarray) -> np.ndarray:
    """The patch area's corners (4, 2) in raw pixels of a ColorChecker 24 found in the cell-grid camera RGB image
    (H/2, W/2, 3) (:func:`camera_rgb_image`) by OpenCV's Macbeth chart detector (``cv2.mcc``, on a gamma-encoded
    8-bit copy), in the order it gives; :func:`calibrate_color` checks that order against the colours. The 24
    sampling squares it returns place a least-squares homography from chart units, so the corners do not hang
    on its outline. Raises CalibrationError naming what the frame shows (too dark, saturated, a small chart)."""
    import cv2

    image = np.nan_to_num(np.asarray(camera_rgb, np.float64), nan=1.0)
    level = float(np.percentile(image, 99.5))
    encoded = np.clip(image / max(level, 1e-6), 0, 1) ** (1 / 2.2)
    bgr = np.ascontiguousarray((encoded[..., ::-1] * 255).round().astype(np.uint8))
    # the detector places its squares best on an image about 600 px wide (measured: a 1224 px cell grid put
    # them 10 cells off, its half 3)
    factor = max(1, int(round(bgr.shape[1] / DETECT_WIDTH_PX)))
    if factor > 1:
        bgr = cv2.resize(bgr, (bgr.shape[1] // factor, bgr.shape[0] // factor), interpolation=cv2.INTER_AREA)
    detector = cv2.mcc.CCheckerDetector_create()
    detector.setColorChartType(cv2.mcc.MCC24)
    found = detector.process(bgr)
    checkers = detector.getListColorChecker() if found else []
    if not checkers:
        raise CalibrationError("no ColorChecker 24 found in the frame" + _frame_causes(camera_rgb)
                               + "; or give its corners with --corners")
    squares = np.asarray(detector.getBestColorChecker().getColorCharts(), np.float64).reshape(24, 4, 2)
    centres = ((squares.mean(axis=1) + 0.5) * factor - 0.5) * 2 + 0.5  # detector's image -> cell -> raw pixels
    i, j = np.divmod(np.arange(24), 6)
    chart = np.stack([j + 0.5, i + 0.5], axis=-1)
    homography, _ = cv2.findHomography(chart, centres, 0)
    outline = np.array([[0, 0, 1], [6, 0, 1], [6, 4, 1], [0, 4, 1]], np.float64) @ homography.T
    return outline[:, :2] / outline[:, 2:]


SHEEN_MIN = 0.03
"""A patch whose light is more than this fraction linearly polarized (green) has the flash's sheen taken out."""

SHEEN_FRACTION = 0.2
"""A patch whose light is more than this fraction linearly polarized shows the flash's sheen (named as a cause)."""

DETECT_WIDTH_PX = 612
"""The chart is found on the cell-grid image binned to about this width."""

MIN_PATCH_CELLS = 16
"""Cells (2x2 raw pixels) a patch's sampled centre needs: fewer, the chart is too small in the frame."""


def _frame_causes(camera_rgb: np.ndarray) -> str:
    """What a frame shows that hides a chart: saturation, too little light (as a sentence tail, or empty)."""
    image = np.asarray(camera_rgb)
    clipped = float(np.mean(~np.isfinite(image).all(axis=-1)))
    level = float(np.nanpercentile(image[..., 1], 99)) if np.isfinite(image).any() else 0.0
    causes = []
    if clipped > 0.01:
        causes.append(f"{clipped:.0%} of the frame is saturated: lower the flash or the exposure")
    if level < 5 * MIN_PATCH_LEVEL:
        causes.append(f"the frame is too dark (its brightest 1 % reads {level:.3f} of full scale in green, expected "
                      f"at least {5 * MIN_PATCH_LEVEL:g}): raise the flash or bring the chart into its light")
    causes.append("a chart too small in the frame is not found either: fill a good part of the frame with it")
    return ": " + "; ".join(causes)


def chart_falloff(corners_px: np.ndarray, device: Mapping, pitch_m: float = PATCH_PITCH_M) -> np.ndarray:
    """(24,) the flash's irradiance at each patch centre, cos(incidence) / distance^2, relative to its mean: the
    chart's pose from its corners (``cv2.solvePnP`` with the device's intrinsics and distortion; the patch pitch
    ``pitch_m`` fixes its scale), the flash at ``light.position_m`` (camera coordinates), or at the lens when the
    device has none yet."""
    import cv2

    cam = device["camera"]
    matrix = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], np.float64)
    chart = np.array([[0, 0, 0], [6, 0, 0], [6, 4, 0], [0, 4, 0]], np.float64) * pitch_m
    ok, rvec, tvec = cv2.solvePnP(chart, np.asarray(corners_px, np.float64), matrix,
                                  np.asarray(cam.get("distortion", [0.0] * 5), np.float64),
                                  flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("the chart's pose cannot be found from its corners: check --corners")
    rotation = cv2.Rodrigues(rvec)[0]
    i, j = np.divmod(np.arange(24), 6)
    centres = np.stack([(j + 0.5) * pitch_m, (i + 0.5) * pitch_m, np.zeros(24)], -1) @ rotation.T + tvec.ravel()
    light = np.asarray(device.get("light", {}).get("position_m", [0.0, 0.0, 0.0]), np.float64)
    to_light = light - centres
    distance = np.linalg.norm(to_light, axis=-1)
    cos_i = np.abs(to_light @ rotation[:, 2]) / distance
    irradiance = cos_i / distance ** 2
    return irradiance / irradiance.mean()


def calibrate_color(raw: np.ndarray, device: Mapping, corners_px: np.ndarray | None = None,
                    min_patches: int = MIN_PATCHES, pitch_m: float = PATCH_PITCH_M) -> ColorResult:
    """The colour matrix from one raw frame of a ColorChecker (module docstring). ``corners_px`` (4, 2): the patch
    area's corners, dark skin's outer corner first, then clockwise; None: the chart is found
    (:func:`detect_chart`) and the order that fits the colours best is taken. Raises CalibrationError naming the
    patches when fewer than ``min_patches`` are usable, or why no chart is found."""
    analyzers = analyzer_images(raw, device["sensor"])
    if corners_px is None:
        found = detect_chart(analyzers.mean(axis=0))
        fits = []
        for _words, order in [("as found", found), *corner_orders(found)]:
            try:
                fits.append((float(np.nanmean(_fit(analyzers, device, order, min_patches, pitch_m).delta_e)), order))
            except CalibrationError:
                continue
        if not fits:
            return _fit(analyzers, device, found, min_patches, pitch_m)  # raises, naming the patches
        corners_px = min(fits, key=lambda f: f[0])[1]
    return _fit(analyzers, device, np.asarray(corners_px, np.float64), min_patches, pitch_m)


def _fit(analyzers: np.ndarray, device: Mapping, corners_px: np.ndarray, min_patches: int,
         pitch_m: float) -> ColorResult:
    stats = patch_stats(analyzers, corners_px)
    falloff = chart_falloff(corners_px, device, pitch_m)
    camera = stats.unpolarized / falloff[:, None]
    reference = reference_srgb()
    left_out = {}
    for k in range(24):
        if stats.clipped[k]:
            left_out[PATCH_NAMES[k]] = "clipped (saturated samples): lower the flash"
        elif stats.cells[k] < MIN_PATCH_CELLS:
            left_out[PATCH_NAMES[k]] = (f"too small: {stats.cells[k]} cells sampled, expected at least "
                                        f"{MIN_PATCH_CELLS} (fill more of the frame with the chart)")
        elif not stats.rgb[k, 1] >= MIN_PATCH_LEVEL:
            left_out[PATCH_NAMES[k]] = (f"too dark: green {stats.rgb[k, 1]:.4f} of full scale, expected at least "
                                        f"{MIN_PATCH_LEVEL} (chart in shadow, or the flash too weak)")
    used = np.array([PATCH_NAMES[k] not in left_out for k in range(24)])
    if used.sum() < min_patches:
        lines = "".join(f"\n  {k}: {v}" for k, v in left_out.items())
        raise CalibrationError(f"{int(used.sum())} usable ColorChecker patches, at least {min_patches} needed "
                               f"({min_patches - int(used.sum())} more): light the whole chart with the flash, "
                               f"below the white level, filling a good part of the frame.{lines}")
    fitted = fit_color_matrix(camera[used], reference[used])
    delta_e = np.full(24, np.nan)
    delta_e[used] = delta_e_2000(camera[used] @ fitted.T, reference[used])
    neutral = used[NEUTRALS]
    if neutral.any():
        grey = camera[NEUTRALS][neutral]
        scale = float(np.sum(grey[:, 1]) / np.sum((grey @ fitted.T)[:, 1]))
    else:
        scale = float(np.mean(camera[used, 1]) / np.mean((camera[used] @ fitted.T)[:, 1]))
    sheen = np.where(used, stats.polarized[:, 1] / np.maximum(stats.rgb[:, 1], 1e-9), np.nan)
    return ColorResult(matrix=fitted * scale, delta_e=delta_e, left_out=left_out, corners_px=np.asarray(corners_px),
                       falloff=falloff, sheen=sheen)


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
    patches whose light is strongly polarized (the flash's sheen), patches whose samples spread (uneven light)."""
    causes = []
    analyzers = analyzer_images(raw, device["sensor"])
    best = None
    for words, order in corner_orders(corners_px):
        try:
            result = _fit(analyzers, device, order, MIN_PATCHES, PATCH_PITCH_M)
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
    stats = patch_stats(analyzers, np.asarray(corners_px))
    glossy = [PATCH_NAMES[k] for k in range(24)
              if not stats.clipped[k] and stats.polarized[k, 1] > SHEEN_FRACTION * stats.rgb[k, 1]]
    if glossy and not causes:
        causes.append(f"{len(glossy)} patch(es) reflect the flash's polarized sheen ({', '.join(glossy[:4])}"
                      f"{' ...' if len(glossy) > 4 else ''}): tilt the chart 15-30° away from the camera so that "
                      "the flash's mirror reflection misses it")
    uneven = [PATCH_NAMES[k] for k in range(24) if stats.spread[k] > 0.05 and not stats.clipped[k]]
    if uneven and not causes:
        causes.append(f"{len(uneven)} patch(es) vary by more than 5 % across their centre ({', '.join(uneven[:4])}"
                      f"{' ...' if len(uneven) > 4 else ''}): sheen or uneven light; tilt the chart away from the "
                      "flash's mirror direction")
    return causes
