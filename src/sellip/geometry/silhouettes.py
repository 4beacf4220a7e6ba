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

from sellip.settings import setting

# --------------------------------------------------------------------------- silhouettes


def disk(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius


BACKGROUND_NOISE_SIGMAS = 5.0  # a silhouette level at least this many noise sd above the background (silhouette_level)
BACKGROUND_BINS = 200  # histogram bins over the darker half of a view's pixels that find its background peak


def background_noise(luminance: np.ndarray, usable: np.ndarray) -> tuple[float, float]:
    """The background (the peak of the histogram of the darker half of the ``usable`` pixels of a (H, W)
    ``luminance``) and its noise sd, from the pixels below the peak (object pixels lie above it):
    1.4826 times their median distance to it. A flash photograph's background is dark noise (docs/design.md §2)."""
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
    """How a silhouette is cut (config section ``silhouette``: its ``threshold``, the one field the workflow sets;
    :func:`silhouette_masks`, :meth:`Silhouette.of`): ``threshold`` times the
    ``percentile`` of the pixels above the background's noise floor is the level (:func:`silhouette_level`); then an
    opening with a disk of ``open_px`` (noise specks), a closing with ``close_px`` (cracks), background holes
    smaller than ``max_hole_fraction`` of the object area filled, object blobs smaller than ``min_blob_fraction`` of
    the largest dropped (docs/geometry.md). Where the object is darker than that level (a black patch on a white
    figure), a pixel is object too when it exceeds ``local_fraction`` of the brightest pixel within ``local_px``
    and is connected to the pixels above the level (:func:`level_map`); ``local_fraction`` 0 turns that off."""

    threshold: float = setting(0.03, "object where the luminance exceeds this fraction of the view's robust maximum "
                               "(the percentile of the pixels above the background's noise floor)", exclusive_minimum=0,
                               exclusive_maximum=1)
    percentile: float = 99.0
    local_fraction: float = 0.1
    local_px: int = 2
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
    luminance, level, _ = _levels(image, valid, threshold, percentile)
    return luminance, level


def _levels(image: np.ndarray, valid: np.ndarray | None, threshold: float,
            percentile: float) -> tuple[np.ndarray, float, float]:
    """(luminance, level, noise floor) of :func:`silhouette_level` (level and floor 0 with no positive pixel)."""
    image = np.asarray(image)
    luminance = image.mean(axis=-1) if image.ndim == 3 else image
    luminance = np.nan_to_num(luminance.astype(np.float32), nan=0.0)
    considered = np.ones(luminance.shape, bool) if valid is None else np.asarray(valid, bool)
    usable = (luminance > 0) & considered
    if not usable.any():
        return luminance, 0.0, 0.0
    background, noise = background_noise(luminance, considered)
    floor = max(background + BACKGROUND_NOISE_SIGMAS * noise, 0.0)
    above = considered & (luminance > floor)
    level = max(float(threshold * np.percentile(luminance[above if above.any() else usable], percentile)), floor)
    return luminance, level, floor


def level_map(luminance: np.ndarray, level: float, floor: float,
              local_fraction: float = DEFAULT_SILHOUETTE.local_fraction,
              local_px: int = DEFAULT_SILHOUETTE.local_px) -> np.ndarray:
    """(H, W) float32 per-pixel level of a (H, W) ``luminance``: the view's ``level`` (:func:`silhouette_level`),
    except in dim neighbourhoods, where ``local_fraction`` of the brightest pixel within ``local_px`` (a square
    window) is below half of it: there that, and never below the background's noise ``floor``.

    A black patch on the outline of a white figure (ρ_d 0.03 against 0.7: below 3 % of the view's maximum once
    foreshortened) is cut at a tenth of its own brightness, so it stays object; an outline bright enough for the
    view's level keeps it, so its sub-pixel placement (:func:`boundary_distance`) is unchanged (the dim limb of
    ``test_boundary_distance_measures_a_sub_pixel_shift_of_a_dim_limb``: the lowered level wherever it was below
    the view's level moved the limb's crossings by 0.15 px RMS instead of 0.13). The window reaches past the lens
    blur into the patch's plateau. The cow's silhouettes: IoU with the true ones 0.75 at the view's level alone,
    0.92 with this map; a uniform sphere's the same 0.99 (docs/geometry.md)."""
    luminance = np.asarray(luminance, np.float32)
    if local_fraction <= 0:
        return np.full(luminance.shape, max(level, floor), np.float32)
    lowered = local_fraction * ndimage.maximum_filter(luminance, size=2 * local_px + 1, mode="nearest")
    return np.maximum(np.where(lowered < 0.5 * level, lowered, level), floor).astype(np.float32)


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
        masks[k] = _silhouette(images[k], view_valid, cut)[0]
    return masks


def _silhouette(image: np.ndarray, valid: np.ndarray | None,
                cut: SilhouetteOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mask, luminance, level map) of one (H, W[, C]) view: :func:`silhouette_masks` for one image."""
    luminance, level, floor = _levels(image, valid, cut.threshold, cut.percentile)
    levels = level_map(luminance, level, floor, cut.local_fraction, cut.local_px)
    return _cut(luminance, level, levels, valid, cut), luminance, levels


def _cut(luminance: np.ndarray, level: float, levels: np.ndarray, valid: np.ndarray | None,
         cut: SilhouetteOptions) -> np.ndarray:
    """One view's mask of :func:`silhouette_masks` from its luminance (H, W), the view's level and the level map
    (H, W) of :func:`level_map` (all False at level 0): the pixels above the map, in connected parts that come within
    ``local_px`` + 1 pixels of one above the view's level (a dim background apart from the object is not object
    because the map reaches down to its noise floor; a dark patch beside a bright one is, across the band of
    ``local_px`` where the bright one's level holds)."""
    if level <= 0:
        return np.zeros(luminance.shape, bool)
    mask = luminance > levels
    if cut.local_fraction > 0:
        parts, count = ndimage.label(mask)
        if count:
            seeded = np.zeros(count + 1, bool)
            seeds = ndimage.binary_dilation(luminance > level, iterations=cut.local_px + 1)
            seeded[np.unique(parts[seeds])] = True
            seeded[0] = False
            mask = seeded[parts]
    if valid is not None:
        mask |= ~np.asarray(valid, bool) & ndimage.binary_dilation(mask)
    if cut.open_px:
        mask = ndimage.binary_opening(mask, disk(cut.open_px))
    if cut.close_px:
        c = cut.close_px
        mask = ndimage.binary_closing(np.pad(mask, c), disk(c))[c:-c, c:-c]
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
    and the ``level`` (H, W) it was cut at (:func:`level_map`), which place its boundary to a fraction of a pixel
    (:func:`boundary_distance`)."""

    mask: np.ndarray
    luminance: np.ndarray
    level: np.ndarray

    @staticmethod
    def of(image: np.ndarray, valid: np.ndarray | None = None, **options) -> Silhouette:
        """The silhouette of one (H, W) or (H, W, C) image; ``options``: fields of :class:`SilhouetteOptions`."""
        return Silhouette(*_silhouette(image, valid, dataclasses.replace(DEFAULT_SILHOUETTE, **options)))

    @functools.cached_property
    def distance(self) -> np.ndarray:
        """(H, W) :func:`signed_distance` of the mask (computed once)."""
        return signed_distance(self.mask)

    @functools.cached_property
    def excess(self) -> np.ndarray:
        """(H, W) luminance above the level (negative below; computed once)."""
        return self.luminance - self.level


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
    level = ndimage.map_coordinates(silhouette.excess, [where[..., 1].ravel(), where[..., 0].ravel()], order=1,
                                    mode="nearest").reshape(along.shape)
    falls = (level[:, :-1] > 0) & (level[:, 1:] <= 0)
    fraction = level[:, :-1] / np.where(falls, level[:, :-1] - level[:, 1:], 1.0)
    crossing = np.where(falls, along[:, :-1] + fraction * step_px, np.inf)
    nearest = np.argmin(np.abs(crossing + coarse[:, None]), axis=1)
    best = crossing[np.arange(len(points)), nearest]
    return np.where(np.isfinite(best), -best, coarse)


