"""Ingest kernels: raw mosaic frames -> linear analyzer images -> one HDR image per view (docs/design.md §2, §3).

Pure numpy functions (the only file access is :func:`rawpy_black_level`); the
stages :mod:`sellip.stages.linearize` and :mod:`sellip.stages.merge_hdr` do the
reading and writing. Raw decoding and its checks live in :mod:`sellip.capture`.

Chain for one frame (:func:`process_frame`):

1. :func:`linearize` -- ``(raw - black) / (white - mean(black))``, with the
   black level per mosaic position; saturated pixels (``saturation`` of their range
   or more) and dead ones (reading 0 although the black level is positive)
   are invalid.
2. :func:`demosaic` -- per analyzer, the pixels of that analyzer form one
   image on the grid of 2x2 polarizer cells; for a colour sensor it carries a
   Bayer pattern (colour per cell). G (on the diagonal) is filled in by
   bilinear interpolation (normalized convolution); R and B by the same
   analyzer's G times their locally interpolated colour ratio to G, so every
   colour shares G's finer resolution and an analyzer never mixes with another.
3. :func:`apply_color_matrix` -- camera RGB -> linear sRGB (colour sensors).
4. :func:`remap` -- undistortion with the calibrated intrinsics, which also
   moves every analyzer's samples to the centre of their polarizer cell.

Output grid
    One output pixel per 2x2 polarizer cell: ``(H/2, W/2)`` for an ``(H, W)``
    mosaic. Output pixel ``(i, j)`` is centred on raw position
    ``(x, y) = (2j + 0.5, 2i + 0.5)``, the centre of its cell, for all four
    analyzers: each analyzer's samples sit half a raw pixel off that centre
    (at ``(2j + dx, 2i + dy)``, see :func:`analyzer_phases`) and the remap
    interpolates them onto it, so no analyzer is displaced against another.
    Pixel centres are at integer coordinates (OpenCV), hence
    :func:`output_intrinsics`: ``f' = f / 2``, ``c' = (c - 0.5) / 2``; the
    output is undistorted (zero distortion coefficients). Half resolution is
    the finest grid with one sample of every analyzer per output pixel; a
    full-resolution grid would interpolate 3 of 4 analyzers at every pixel
    without adding information.

Invalid samples
    From step 2 on, an invalid sample is NaN. Every step propagates NaN from
    any input with a nonzero interpolation weight, so an output sample is
    invalid exactly when it depends on a saturated, dead or out-of-image
    pixel. The colour matrix makes a pixel's three channels invalid together.

HDR (:func:`merge_hdr`)
    Each frame estimates the relative radiance ``linear / (flash_level *
    exposure_s)``; frames are averaged with weights ``gain * hdr_weight(box)``
    (``box`` the frame averaged over 5x5 pixels, so that no weight follows its
    sample's own noise) that favour mid-range values, are zero for invalid
    samples and small (not zero) for dark ones, so a pixel dark in every frame
    still gets a value.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from sellip.capture.mosaic import MosaicError, MosaicLayout
from sellip.model.conventions import ANALYZER_ANGLES_DEG
from sellip.model.render import distort_normalized
from sellip.settings import setting

CELL = 2
"""Raw pixels per side of a polarizer cell; the output grid has one pixel per cell."""

BLACK_LEVEL_SOURCES = ("capture", "file")
"""Where black levels come from: capture.yaml (all formats), or a RAW file's own (rawpy) levels."""

BAD_FRAME_POLICIES = ("error", "skip")
"""What a missing or unreadable raw frame does: stop the stage, or leave the frame out with a warning."""


@dataclass(frozen=True)
class IngestSettings:
    """Settings of ingest (config section ``ingest``; each declared once here, :mod:`sellip.settings`):
    :func:`sellip.capture.linearize.linearize_capture` and :func:`sellip.capture.hdr.merge_capture`."""

    saturation: float = setting(0.98, "a pixel at or above this fraction of its range (white - black) counts as "
                                "saturated", unit="fraction of the range", exclusive_minimum=0, maximum=1)
    black_level_from: str = setting("capture", "black levels from capture.yaml (capture), or from each RAW file's "
                                    "own metadata (file; DNG etc.)", choices=BLACK_LEVEL_SOURCES)
    bad_frames: str = setting("error", "a raw frame that is missing or unreadable: stop with its file and frames.csv "
                              "row (error), or leave it out with a warning (skip; its view is merged from its other "
                              "frames, and dropped when none is left)", choices=BAD_FRAME_POLICIES)
    flash_ratio_tolerance: float = setting(1.5, "a frame whose brightness relative to its view's other frames "
                                           "differs from its label (flash_level * exposure_s) by more than this "
                                           "factor either way stops merge_hdr, naming the view and frame (a "
                                           "mislabelled flash level)", unit="factor", exclusive_minimum=1)

    def __post_init__(self):
        if not 0 < self.saturation <= 1:
            raise ValueError(f"saturation must be in (0, 1], got {self.saturation}")
        if self.black_level_from not in BLACK_LEVEL_SOURCES:
            raise ValueError(f"black_level_from must be one of {BLACK_LEVEL_SOURCES}, got {self.black_level_from!r}")
        if self.bad_frames not in BAD_FRAME_POLICIES:
            raise ValueError(f"bad_frames must be one of {BAD_FRAME_POLICIES}, got {self.bad_frames!r}")
        if not self.flash_ratio_tolerance > 1:
            raise ValueError(f"flash_ratio_tolerance must be a factor > 1, got {self.flash_ratio_tolerance}")


DEFAULT_SATURATION = IngestSettings.saturation
"""Fraction of a pixel's range (white - black) at or above which it counts as saturated (the declared default of
``IngestSettings.saturation``)."""

HDR_WEIGHT_FLOOR = 1e-3
"""Smallest weight of a valid sample in the HDR merge (dark samples keep a little weight)."""

HDR_WEIGHT_WINDOW = 5
"""Side (pixels) of the box that a frame is averaged over before its merge weights are taken from it: a weight
from the sample's own value grows with its own noise (h rises from black) and biased dark pixels upward by 0.3-0.6
noise sd (the background of the stability suite's captures at +0.17 against a dim limb's 5); a 5x5 box leaves a
hundredth of it (docs/ingest.md)."""

GUIDE_FLOOR = 1e-3
"""Colour-ratio demosaicing needs the guide colour (G) above this (linear, 1 = full scale) where the ratio is
taken; darker, a colour is interpolated bilinearly on its own."""

# Bilinear interpolation on a Bayer lattice as normalized 3x3 convolution on the cell grid:
# a colour present once per 2x2 cells (R, B) uses the tent, a colour on the diagonal (G) the cross.
_TENT = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]], np.float32)
_CROSS = np.array([[0.0, 0.25, 0.0], [0.25, 1.0, 0.25], [0.0, 0.25, 0.0]], np.float32)
_TENT_1D = np.array([0.5, 1.0, 0.5], np.float32)  # _TENT = outer(_TENT_1D, _TENT_1D)


class IngestError(ValueError):
    """Inputs the ingest kernels cannot process (inconsistent shapes, layouts or levels)."""


# --------------------------------------------------------------------------- black level / linearize


def black_level_map(black_level, height: int, width: int) -> np.ndarray:
    """Per-pixel black level (height, width) float32 from a scalar or a (P, P) per-position pattern.

    The pattern is indexed by raster position in the mosaic period (row, column
    from the top-left pixel), as capture.yaml's ``sensor.black_level``.
    """
    black = np.asarray(black_level, dtype=np.float32)
    if black.ndim == 0:
        return np.full((height, width), black, np.float32)
    if black.ndim != 2 or height % black.shape[0] or width % black.shape[1]:
        raise IngestError(f"black level must be a scalar or a (P, P) pattern that tiles a {height}x{width} "
                          f"mosaic, got shape {black.shape}")
    return np.tile(black, (height // black.shape[0], width // black.shape[1]))


def rawpy_black_level(path) -> np.ndarray:
    """Per-pixel black level (H, W) float32 that a RAW file (DNG, ...) declares, read with rawpy.

    rawpy's ``black_level_per_channel`` is ordered by colour index (LibRaw's
    0..3, e.g. R, G, B, G2), not by raster position; ``raw_colors`` gives the
    colour index of every pixel of ``raw_image``, so the map is
    ``black_level_per_channel[raw_colors]``. rawpy cannot read black-level
    patterns larger than the file's CFA (e.g. 4x4); those come back as 0.
    """
    import rawpy

    with rawpy.imread(str(path)) as raw:
        per_channel = np.asarray(raw.black_level_per_channel, dtype=np.float32)
        return per_channel[np.asarray(raw.raw_colors)]


def linearize(raw: np.ndarray, black: np.ndarray | float, white_level: float,
              saturation: float = DEFAULT_SATURATION) -> tuple[np.ndarray, np.ndarray]:
    """Linear values and the invalid-pixel mask of raw mosaics.

    raw: (..., H, W) unsigned integers (raw units); black: scalar or (H, W)
    per-pixel black level; white_level: the raw value of a full pixel.
    Returns ``(linear, invalid)``: linear (..., H, W) float32
    ``(raw - black) / (white_level - mean(black))`` (1 = full scale; one gain for
    all pixels, since the black offset does not change a pixel's gain; noise
    may make it negative), invalid (..., H, W) bool: saturated (``raw - black``
    at or above ``saturation`` of the pixel's own range ``white_level - black``)
    or dead (reads 0 although its black level is positive).
    """
    black = np.asarray(black, dtype=np.float32)
    headroom = np.float32(white_level) - black
    if np.any(headroom <= 0):
        raise IngestError(f"white level {white_level} must exceed the black level (max {float(black.max())})")
    signal = raw.astype(np.float32) - black
    invalid = signal >= np.float32(saturation) * headroom
    invalid |= (raw == 0) & (black > 0)
    signal /= np.float32(white_level - float(black.mean()))
    return signal, invalid


# --------------------------------------------------------------------------- demosaic


def analyzer_phases(layout: MosaicLayout) -> np.ndarray:
    """(4, 2) int: (row, column) of each analyzer inside the 2x2 polarizer cell, in ANALYZER_ANGLES_DEG order."""
    cell = layout.analyzer[:CELL, :CELL]
    reps = layout.period // CELL
    if not np.array_equal(layout.analyzer, np.tile(cell, (reps, reps))):
        raise MosaicError(f"the analyzer pattern must repeat every {CELL}x{CELL} pixels, "
                          f"got {layout.analyzer.tolist()}")
    return np.array([np.argwhere(cell == k)[0] for k in range(len(ANALYZER_ANGLES_DEG))], np.int64)


def _cell_colors(layout: MosaicLayout) -> np.ndarray:
    """(4, Q, Q) colour index of each analyzer's cells over one period of the cell grid (Q = period / 2)."""
    return np.stack([layout.color[dy::CELL, dx::CELL] for dy, dx in analyzer_phases(layout)])


def _kernel_for(present: np.ndarray) -> np.ndarray | None:
    """The bilinear kernel for a colour present at ``present`` (Q, Q) cells of the period; None if everywhere."""
    if present.all():
        return None
    if present.shape == (2, 2) and present.sum() == 1:
        return _TENT
    if present.shape == (2, 2) and present.sum() == 2 and present[0, 0] == present[1, 1]:
        return _CROSS
    raise MosaicError(f"cannot interpolate a colour present at cells {present.astype(int).tolist()} of the period")


def _tent_1d(x: np.ndarray, axis: int, out: np.ndarray) -> np.ndarray:
    """``out = x + (left + right neighbour) / 2`` along ``axis`` (taps 0.5, 1, 0.5), zero padding. Returns out."""
    xm, om = np.moveaxis(x, axis, -1), np.moveaxis(out, axis, -1)
    np.add(xm[..., :-2], xm[..., 2:], out=om[..., 1:-1])
    om[..., 0] = xm[..., 1]
    om[..., -1] = xm[..., -2]
    om *= np.float32(0.5)
    om += xm
    return out


def _correlate3x3(x: np.ndarray, kernel: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``out`` = 3x3 correlation of ``x`` over the last two axes, zero padding. Returns out.

    Taps with weight 0 are skipped, so a NaN reaches only the outputs whose kernel weight on it is nonzero.
    """
    if kernel is _TENT:  # separable: rows, then columns
        return _tent_1d(_tent_1d(x, -1, np.empty_like(x)), -2, out)
    height, width = x.shape[-2:]
    np.multiply(x, kernel[1, 1], out=out)
    scaled = {}
    for (dy, dx), weight in np.ndenumerate(kernel):
        if weight == 0 or (dy, dx) == (1, 1):
            continue
        if weight not in scaled:
            scaled[weight] = x * weight
        rows_out = slice(max(0, 1 - dy), height - max(0, dy - 1))
        rows_in = slice(max(0, dy - 1), height - max(0, 1 - dy))
        cols_out = slice(max(0, 1 - dx), width - max(0, dx - 1))
        cols_in = slice(max(0, dx - 1), width - max(0, 1 - dx))
        out[..., rows_out, cols_out] += scaled[weight][..., rows_in, cols_in]
    return out


@dataclass(frozen=True)
class DemosaicPlan:
    """What :func:`demosaic` precomputes for one layout and mosaic size.

    phases: (4, 2) analyzer positions in the cell; channels: C.
    kernels: per colour the 3x3 kernel (None: no interpolation needed).
    present: (C, 4, Hc, Wc) bool, the cells where each analyzer samples each colour.
    inv_norm: (C, 4, Hc, Wc) float32, 1 / (kernel * present) (the normalization of the convolution).
    guide: the colour on the diagonal of the Bayer lattice (G), which guides the others; None without one.
    """

    phases: np.ndarray
    channels: int
    kernels: tuple
    present: np.ndarray
    inv_norm: np.ndarray
    guide: int | None = None


def make_demosaic_plan(layout: MosaicLayout, height: int, width: int) -> DemosaicPlan:
    """Precompute :class:`DemosaicPlan` for an (height, width) mosaic (multiples of ``layout.period``)."""
    if height % layout.period or width % layout.period:
        raise IngestError(f"mosaic size {height}x{width} is not a multiple of the period {layout.period}")
    colors = _cell_colors(layout)
    q = colors.shape[-1]
    hc, wc = height // CELL, width // CELL
    kernels, present, inv_norm = [], [], []
    for c in range(layout.channels):
        period_present = colors == c  # (4, Q, Q)
        kernel = _kernel_for(period_present[0])
        if any(_kernel_for(p) is not kernel for p in period_present[1:]):
            raise MosaicError(f"the analyzers sample colour {c} in differently shaped lattices")
        cells = np.tile(period_present, (1, hc // q, wc // q))
        norm = cells.astype(np.float32)
        if kernel is not None:
            norm = _correlate3x3(norm, kernel, np.empty_like(norm))
        kernels.append(kernel)
        present.append(cells)
        inv_norm.append((1.0 / norm).astype(np.float32))
    guides = [c for c, kernel in enumerate(kernels) if kernel is _CROSS]
    return DemosaicPlan(phases=analyzer_phases(layout), channels=layout.channels, kernels=tuple(kernels),
                        present=np.stack(present), inv_norm=np.stack(inv_norm),
                        guide=guides[0] if len(guides) == 1 else None)


def analyzer_cells(linear: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """Split (..., H, W) mosaics into (..., 4, H/2, W/2): analyzer k's pixel of every polarizer cell."""
    return np.stack([linear[..., dy::CELL, dx::CELL] for dy, dx in phases], axis=-3)


def demosaic(linear: np.ndarray, plan: DemosaicPlan) -> np.ndarray:
    """Four analyzer images on the cell grid from linear mosaics; no analyzer mixes with another.

    linear: (..., H, W) float32, NaN where invalid. Returns (..., 4, H/2, W/2, C):
    analyzer k's value at cell (i, j) is located at raw (x, y) = (2j + dx_k, 2i + dy_k)
    (``plan.phases[k] = (dy_k, dx_k)``); :func:`remap` moves it to the cell centre.

    The guide colour G (``plan.guide``, on the Bayer lattice's diagonal) is a bilinear interpolation of
    the analyzer's own G cells. Another colour X, where it is missing, is G times the bilinear
    interpolation (kernel T over X's own cells) of the ratios X / G there (colour-ratio interpolation).
    X then has G's resolution wherever its ratio to G is smooth (shading, and the polarization, which
    is the same in every colour), where plain bilinear interpolation would blur X over two cells: at
    612x512 that blur averaged grazing samples with brighter, less polarized ones and biased eta 1-2 %
    low (docs/accuracy.md). Cells whose G is at most GUIDE_FLOOR give no ratio; where none of X's cells
    in reach gives one, X is interpolated bilinearly on its own. Without a guide (mono, other
    lattices) every colour is bilinear.
    """
    cells = analyzer_cells(linear, plan.phases)
    planes = np.empty((plan.channels,) + cells.shape, np.float32)  # colour planes, returned channels-last
    sparse = np.empty_like(cells)
    for c in sorted(range(plan.channels), key=lambda c: c != plan.guide):  # the guide first
        kernel = plan.kernels[c]
        if kernel is None:
            planes[c] = cells
            continue
        sparse.fill(0)
        np.copyto(sparse, cells, where=plan.present[c])  # this colour's samples, zero elsewhere
        own = _correlate3x3(sparse, kernel, planes[c])  # T[X] (unnormalized)
        if plan.guide is None or c == plan.guide:
            own *= plan.inv_norm[c]
            continue
        bilinear = own * plan.inv_norm[c]
        guide = planes[plan.guide]
        with np.errstate(divide="ignore", invalid="ignore"):
            usable = plan.present[c] & ~(guide <= GUIDE_FLOOR)  # NaN G stays in, so its NaN spreads
            sparse.fill(0)
            np.divide(cells, guide, out=sparse, where=usable)  # X / G at X's cells
            ratio = _correlate3x3(sparse, kernel, np.empty_like(sparse))
            weight = _correlate3x3(usable.astype(np.float32), kernel, np.empty_like(sparse))
            guided = (weight > 0) & ~plan.present[c]
            np.multiply(guide, ratio / weight, out=planes[c], where=guided)
        np.copyto(planes[c], bilinear, where=~guided)
    return np.moveaxis(planes, 0, -1)


# --------------------------------------------------------------------------- colour, geometry


def apply_color_matrix(rgb: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Camera RGB (..., 3) -> linear sRGB (..., 3) with the 3x3 ``matrix``; NaN in any channel -> NaN in all.

    Works channel plane by channel plane (fast when the colour planes are contiguous, as
    :func:`demosaic` returns them); every term is computed, so 0 * NaN keeps NaN.
    """
    matrix = np.asarray(matrix, dtype=np.float32)
    out = np.empty((3,) + rgb.shape[:-1], np.float32)
    for c in range(3):
        np.multiply(rgb[..., 0], matrix[c, 0], out=out[c])
        out[c] += rgb[..., 1] * matrix[c, 1]
        out[c] += rgb[..., 2] * matrix[c, 2]
    return np.moveaxis(out, 0, -1)


def output_intrinsics(camera: Mapping, height: int, width: int) -> dict:
    """Intrinsics of the output grid from raw-pixel ``camera`` (fx, fy, cx, cy) and the raw size.

    Output pixel (i, j) is centred on raw (2j + 0.5, 2i + 0.5); with pixel
    centres at integer coordinates: fx' = fx / 2, cx' = (cx - 0.5) / 2 (same in y).
    The output images are undistorted: distortion is all zeros.
    """
    return {
        "fx": float(camera["fx"]) / CELL,
        "fy": float(camera["fy"]) / CELL,
        "cx": (float(camera["cx"]) - (CELL - 1) / 2) / CELL,
        "cy": (float(camera["cy"]) - (CELL - 1) / 2) / CELL,
        "width": width // CELL,
        "height": height // CELL,
        "distortion": [0.0] * 5,
    }


def source_positions(camera: Mapping, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw-pixel (x, y) where each output pixel's ray lands on the distorted sensor; two (H/2, W/2) float64.

    The lens model is OpenCV's (:func:`sellip.model.render.distort_normalized`).
    """
    out = output_intrinsics(camera, height, width)
    j, i = np.meshgrid(np.arange(out["width"], dtype=np.float64), np.arange(out["height"], dtype=np.float64))
    xd, yd = distort_normalized((j - out["cx"]) / out["fx"], (i - out["cy"]) / out["fy"],
                                list(camera.get("distortion", [0.0] * 5)))
    return float(camera["fx"]) * xd + float(camera["cx"]), float(camera["fy"]) * yd + float(camera["cy"])


@dataclass(frozen=True)
class RemapTable:
    """Bilinear gather from each analyzer's cell grid to the output grid.

    index: (4, 4, N) int64, per analyzer and tap the flat source cell; weight:
    (4, 4, N) float32, NaN for output pixels whose ray leaves the image.
    shape: (Hout, Wout).
    """

    index: np.ndarray
    weight: np.ndarray
    shape: tuple[int, int]


def make_remap(camera: Mapping, phases: np.ndarray, height: int, width: int) -> RemapTable:
    """Undistortion + cell-centre alignment for an (height, width) mosaic with raw-pixel ``camera``.

    Analyzer k's cell (i, j) sits at raw (2j + dx_k, 2i + dy_k), so a raw
    position (x, y) is cell coordinate ((y - dy_k) / 2, (x - dx_k) / 2). A
    sample within half a cell of the border is clamped to it; farther out is invalid.
    """
    x, y = source_positions(camera, height, width)
    hc, wc = height // CELL, width // CELL
    n = x.size
    index = np.empty((len(phases), 4, n), np.int64)
    weight = np.empty((len(phases), 4, n), np.float32)
    columns = np.arange(n)
    for k, (dy, dx) in enumerate(phases):
        ci, cj = ((y - dy) / CELL).ravel(), ((x - dx) / CELL).ravel()
        inside = (ci >= -0.5) & (ci <= hc - 0.5) & (cj >= -0.5) & (cj <= wc - 0.5)
        ci, cj = np.clip(ci, 0, hc - 1), np.clip(cj, 0, wc - 1)
        i0 = np.minimum(np.floor(ci), max(hc - 2, 0)).astype(np.int64)
        j0 = np.minimum(np.floor(cj), max(wc - 2, 0)).astype(np.int64)
        fi, fj = ci - i0, cj - j0
        taps, w = index[k], weight[k]
        taps[0] = i0 * wc + j0
        taps[1] = taps[0] + 1
        taps[2] = taps[0] + wc
        taps[3] = taps[2] + 1
        w[0], w[1], w[2], w[3] = (1 - fi) * (1 - fj), (1 - fi) * fj, fi * (1 - fj), fi * fj
        # a tap with weight 0 reads the strongest tap instead, so NaN there cannot leak in
        strongest = taps[np.argmax(w, axis=0), columns]
        np.copyto(taps, strongest, where=w <= 0)
        w[:, ~inside] = np.nan
    return RemapTable(index=index, weight=weight, shape=(hc, wc))


def remap(images: np.ndarray, table: RemapTable) -> np.ndarray:
    """Resample analyzer images (4, Hc, Wc, C) onto the output grid: (Hout, Wout, 4, C) float32.

    Gathers plane by plane (``images[k, :, :, c]``); the result's memory is planar too.
    """
    n_analyzers, hc, wc, channels = images.shape
    out = np.empty((n_analyzers, channels, table.index.shape[-1]), np.float32)
    for k in range(n_analyzers):
        index, weight = table.index[k], table.weight[k]
        for c in range(channels):
            plane = np.ravel(images[k, :, :, c])
            acc = out[k, c]
            np.multiply(np.take(plane, index[0]), weight[0], out=acc)
            for t in range(1, index.shape[0]):
                acc += np.take(plane, index[t]) * weight[t]
    return np.moveaxis(out.reshape((n_analyzers, channels) + table.shape), (0, 1), (-2, -1))


# --------------------------------------------------------------------------- one frame


@dataclass(frozen=True)
class IngestPlan:
    """Everything :func:`process_frame` needs for one capture, computed once (:func:`make_ingest_plan`).

    black: (H, W) float32 per-pixel black level (raw units); white_level (raw units);
    saturation: fraction of a pixel's range (:func:`linearize`); color_matrix: (3, 3) or None (mono);
    intrinsics: the output grid's (:func:`output_intrinsics`).
    """

    raw_shape: tuple[int, int]
    black: np.ndarray
    white_level: float
    saturation: float
    demosaic: DemosaicPlan
    color_matrix: np.ndarray | None
    remap: RemapTable
    intrinsics: dict


def make_ingest_plan(sensor: Mapping, camera: Mapping, layout: MosaicLayout,
                     saturation: float = DEFAULT_SATURATION) -> IngestPlan:
    """Build the per-capture plan from capture.yaml's ``sensor`` and ``camera`` sections and the mosaic layout."""
    height, width = int(sensor["height"]), int(sensor["width"])
    if not 0 < saturation <= 1:
        raise IngestError(f"saturation must be in (0, 1], got {saturation}")
    dem = make_demosaic_plan(layout, height, width)
    matrix = None
    if layout.channels == 3:
        matrix = np.asarray(camera.get("color_matrix", np.eye(3)), np.float32)
        if np.array_equal(matrix, np.eye(3, dtype=np.float32)):
            matrix = None
    return IngestPlan(
        raw_shape=(height, width),
        black=black_level_map(sensor["black_level"], height, width),
        white_level=float(sensor["white_level"]),
        saturation=float(saturation),
        demosaic=dem,
        color_matrix=matrix,
        remap=make_remap(camera, dem.phases, height, width),
        intrinsics=output_intrinsics(camera, height, width),
    )


def process_frame(raw: np.ndarray, plan: IngestPlan, black: np.ndarray | None = None) -> np.ndarray:
    """One raw mosaic (H, W) -> linear, colour-corrected, undistorted analyzer images (H/2, W/2, 4, C) float32.

    ``black`` overrides ``plan.black`` (e.g. a RAW file's own levels). Invalid samples are NaN.
    """
    if raw.shape != plan.raw_shape:
        raise IngestError(f"expected a mosaic of shape {plan.raw_shape}, got {raw.shape}")
    linear, invalid = linearize(raw, plan.black if black is None else black, plan.white_level, plan.saturation)
    linear[invalid] = np.nan
    return develop(linear, plan)


def analyzer_plan(plan: IngestPlan, analyzer: int) -> IngestPlan:
    """``plan`` for one analyzer (index into ANALYZER_ANGLES_DEG): :func:`develop` then returns
    (H/2, W/2, 1, C), the same values as its analyzer ``analyzer`` of the full plan, in a quarter of the time."""
    one = slice(analyzer, analyzer + 1)
    dem = plan.demosaic
    return replace(plan, demosaic=replace(dem, phases=dem.phases[one], present=dem.present[:, one],
                                          inv_norm=dem.inv_norm[:, one]),
                   remap=replace(plan.remap, index=plan.remap.index[one], weight=plan.remap.weight[one]))


def develop(linear: np.ndarray, plan: IngestPlan) -> np.ndarray:
    """A linear mosaic (H, W) float32 (NaN where invalid) -> colour-corrected, undistorted analyzer images
    (H/2, W/2, 4, C) float32: demosaicing, the colour matrix, the remap. What :func:`process_frame` does after
    :func:`linearize`; also what makes a render look like an ingested photograph
    (:func:`sellip.fit.geometry_jobs.predicted_diffuse`)."""
    images = demosaic(np.asarray(linear, np.float32), plan.demosaic)  # (4, Hc, Wc, C)
    if plan.color_matrix is not None:
        images = apply_color_matrix(images, plan.color_matrix)
    return remap(images, plan.remap)


# --------------------------------------------------------------------------- HDR


def hdr_weight(linear: np.ndarray) -> np.ndarray:
    """Merge weight of linear values (any shape): 1 - (2v - 1)^4 on [0, 1], at least HDR_WEIGHT_FLOOR; 0 for NaN.

    Peaks at mid-range (v = 0.5), falls towards saturation and towards black;
    saturated samples are already NaN (see :func:`linearize`).
    """
    t = np.multiply(linear, np.float32(2), dtype=np.float32)
    t -= 1
    t *= t
    t *= t  # (2v - 1)^4, >= 1 outside [0, 1] where the floor takes over
    np.subtract(1, t, out=t)
    np.maximum(t, np.float32(HDR_WEIGHT_FLOOR), out=t)
    return np.nan_to_num(t, copy=False, nan=0.0)


def merge_hdr(frames: Iterable[np.ndarray], gains: Iterable[float]) -> tuple[np.ndarray, np.ndarray]:
    """Merge frames of one view into relative radiance.

    frames: F arrays (..., H, W, 4, C) float32 linear values, NaN where invalid (an (F, ..., 4, C) array
    works too); gains: F values flash_level * exposure_s. Frame f estimates ``frame / gain_f``; its weight is
    ``gain_f * hdr_weight(box)`` where the sample is valid, ``box`` the frame averaged over
    :data:`HDR_WEIGHT_WINDOW` pixels per side (invalid samples as 0), so that no sample's weight follows its
    own noise. Returns ``(merged, valid)``: merged (..., 4, C) float32 (0 where no frame is valid), valid (...)
    bool, True where every analyzer and channel has a valid frame.
    """
    num = den = None
    for frame, gain in zip(frames, gains, strict=True):
        if not gain > 0:
            raise IngestError(f"gain (flash_level * exposure_s) must be > 0, got {gain}")
        if num is not None and frame.shape != num.shape:
            raise IngestError(f"frames of one view must have equal shapes, got {num.shape} and {frame.shape}")
        value = np.nan_to_num(frame, nan=0.0)
        box = ndimage.uniform_filter(value, size=(HDR_WEIGHT_WINDOW,) * (frame.ndim - 2) + (1, 1), mode="nearest")
        h = hdr_weight(box)
        h[np.isnan(frame)] = 0
        term = np.multiply(value, h, dtype=np.float32)
        h *= np.float32(gain)
        if num is None:
            num, den = term, h
        else:
            num += term
            den += h
    if num is None:
        raise IngestError("no frames to merge")
    has_data = den > 0
    np.divide(num, den, out=num, where=has_data)
    num[~has_data] = 0
    return num, has_data.all(axis=(-2, -1))


# --------------------------------------------------------------------------- flash levels against the data

FLASH_RATIO_TOLERANCE = IngestSettings.flash_ratio_tolerance
"""The declared default of config ``ingest.flash_ratio_tolerance`` (:class:`IngestSettings`): a frame whose measured
brightness relative to its view's other frames differs from its label's (flash_level * exposure_s) by more than this
factor either way is mislabelled. A flash's output varies by a few percent from shot to shot; a wrong flash level is
a factor of 2 or more."""

RATIO_FLOOR = 0.02
"""Samples (linear, 1 = full scale) at or below this in either frame are left out of a brightness ratio: there
noise and the black level's error dominate."""

RATIO_MIN_SAMPLES = 50
"""Fewer samples lit and valid in both frames than this: the ratio is not measured."""


def brightness_ratios(frames, gains) -> tuple[int, np.ndarray, np.ndarray]:
    """Each frame's brightness measured against one reference frame of the same view, and as labelled.

    frames: F arrays (..., 4, C) float32 linear values (analyzers I0, I45, I90, I135; NaN where invalid) of one view;
    gains: F labels flash_level * exposure_s. The reference is the frame with the most samples valid and above
    RATIO_FLOOR. Each analyzer pair measures the intensity (I0 + I90 = I45 + I135): the samples are chosen where the
    reference's (I0 + I90) / 2 is above RATIO_FLOOR, and the ratio is measured on the other pair, (I45 + I135) / 2,
    of frame and reference (valid in both; independent noise: docs/reliability.md, "Flash levels").
    Returns ``(reference, measured, labelled)``: measured (F,) the median of frame / reference over those samples (NaN
    where fewer than RATIO_MIN_SAMPLES), labelled (F,) gain / gain of the reference. Both are 1 at the reference."""
    frames = [np.asarray(f, np.float32) for f in frames]
    if any(f.ndim < 2 or f.shape[-2] != 4 for f in frames):
        raise IngestError(f"brightness ratios need frames of shape (..., 4, C) (four analyzers), got "
                          f"{[f.shape for f in frames]}")
    gains = np.asarray(list(gains), np.float64)
    a0, a45, a90, a135 = (ANALYZER_ANGLES_DEG.index(angle) for angle in (0, 45, 90, 135))
    chooses = [(f[..., a0, :] + f[..., a90, :]) / 2 for f in frames]
    measures = [(f[..., a45, :] + f[..., a135, :]) / 2 for f in frames]
    lit = [np.nan_to_num(c, nan=0.0) > RATIO_FLOOR for c in chooses]
    reference = int(np.argmax([m.sum() for m in lit]))
    base = measures[reference]
    chosen = lit[reference] & np.isfinite(base) & (base > 0)
    measured = np.full(len(frames), np.nan)
    for f, value in enumerate(measures):
        both = chosen & np.isfinite(value)
        if both.sum() >= RATIO_MIN_SAMPLES:
            measured[f] = float(np.median(value[both] / base[both]))
    return reference, measured, gains / gains[reference]


def mislabelled_frames(measured: np.ndarray, labelled: np.ndarray, tolerance: float = FLASH_RATIO_TOLERANCE
                       ) -> np.ndarray:
    """(F,) bool: frames whose measured / labelled brightness ratio lies more than ``tolerance`` (a factor > 1)
    from the view's consensus (the median of that ratio over the measured frames, in log), so a mislabelled
    reference frame does not make the others look wrong. Frames not measured (NaN) are never flagged."""
    if not tolerance > 1:
        raise IngestError(f"the flash ratio tolerance must be a factor > 1, got {tolerance}")
    deviation = np.log(np.asarray(measured, np.float64) / np.asarray(labelled, np.float64))
    known = np.isfinite(deviation)
    if known.sum() < 2:
        return np.zeros(len(deviation), bool)
    centre = float(np.median(deviation[known]))
    return known & (np.abs(deviation - centre) > np.log(tolerance))
