"""Preview images of HDR analyzer images for people (``snakemake --report``): pure numpy in, uint8 RGB out.

Per view (:func:`preview_images`):

``s0``        total intensity, tone-mapped: scaled so the 99.5th percentile of valid pixels is white, sRGB-encoded.
``dolp``      degree of linear polarization of the colour-averaged Stokes vector, clipped to [0, 1], viridis.
``aolp``      angle of linear polarization as hue (0 and 180 deg red, 60 deg green, 120 deg blue; HSV with
              full saturation and value), the usual colour code of polarization imaging (e.g. polanalyser).
``diffuse``   I_d = 2 I90, same exposure as s0.
``specular``  I_s = I0 - I90 (negative values black), same exposure as s0.

Invalid pixels are black everywhere; DoLP and AoLP are also black where s0 is
below ``dark_fraction`` of the exposure scale (there the angle is noise).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from sellip.capture.hdr import read_hdr
from sellip.jobs import atomic_directory, progress_logger
from sellip.model.conventions import analyzers_to_stokes, observations_from_analyzers

log = logging.getLogger(__name__)

PREVIEW_KINDS = ("s0", "dolp", "aolp", "diffuse", "specular")
"""The preview images of every view, in this order."""

WHITE_PERCENTILE = 99.5
"""Percentile of valid s0 that maps to white in the tone-mapped previews."""


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function of linear values (clipped to [0, 1]); same shape, float32."""
    x = np.clip(np.nan_to_num(linear, nan=0.0), 0, 1).astype(np.float32)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[0, 1] floats -> uint8 (rounded); grey (H, W) or mono (H, W, 1) become RGB (H, W, 3)."""
    image = np.asarray(image, np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return np.rint(np.clip(image, 0, 1) * 255).astype(np.uint8)


def linear_stokes(analyzers: np.ndarray) -> np.ndarray:
    """(s0, s1, s2) of the colour-averaged analyzer images: (H, W, 4, C) -> (H, W, 3) float32."""
    return analyzers_to_stokes(np.asarray(analyzers, np.float32).mean(axis=-1), axis=-1)


def dolp_aolp(stokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """DoLP in [0, 1] and AoLP in [0, pi) radians from linear Stokes (..., 3); float32 numpy.

    :func:`sellip.model.polar.dolp` (0 where s0 <= 0) clipped at 1, since noise can push the
    estimate from four analyzers above 1; :func:`sellip.model.polar.aolp` wrapped to [0, pi)
    (counter-clockwise from image x, :mod:`sellip.model.conventions`).
    """
    from sellip.model import polar

    stokes = np.asarray(stokes, np.float32)
    dolp = np.clip(np.asarray(polar.dolp(stokes)), 0, 1)
    aolp = np.mod(np.asarray(polar.aolp(stokes)), np.pi)
    return dolp.astype(np.float32), aolp.astype(np.float32)


def aolp_colors(aolp: np.ndarray) -> np.ndarray:
    """Hue-coded AoLP: angles (...) in radians -> RGB (..., 3) in [0, 1], hue = angle / pi."""
    from matplotlib.colors import hsv_to_rgb

    hue = np.mod(aolp, np.pi) / np.pi
    return hsv_to_rgb(np.stack([hue, np.ones_like(hue), np.ones_like(hue)], axis=-1)).astype(np.float32)


def preview_images(analyzers: np.ndarray, valid: np.ndarray, dark_fraction: float = 0.01) -> dict[str, np.ndarray]:
    """The previews of one view: analyzers (H, W, 4, C), valid (H, W) -> {kind: (H, W, 3) uint8} (PREVIEW_KINDS)."""
    from matplotlib import colormaps

    analyzers = np.asarray(analyzers, np.float32)
    valid = np.asarray(valid, bool)
    stokes = linear_stokes(analyzers)
    s0 = stokes[..., 0]
    s0_color = analyzers_to_stokes(analyzers, axis=-2)[..., 0, :]  # (H, W, C)
    scale = float(np.percentile(s0[valid], WHITE_PERCENTILE)) if valid.any() else 1.0
    scale = scale if scale > 0 else 1.0
    diffuse, _, specular = observations_from_analyzers(analyzers, axis=-2)
    dolp, aolp = dolp_aolp(stokes)
    bright = valid & (s0 > dark_fraction * scale)
    mask = valid[..., None]
    images = {
        "s0": srgb_encode(s0_color / scale) * mask,
        "dolp": colormaps["viridis"](dolp)[..., :3] * bright[..., None],
        "aolp": aolp_colors(aolp) * bright[..., None],
        "diffuse": srgb_encode(diffuse / scale) * mask,
        "specular": srgb_encode(np.maximum(specular, 0) / scale) * mask,
    }
    return {kind: to_uint8(images[kind]) for kind in PREVIEW_KINDS}


def write_previews(hdr_path: str | Path, output: str | Path) -> Path:
    """Write the previews of every view of ``hdr_path`` into the folder ``output``."""
    import imageio.v3 as iio

    hdr = read_hdr(hdr_path)
    done = progress_logger(len(hdr.view_ids), "previewed views", log)
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        for count, view_id in enumerate(hdr.view_ids, start=1):
            for kind, image in preview_images(*hdr.view(view_id)).items():
                iio.imwrite(tmp / f"{view_id}_{kind}.png", image)
            done(count)
    return Path(output)
