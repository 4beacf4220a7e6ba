"""The polarizer layout and the flash polarizer, checked on the sphere frames of the flash calibration.

Public API::

    candidate_layouts() -> list of 2x2 layouts     # all 24 arrangements of 0/45/90/135
    permutation(claimed, candidate) -> (4,) int    # analyzer axis of images developed with ``claimed`` -> candidate
    limb_samples(analyzers, sphere, radius_m, intrinsics) -> (stokes (N, 3), azimuth (N,), zenith (N,))
    layout_agreement(analyzers, long_analyzers, intrinsics, centres, radius_m) -> (K,)   # a bracket's same layout
    check_polarization(frames, device, radius_m, exposures=None) -> PolarizationReport

Two physical facts, on glossy dielectric spheres (camera-frame Stokes, sellip.conventions):

* Diffuse light leaves a dielectric polarized in its plane of exitance: its AoLP is the normal's azimuth phi in
  the ray's Stokes frame (x image right, y image up), known on a sphere. The score of a layout is
  sum_w cos 2 (AoLP - phi) / sum_w (w = the polarized intensity): positive for the right layout, negative when
  0/90 (and 45/135) are exchanged (AoLP turned by 90 deg), about 0 for a mirrored (45 <-> 135) or rotated
  layout. It is taken where the normal is 25-45 deg from the view ray (DIFFUSE_ZENITH_DEG): on the limb a
  glossy sphere mirrors the bright background, polarized tangentially, which turns the limb's verdict; the limb
  (LIMB_ZENITH_DEG) is scored and reported only. Before that, the pairing: orthogonal analyzers sum to s0
  (I0 + I90 = I45 + I135), which only one of the three ways to pair the cell's four positions satisfies; the 8
  layouts with that pairing are scored. All 24 arrangements are scored from ONE development of each frame: a
  layout only says which of the four cell positions is which angle, so another layout is a permutation of the
  developed analyzer axis.
* A mirror highlight keeps the flash's linear polarization (at 3.5 deg from normal incidence the Fresnel
  coefficients of s and p agree to 1e-3): under the right layout the highlight's AoLP is ``light.polarizer_deg``.
  The two cues are checked against each other (:func:`_check_cues`): when they disagree about a 90-degree turn
  the check fails and names no layout.

The two cues want different exposures: a dark glossy ball's highlight is 30-100x brighter than its diffuse light,
so a frame exposed for the highlight leaves the diffuse light at 25-45 deg below 1 % of full scale, where its
0.5-2 % polarization is lost in the noise. So each sphere layout is shot as a bracket: NAME (exposed for the
highlights, which give the flash polarizer) and NAME_long (:data:`sellip.calibrate.flash.LONG_SUFFIX`; the same
layout from the same camera position, exposed for the spheres' diffuse light, the highlights clipped: saturated
pixels are NaN after development and left out). The spheres are found in NAME; the diffuse band is read in
NAME_long, whose brightness on the spheres against NAME's must be at least :data:`MIN_BRACKET` and which must show
NAME's layout (:func:`layout_agreement`, :data:`MIN_LAYOUT_AGREEMENT`); else it is left out, named.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sellip.calibrate.flash import (
    LONG_SUFFIX,
    develop_frame,
    find_highlight,
    find_spheres_or_why,
    intensity,
    is_long,
    pixel_rays,
)
from sellip.calibrate.intrinsics import CalibrationError
from sellip.model.conventions import ANALYZER_ANGLES_DEG

POLARIZER_TOLERANCE_DEG = 2.0
"""A flash polarizer this far from capture.yaml's ``light.polarizer_deg`` is reported."""

DIFFUSE_ZENITH_DEG = (25.0, 45.0)
"""Normal zenith angles (from the view ray) whose diffuse polarization decides the layout: there the camera ray's
mirror direction turns back towards the camera's side (zenith < 45 deg), so a bright background behind the
spheres is not mirrored; its diffuse DoP is small (0.5-2 %) but thousands of pixels decide (score about +0.6 for
the right layout, -0.6 turned by 90 deg, on the synthetic spheres with and without the background mirrored)."""

LIMB_ZENITH_DEG = (60.0, 85.0)
"""The limb (normal zenith from the view ray): its diffuse DoP is larger, but a glossy sphere mirrors the bright
background there, polarized tangentially (across the diffuse light's plane), which can turn its verdict by 90
deg (score -0.95 for the right layout on the synthetic spheres that mirror the panel). Scored and reported as a
check; it does not decide."""

MIN_SCORE_MARGIN = 0.3
"""The best layout must beat the second by this much in score, or the frames cannot decide."""

MIN_BRACKET = 2.0
"""A long exposure (NAME_long) must read at least this many times its sphere frame's (NAME) brightness on the
spheres' diffuse band, or it is left out (named): it adds nothing the sphere frame has not."""

MIN_LAYOUT_AGREEMENT = 0.5
"""A long exposure must show its sphere frame's layout: around each sphere of NAME, the two frames must rank
their pixels alike (:func:`layout_agreement`) by at least this much, or NAME_long is left out (named). A sphere
moved between the two shots, or a long frame of another layout, would read the background's (or another
sphere's) light on the diffuse band. Measured in docs/calibration.md (section 4)."""


def candidate_layouts() -> list[list[list[int]]]:
    """Every 2x2 arrangement of the four analyzer angles (row-major), 24 in all."""
    return [[[a, b], [c, d]] for a, b, c, d in itertools.permutations(ANALYZER_ANGLES_DEG)]


def permutation(claimed, candidate) -> np.ndarray:
    """(4,) index: ``developed[..., perm, :]`` are the analyzer images in ANALYZER_ANGLES_DEG order if the sensor
    really has ``candidate`` where the images were developed with ``claimed``."""
    claimed, candidate = np.asarray(claimed).ravel(), np.asarray(candidate).ravel()
    order = list(ANALYZER_ANGLES_DEG)
    return np.array([order.index(int(claimed[list(candidate).index(angle)])) for angle in ANALYZER_ANGLES_DEG])


def _stokes(analyzers: np.ndarray) -> np.ndarray:
    """(..., 3) linear Stokes (s0, s1, s2) from analyzers (..., 4) in ANALYZER_ANGLES_DEG order."""
    i0, i45, i90, i135 = np.moveaxis(analyzers, -1, 0)
    return np.stack([(i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135], axis=-1)


def _projected_disc(centre: np.ndarray, radius_m: float, intrinsics: Mapping) -> tuple[float, float, float]:
    """(u, v, radius) in output pixels of a sphere at ``centre`` (3,) of ``radius_m`` seen by ``intrinsics``."""
    u = intrinsics["fx"] * centre[0] / centre[2] + intrinsics["cx"]
    v = intrinsics["fy"] * centre[1] / centre[2] + intrinsics["cy"]
    f = float(np.sqrt(intrinsics["fx"] * intrinsics["fy"]))
    return float(u), float(v), f * radius_m / float(np.sqrt(max(centre @ centre - radius_m ** 2, 1e-12)))


def limb_samples(analyzers: np.ndarray, centre: np.ndarray, radius_m: float, intrinsics: Mapping,
                 zenith_deg: tuple[float, float] = LIMB_ZENITH_DEG) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The limb's pixels of one sphere: analyzers (N, 4) (colour-averaged), the normal's azimuth phi (N,) in each
    ray's Stokes frame and its zenith (N,) (radians), from the sphere's centre (3,) and radius."""
    height, width = analyzers.shape[:2]
    u0, v0, r_px = _projected_disc(centre, radius_m, intrinsics)
    r_px = r_px * 1.1 + 2
    top, bottom = max(int(v0 - r_px), 0), min(int(v0 + r_px) + 1, height)
    left, right = max(int(u0 - r_px), 0), min(int(u0 + r_px) + 1, width)
    yy, xx = np.mgrid[top:bottom, left:right]
    d = pixel_rays(np.stack([xx, yy], axis=-1).astype(np.float64), intrinsics)
    b = d @ centre
    disc = b * b - (centre @ centre - radius_m ** 2)
    hit = disc > 0
    point = d * (b - np.sqrt(np.maximum(disc, 0)))[..., None]
    normal = (point - centre) / radius_m
    z = -d  # towards the camera
    up = np.array([0.0, -1.0, 0.0])
    y_axis = up - (z @ up)[..., None] * z
    y_axis /= np.linalg.norm(y_axis, axis=-1, keepdims=True)
    x_axis = np.cross(y_axis, z)
    zenith = np.arccos(np.clip(np.sum(normal * z, -1), -1, 1))
    azimuth = np.arctan2(np.sum(normal * y_axis, -1), np.sum(normal * x_axis, -1))
    lo, hi = np.radians(zenith_deg)
    block = analyzers[top:bottom, left:right].mean(axis=-1)  # (h, w, 4)
    use = hit & (zenith >= lo) & (zenith <= hi) & np.all(np.isfinite(block), axis=-1)
    return block[use], azimuth[use], zenith[use]


@dataclass
class PolarizationReport:
    """claimed / best layout with their limb scores (+1: diffuse AoLP radial as it must be), scores of all 24;
    polarizer_deg measured on the highlights (under the best layout) and its spread; claimed_polarizer_deg."""

    claimed_layout: list
    best_layout: list
    claimed_score: float
    best_score: float
    second_score: float
    polarizer_deg: float
    polarizer_std_deg: float
    claimed_polarizer_deg: float
    limb_pixels: int
    highlights: int
    scores: dict = field(default_factory=dict)
    left_out: dict = field(default_factory=dict)
    rim_score: float = float("nan")
    long_frames: int = 0
    diffuse_level: float = float("nan")

    @property
    def layout_ok(self) -> bool:
        return np.array_equal(self.claimed_layout, self.best_layout)

    @property
    def polarizer_error_deg(self) -> float:
        return float((self.polarizer_deg - self.claimed_polarizer_deg + 90) % 180 - 90)

    @property
    def polarizer_ok(self) -> bool:
        return abs(self.polarizer_error_deg) <= POLARIZER_TOLERANCE_DEG

    @property
    def ok(self) -> bool:
        return self.layout_ok and self.polarizer_ok

    def messages(self) -> list[str]:
        out = []
        if self.layout_ok:
            out.append(f"polarizer_layout {self.claimed_layout} fits: diffuse score {self.claimed_score:+.3f} "
                       f"(next best layout {self.second_score:+.3f}) over {self.limb_pixels} pixels at "
                       f"{DIFFUSE_ZENITH_DEG[0]:g}-{DIFFUSE_ZENITH_DEG[1]:g} deg, reading "
                       f"{100 * self.diffuse_level:.2g} % of full scale ({self.long_frames} long exposures)")
        else:
            out.append(f"polarizer_layout {self.claimed_layout} does NOT fit: diffuse score {self.claimed_score:+.3f} "
                       f"({_describe(self.claimed_layout, self.best_layout)}); the layout that fits is "
                       f"{self.best_layout} (score {self.best_score:+.3f})")
        if self.rim_score < 0:
            out.append(f"the limbs ({LIMB_ZENITH_DEG[0]:g}-{LIMB_ZENITH_DEG[1]:g} deg) score {self.rim_score:+.3f} "
                       "under that layout: polarized across the diffuse light's plane, they mirror the bright "
                       "background and were not used")
        verdict = "fits" if self.polarizer_ok else f"is off by more than {POLARIZER_TOLERANCE_DEG} deg"
        out.append(f"light.polarizer_deg {self.claimed_polarizer_deg:g} {verdict}: measured "
                   f"{self.polarizer_deg:.2f} +- {self.polarizer_std_deg:.2f} deg on {self.highlights} highlights")
        return out

    def uncertainty(self) -> dict[str, float]:
        """What :mod:`sellip.calibrate.targets` gates the check on: {polarizer_std_deg}."""
        return {"polarizer_std_deg": self.polarizer_std_deg}

    def causes(self) -> list[str]:
        """Why the flash polarizer's angle may be uncertain, as far as the frames show it."""
        out = []
        if self.highlights < 6:
            out.append(f"only {self.highlights} highlights below the white level (6 or more expected)")
        saturated = sum("saturated" in why for why in self.left_out.values())
        if saturated:
            out.append(f"{saturated} highlight(s) saturated: lower the flash")
        return out

    def record(self) -> dict:
        return {"ok": self.ok, "claimed_layout": self.claimed_layout, "best_layout": self.best_layout,
                "claimed_score": self.claimed_score, "best_score": self.best_score, "second_score": self.second_score,
                "limb_pixels": self.limb_pixels, "rim_score": self.rim_score, "long_frames": self.long_frames,
                "diffuse_level": self.diffuse_level,
                "polarizer_deg_measured": self.polarizer_deg,
                "polarizer_std_deg": self.polarizer_std_deg, "polarizer_deg_claimed": self.claimed_polarizer_deg,
        "highlights": self.highlights, "messages": self.messages(), "left_out": self.left_out}


def _describe(claimed, best) -> str:
    c, b = np.asarray(claimed), np.asarray(best)
    if np.array_equal(np.where(c == 45, 135, np.where(c == 135, 45, c)), b):
        return "45 and 135 swapped"
    if np.array_equal((c + 90) % 180, b):
        return "turned by 90 deg (0 <-> 90, 45 <-> 135)"
    if np.array_equal(c[:, ::-1], b) or np.array_equal(c[::-1, :], b):
        return "mirrored"
    if np.array_equal(np.rot90(c), b) or np.array_equal(np.rot90(c, -1), b) or np.array_equal(np.rot90(c, 2), b):
        return "rotated"
    return "another arrangement"


SUM_RULE_Z = 5.0
"""The right pairing's sum-rule misfit must be below the next pairing's by this many standard errors."""


def _score(analyzers: np.ndarray, phi: np.ndarray) -> float:
    """sum_w cos 2 (AoLP - phi) / sum_w (w the polarized intensity) of analyzers (N, 4) in ANALYZER_ANGLES_DEG
    order against the normals' azimuths phi (N,): +1 radial, -1 tangential."""
    s = _stokes(analyzers)
    aolp = 0.5 * np.arctan2(s[:, 2], s[:, 1])
    weight = np.hypot(s[:, 1], s[:, 2])
    return float(np.sum(weight * np.cos(2 * (aolp - phi))) / max(np.sum(weight), 1e-12))


def _highlight_angle(highlight_pixels: list, perm: np.ndarray) -> tuple[float, float]:
    """(AoLP (deg, [0, 180)), its 1-sigma (deg)) of the highlights' pixels (list of (n, 4)) under the analyzer
    permutation ``perm``; NaN without highlights."""
    if not highlight_pixels:
        return float("nan"), float("nan")
    h = _stokes(np.concatenate(highlight_pixels)[:, perm])
    angles = 0.5 * np.arctan2(h[:, 2], h[:, 1])
    weight = np.hypot(h[:, 1], h[:, 2])
    mean = 0.5 * np.arctan2(np.sum(weight * np.sin(2 * angles)), np.sum(weight * np.cos(2 * angles)))
    spread = np.sqrt(np.sum(weight * ((angles - mean + np.pi / 2) % np.pi - np.pi / 2) ** 2) / np.sum(weight))
    return float(np.degrees(mean) % 180), float(np.degrees(spread) / np.sqrt(len(highlight_pixels)))


def _turned(layout) -> list:
    return (np.asarray(layout) + 90) % 180


def _check_cues(report: PolarizationReport, claimed, best, claimed_highlight_deg: float) -> None:
    """Raise CalibrationError when the two independent cues disagree about a 90-degree turn: the diffuse light
    (polarized radially, :data:`DIFFUSE_ZENITH_DEG`) and the highlights (the flash's polarization, kept by a
    mirror reflection) read with the claimed layout. Either the diffuse light says "turned by 90" while the
    highlights, read with the claimed layout, show the claimed flash polarizer; or the diffuse light says the
    claimed layout fits while the highlights are 90 deg off the claimed polarizer. A turned layout with a flash
    polarizer mounted 90 deg off, or something bright on the camera's side mirrored in the spheres, would give
    either: the frames cannot tell which, so the check names no layout."""
    if not np.isfinite(claimed_highlight_deg):
        return
    off = abs((claimed_highlight_deg - report.claimed_polarizer_deg + 90) % 180 - 90)
    advice = ("something bright on the camera's side (a lit room, a white wall behind the camera) mirrored in the "
              "spheres can turn the diffuse light's verdict: shoot them with only the flash on the camera's side; "
              "else check how the flash polarizer is mounted")
    if np.array_equal(_turned(claimed), best) and off <= POLARIZER_TOLERANCE_DEG:
        raise CalibrationError(
            f"the cues disagree: the diffuse light says polarizer_layout {claimed} is turned by 90 deg (the score of "
            f"{best} is {report.best_score:+.3f}), but the highlights, read with {claimed}, show the flash polarizer "
            f"at {claimed_highlight_deg:.2f} deg, the claimed light.polarizer_deg {report.claimed_polarizer_deg:g}: "
            f"either the layout is turned and the flash polarizer 90 deg off, or {advice}")
    if np.array_equal(np.asarray(claimed), np.asarray(best)) and abs(off - 90) <= POLARIZER_TOLERANCE_DEG:
        raise CalibrationError(
            f"the cues disagree: the diffuse light says polarizer_layout {claimed} fits (score "
            f"{report.best_score:+.3f}), but the highlights show the flash polarizer at {claimed_highlight_deg:.2f} "
            f"deg, 90 deg from the claimed light.polarizer_deg {report.claimed_polarizer_deg:g}: either the flash "
            f"polarizer is mounted 90 deg off, or the layout is {_turned(claimed).tolist()} and {advice}")


def _undecided(best, best_score: float, second, second_score: float, values: np.ndarray,
               long_frames: int, notes: Mapping[str, str]) -> CalibrationError:
    """The error when no layout wins by MIN_SCORE_MARGIN, with the level of the diffuse light that decides
    (``values``: analyzer samples (N, 4) at DIFFUSE_ZENITH_DEG, 1 = full scale; ``notes``: {long exposure: why it
    was left out})."""
    level = float(np.nanmedian(values.mean(axis=-1)))
    return CalibrationError(f"the sphere limbs cannot tell the polarizer layouts apart (best {best} {best_score:+.3f}, "
                            f"next {second} {second_score:+.3f}, at least {MIN_SCORE_MARGIN:g} apart needed): "
                            f"expected dielectric spheres whose diffuse light is lit and below the white level; at "
                            f"{DIFFUSE_ZENITH_DEG[0]:g}-{DIFFUSE_ZENITH_DEG[1]:g} deg it reads {100 * level:.2g} % of "
                            f"full scale over {len(values)} pixels ({long_frames} long exposures), and its "
                            "polarization is 0.5-2 % of that: shoot each sphere layout NAME again as "
                            f"NAME{LONG_SUFFIX} (same camera position), exposed so that the spheres read 10-30 % of "
                            "full scale (the highlights may clip)" +
                            "".join(f"\n  {name}: {why}" for name, why in notes.items()))


def _brackets(names, left_out: dict) -> dict[str, str]:
    """{sphere frame NAME: its long exposure NAME_long} among the frame names; a long exposure without its sphere
    frame goes to ``left_out``."""
    short = {Path(n).stem: n for n in names if not is_long(n)}
    out = {}
    for name in names:
        if not is_long(name):
            continue
        stem = Path(name).stem[: -len(LONG_SUFFIX)]
        if stem in short:
            out[short[stem]] = name
        else:
            left_out[name] = (f"a long exposure without its sphere frame (expected {stem}{Path(name).suffix} beside "
                              "it: the same layout exposed for the highlights)")
    return out


def _bracket_problem(name: str, long_name: str, ratio: float, exposures: Mapping) -> str | None:
    """Why the long exposure ``long_name`` is left out (its spheres' diffuse band only ``ratio`` times as bright as
    in ``name``), or None; the ExposureTime the files record (``exposures``, s or None) is quoted."""
    if ratio >= MIN_BRACKET:
        return None
    t_short, t_long = exposures.get(name), exposures.get(long_name)
    tags = ""
    if t_short and t_long:
        tags = f" (ExposureTime {t_long:.4g} s against {t_short:.4g} s: {t_long / t_short:.3g}x)"
        if t_long / t_short >= MIN_BRACKET:
            tags += (": a flash's pulse is shorter than the shutter, so a longer exposure does not brighten what it "
                     "lights; raise the flash power or the gain instead")
    return (f"only {ratio:.2f}x as bright on the spheres as {name}{tags}, at least {MIN_BRACKET:g}x needed: expose it "
            "so that the spheres read 10-30 % of full scale")


def layout_agreement(analyzers: np.ndarray, long_analyzers: np.ndarray, intrinsics: Mapping,
                     centres: list[np.ndarray], radius_m: float) -> np.ndarray:
    """(K,) for spheres at ``centres`` (camera frame, m) found in a sphere frame (``analyzers``): Spearman's rank
    correlation between that frame's intensity and a long exposure's (``long_analyzers``) over the square of 1.5
    radii around each sphere, saturated pixels ranked above everything. The same layout: the dark disc and the
    bright background rank alike in both (near 1). Another layout, or the sphere moved: near 0. NaN where either
    frame reads the same everywhere there (all of it clipped)."""
    from scipy import stats

    short, long = (np.where(np.isfinite(image), image, np.inf)
                   for image in (intensity(analyzers), intensity(long_analyzers)))
    height, width = short.shape
    out = np.full(len(centres), np.nan)
    for k, centre in enumerate(centres):
        u0, v0, r_px = _projected_disc(centre, radius_m, intrinsics)
        rows = slice(max(int(v0 - 1.5 * r_px), 0), min(int(v0 + 1.5 * r_px) + 2, height))
        cols = slice(max(int(u0 - 1.5 * r_px), 0), min(int(u0 + 1.5 * r_px) + 2, width))
        a, b = stats.rankdata(short[rows, cols].ravel()), stats.rankdata(long[rows, cols].ravel())
        if a.size > 8 and np.ptp(a) > 0 and np.ptp(b) > 0:
            out[k] = float(np.corrcoef(a, b)[0, 1])
    return out


def _layout_change(name: str, analyzers: np.ndarray, long_analyzers: np.ndarray, intrinsics: Mapping,
                   centres: list[np.ndarray], radius_m: float) -> str | None:
    """Why a long exposure does not show the layout of its sphere frame ``name`` (spheres at ``centres``), or None:
    around each sphere the two frames' :func:`layout_agreement` must reach :data:`MIN_LAYOUT_AGREEMENT`."""
    for k, agreement in enumerate(layout_agreement(analyzers, long_analyzers, intrinsics, centres, radius_m)):
        if not agreement >= MIN_LAYOUT_AGREEMENT:
            reads = ("reads the same everywhere there" if np.isnan(agreement) else
                     f"ranks its pixels unlike {name} (rank correlation {agreement:.2f}, at least "
                     f"{MIN_LAYOUT_AGREEMENT:g} expected)")
            return (f"not the layout of {name}: around its sphere #{k} this frame {reads}; shoot the bracket from the "
                    "same place without touching the spheres")
    return None


def _long_exposure(name: str, long_name: str, long_raw: np.ndarray, analyzers: np.ndarray, intrinsics: Mapping,
                   centres: list[np.ndarray], device: Mapping, radius_m: float, exposures: Mapping, left_out: dict,
                   log=None) -> np.ndarray | None:
    """The developed long exposure ``long_name`` of sphere frame ``name`` (its spheres at ``centres``), or None when
    it is not :data:`MIN_BRACKET` times as bright on their diffuse band (then in ``left_out``, logged) or no sphere
    was found."""
    if not centres:
        return None
    long_analyzers, _ = develop_frame(long_raw, device)
    bands = [(limb_samples(analyzers, centre, radius_m, intrinsics, DIFFUSE_ZENITH_DEG)[0],
              limb_samples(long_analyzers, centre, radius_m, intrinsics, DIFFUSE_ZENITH_DEG)[0]) for centre in centres]
    short, long = np.concatenate([b[0] for b in bands]), np.concatenate([b[1] for b in bands])
    if len(long) < 0.5 * len(short):  # saturated pixels are NaN and not sampled
        why = (f"{100 * (1 - len(long) / max(len(short), 1)):.0f} % of the spheres' diffuse band saturated: expose it "
               f"so that the spheres read 10-30 % of full scale (if they do, it is not the layout of {name}: shoot "
               "the bracket from the same place without touching the spheres)")
    else:
        ratio = float(np.median(long.sum(-1))) / max(float(np.median(short.sum(-1))), 1e-12)
        why = _bracket_problem(name, long_name, ratio, exposures) or _layout_change(name, analyzers, long_analyzers,
                                                                                  intrinsics, centres, radius_m)
    if why:
        left_out[long_name] = why
        if log:
            log(f"{long_name}: {why}")
        return None
    if log:
        log(f"{long_name}: the diffuse light of {name}'s spheres, {ratio:.1f}x as bright")
    return long_analyzers


def check_polarization(frames: Mapping[str, np.ndarray], device: Mapping, radius_m: float,
                       log=None, exposures: Mapping[str, float | None] | None = None) -> PolarizationReport:
    """Score every polarizer layout on the spheres' diffuse light and measure the flash polarizer on their
    highlights (module docstring). ``frames``: {file name: raw}; NAME_long is the long exposure of NAME (the
    bracket, module docstring), its diffuse band used instead of NAME's; ``exposures``: {file name: ExposureTime
    (s) the file records, or None}, quoted when a long exposure is not brighter. Raises CalibrationError if no
    sphere gives a limb, if no layout wins by :data:`MIN_SCORE_MARGIN`, if the sum rule cannot pick the pairing,
    or if the cues disagree (:func:`_check_cues`). Long: one pass over the frames gathers both cues' samples, then
    the three decisions follow in order, each failing with its own message."""
    claimed = [list(map(int, row)) for row in device["sensor"]["polarizer_layout"]]
    layouts = candidate_layouts()
    perms = [permutation(claimed, layout) for layout in layouts]
    limb_stokes, limb_phi, rim_stokes, rim_phi, highlight_pixels, left_out = [], [], [], [], [], {}
    brackets = _brackets(list(frames), left_out)
    long_frames = 0
    for name, raw in frames.items():
        if is_long(name):
            continue
        analyzers, intrinsics = develop_frame(raw, device)
        s0 = intensity(analyzers)
        spheres, problem = find_spheres_or_why(s0, intrinsics, radius_m)
        if problem:
            left_out[name] = problem
        long_analyzers = None
        if name in brackets:
            long_analyzers = _long_exposure(name, brackets[name], frames[brackets[name]], analyzers, intrinsics,
                                            [s.centre for s in spheres if not s.problem], device, radius_m,
                                            exposures or {}, left_out, log)
            long_frames += long_analyzers is not None
        for k, sphere in enumerate(spheres):
            label = f"{name}#{k}"
            if sphere.problem:
                left_out[label] = sphere.problem
                continue
            diffuse = analyzers if long_analyzers is None else long_analyzers
            values, phi, _ = limb_samples(diffuse, sphere.centre, radius_m, intrinsics, DIFFUSE_ZENITH_DEG)
            limb_stokes.append(values)
            limb_phi.append(phi)
            values, phi, _ = limb_samples(analyzers, sphere.centre, radius_m, intrinsics)
            rim_stokes.append(values)
            rim_phi.append(phi)
            highlight, problem = find_highlight(s0, sphere)
            if problem:
                left_out[label] = problem
                continue
            # the highlight's pixels: the 5x5 around its centroid, analyzers averaged over colour
            x, y = np.rint(highlight).astype(int)
            highlight_pixels.append(analyzers[y - 2:y + 3, x - 2:x + 3].mean(axis=-1).reshape(-1, 4))
    if not limb_stokes:
        raise CalibrationError("no sphere gave a limb to check the polarizer layout on:" +
                               "".join(f"\n  {k}: {v}" for k, v in left_out.items()))
    values, phi = np.concatenate(limb_stokes), np.concatenate(limb_phi)
    rim_values, rim_phi = np.concatenate(rim_stokes), np.concatenate(rim_phi)
    scores = [_score(values[:, perm], phi) for perm in perms]
    rim_scores = [_score(rim_values[:, perm], rim_phi) for perm in perms]
    everything = np.concatenate([values, rim_values])
    misfit = [np.abs(a[:, 0] + a[:, 2] - a[:, 1] - a[:, 3]) / np.maximum(_stokes(a)[:, 0], 1e-12)
              for a in (everything[:, perm] for perm in perms)]
    consistency = [float(np.mean(m)) for m in misfit]
    # Orthogonal analyzers sum to s0: only the right pairing of the cell's positions into (0, 90) and
    # (45, 135) is consistent; among the 8 layouts with that pairing the radial diffuse AoLP decides.
    paired = np.isclose(consistency, min(consistency), rtol=1e-6)
    ranked = np.where(paired, scores, -np.inf)
    order = np.argsort(ranked)[::-1]
    best = int(order[0])
    claimed_index = next(i for i, layout in enumerate(layouts) if layout == claimed)
    polarizer, polarizer_std = _highlight_angle(highlight_pixels, perms[best])
    report = PolarizationReport(
        claimed_layout=claimed, best_layout=layouts[best], claimed_score=scores[claimed_index],
        best_score=scores[best], second_score=float(ranked[order[1]]), polarizer_deg=polarizer,
        polarizer_std_deg=polarizer_std, claimed_polarizer_deg=float(device.get("light", {}).get("polarizer_deg", 0.0)),
        limb_pixels=len(values), highlights=len(highlight_pixels),
        scores={str(layouts[i]): scores[i] for i in np.argsort(scores)[::-1]}, left_out=left_out,
        rim_score=rim_scores[best], long_frames=long_frames,
        diffuse_level=float(np.nanmedian(values.mean(axis=-1))) if len(values) else float("nan"))
    if scores[best] - ranked[order[1]] < MIN_SCORE_MARGIN:
        raise _undecided(layouts[best], scores[best], layouts[order[1]], scores[order[1]], values, long_frames,
                         {name: why for name, why in left_out.items() if is_long(name)})
    # the sum rule must pick the pairing clearly: the per-pixel misfit of the next pairing exceeds the best's by
    # SUM_RULE_Z standard errors of their paired difference
    other = [i for i in range(len(perms)) if not paired[i]]
    if other:
        runner = min(other, key=lambda i: consistency[i])
        diff = misfit[runner] - misfit[best]
        z = float(np.mean(diff) / max(np.std(diff) / np.sqrt(len(diff)), 1e-300))
        if not z > SUM_RULE_Z:
            raise CalibrationError(f"the analyzers' sum rule I0 + I90 = I45 + I135 cannot pick the pairing of the "
                                   f"cell's positions (mean relative misfit {consistency[best]:.3g} for the best "
                                   f"pairing, {consistency[runner]:.3g} for the next, {z:.1f} standard errors apart, "
                                   f"{SUM_RULE_Z:g} needed): expected polarized light on the spheres, below the "
                                   "white level")
    _check_cues(report, claimed, layouts[best], _highlight_angle(highlight_pixels, perms[claimed_index])[0])
    if log:
        for line in report.messages():
            log(line)
    return report
