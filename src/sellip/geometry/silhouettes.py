"""Silhouettes of the object in the HDR views: the level above the background's noise floor, the
masks, and signed distances to their boundary (to a fraction of a pixel).

Images are (V, H, W[, C]) batch first; pixel centres at integer coordinates (OpenCV).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

# --------------------------------------------------------------------------- silhouettes


def _disk(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius


BACKGROUND_NOISE_SIGMAS = 5.0  # a silhouette level at least this many noise sd above the background (silhouette_level)
BACKGROUND_BINS = 200  # histogram bins over the darker half of a view's pixels that find its background peak


def background_noise(luminance: np.ndarray, usable: np.ndarray) -> tuple[float, float]:
    """The background (the peak of the histogram of the darker half of the ``usable`` pixels of a (H, W)
    ``luminance``) and its noise sd, from the pixels below the peak (object pixels lie above it):
    1.4826 times their median distance to it. A flash photograph's background is dark noise (DESIGN §2)."""
    values = luminance[usable]
    if values.size == 0:
        return 0.0, 0.0
    low, middle = np.percentile(values, [0.5, 50])
    if middle <= low:  # half the pixels have one value (an exactly black background): no noise to measure
        return float(middle), 0.0
    counts, edges = np.histogram(values[(values >= low) & (values <= middle)], BACKGROUND_BINS)
    peak = int(np.argmax(counts))
    background = 0.5 * float(edges[peak] + edges[peak + 1])
    below = values[values < background]
    return background, 1.4826 * float(np.median(background - below)) if below.size else 0.0


@dataclass(frozen=True)
class SilhouetteOptions:
    """How a silhouette is cut (:func:`silhouette_masks`, :meth:`Silhouette.of`): ``threshold`` times the
    ``percentile`` of the pixels above the background's noise floor is the level (:func:`silhouette_level`); then an
    opening with a disk of ``open_px`` (noise specks), a closing with ``close_px`` (cracks), background holes
    smaller than ``max_hole_fraction`` of the object area filled, object blobs smaller than ``min_blob_fraction`` of
    the largest dropped (docs/geometry.md)."""

    threshold: float = 0.03
    percentile: float = 99.0
    open_px: int = 1
    close_px: int = 2
    max_hole_fraction: float = 0.02
    min_blob_fraction: float = 0.01


DEFAULT_SILHOUETTE = SilhouetteOptions()


def silhouette_level(image: np.ndarray, valid: np.ndarray | None = None,
                     threshold: float = DEFAULT_SILHOUETTE.threshold,
                     percentile: float = DEFAULT_SILHOUETTE.percentile) -> tuple[np.ndarray, float]:
    """The luminance (H, W) float32 (mean over channels of an (H, W) or (H, W, C) image, NaN as 0) and the level
    above which :func:`silhouette_masks` calls a pixel object: ``threshold`` times the ``percentile`` of the
    ``valid`` pixels above the background's noise floor (:func:`background_noise`, :data:`BACKGROUND_NOISE_SIGMAS`
    sd above it; of the positive ones where none is above), and at least that floor; 0 for an image with no
    positive pixel.

    The floor: a dark object in a noisy view (the stability case ``dark_noisy``) is no brighter at 3 % of its
    highlight than its background, whose pixels the level alone called object (masks of 0.15 IoU with the true
    silhouettes; 0.94 with the floor, docs/geometry.md). The percentile over the pixels above it: over the
    positive pixels it counted the half of the background that noise makes positive, so the level of a photograph
    moved with its noise (the unbiased HDR merge counts fewer) and differed from that of a noise-free render of
    the same scene (the geometry update's prediction), whose background is exact: the photographs' silhouettes of
    the true model lay 0.05 px inside its render's, 0.008 px now (docs/geometry_update.md)."""
    image = np.asarray(image)
    luminance = image.mean(axis=-1) if image.ndim == 3 else image
    luminance = np.nan_to_num(luminance.astype(np.float32), nan=0.0)
    considered = np.ones(luminance.shape, bool) if valid is None else np.asarray(valid, bool)
    usable = (luminance > 0) & considered
    if not usable.any():
        return luminance, 0.0
    background, noise = background_noise(luminance, considered)
    floor = background + BACKGROUND_NOISE_SIGMAS * noise
    above = considered & (luminance > max(floor, 0.0))
    return luminance, max(float(threshold * np.percentile(luminance[above if above.any() else usable], percentile)),
                          floor)


def silhouette_masks(images: np.ndarray, valid: np.ndarray | None = None, **options) -> np.ndarray:
    """Object silhouettes of flash photographs (the lit object against a dark background).

    images: (V, H, W) or (V, H, W, C) linear intensities (e.g. I_d); valid: optional (V, H, W) bool
    (invalid pixels, e.g. saturated highlights, count as object when a neighbour is object).
    A pixel is object when its mean over channels exceeds ``threshold`` times the view's robust
    maximum (the ``percentile`` of its valid pixels above the background's noise floor) and that floor
    (:func:`silhouette_level`). Cleanup per view: opening with a
    disk of ``open_px`` (noise specks), closing with ``close_px`` (cracks), background holes
    smaller than ``max_hole_fraction`` of the object area filled (dark texture inside the object;
    larger holes such as a torus's are kept), object blobs smaller than ``min_blob_fraction`` of
    the largest removed: ``options`` are fields of :class:`SilhouetteOptions` (its defaults otherwise).
    Returns (V, H, W) bool.
    """
    cut = dataclasses.replace(DEFAULT_SILHOUETTE, **options)
    images = np.asarray(images)
    masks = np.zeros(images.shape[:3], bool)
    for k in range(len(images)):
        view_valid = None if valid is None else valid[k]
        luminance, level = silhouette_level(images[k], view_valid, cut.threshold, cut.percentile)
        masks[k] = _cut(luminance, level, view_valid, cut)
    return masks


def _cut(luminance: np.ndarray, level: float, valid: np.ndarray | None, cut: SilhouetteOptions) -> np.ndarray:
    """One view's mask of :func:`silhouette_masks` from its luminance (H, W) and level (all False at level 0)."""
    if level <= 0:
        return np.zeros(luminance.shape, bool)
    mask = luminance > level
    if valid is not None:
        mask |= ~np.asarray(valid, bool) & ndimage.binary_dilation(mask)
    if cut.open_px:
        mask = ndimage.binary_opening(mask, _disk(cut.open_px))
    if cut.close_px:
        c = cut.close_px
        mask = ndimage.binary_closing(np.pad(mask, c), _disk(c))[c:-c, c:-c]
    return _clean_components(mask, cut.max_hole_fraction, cut.min_blob_fraction)


def _clean_components(mask: np.ndarray, max_hole_fraction: float, min_blob_fraction: float) -> np.ndarray:
    """Fill small enclosed background holes and drop small object blobs of one (H, W) mask."""
    labels, count = ndimage.label(mask)
    if count == 0:
        return mask
    sizes = ndimage.sum_labels(np.ones_like(mask), labels, index=np.arange(1, count + 1))
    keep = np.concatenate([[False], sizes >= min_blob_fraction * sizes.max()])
    mask = keep[labels]
    holes, hole_count = ndimage.label(~mask)
    if hole_count:
        hole_sizes = ndimage.sum_labels(np.ones_like(mask), holes, index=np.arange(1, hole_count + 1))
        border = np.unique(np.concatenate([holes[0], holes[-1], holes[:, 0], holes[:, -1]]))
        small = np.concatenate([[False], hole_sizes < max_hole_fraction * mask.sum()])
        small[border] = False
        mask = mask | small[holes]
    return mask


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 distance in pixels from each pixel centre to the boundary of the (H, W) bool ``mask``,
    negative inside. The boundary lies half a pixel outside the mask's outermost pixel centres."""
    mask = np.asarray(mask, bool)
    inside = ndimage.distance_transform_edt(mask)
    outside = ndimage.distance_transform_edt(~mask)
    return np.where(mask, 0.5 - inside, outside - 0.5).astype(np.float32)


@dataclass(frozen=True)
class Silhouette:
    """One view's silhouette: the ``mask`` (H, W) bool of :func:`silhouette_masks`, and the ``luminance`` (H, W)
    and ``level`` it was cut at, which place its boundary to a fraction of a pixel (:func:`boundary_distance`)."""

    mask: np.ndarray
    luminance: np.ndarray
    level: float

    @staticmethod
    def of(image: np.ndarray, valid: np.ndarray | None = None, **options) -> Silhouette:
        """The silhouette of one (H, W) or (H, W, C) image; ``options``: fields of :class:`SilhouetteOptions`."""
        cut = dataclasses.replace(DEFAULT_SILHOUETTE, **options)
        luminance, level = silhouette_level(image, valid, cut.threshold, cut.percentile)
        return Silhouette(_cut(luminance, level, valid, cut), luminance, level)

    @functools.cached_property
    def distance(self) -> np.ndarray:
        """(H, W) :func:`signed_distance` of the mask (computed once)."""
        return signed_distance(self.mask)


def boundary_distance(silhouette: Silhouette, points: np.ndarray, outward: np.ndarray, reach_px: float = 1.5,
                      step_px: float = 0.125) -> np.ndarray:
    """(K,) signed distance in pixels (negative inside) from points (K, 2) (column, row; pixel centres at integers)
    to the ``silhouette``'s boundary along the unit directions ``outward`` (K, 2): where the luminance, bilinear
    between pixel centres, falls through the level. Of such crossings within ``reach_px`` of the mask's own
    boundary (:func:`signed_distance`), the nearest to it; where there is none, the mask's distance.

    The mask's distance is quantised by its pixels (a straight edge at an angle is a staircase, up to half a
    pixel off); the crossing is not."""
    points, outward = np.asarray(points, np.float64), np.asarray(outward, np.float64)
    coarse = ndimage.map_coordinates(silhouette.distance, points[:, ::-1].T, order=1, mode="nearest")
    steps = np.arange(-reach_px, reach_px + step_px / 2, step_px)
    along = -coarse[:, None] + steps[None, :]  # (K, S): where the mask puts the boundary, and around it
    where = points[:, None, :] + along[..., None] * outward[:, None, :]
    level = ndimage.map_coordinates(silhouette.luminance, [where[..., 1].ravel(), where[..., 0].ravel()], order=1,
                                    mode="nearest").reshape(along.shape) - silhouette.level
    falls = (level[:, :-1] > 0) & (level[:, 1:] <= 0)
    fraction = level[:, :-1] / np.where(falls, level[:, :-1] - level[:, 1:], 1.0)
    crossing = np.where(falls, along[:, :-1] + fraction * step_px, np.inf)
    nearest = np.argmin(np.abs(crossing + coarse[:, None]), axis=1)
    best = crossing[np.arange(len(points)), nearest]
    return np.where(np.isfinite(best), -best, coarse)


