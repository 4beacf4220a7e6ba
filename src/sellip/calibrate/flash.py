"""The flash position from mirror highlights on spheres of known radius (Lensch et al. 2003; paper §6).

Public API::

    develop_frame(raw, device) -> (analyzers (H', W', 4, C), intrinsics)   # the ingest chain, undistorted
    find_spheres(s0, intrinsics, radius_m) -> list[Sphere]                  # outlines -> centres, or problems
    find_spheres_or_why(s0, intrinsics, radius_m) -> (list[Sphere], why | None)   # no bright background: why
    rim_silhouette(s0, intrinsics, axis, alpha, background, eta) -> (axis, alpha)  # the rim's mirrored background
    find_highlight(s0, sphere) -> (centre (x, y) | None, problem | None)    # refine_highlight: a Gaussian fit
    mirror_ray(sphere, highlight_px, intrinsics) -> (point (3,), direction (3,))
    highlight_rays(s0, sphere, centres, radius_m, intrinsics, label, left_out, miss) -> (highlight, lines) | None
    calibrate_flash(frames: {name: raw}, device, radius_m) -> FlashResult   # the outline protocol
    MIN_HIGHLIGHTS

Two protocols (docs/calibration.md, "Flash position"). **Board** (recommended, :mod:`sellip.calibrate.board_spheres`):
pairs of frames from one camera position, the board alone (NAME_board) and glossy spheres set down on its squares'
centres (NAME); the board's pose fixes each centre, and the 1-sigma adds the flash's spread over draws of the poses
and intrinsics.
**Outline**: spheres before a bright background, centres from their outlines (steps 1-2 below); the 1-sigma adds
how far the flash moves between the half-level outline's centres and the rim model's (a glossy sphere mirrors
the background at its rim, so neither is exact).

Geometry (camera coordinates, metres; the images are the ingest chain's undistorted half-resolution grid,
:func:`sellip.ingest.output_intrinsics`, so a pixel's ray is K'^-1 (x, y, 1)):

1. A sphere is photographed in front of a bright background (a light panel or a lit wall): its outline is
   where the intensity s0 crosses half the background's. The outline is sampled along 360 rays from the
   blob's centroid with sub-pixel interpolation.
2. The rays r_i through the outline are tangent to the sphere: they make one angle alpha with the axis a
   through the sphere's centre, r_i . a = cos(alpha). Linear least squares on a / cos(alpha) (twice, the
   second time without outliers beyond 3 MADs) gives a and alpha; the centre is a R / sin(alpha).
3. The highlight is the flash's mirror image: its intensity-weighted centroid (s0 above the sphere's own
   median, pixels above half the peak), refined by fitting a round Gaussian around it
   (:func:`refine_highlight`), gives a ray d; it meets the sphere at P with normal n; the flash lies
   on P + t (d - 2 (d . n) n), t > 0.
4. The flash is the point nearest all those lines: iteratively reweighted least squares with Huber weights
   (scale 1 mm), so one bad highlight cannot pull it far; the residual of each highlight is its line's distance.
   Before that, a highlight whose line passes more than 5 times the others' residual sigma from the flash fitted
   to the others (leave-one-out) is dropped, named and logged, and the rest refitted
   (:func:`sellip.calibrate.flash_fit.drop_outliers`): Huber weights only damp a line hundreds of mm off.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from sellip.calibrate.flash_fit import OUTLIER_SIGMA, drop_outlier_highlights, nearest_point, solve_flash
from sellip.calibrate.intrinsics import CalibrationError
from sellip.capture import ingest
from sellip.capture.mosaic import mosaic_layout

MIN_HIGHLIGHTS = 6
"""Highlights needed: 2 determine a point; 6 from spheres spread over the field make its depth trustworthy."""

OUTLINE_SAMPLES = 360
MIN_RADIUS_PX = 15.0
"""A dark blob smaller than this radius (output pixels) is not a sphere (dust, a screw)."""

HIGHLIGHT_REACH = 2.0
"""The highlight's Gaussian is fitted on the pixels within this many of its sigmas (from the half-maximum area)."""

MAX_OUTLINE_RMS_PX = 0.5
"""An outline farther than this (RMS, output pixels) from a sphere's silhouette: not a sphere, or occluded."""

MIN_BACKGROUND_SNR = 20.0
"""The background (the frame's median) must be this many times its own noise above black, or it is not bright."""

MIN_SOLIDITY = 0.93
"""A dark blob whose area is less than this share of its convex hull is two spheres touching (or a sphere and
another object), not one sphere."""

FIELD_SPREAD = 0.4
"""Highlights spanning less than this share of the width or height: spheres all near the centre (depth poorly
determined)."""

RIM_ETA = 1.5
"""Index of refraction assumed for the spheres' rim model (glass, glaze, phenolic resin: 1.45-1.6; the half-level
crossing of the model moves by 0.03 % of the radius between those)."""

RIM_BAND = (0.92, 1.08)
"""The rim model is fitted on pixels whose ray makes this range of multiples of the outline's cone angle."""

RIM_SECTORS = 8

NO_SPHERE = "no sphere found (expected dark spheres in front of a bright background)"

LONG_SUFFIX = "_long"
"""NAME_long.ext is the long exposure of the sphere frame NAME.ext (the same layout from the same camera position,
exposed for the spheres' diffuse light, the highlights clipped): the polarization check's bracket
(:func:`sellip.calibrate.polarization.check_polarization`); the flash step leaves it out."""


@dataclass
class Sphere:
    """One sphere in a frame: centre (3,) camera coordinates (m), radius_px (output pixels), centroid_px (x, y),
    outline_rms_px (how well the outline fits a sphere), problem (None or why it is left out), outline_centre (3,):
    the centre from the half-level outline alone (before the rim model; the flash's systematic 1-sigma compares the
    two)."""

    centre: np.ndarray | None
    radius_px: float
    centroid_px: np.ndarray
    outline_rms_px: float = float("nan")
    problem: str | None = None
    outline_centre: np.ndarray | None = None


def is_long(name: str) -> bool:
    """Whether the frame ``name`` (a file name) is a long exposure of a sphere frame (:data:`LONG_SUFFIX`)."""
    from pathlib import Path

    return Path(name).stem.endswith(LONG_SUFFIX)


def develop_frame(raw: np.ndarray, device: Mapping) -> tuple[np.ndarray, dict]:
    """The ingest chain (:func:`sellip.ingest.process_frame`) with the device's sensor and camera: linear,
    demosaiced, colour-corrected, undistorted analyzer images (H/2, W/2, 4, C), NaN where saturated; and the
    output grid's intrinsics."""
    sensor, camera = device["sensor"], device["camera"]
    layout = mosaic_layout(sensor["polarizer_layout"], sensor["color_layout"])
    plan = ingest.make_ingest_plan(sensor, camera, layout)
    return ingest.process_frame(raw, plan), plan.intrinsics


def pixel_rays(px: np.ndarray, intrinsics: Mapping) -> np.ndarray:
    """Unit rays (..., 3) through output-grid positions (..., 2) (x, y)."""
    px = np.asarray(px, np.float64)
    rays = np.stack([(px[..., 0] - intrinsics["cx"]) / intrinsics["fx"],
                     (px[..., 1] - intrinsics["cy"]) / intrinsics["fy"], np.ones(px.shape[:-1])], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def _outline(s0: np.ndarray, centroid: np.ndarray, radius: float, level: float) -> np.ndarray:
    """(K, 2) sub-pixel points where s0 first falls below ``level`` coming in from outside, along rays from the
    centroid."""
    angles = np.linspace(0, 2 * np.pi, OUTLINE_SAMPLES, endpoint=False)
    radii = np.arange(1.4 * radius, 0.6 * radius, -0.25)
    dirs = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    pts = centroid + radii[None, :, None] * dirs[:, None, :]  # (A, R, 2) x, y
    filled = np.where(np.isfinite(s0), s0, np.nanmax(s0))
    values = ndimage.map_coordinates(filled, [pts[..., 1].ravel(), pts[..., 0].ravel()], order=1,
                                     mode="nearest").reshape(pts.shape[:2])
    below = values < level
    out = []
    for a in range(len(angles)):
        k = int(np.argmax(below[a]))
        if not below[a, k] or k == 0:
            continue
        v0, v1 = values[a, k - 1], values[a, k]
        frac = (v0 - level) / (v0 - v1)
        r = radii[k - 1] + frac * (radii[k] - radii[k - 1])
        out.append(centroid + r * dirs[a])
    return np.asarray(out)


def _fit_cone(rays: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Axis a (3,), cos(alpha) and angular residuals (rad) of rays (N, 3) tangent to a sphere: r . a = cos(alpha)."""
    keep = np.ones(len(rays), bool)
    for _ in range(2):
        solution, *_ = np.linalg.lstsq(rays[keep], np.ones(keep.sum()), rcond=None)
        cos_alpha = 1.0 / np.linalg.norm(solution)
        axis = solution * cos_alpha
        residual = np.arccos(np.clip(rays @ axis, -1, 1)) - np.arccos(cos_alpha)
        mad = np.median(np.abs(residual[keep] - np.median(residual[keep])))
        keep = np.abs(residual - np.median(residual[keep])) <= max(3 * 1.4826 * mad, 1e-9)
    return axis, cos_alpha, residual


def find_spheres_or_why(s0: np.ndarray, intrinsics: Mapping, radius_m: float, rim_eta: float | None = RIM_ETA
                        ) -> tuple[list[Sphere], str | None]:
    """:func:`find_spheres`, or ([], why) when the frame shows no sphere against a bright background: the
    background (the frame's median) must stand :data:`MIN_BACKGROUND_SNR` times its noise above black, else the
    dark discs found would be the background's noise."""
    finite = np.isfinite(s0)
    values = s0[finite]
    background = float(np.median(values))
    # the background's noise: the MAD of the pixels brighter than half of it (the spheres' discs excluded)
    bright = values[values > background / 2]
    noise = 1.4826 * float(np.median(np.abs(bright - np.median(bright)))) if bright.size else np.inf
    if not background > MIN_BACKGROUND_SNR * max(noise, 1e-12):
        return [], (f"{NO_SPHERE}: the background reads {background:.3g} of full scale with noise {noise:.2g}, "
                    f"at least {MIN_BACKGROUND_SNR:g}x its noise expected (light the panel or wall behind the spheres)")
    spheres = find_spheres(s0, intrinsics, radius_m, rim_eta)
    return spheres, (None if spheres else NO_SPHERE)




def _r_plus(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Fresnel reflectance (Rs + Rp) / 2 of unpolarized light at incidence cos_i, air -> index eta."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    cos_t = np.sqrt(1 - (1 - cos_i ** 2) / eta ** 2)
    r_s = ((cos_i - eta * cos_t) / (cos_i + eta * cos_t)) ** 2
    r_p = ((eta * cos_i - cos_t) / (eta * cos_i + cos_t)) ** 2
    return (r_s + r_p) / 2


def rim_silhouette(s0: np.ndarray, intrinsics: Mapping, axis: np.ndarray, alpha: float, background: float,
                   eta: float = RIM_ETA) -> tuple[np.ndarray, float]:
    """The sphere's silhouette cone, axis (3,) and angle (rad), from the intensity across its rim.

    A glossy sphere mirrors the bright background at its rim: at grazing incidence the Fresnel reflectance goes
    to 1, so the rim is as bright as the background and the dark disc (the half-level outline) is smaller than
    the sphere -- on the synthetic spheres that mirror their panel, centres 11-13 mm too far at 0.45 m. Model of
    s0 against the angle b between a pixel's ray and the cone ``axis``: the background ``background`` * g outside
    (b > A), inside k * background * R+(theta) + c_sector + c1 (A - b) with sin(theta) = sin(b) / sin(A) (the normal's
    zenith from the view ray), blurred by a Gaussian of width s; fitted by least squares for A, k in [0, 1.2],
    s, g, c1, the axis' tilt (the half-level outline's axis leans where the flash lights the rim more) and one c
    per 45-degree sector (the flash's shading varies around the rim) on the pixels with b in :data:`RIM_BAND` x
    ``alpha``. Returns (``axis``, ``alpha``) when the fit fails."""
    from scipy.optimize import least_squares

    height, width = s0.shape
    f = float(np.sqrt(intrinsics["fx"] * intrinsics["fy"]))
    u0 = intrinsics["fx"] * axis[0] / axis[2] + intrinsics["cx"]
    v0 = intrinsics["fy"] * axis[1] / axis[2] + intrinsics["cy"]
    reach = f * np.tan(alpha * RIM_BAND[1]) + 3
    top, bottom = max(int(v0 - reach), 0), min(int(v0 + reach) + 2, height)
    left, right = max(int(u0 - reach), 0), min(int(u0 + reach) + 2, width)
    yy, xx = np.mgrid[top:bottom, left:right]
    rays = pixel_rays(np.stack([xx, yy], axis=-1).astype(np.float64), intrinsics)
    beta = np.arccos(np.clip(rays @ axis, -1, 1))
    values = s0[top:bottom, left:right]
    use = (beta > RIM_BAND[0] * alpha) & (beta < RIM_BAND[1] * alpha) & np.isfinite(values)
    if use.sum() < 50:
        return axis, alpha
    beta, values = beta[use], values[use].astype(np.float64)
    # the sector of each pixel around the axis
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    r = rays[use]
    sector = ((np.arctan2(r @ e2, r @ e1) + np.pi) / (2 * np.pi) * RIM_SECTORS).astype(int) % RIM_SECTORS
    pixel = 1.0 / f  # one pixel in angle
    grid_step = pixel / 8

    def tilted(dx, dy):
        turned = axis + dx * e1 + dy * e2
        return turned / np.linalg.norm(turned)

    def model(p):
        a, k, sigma, gain, c1, dx, dy, *c = p
        beta = np.arccos(np.clip(r @ tilted(dx, dy), -1, 1))
        sigma = abs(sigma) + 0.2 * pixel
        # a grid that moves with A, so that the step at the silhouette moves continuously with it
        below = np.ceil((a - RIM_BAND[0] * alpha + 4 * sigma) / grid_step)
        above = np.ceil((RIM_BAND[1] * alpha - a + 4 * sigma) / grid_step)
        grid = a + np.arange(-below, above + 1) * grid_step
        inside = grid < a
        sin_theta = np.clip(np.sin(grid) / np.sin(a), 0, 1)
        rim = np.where(inside, k * background * _r_plus(np.sqrt(1 - sin_theta ** 2), eta) + c1 * (a - grid),
                       gain * background)
        step = np.where(inside, 1.0, 0.0)
        half = int(np.ceil(4 * sigma / grid_step))
        kernel = np.exp(-0.5 * (np.arange(-half, half + 1) * grid_step / sigma) ** 2)
        kernel /= kernel.sum()
        rim_b = np.convolve(np.pad(rim, half, mode="edge"), kernel, mode="valid")
        step_b = np.convolve(np.pad(step, half, mode="edge"), kernel, mode="valid")
        at = np.interp(beta, grid, rim_b) + np.asarray(c)[sector] * np.interp(beta, grid, step_b)
        return at - values

    interior = [float(np.median(values[(sector == j) & (beta < 0.97 * alpha)])) if np.any((sector == j) &
                (beta < 0.97 * alpha)) else 0.0 for j in range(RIM_SECTORS)]
    start = [alpha, 0.5, 0.7 * pixel, 1.0, 0.0, 0.0, 0.0, *interior]
    shift = 0.05 * alpha
    lower = [RIM_BAND[0] * alpha, 0.0, 0.0, 0.5, -np.inf, -shift, -shift] + [-np.inf] * RIM_SECTORS
    upper = [RIM_BAND[1] * alpha, 1.2, 5 * pixel, 1.5, np.inf, shift, shift] + [np.inf] * RIM_SECTORS
    scale = [pixel, 0.1, pixel, 0.1, background / alpha, pixel, pixel] + [0.1 * background] * RIM_SECTORS
    try:
        fit = least_squares(model, start, bounds=(lower, upper), x_scale=scale)
    except ValueError:
        return axis, alpha
    if not fit.success:
        return axis, alpha
    return tilted(fit.x[5], fit.x[6]), float(fit.x[0])


def _solidity(blob: np.ndarray) -> float:
    """A blob's area over its convex hull's (1 for a disc, < 0.9 for two touching discs)."""
    from scipy.spatial import ConvexHull, QhullError

    ys, xs = np.nonzero(blob)
    # pixel corners, so that the hull encloses whole pixels
    pts = np.concatenate([np.stack([xs + dx, ys + dy], axis=-1) for dx in (0, 1) for dy in (0, 1)])
    try:
        return float(blob.sum() / ConvexHull(pts).volume)
    except QhullError:
        return 1.0


def find_spheres(s0: np.ndarray, intrinsics: Mapping, radius_m: float, rim_eta: float | None = RIM_ETA
                 ) -> list[Sphere]:
    """Spheres in an intensity image (H', W') on the undistorted output grid: dark discs on a bright background.
    A disc touching the image border is returned with a problem (clipped), as is one that is two discs touching
    (:data:`MIN_SOLIDITY`) or whose outline is not a sphere's. The outline (where s0 crosses half the background)
    gives the cone's axis; its angle is then refined by :func:`rim_silhouette` (the background mirrored at the
    rim, Fresnel for index ``rim_eta``), unless ``rim_eta`` is None."""
    finite = np.isfinite(s0)
    background = float(np.median(s0[finite]))
    level = background / 2
    dark = ndimage.binary_fill_holes(np.where(finite, s0 < level, False))
    labels, _count = ndimage.label(dark)
    spheres = []
    height, width = s0.shape
    pixel_scale = 1.0 / np.sqrt(intrinsics["fx"] * intrinsics["fy"])
    for index, box in enumerate(ndimage.find_objects(labels), start=1):
        blob = labels[box] == index
        area = float(blob.sum())
        radius = np.sqrt(area / np.pi)
        if radius < MIN_RADIUS_PX:
            continue
        ys, xs = np.nonzero(blob)
        centroid = np.array([xs.mean() + box[1].start, ys.mean() + box[0].start])
        clipped = box[0].start == 0 or box[1].start == 0 or box[0].stop == height or box[1].stop == width
        if clipped:
            spheres.append(Sphere(None, radius, centroid, problem="sphere clipped by the frame edge: its outline is "
                                                                  "not whole; expected every sphere wholly in view"))
            continue
        solidity = _solidity(blob)
        if solidity < MIN_SOLIDITY:
            spheres.append(Sphere(None, radius, centroid, problem=f"spheres touching: the dark blob fills "
                                  f"{100 * solidity:.0f} % of its convex hull (a lone sphere: ~100 %); expected "
                                  "spheres apart, each with background around it"))
            continue
        outline = _outline(s0, centroid, radius, level)
        if len(outline) < OUTLINE_SAMPLES // 2:
            spheres.append(Sphere(None, radius, centroid, problem="outline not found against the background"))
            continue
        axis, cos_alpha, residual = _fit_cone(pixel_rays(outline, intrinsics))
        rms = float(np.sqrt(np.mean(residual ** 2)) / pixel_scale)
        alpha = float(np.arccos(cos_alpha))
        outline_centre = axis * radius_m / np.sin(alpha)
        if rim_eta is not None:
            axis, alpha = rim_silhouette(s0, intrinsics, axis, alpha, background, rim_eta)
        sphere = Sphere(axis * radius_m / np.sin(alpha), radius, centroid, rms, outline_centre=outline_centre)
        if rms > MAX_OUTLINE_RMS_PX:
            sphere.problem = (f"outline is {rms:.2f} px RMS from a sphere's silhouette (at most {MAX_OUTLINE_RMS_PX}"
                              " expected): occluded, touching another object, or not a sphere")
        spheres.append(sphere)
    return spheres


def find_highlight(s0: np.ndarray, sphere: Sphere) -> tuple[np.ndarray | None, str | None]:
    """The mirror highlight's centre (x, y) inside a sphere's disc (its centroid refined by
    :func:`refine_highlight`), or (None, why)."""
    height, width = s0.shape
    yy, xx = np.mgrid[0:height, 0:width]
    r = np.hypot(xx - sphere.centroid_px[0], yy - sphere.centroid_px[1])
    inside = r < 0.9 * sphere.radius_px
    if np.isnan(s0[inside]).any():
        count = int(np.isnan(s0[inside]).sum())
        return None, (f"highlight saturated ({count} pixels at the white level): its centre is unknown; "
                      "expected a highlight below the white level (lower the flash or the exposure)")
    values = s0[inside]
    base = float(np.median(values))
    noise = 1.4826 * float(np.median(np.abs(values - base)))
    peak = float(values.max()) - base
    if peak < 20 * max(noise, 1e-6):
        return None, f"no mirror highlight (peak {peak:.3g} over the sphere's {base:.3g}); expected a glossy sphere"
    excess = np.where(inside, s0 - base, 0.0)
    core = excess > 0.5 * peak
    labels, _ = ndimage.label(core)
    top = labels.flat[int(np.argmax(np.where(inside, excess, -np.inf)))]
    weights = np.where(labels == top, excess, 0.0)
    centroid = np.array([np.sum(weights * xx), np.sum(weights * yy)]) / np.sum(weights)
    sigma = np.sqrt(np.sum(labels == top) / (2 * np.pi * np.log(2)))  # a Gaussian's half-maximum disc
    refined = refine_highlight(np.where(inside, s0 - base, np.nan), centroid, sigma)
    return (centroid if refined is None else refined), None


def refine_highlight(excess: np.ndarray, centroid: np.ndarray, sigma: float, reach: float = HIGHLIGHT_REACH
                     ) -> np.ndarray | None:
    """The highlight's centre (x, y) by least squares of a round Gaussian a exp(-|p - c|^2 / 2 s^2) + b on the
    pixels within ``reach`` * ``sigma`` of ``centroid`` (``excess``: s0 over the sphere's median, NaN off the
    sphere). The centroid of the pixels above half the peak is biased by the threshold's cut through a noisy,
    asymmetric spot (on the 2448x2048 synthetic set 0.04 px RMS, which put the flash 0.9 mm off in depth; the fit:
    0.015 px, 0.15 mm; docs/calibration.md). None when the fit fails or wanders (then the centroid is used)."""
    from scipy.optimize import least_squares

    half = int(np.ceil(reach * max(sigma, 1.0)))
    x0, y0 = np.round(centroid).astype(int)
    rows = slice(max(y0 - half, 0), min(y0 + half + 1, excess.shape[0]))
    cols = slice(max(x0 - half, 0), min(x0 + half + 1, excess.shape[1]))
    yy, xx = np.mgrid[rows, cols]
    values = excess[rows, cols].astype(np.float64)
    ok = np.isfinite(values)
    if ok.sum() < 25:
        return None
    xx, yy, values = xx[ok], yy[ok], values[ok]

    def residual(p):
        amplitude, cx, cy, s, b = p
        return amplitude * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s)) + b - values

    start = [float(values.max()), centroid[0], centroid[1], max(sigma, 1.0), 0.0]
    fit = least_squares(residual, start, x_scale=[start[0], 1.0, 1.0, 1.0, start[0]])
    amplitude, cx, cy, s, _ = fit.x
    centre = np.array([cx, cy])
    if not fit.success or amplitude <= 0 or not 0.3 * sigma < s < 3 * sigma or np.hypot(*(centre - centroid)) > sigma:
        return None
    return centre


def mirror_ray(centre: np.ndarray, radius_m: float, highlight_px: np.ndarray, intrinsics: Mapping
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """The line the flash lies on: the highlight's ray meets the sphere at P (3,); returns (P, unit reflected
    direction (3,)), or None if the ray misses the sphere."""
    d = pixel_rays(highlight_px, intrinsics)
    b = d @ centre
    disc = b * b - (centre @ centre - radius_m ** 2)
    if disc < 0:
        return None
    point = d * (b - np.sqrt(disc))
    normal = (point - centre) / radius_m
    reflected = d - 2 * (d @ normal) * normal
    return point, reflected / np.linalg.norm(reflected)


HIGHLIGHT_SHARED_PX = 0.015
"""One-sigma (output pixels, each axis) of an error that every highlight shares: the highlight's centre is a
Gaussian fit about its centroid, but a lobe on a curved surface lit from off the camera's axis is not symmetric
about the mirror point; at 2448x2048 all 18 highlights lay +0.013 px (sellip's renderer) and +0.008 px (Mitsuba 3)
from it, all towards the flash (docs/calibration.md). The lines' spread cannot see a shift they share."""


def shared_highlight_covariance(highlights: list[dict], radius_m: float, intrinsics: Mapping, position: np.ndarray,
                                scale_m: float = 1e-3, shift_px: float = HIGHLIGHT_SHARED_PX) -> np.ndarray:
    """(3, 3) covariance of the flash from an error of ``shift_px`` (1-sigma, output px) in x and in y shared by
    all ``highlights`` (records with ``centre_m`` and ``highlight_px``): the flash refitted with every highlight
    moved by ``shift_px`` along each axis, the two moves taken as independent 1-sigma errors (linear)."""
    cov = np.zeros((3, 3))
    for axis in np.eye(2):
        lines = [mirror_ray(np.asarray(h["centre_m"]), radius_m, np.asarray(h["highlight_px"]) + shift_px * axis,
                            intrinsics) for h in highlights]
        lines = [line for line in lines if line is not None]
        if len(lines) < 2:
            continue
        moved = nearest_point(np.asarray([p for p, _ in lines]), np.asarray([d for _, d in lines]), scale_m)[0]
        cov += np.outer(moved - position, moved - position)
    return cov


def highlight_rays(s0: np.ndarray, sphere: Sphere, centres: list[np.ndarray], radius_m: float, intrinsics: Mapping,
                   label: str, left_out: dict, miss: str, log=None
                   ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]] | None:
    """One sphere's highlight in the intensity ``s0`` (:func:`find_highlight`) and the flash's line mirrored at it
    (:func:`mirror_ray`) for each of ``centres`` (each (3,), the same sphere's centre by different estimates):
    (highlight (x, y), [(point (3,), direction (3,)), ...]). When the sphere has a problem of its own, no highlight
    is found or a ray misses (``miss``: why, in the protocol's words), records ``left_out[label]`` (and logs it)
    and returns None. Both protocols' loop over the spheres (:func:`calibrate_flash`,
    :func:`sellip.calibrate.board_spheres.calibrate_flash_on_board`)."""
    highlight, problem = (None, sphere.problem) if sphere.problem else find_highlight(s0, sphere)
    lines = [] if problem else [mirror_ray(centre, radius_m, highlight, intrinsics) for centre in centres]
    if problem is None and any(line is None for line in lines):
        problem = miss
    if problem is not None:
        left_out[label] = problem
        if log:
            log(f"{label}: {problem}")
        return None
    return highlight, lines


@dataclass
class FlashResult:
    """position_m (3,) camera coordinates; std_m (3,) one-sigma: the lines' spread, the sphere centres' error and
    the highlights' shared error together (:func:`solve_flash`, :func:`shared_highlight_covariance`);
    centre_std_m (3,) the centres' part alone; highlights: one record per used highlight (frame, sphere index,
    centre, residual_mm); left_out: {"frame[#k]": why}; protocol: "board" (spheres resting on the board, centres
    from its pose) or "outline" (spheres before a bright background); dropped: the highlights dropped as outliers
    (:func:`sellip.calibrate.flash_fit.drop_outliers`, also in left_out)."""

    position_m: np.ndarray
    std_m: np.ndarray
    rms_mm: float
    highlights: list[dict]
    left_out: dict[str, str] = field(default_factory=dict)
    image_size: tuple[int, int] = (0, 0)
    centre_std_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    protocol: str = "outline"
    dropped: int = 0

    def uncertainty(self) -> dict[str, float]:
        """What :mod:`sellip.calibrate.targets` gates the flash on: {flash_std_mm (largest axis), flash_rms_mm}."""
        return {"flash_std_mm": float(np.max(self.std_m) * 1e3), "flash_rms_mm": self.rms_mm}

    def causes(self) -> list[str]:
        """Why the position may be uncertain, as far as the frames show it: spheres left out (clipped, touching,
        saturated), too few highlights, highlights all near the image centre or at one distance, large residuals,
        sphere centres that the rim reflection makes uncertain."""
        out = []
        kinds = {"clipped": "clipped by the frame edge", "touching": "touching another sphere or object",
                 "saturated": "with a saturated highlight (lower the flash)", "no sphere": "frames without a sphere "
                 "against a bright background", "no mirror highlight": "without a mirror highlight",
                 "board not found": "frames whose board was not found"}
        for key, words in kinds.items():
            count = sum(key in why for why in self.left_out.values())
            if count:
                out.append(f"{count} sphere(s) {words}" if key not in ("no sphere", "board not found")
                           else f"{count} {words}")
        if self.dropped:
            out.append(f"{self.dropped} highlight(s) dropped as outliers (more than {OUTLIER_SIGMA:g} sigma from the "
                       "flash fitted to the others; named above)")
        count = len(self.highlights)
        if count < 2 * MIN_HIGHLIGHTS:
            out.append(f"only {count} highlights: take more frames, 2-3 spheres each "
                       f"({3 * MIN_HIGHLIGHTS} recommended)")
        if self.highlights and self.image_size[0]:
            px = np.asarray([h["highlight_px"] for h in self.highlights])
            extent = (px.max(axis=0) - px.min(axis=0)) / np.asarray(self.image_size, np.float64)
            if np.min(extent) < FIELD_SPREAD:
                out.append(f"the spheres were all near the image centre: their highlights span {100 * extent[0]:.0f} % "
                           f"of the width and {100 * extent[1]:.0f} % of the height (at least {100 * FIELD_SPREAD:.0f} "
                           "% expected): place them over the whole field")
            depth = np.asarray([h["centre_m"][2] for h in self.highlights if "centre_m" in h])
            if depth.size > 1 and depth.max() - depth.min() < DEPTH_SPREAD * np.median(depth):
                out.append(f"the spheres were all at one distance ({1e3 * depth.min():.0f}-{1e3 * depth.max():.0f} mm):"
                           f" expected depths {100 * DEPTH_SPREAD:.0f} % apart or more (near and far spheres, or the "
                           "board tilted)")
            worst = max(self.highlights, key=lambda h: h.get("residual_mm", 0.0))
            if worst.get("residual_mm", 0.0) > 3 * max(np.median([h["residual_mm"] for h in self.highlights]), 0.1):
                out.append(f"highlight residuals up to {worst['residual_mm']:.1f} mm ({worst['frame']} sphere "
                           f"{worst['sphere']}): a sphere's outline or centre is wrong there (a bright rim "
                           "reflection, a wrong --sphere-radius-mm, a sphere off its square's centre)")
        centre = float(np.max(self.centre_std_m) * 1e3)
        if self.protocol == "outline" and centre > 0.5 * float(np.max(self.std_m) * 1e3):
            out.append(f"the sphere centres from their outlines are uncertain: the flash moves by {centre:.1f} mm "
                       "between the half-level outline and the rim model (glossy spheres mirror the bright background "
                       "at their rims): set the spheres down on the board instead (--board, docs/calibration.md)")
        elif self.protocol == "board" and centre > 0.5 * float(np.max(self.std_m) * 1e3):
            out.append(f"the board's pose (and the intrinsics' 1-sigma) move the flash by {centre:.1f} mm: the board "
                       "too small or too far in the frame, or the intrinsics uncertain")
        return out


DEPTH_SPREAD = 0.1
"""Sphere centres whose depths span less than this share of their median: all at one distance (depth poorly
determined)."""


def intensity(analyzers: np.ndarray) -> np.ndarray:
    """s0 averaged over colour channels (H, W) from analyzer images (H, W, 4, C): (I0 + I45 + I90 + I135) / 2."""
    return analyzers.sum(axis=-2).mean(axis=-1) / 2


def too_few_highlights(count: int, min_highlights: int, left_out: Mapping[str, str]) -> CalibrationError:
    lines = "".join(f"\n  {k}: {v}" for k, v in left_out.items())
    return CalibrationError(f"{count} usable sphere highlight(s), at least {min_highlights} needed: take "
                            f"{min_highlights - count} more (spheres wholly in view, over the whole field, "
                            f"highlights below the white level).{lines}")


def calibrate_flash(frames: Mapping[str, np.ndarray], device: Mapping, radius_m: float,
                    min_highlights: int = MIN_HIGHLIGHTS, scale_m: float = 1e-3, log=None) -> FlashResult:
    """The flash position from raw frames {name: (H, W)} of glossy spheres of radius ``radius_m`` (module
    docstring), the spheres before a bright background (the outline protocol; spheres resting on the board:
    :func:`sellip.calibrate.board_spheres.calibrate_flash_on_board`). ``device`` needs sensor and camera
    (intrinsics calibrated). The 1-sigma includes, as the centres' systematic error, how far the flash moves
    between the half-level outline's centres and the rim model's. Every sphere left out is named with why; fewer
    than ``min_highlights`` usable highlights raise CalibrationError saying how many more are needed."""
    points, directions, records, left_out, outline_lines = [], [], [], {}, []
    image_size = (0, 0)
    labels = []
    for name, raw in frames.items():
        if is_long(name):
            if log:
                log(f"{name}: a long exposure for the polarization check ({LONG_SUFFIX}), not used for the flash")
            continue
        analyzers, intrinsics = develop_frame(raw, device)
        s0 = intensity(analyzers)
        image_size = (s0.shape[1], s0.shape[0])
        spheres, problem = find_spheres_or_why(s0, intrinsics, radius_m)
        if problem:
            left_out[name] = problem
            if log:
                log(f"{name}: {problem}")
        for k, sphere in enumerate(spheres):
            label = f"{name}#{k} at ({sphere.centroid_px[0]:.0f}, {sphere.centroid_px[1]:.0f})"
            found = highlight_rays(s0, sphere, [sphere.centre, sphere.outline_centre], radius_m, intrinsics, label,
                                   left_out, "the highlight's ray misses the fitted sphere (wrong --sphere-radius-mm?)",
                                   log)
            if found is None:
                continue
            highlight, (line, outline_line) = found
            points.append(line[0])
            directions.append(line[1])
            outline_lines.append(outline_line)
            records.append({"frame": name, "sphere": k, "centre_m": sphere.centre.tolist(),
                            "outline_rms_px": sphere.outline_rms_px, "highlight_px": highlight.tolist()})
            labels.append(label)
    if len(points) < min_highlights:
        raise too_few_highlights(len(points), min_highlights, left_out)
    points, directions = np.asarray(points), np.asarray(directions)
    keep = drop_outlier_highlights(points, directions, labels, left_out, scale_m, min_highlights, log)
    points, directions = points[keep], directions[keep]
    records = [r for r, k in zip(records, keep) if k]
    outline_lines = [line for line, k in zip(outline_lines, keep) if k]
    # the rim model's correction of the centres, taken as their systematic error: the flash from the half-level
    # outline's centres is one draw at +1 sigma and its mirror at -1 sigma
    outline, *_ = nearest_point(np.asarray([p for p, _ in outline_lines]),
                                np.asarray([d for _, d in outline_lines]), scale_m)
    position, *_ = nearest_point(points, directions, scale_m)
    samples = np.stack([outline, 2 * position - outline])
    position, cov, distances, centre = solve_flash(points, directions, scale_m, samples)
    cov = cov + shared_highlight_covariance(records, radius_m, intrinsics, position, scale_m)
    for record, distance in zip(records, distances):
        record["residual_mm"] = float(distance * 1e3)
    return FlashResult(position_m=position, std_m=np.sqrt(np.diag(cov)),
                       rms_mm=float(np.sqrt(np.mean(distances ** 2)) * 1e3), highlights=records, left_out=left_out,
                       image_size=image_size, centre_std_m=np.sqrt(np.diag(centre)), protocol="outline",
                       dropped=int(np.sum(~keep)))
