"""Geometry kernels of the bootstrap stages (DESIGN §2 sfm, mesh_init; §8 geometry figures).

Public API::

    Similarity(scale, rotation, translation)          # x' = s R x + t; .apply(points), .apply_to_poses(R, t)
    umeyama(source, target, with_scale=True, weights=None) -> Similarity
    align_cameras(rotations, translations, ref_rotations, ref_translations, with_scale=True,
                  trim=3.0) -> Similarity                  # robust Umeyama on camera centres
    pose_errors(rotations, translations, ref_rotations, ref_translations) -> (rotation_deg (N,), centre (N,))
    surface_samples(vertices, faces, count, seed=0) -> (count, 3)
    mesh_distances(vertices_a, faces_a, vertices_b, faces_b, count=50000, seed=0) -> MeshDistances
    silhouette_masks(images, valid=None, threshold=0.03, ...) -> (V, H, W) bool
    silhouette_level(image, valid=None, threshold=0.03, percentile=99) -> (luminance (H, W), level)
    background_noise(luminance, usable) -> (background, noise sd)
    Silhouette(mask, luminance, level); Silhouette.of(image, valid=None, **mask_options)
    signed_distance(mask) -> (H, W)                      # pixels, negative inside
    boundary_distance(silhouette, points, outward) -> (K,)   # the same, to a fraction of a pixel
    VoxelGrid(origin, voxel_size, shape)                 # .centers(), .from_bounds(lo, hi, resolution)
    view_volume_bounds(intrinsics, rotations, translations, width, height) -> (lo (3,), hi (3,))
    carve(masks, intrinsics, rotations, translations, grid, min_inside_fraction=0.9, min_views=3) -> Carving
    visual_hull(masks, intrinsics, rotations, translations, resolution=128, ...) -> Carving
    surface_points(occupancy, grid, smoothing_voxels=1.0) -> (points (N, 3), normals (N, 3))
    occluding_points(points, sparse_points, sparse_views, intrinsics, rotations, translations, ...) -> (N,) bool
    estimate_normals(points, towards, neighbours=12) -> (N, 3)
    poisson_surface(points, normals, depth=7, trim_density=...) -> (vertices, faces)
    largest_component(vertices, faces) -> (vertices, faces)
    remesh_to_count(vertices, faces, target_vertices, iterations=6) -> (vertices, faces)
    depth_vertex_count(vertices_at_depth, depth, target_depth) -> int
    mesh_area(vertices, faces) -> float
    vertex_normals(vertices, faces) -> (V, 3)
    mesh_edges(faces) -> (E, 2)
    blend_normals(fitted, geometric, confidence) -> (N, 3)
    SilhouetteConstraints(vertex, direction, offset, pixel)
    silhouette_constraints(vertices, normals, intrinsics, rotation, translation, observed, predicted, ...)
    refine_from_normals(vertices, faces, fitted_normals, confidence, smoothness=0.01, anchor=1e-3,
                        rounds=3, reference=None, silhouettes=None, silhouette_weight=0.01,
                        smoothness_unconfident=1.0) -> (V, 3)   # the geometry update: normal integration
    InitMeshOptions(...); initial_mesh(masks, intrinsics, rotations, translations, options, sparse_points=None,
                                       sparse_views=None, sparse_errors=None, extra_points=None) -> InitialMesh
    orient_outward(vertices, faces, normals=None) -> (faces, consistent)
    resample_to_count(vertices, faces, target_vertices) -> (vertices, faces)
    check_against_silhouettes(vertices, masks, intrinsics, rotations, translations, carving, ...) -> MeshCheck
    user_initial_mesh(vertices, faces, masks, intrinsics, rotations, translations, options,
                      normals=None) -> InitialMesh      # init.mode mesh: a scan, resampled and checked

Conventions: metres; poses are COLMAP cam_from_world ``x_cam = R x_world + t`` (sellip.conventions);
intrinsics are OpenCV K with pixel centres at integer coordinates; images are (V, H, W[, C]),
batch first. Every function is pure (no I/O); open3d and pymeshlab are used as numerical libraries.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from sellip.conventions import camera_center, camera_forward

# --------------------------------------------------------------------------- Sim(3)


@dataclass(frozen=True)
class Similarity:
    """A similarity transform of world points: ``x' = scale * rotation @ x + translation``."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    @staticmethod
    def identity() -> Similarity:
        return Similarity(1.0, np.eye(3), np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transformed points (..., 3)."""
        return self.scale * np.einsum("ij,...j->...i", self.rotation, points) + self.translation

    def apply_to_poses(self, rotations: np.ndarray, translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """cam_from_world poses (..., 3, 3), (..., 3) expressed in the transformed world.

        Camera coordinates are scaled with the world (projections are unchanged):
        ``R' = R S^T``, ``t' = s t - R' T`` for the similarity (s, S, T).
        """
        new_rotations = np.einsum("...ij,kj->...ik", rotations, self.rotation)
        new_translations = self.scale * translations - np.einsum("...ij,j->...i", new_rotations, self.translation)
        return new_rotations, new_translations

    def inverse(self) -> Similarity:
        rotation = self.rotation.T
        return Similarity(1.0 / self.scale, rotation, -rotation @ self.translation / self.scale)

    def compose(self, first: Similarity) -> Similarity:
        """The transform that applies ``first``, then ``self``."""
        return Similarity(self.scale * first.scale, self.rotation @ first.rotation,
                          self.scale * self.rotation @ first.translation + self.translation)


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True,
            weights: np.ndarray | None = None) -> Similarity:
    """Least-squares similarity with ``target ≈ s R source + t`` (Umeyama 1991). source, target (N, 3), N >= 3.

    weights: optional (N,) non-negative weights. Without scale, s = 1 (a rigid fit).
    """
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    w = np.ones(len(source)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mu_s, mu_t = w @ source, w @ target
    xs, xt = source - mu_s, target - mu_t
    covariance = (w[:, None] * xt).T @ xs
    u, d, vt = np.linalg.svd(covariance)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = (u * sign) @ vt
    variance = w @ np.sum(xs * xs, axis=1)
    scale = float((d * sign).sum() / variance) if with_scale else 1.0
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def align_cameras(rotations: np.ndarray, translations: np.ndarray, ref_rotations: np.ndarray,
                  ref_translations: np.ndarray, with_scale: bool = True, trim: float = 3.0) -> Similarity:
    """The similarity that maps the world of the first poses onto the reference world.

    Umeyama on camera centres, refit once without the centres whose residual exceeds ``trim``
    times the median residual (a few grossly wrong poses do not bias it). Poses (N, 3, 3), (N, 3).
    """
    centers = camera_center(np.asarray(rotations, np.float64), np.asarray(translations, np.float64))
    ref_centers = camera_center(np.asarray(ref_rotations, np.float64), np.asarray(ref_translations, np.float64))
    transform = umeyama(centers, ref_centers, with_scale)
    residual = np.linalg.norm(transform.apply(centers) - ref_centers, axis=1)
    keep = residual <= trim * max(np.median(residual), 1e-12)
    if 3 <= keep.sum() < len(keep):
        transform = umeyama(centers[keep], ref_centers[keep], with_scale)
    return transform


def pose_errors(rotations: np.ndarray, translations: np.ndarray, ref_rotations: np.ndarray,
                ref_translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per camera: rotation error (deg, angle of R R_ref^T) and camera-centre distance (world units). (N,) each."""
    # ||R - R_ref||_F = 2 sqrt(2) sin(angle / 2): accurate for small angles, unlike arccos of the trace.
    chord = np.linalg.norm(rotations - ref_rotations, axis=(-2, -1)) / (2 * np.sqrt(2))
    centers = camera_center(rotations, translations)
    ref_centers = camera_center(ref_rotations, ref_translations)
    return np.degrees(2 * np.arcsin(np.clip(chord, 0.0, 1.0))), np.linalg.norm(centers - ref_centers, axis=-1)


# --------------------------------------------------------------------------- mesh distances


def surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) points drawn uniformly (by area) on a triangle mesh."""
    rng = np.random.default_rng(seed)
    a, b, c = (np.asarray(vertices, np.float64)[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    face = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    return ((1 - r1)[:, None] * a[face] + (r1 * (1 - r2))[:, None] * b[face] + (r1 * r2)[:, None] * c[face])


def _distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) unsigned distance of each point to the nearest point of a triangle mesh (exact, open3d)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy().astype(np.float64)


@dataclass(frozen=True)
class MeshDistances:
    """Surface-to-surface distances between meshes A and B (world units).

    a_to_b / b_to_a: mean distance of samples of one surface to the other surface;
    chamfer: their average; hausdorff: the largest sample distance either way;
    b_to_a_p95: 95th percentile of B-to-A distances.
    """

    a_to_b: float
    b_to_a: float
    chamfer: float
    hausdorff: float
    b_to_a_p95: float


def mesh_distances(vertices_a: np.ndarray, faces_a: np.ndarray, vertices_b: np.ndarray, faces_b: np.ndarray,
                   count: int = 50000, seed: int = 0) -> MeshDistances:
    """Chamfer (mean of both directed mean distances) and Hausdorff distance between two meshes.

    ``count`` area-uniform samples per surface are measured against the other surface exactly.
    """
    from_a = _distance_to_mesh(surface_samples(vertices_a, faces_a, count, seed), vertices_b, faces_b)
    from_b = _distance_to_mesh(surface_samples(vertices_b, faces_b, count, seed + 1), vertices_a, faces_a)
    return MeshDistances(a_to_b=float(from_a.mean()), b_to_a=float(from_b.mean()),
                         chamfer=float(0.5 * (from_a.mean() + from_b.mean())),
                         hausdorff=float(max(from_a.max(), from_b.max())),
                         b_to_a_p95=float(np.percentile(from_b, 95)))


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


def silhouette_level(image: np.ndarray, valid: np.ndarray | None = None, threshold: float = 0.03,
                     percentile: float = 99.0) -> tuple[np.ndarray, float]:
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


def silhouette_masks(images: np.ndarray, valid: np.ndarray | None = None, threshold: float = 0.03,
                     percentile: float = 99.0, open_px: int = 1, close_px: int = 2,
                     max_hole_fraction: float = 0.02, min_blob_fraction: float = 0.01) -> np.ndarray:
    """Object silhouettes of flash photographs (the lit object against a dark background).

    images: (V, H, W) or (V, H, W, C) linear intensities (e.g. I_d); valid: optional (V, H, W) bool
    (invalid pixels, e.g. saturated highlights, count as object when a neighbour is object).
    A pixel is object when its mean over channels exceeds ``threshold`` times the view's robust
    maximum (the ``percentile`` of its valid pixels above the background's noise floor) and that floor
    (:func:`silhouette_level`). Cleanup per view: opening with a
    disk of ``open_px`` (noise specks), closing with ``close_px`` (cracks), background holes
    smaller than ``max_hole_fraction`` of the object area filled (dark texture inside the object;
    larger holes such as a torus's are kept), object blobs smaller than ``min_blob_fraction`` of
    the largest removed. Returns (V, H, W) bool.
    """
    images = np.asarray(images)
    masks = np.zeros(images.shape[:3], bool)
    for k in range(len(images)):
        view_valid = None if valid is None else valid[k]
        luminance, level = silhouette_level(images[k], view_valid, threshold, percentile)
        masks[k] = _cut(luminance, level, view_valid, open_px, close_px, max_hole_fraction, min_blob_fraction)
    return masks


def _cut(luminance: np.ndarray, level: float, valid: np.ndarray | None, open_px: int, close_px: int,
         max_hole_fraction: float, min_blob_fraction: float) -> np.ndarray:
    """One view's mask of :func:`silhouette_masks` from its luminance (H, W) and level (all False at level 0)."""
    if level <= 0:
        return np.zeros(luminance.shape, bool)
    mask = luminance > level
    if valid is not None:
        mask |= ~np.asarray(valid, bool) & ndimage.binary_dilation(mask)
    if open_px:
        mask = ndimage.binary_opening(mask, _disk(open_px))
    if close_px:
        mask = ndimage.binary_closing(np.pad(mask, close_px), _disk(close_px))[close_px:-close_px, close_px:-close_px]
    return _clean_components(mask, max_hole_fraction, min_blob_fraction)


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


# --------------------------------------------------------------------------- visual hull


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid: voxel (i, j, k) is centred at ``origin + voxel_size * (i, j, k)``. shape (3,) ints."""

    origin: np.ndarray
    voxel_size: float
    shape: tuple[int, int, int]

    @staticmethod
    def from_bounds(lo: np.ndarray, hi: np.ndarray, resolution: int) -> VoxelGrid:
        """A grid covering the box [lo, hi] with ``resolution`` voxels along its longest side."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        size = float((hi - lo).max()) / resolution
        shape = tuple(int(n) for n in np.maximum(np.ceil((hi - lo) / size), 1))
        center = 0.5 * (lo + hi)
        origin = center - 0.5 * size * (np.array(shape) - 1)
        return VoxelGrid(origin, size, shape)

    def centers(self) -> np.ndarray:
        """(X, Y, Z, 3) voxel centres."""
        axes = [self.origin[d] + self.voxel_size * np.arange(self.shape[d]) for d in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def bounds_of(self, occupancy: np.ndarray, margin_voxels: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
        """Box (lo, hi) around the occupied voxels' extents, widened by ``margin_voxels`` voxels."""
        index = np.argwhere(occupancy)
        lo = self.origin + self.voxel_size * (index.min(axis=0) - 0.5 - margin_voxels)
        hi = self.origin + self.voxel_size * (index.max(axis=0) + 0.5 + margin_voxels)
        return lo, hi


def view_volume_bounds(intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                       width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """A box (lo, hi) that contains what all cameras look at.

    The centre is the least-squares intersection of the optical axes; the half-size is the
    largest half-width of a view's frustum at its distance to that point. intrinsics (V, 3, 3) or (3, 3).
    """
    rotations = np.asarray(rotations, np.float64)
    centers = camera_center(rotations, np.asarray(translations, np.float64))
    axes = camera_forward(rotations)
    projector = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # (V, 3, 3)
    target = np.linalg.solve(projector.sum(axis=0), np.einsum("vij,vj->i", projector, centers))
    k = np.broadcast_to(np.asarray(intrinsics, np.float64), (len(rotations), 3, 3))
    half_fov = np.maximum(width / (2 * k[:, 0, 0]), height / (2 * k[:, 1, 1]))
    distance = np.einsum("vi,vi->v", target - centers, axes)
    half = float(np.max(distance * half_fov))
    return target - half, target + half


def _project(points: np.ndarray, intrinsics: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """Pixel coordinates (N, 2) and depth (N,) of world points (N, 3) in one camera."""
    cam = points @ rotation.T.astype(points.dtype) + translation.astype(points.dtype)
    depth = cam[:, 2]
    safe = np.where(depth > 0, depth, 1.0)
    k = intrinsics.astype(points.dtype)
    u = k[0, 0] * cam[:, 0] / safe + k[0, 1] * cam[:, 1] / safe + k[0, 2]
    v = k[1, 1] * cam[:, 1] / safe + k[1, 2]
    return np.stack([u, v], axis=-1), depth


@dataclass(frozen=True)
class Carving:
    """Result of silhouette carving.

    grid: the VoxelGrid; occupancy: (X, Y, Z) bool, kept voxels; inside_fraction: (X, Y, Z) float32,
    fraction of the views that see a voxel in frame and have it inside their silhouette;
    disagreement: (V,) float, per view the fraction of kept voxels it sees in frame but outside its mask.
    """

    grid: VoxelGrid
    occupancy: np.ndarray
    inside_fraction: np.ndarray
    disagreement: np.ndarray


def carve(masks: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
          grid: VoxelGrid, min_inside_fraction: float = 0.9, min_views: int = 3) -> Carving:
    """Keep the voxels whose centre projects inside the silhouette in at least ``min_inside_fraction``
    of the views that see it in frame (and that at least ``min_views`` views see in frame).

    masks (V, H, W) bool; intrinsics (V, 3, 3) or (3, 3); rotations (V, 3, 3); translations (V, 3).
    A fraction below 1 makes the hull robust to a few bad masks (a dark patch cut out of one view).
    """
    count, height, width = masks.shape
    k = np.broadcast_to(np.asarray(intrinsics, np.float64), (count, 3, 3))
    centers = grid.centers().reshape(-1, 3).astype(np.float32)
    in_frame = np.zeros(len(centers), np.int32)
    inside = np.zeros(len(centers), np.int32)
    for view in range(count):
        pixels, depth = _project(centers, k[view], rotations[view], translations[view])
        col, row = np.rint(pixels[:, 0]).astype(np.int64), np.rint(pixels[:, 1]).astype(np.int64)
        seen = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        in_frame += seen
        inside[seen] += masks[view][row[seen], col[seen]]
    fraction = inside / np.maximum(in_frame, 1)
    occupancy = (in_frame >= min(min_views, count)) & (fraction >= min_inside_fraction - 1e-9)
    disagreement = np.zeros(count)
    kept = centers[occupancy]
    for view in range(count):
        pixels, depth = _project(kept, k[view], rotations[view], translations[view])
        col, row = np.rint(pixels[:, 0]).astype(np.int64), np.rint(pixels[:, 1]).astype(np.int64)
        seen = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        if seen.any():
            disagreement[view] = 1.0 - masks[view][row[seen], col[seen]].mean()
    return Carving(grid, occupancy.reshape(grid.shape), fraction.reshape(grid.shape).astype(np.float32),
                   disagreement)


def visual_hull(masks: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                resolution: int = 128, coarse_resolution: int = 48, min_inside_fraction: float = 0.9,
                min_views: int = 3, bounds: tuple[np.ndarray, np.ndarray] | None = None,
                margin_voxels: float = 2.0) -> Carving:
    """Silhouette carving in two passes: a coarse grid over ``bounds`` (default: the cameras' common
    view volume), then ``resolution`` voxels along the longest side of the coarse hull's box.

    See :func:`carve` for the arguments. Raises ValueError when nothing survives the coarse pass.
    """
    height, width = masks.shape[1:]
    lo, hi = bounds if bounds is not None else view_volume_bounds(intrinsics, rotations, translations, width, height)
    coarse = carve(masks, intrinsics, rotations, translations, VoxelGrid.from_bounds(lo, hi, coarse_resolution),
                   min_inside_fraction, min_views)
    if not coarse.occupancy.any():
        raise ValueError("silhouette carving removed every voxel: the masks and the poses disagree")
    lo, hi = coarse.grid.bounds_of(coarse.occupancy, margin_voxels)
    return carve(masks, intrinsics, rotations, translations, VoxelGrid.from_bounds(lo, hi, resolution),
                 min_inside_fraction, min_views)


def surface_points(occupancy: np.ndarray, grid: VoxelGrid, smoothing_voxels: float = 1.0) -> tuple[np.ndarray,
                                                                                                 np.ndarray]:
    """Oriented points on the boundary of an occupancy grid.

    The occupancy is smoothed with a Gaussian of ``smoothing_voxels``; points are the 0.5 crossings on
    the grid edges (the vertices marching cubes would make), normals the normalized negative gradient
    there (pointing out of the object). Returns points (N, 3) and unit normals (N, 3).
    """
    field = ndimage.gaussian_filter(np.pad(occupancy.astype(np.float32), 2), smoothing_voxels)
    gradient = np.stack(np.gradient(field), axis=-1)
    points, normals = [], []
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        fa, fb = field[tuple(a)], field[tuple(b)]
        crossing = (fa - 0.5) * (fb - 0.5) < 0
        index = np.argwhere(crossing)
        t = ((0.5 - fa[crossing]) / (fb[crossing] - fa[crossing]))[:, None]
        step = np.zeros(3)
        step[axis] = 1.0
        position = index + t * step
        grad = (1 - t) * gradient[tuple(a)][crossing] + t * gradient[tuple(b)][crossing]
        points.append(grid.origin + grid.voxel_size * (position - 2))
        normals.append(-grad)
    points, normals = np.concatenate(points), np.concatenate(normals)
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-6
    return points[ok], normals[ok] / length[ok, None]


# --------------------------------------------------------------------------- fusion with sparse points


def occluding_points(points: np.ndarray, sparse_points: np.ndarray, sparse_views: list[np.ndarray],
                     intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                     radius_px: float = 2.0, depth_margin: float = 0.0, min_views: int = 2) -> np.ndarray:
    """Which points hide an observed sparse point: (N,) bool.

    A point occludes a sparse point in view v when v observed that sparse point, the point projects
    within ``radius_px`` of it and lies more than ``depth_margin`` in front of it. Points that occlude
    in at least ``min_views`` views are free space that the silhouettes could not carve (a concavity).
    sparse_views[j]: the view indices that observed sparse point j.
    """
    count = len(rotations)
    k = np.broadcast_to(np.asarray(intrinsics, np.float64), (count, 3, 3))
    observed_in = [[] for _ in range(count)]
    for j, views in enumerate(sparse_views):
        for view in views:
            observed_in[int(view)].append(j)
    votes = np.zeros(len(points), np.int32)
    for view in range(count):
        if not observed_in[view]:
            continue
        index = np.asarray(observed_in[view])
        sparse_px, sparse_depth = _project(sparse_points[index], k[view], rotations[view], translations[view])
        px, depth = _project(points, k[view], rotations[view], translations[view])
        tree = cKDTree(sparse_px)
        neighbours = tree.query_ball_point(px, radius_px)
        nearest_depth = np.array([sparse_depth[n].max() if n else -np.inf for n in neighbours])
        votes += (depth > 0) & (depth < nearest_depth - depth_margin)
    return votes >= min_views


def estimate_normals(points: np.ndarray, towards: np.ndarray, neighbours: int = 12) -> np.ndarray:
    """Unit normals (N, 3) by PCA of each point's ``neighbours`` nearest points, flipped to face ``towards`` (N, 3)
    (e.g. the mean direction to the cameras that observed the point)."""
    count = min(neighbours, len(points))
    _, index = cKDTree(points).query(points, k=count)
    local = points[index] - points[index].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    normals = vectors[:, :, 0]
    flip = np.einsum("ni,ni->n", normals, towards) < 0
    normals[flip] *= -1
    return normals


# --------------------------------------------------------------------------- meshing


def poisson_surface(points: np.ndarray, normals: np.ndarray, depth: int = 7, trim_density: float = 2.0,
                    point_weight: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson reconstruction (open3d, Kazhdan & Hoppe 2013) of oriented points.

    Vertices whose Poisson density (about log2 of the local sample support) is more than ``trim_density``
    below the median are removed with their faces: surface the points do not support (2: less than a
    quarter of the typical support; SfM-only regions are sparser than hull points and must survive).
    Returns vertices (V, 3) float64 and faces (F, 3) int64.
    """
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=depth, point_weight=point_weight, n_threads=1)  # more threads: not deterministic
    density = np.asarray(density)
    if trim_density is not None and len(density):
        mesh.remove_vertices_by_mask(density < np.median(density) - trim_density)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)


def largest_component(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The connected component with the most faces; unreferenced vertices removed."""
    labels, count = _face_components(faces, len(vertices))
    if count > 1:
        faces = faces[labels == np.bincount(labels).argmax()]
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def _face_components(faces: np.ndarray, vertex_count: int) -> tuple[np.ndarray, int]:
    """Per-face component label (F,) of faces connected through shared vertices, and the count."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = mesh_edges(faces)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(vertex_count, vertex_count))
    _, vertex_labels = connected_components(graph, directed=False)
    labels = vertex_labels[faces[:, 0]]
    _, labels = np.unique(labels, return_inverse=True)
    return labels, int(labels.max()) + 1 if len(labels) else 0


def depth_vertex_count(vertices_at_depth: int, depth: int, target_depth: int) -> int:
    """Vertex count of a surface reconstructed at ``target_depth`` given the count at ``depth``:
    one octree level halves the cell size, so a surface has four times the vertices."""
    return int(round(vertices_at_depth * 4.0 ** (target_depth - depth)))


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def remesh_to_count(vertices: np.ndarray, faces: np.ndarray, target_vertices: int,
                    iterations: int = 6, attempts: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing (pymeshlab) to about ``target_vertices`` vertices of near-equilateral triangles.

    The edge length comes from the area (a regular triangulation has about two faces per vertex:
    ``L = sqrt(2 A / (sqrt(3) V))``) and is corrected once from the count actually reached.
    Returns vertices (V, 3) float64 and faces (F, 3) int64.
    """
    import pymeshlab

    area = mesh_area(vertices, faces)
    length = np.sqrt(2 * area / (np.sqrt(3) * target_vertices))
    out_vertices, out_faces = vertices, faces
    for _ in range(attempts):
        meshes = pymeshlab.MeshSet()
        meshes.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64),
                                       face_matrix=np.asarray(faces, np.int32)))
        meshes.meshing_isotropic_explicit_remeshing(iterations=iterations,
                                                    targetlen=pymeshlab.PureValue(float(length)),
                                                    featuredeg=180.0)
        mesh = meshes.current_mesh()
        out_vertices = mesh.vertex_matrix().astype(np.float64)
        out_faces = mesh.face_matrix().astype(np.int64)
        ratio = len(out_vertices) / target_vertices
        if abs(ratio - 1) < 0.1:
            break
        length *= np.sqrt(ratio)
    return out_vertices, out_faces


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3) of a mesh with counter-clockwise faces seen from outside (open3d)."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    mesh.compute_vertex_normals()
    return np.asarray(mesh.vertex_normals, np.float64)



def blend_normals(fitted: np.ndarray, geometric: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) between the ``fitted`` and the mesh's ``geometric`` normals (N, 3) by the
    fit's ``confidence`` (N,) in [0, 1]: a confident fit moves the surface, a failed one leaves it."""
    weight = np.clip(np.nan_to_num(confidence), 0, 1)[:, None]
    blended = weight * fitted + (1 - weight) * geometric
    length = np.linalg.norm(blended, axis=1, keepdims=True)
    return np.where(length > 1e-9, blended / np.maximum(length, 1e-12), geometric)


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """The unique undirected edges (E, 2) of a triangle mesh, each as (smaller, larger) vertex index."""
    faces = np.asarray(faces, np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0)


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
    def of(image: np.ndarray, valid: np.ndarray | None = None, threshold: float = 0.03, percentile: float = 99.0,
           open_px: int = 1, close_px: int = 2, max_hole_fraction: float = 0.02,
           min_blob_fraction: float = 0.01) -> Silhouette:
        """The silhouette of one (H, W) or (H, W, C) image; the options of :func:`silhouette_masks`."""
        luminance, level = silhouette_level(image, valid, threshold, percentile)
        return Silhouette(_cut(luminance, level, valid, open_px, close_px, max_hole_fraction, min_blob_fraction),
                          luminance, level)

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


@dataclass(frozen=True)
class SilhouetteConstraints:
    """Where the observed silhouettes put the mesh's contour (:func:`silhouette_constraints`).

    vertex: (K,) int, the contour vertex of each constraint; direction: (K, 3), the world direction g for which
    moving that vertex by dx moves its view's predicted silhouette outward by g . dx metres (at the vertex's
    depth); offset: (K,) metres, how far the observed silhouette lies outside the predicted one there; pixel: (K,)
    metres per pixel at the vertex's depth. The constraints were measured at the vertices given to
    :func:`silhouette_constraints`.
    """

    vertex: np.ndarray
    direction: np.ndarray
    offset: np.ndarray
    pixel: np.ndarray

    @staticmethod
    def concatenate(parts: list[SilhouetteConstraints]) -> SilhouetteConstraints:
        if not parts:
            return SilhouetteConstraints(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        return SilhouetteConstraints(*(np.concatenate([getattr(p, name) for p in parts])
                                       for name in ("vertex", "direction", "offset", "pixel")))

    @property
    def offset_px(self) -> np.ndarray:
        """(K,) the offsets in pixels."""
        return self.offset / self.pixel

    def __len__(self) -> int:
        return len(self.vertex)


def silhouette_constraints(vertices: np.ndarray, normals: np.ndarray, intrinsics: np.ndarray, rotation: np.ndarray,
                           translation: np.ndarray, observed: Silhouette | np.ndarray,
                           predicted: Silhouette | np.ndarray,
                           band_px: float = 1.0, max_cos: float = 0.3, min_alignment: float = 0.5,
                           max_offset_px: float = 3.0) -> SilhouetteConstraints:
    """The silhouette constraints of one view: vertices (V, 3) with unit normals (V, 3) on the mesh's contour,
    and how far the ``observed`` silhouette lies outside the ``predicted`` one (the mesh's, made by
    the same operator from a render of the current model, so that what the operator cuts from a dim limb cuts
    both alike) at each vertex's projection. Each is a :class:`Silhouette`, whose boundary is placed to a
    fraction of a pixel (:func:`boundary_distance`), or an (H, W) bool mask, whose boundary is its pixels'.

    A contour vertex projects within ``band_px`` of the predicted boundary, its normal is within
    ``max_cos`` of perpendicular to its view ray, and its projected normal points out across the boundary
    (cosine with the predicted silhouette's outward gradient at least ``min_alignment``). Offsets larger than
    ``max_offset_px`` (a mask that cut or added a piece) are dropped. intrinsics (3, 3) of the masks' pixel
    grid (undistorted), rotation (3, 3), translation (3,): cam_from_world.
    """
    vertices, normals = np.asarray(vertices, np.float64), np.asarray(normals, np.float64)
    k, rotation = np.asarray(intrinsics, np.float64), np.asarray(rotation, np.float64)
    translation = np.asarray(translation, np.float64)
    pixels, depth = _project(vertices, k, rotation, translation)
    u, v = pixels[:, 0], pixels[:, 1]
    predicted_mask = predicted.mask if isinstance(predicted, Silhouette) else np.asarray(predicted, bool)
    height, width = predicted_mask.shape
    centre = -rotation.T @ translation
    ray = vertices - centre
    facing = np.sum(ray * normals, axis=1) / np.linalg.norm(ray, axis=1)
    candidate = ((depth > 1e-9) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
                 & (np.abs(facing) < max_cos))
    index = np.flatnonzero(candidate)
    where = np.stack([v[index], u[index]])
    sdf_predicted = predicted.distance if isinstance(predicted, Silhouette) else signed_distance(predicted_mask)
    gradient = np.stack([ndimage.map_coordinates(g, where, order=1, mode="nearest")
                         for g in np.gradient(sdf_predicted)[::-1]], axis=1)  # (K, 2): d/du, d/dv
    outward = gradient / np.maximum(np.linalg.norm(gradient, axis=1, keepdims=True), 1e-9)

    def distance(silhouette, where, outward):
        if isinstance(silhouette, Silhouette):
            return boundary_distance(silhouette, where[::-1].T, outward)
        return ndimage.map_coordinates(signed_distance(silhouette), where, order=1, mode="nearest")

    at = distance(predicted, where, outward)
    near = np.abs(at) < band_px
    index, where, at, outward = index[near], where[:, near], at[near], outward[near]
    # d(u, v)/d(world point): the pinhole's Jacobian in camera coordinates times the rotation.
    cam = vertices[index] @ rotation.T + translation
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    jacobian_cam = np.zeros((len(index), 2, 3))
    jacobian_cam[:, 0, 0] = k[0, 0] / z
    jacobian_cam[:, 0, 1] = k[0, 1] / z
    jacobian_cam[:, 0, 2] = -(k[0, 0] * x + k[0, 1] * y) / z ** 2
    jacobian_cam[:, 1, 1] = k[1, 1] / z
    jacobian_cam[:, 1, 2] = -k[1, 1] * y / z ** 2
    jacobian = jacobian_cam @ rotation  # (K, 2, 3)
    projected_normal = np.einsum("kij,kj->ki", jacobian, normals[index])
    alignment = np.sum(projected_normal * outward, axis=1) / np.maximum(np.linalg.norm(projected_normal, axis=1), 1e-12)
    metres_per_px = z / np.sqrt(k[0, 0] * k[1, 1])
    offset_px = at - distance(observed, where, outward)
    keep = (alignment >= min_alignment) & (np.abs(offset_px) <= max_offset_px)
    direction = metres_per_px[:, None] * np.einsum("kij,ki->kj", jacobian, outward)
    return SilhouetteConstraints(index[keep], direction[keep], (offset_px * metres_per_px)[keep], metres_per_px[keep])


def refine_from_normals(vertices: np.ndarray, faces: np.ndarray, fitted_normals: np.ndarray,
                        confidence: np.ndarray, smoothness: float = 0.01, anchor: float = 1e-3,
                        rounds: int = 3, reference: np.ndarray | None = None,
                        silhouettes: SilhouetteConstraints | None = None,
                        silhouette_weight: float = 0.01, smoothness_unconfident: float = 1.0) -> np.ndarray:
    """The geometry update of one iteration (paper §4.4): the mesh's vertices (V, 3) moved along its
    normals so that its surface agrees with the fitted normals (V, 3), as far as their ``confidence``
    (V,) in [0, 1] allows. Returns the new vertices (V, 3); the faces (F, 3) are kept.

    Normal integration on the mesh: each vertex moves by an offset d along its current normal m; every
    edge (i, j) should be perpendicular to the mean t_ij of the target normals at its ends (exact on
    a sphere at any edge length), the targets being the fitted normals blended towards the mesh's by
    confidence (:func:`blend_normals`). The offsets minimise, in one sparse linear solve per round
    (conjugate gradients),

        sum_ij c_ij (t_ij . (x_j + d_j m_j - x_i - d_i m_i))^2
        + sum_ij (smoothness + smoothness_unconfident (1 - c_ij)) (d_i - d_j)^2
        + anchor sum_i (d_i - c_i m_i . (r_i - x_i))^2,

    with c_ij = sqrt(c_i c_j) and r the ``reference`` vertices (V, 3) of the same mesh (default: the
    current ones, i.e. d_i^2). A vertex is held at the reference as far as it is confident, else
    where it is. Every term is a squared length, so the weights have no units: the
    normals set the shape, ``smoothness`` keeps the offsets continuous, ``smoothness_unconfident`` (about the
    normals' own weight) makes them nearly constant where the fit says nothing (there the surface moves with
    its neighbours; without it the silhouettes pulled single contour vertices out of an unseen underside and
    roughened it over the iterations, docs/geometry_update.md), and
    the small ``anchor`` holds what normals cannot tell (the mean offset, the shape far from any
    confident vertex) at the reference surface. The loop passes its initial mesh: anchored to the
    current surface instead, small biases of the normals add up over the iterations (the demo shrank
    by about 0.6 mm per iteration). ``rounds`` re-linearise around the moved surface.
    Confidence 0 everywhere leaves every vertex where it was (the offsets solve a system whose
    right-hand side is zero). Screened Poisson from the same points cannot do this: it reconstructs
    the surface through the sample positions, so their errors stay (docs/geometry_update.md).

    ``silhouettes`` (:func:`silhouette_constraints`, measured at ``vertices``) add
    ``silhouette_weight sum_k (g_k . (x_i + d_i m_i - x0_i) - offset_k)^2``: each contour vertex moves its
    view's silhouette onto the observed one. This is what fixes the mean offset and size that normals cannot tell,
    and that the anchor would otherwise keep from the initial mesh.
    """
    from scipy import sparse
    from scipy.sparse.linalg import cg, spsolve

    vertices = np.asarray(vertices, np.float64)
    measured_at = vertices
    weight = np.clip(np.nan_to_num(np.asarray(confidence, np.float64)), 0, 1)
    reference = vertices if reference is None else np.asarray(reference, np.float64)
    if reference.shape != vertices.shape:
        raise ValueError(f"reference vertices {reference.shape} do not match the mesh's {vertices.shape}")
    reference = vertices + weight[:, None] * (reference - vertices)
    edges = mesh_edges(faces)
    i, j = edges[:, 0], edges[:, 1]
    rows = np.concatenate([np.arange(len(edges))] * 2)
    columns = np.concatenate([i, j])
    edge_weight = np.sqrt(np.sqrt(weight[i] * weight[j]))  # square root of c_ij: it scales the rows
    difference = sparse.csr_matrix((np.concatenate([-np.ones(len(edges)), np.ones(len(edges))]), (rows, columns)),
                                   shape=(len(edges), len(vertices)))
    # Smooth offsets, much stiffer where the normals say nothing (1 - c_ij): there the surface moves with its
    # neighbours, so that a silhouette cannot pull one vertex out of it.
    smooth = np.sqrt(smoothness + smoothness_unconfident * (1 - np.sqrt(weight[i] * weight[j])))
    regulariser = ((sparse.diags(smooth) @ difference).T @ (sparse.diags(smooth) @ difference)
                   + anchor * sparse.identity(len(vertices)))
    target = blend_normals(np.asarray(fitted_normals, np.float64), vertex_normals(vertices, faces), weight)
    edge_normal = target[i] + target[j]
    edge_normal /= np.maximum(np.linalg.norm(edge_normal, axis=1, keepdims=True), 1e-12)
    for _ in range(rounds):
        normals = vertex_normals(vertices, faces)
        values = np.concatenate([-np.sum(edge_normal * normals[i], 1), np.sum(edge_normal * normals[j], 1)])
        system = sparse.csr_matrix((values * np.concatenate([edge_weight] * 2), (rows, columns)),
                                   shape=(len(edges), len(vertices)))
        residual = -edge_weight * np.sum(edge_normal * (vertices[j] - vertices[i]), 1)
        matrix = (system.T @ system + regulariser).tocsr()
        right = system.T @ residual + anchor * np.sum(normals * (reference - vertices), axis=1)
        if silhouettes is not None and len(silhouettes) and silhouette_weight > 0:
            at = silhouettes.vertex
            along = np.sum(silhouettes.direction * normals[at], axis=1)
            missing = silhouettes.offset - np.sum(silhouettes.direction * (vertices[at] - measured_at[at]), axis=1)
            matrix = (matrix + sparse.diags(silhouette_weight * np.bincount(at, along ** 2, len(vertices)))).tocsr()
            right = right + silhouette_weight * np.bincount(at, along * missing, len(vertices))
        # Conjugate gradients with a Jacobi preconditioner: 7x faster than a direct solve at 160k vertices
        # and 1 nm from it at this tolerance; the direct solve where it does not converge.
        offsets, info = cg(matrix, right, rtol=1e-8, maxiter=10 * int(np.sqrt(len(vertices))) + 1000,
                           M=sparse.diags(1.0 / matrix.diagonal()))
        if info != 0:
            offsets = spsolve(matrix.tocsc(), right)
        vertices = vertices + offsets[:, None] * normals
    return vertices


# --------------------------------------------------------------------------- the initial mesh


@dataclass(frozen=True)
class InitMeshOptions:
    """Settings of :func:`initial_mesh` (config section ``init``).

    hull_resolution: voxels along the longest side of the hull's box; min_inside_fraction: share of
    the in-frame views whose silhouette must contain a voxel; poisson_depth: octree depth of the
    screened Poisson solve; target_depth: the mesh is remeshed to the vertex density a solve at this
    depth would give (4x the vertices per level), capped at ``max_vertices``; trim_density: Poisson
    density trim (see :func:`poisson_surface`); sparse_max_error_px / sparse_min_track: which SfM
    points are fused; sparse_margin_voxels: SfM points farther outside the hull are background;
    check_min_inside_fraction / check_scale_range: when a mesh the user supplies fits the silhouettes
    (:func:`check_against_silhouettes`).
    """

    hull_resolution: int = 128
    min_inside_fraction: float = 0.9
    min_views: int = 3
    poisson_depth: int = 7
    target_depth: int = 9
    max_vertices: int = 30000
    trim_density: float = 2.0
    sparse_max_error_px: float = 2.0
    sparse_min_track: int = 3
    sparse_margin_voxels: float = 3.0
    threads: int = -1
    check_min_inside_fraction: float = 0.9
    check_scale_range: tuple[float, float] = (0.8, 1.25)


@dataclass
class InitialMesh:
    """vertices (V, 3), faces (F, 3), normals (V, 3), the carving, statistics for the report, and for a mesh
    the user supplied, how it fits the silhouettes."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    carving: Carving
    stats: dict
    check: MeshCheck | None = None


def initial_mesh(masks: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                 options: InitMeshOptions = InitMeshOptions(), sparse_points: np.ndarray | None = None,
                 sparse_views: list[np.ndarray] | None = None, sparse_errors: np.ndarray | None = None,
                 extra_points: tuple[np.ndarray, np.ndarray] | None = None) -> InitialMesh:
    """The initial mesh of DESIGN §2 mesh_init from silhouettes, fused with SfM points.

    1. visual hull (:func:`visual_hull`) and its oriented surface points (:func:`surface_points`);
    2. SfM points (``sparse_points`` (P, 3), observing view indices ``sparse_views``, reprojection
       errors ``sparse_errors`` (P,) px) near or inside the hull are added with PCA normals facing
       their cameras, and hull points that hide an SfM point in two or more views (a concavity the
       silhouettes cannot carve) are dropped (:func:`occluding_points`);
       ``extra_points``: further oriented points (points, normals), e.g. from dense stereo;
    3. screened Poisson at ``poisson_depth``, density trim, largest component;
    4. isotropic remeshing to the vertex count of ``target_depth``, at most ``max_vertices``.
    """
    timings = {}
    start = time.perf_counter()
    carving = visual_hull(masks, intrinsics, rotations, translations, resolution=options.hull_resolution,
                          min_inside_fraction=options.min_inside_fraction, min_views=options.min_views)
    points, normals = surface_points(carving.occupancy, carving.grid)
    timings["hull_s"] = time.perf_counter() - start
    stats = {"hull_voxels": int(carving.occupancy.sum()), "voxel_size_m": carving.grid.voxel_size,
             "hull_points": len(points), "sparse_points_used": 0, "hull_points_removed": 0}

    start = time.perf_counter()
    if sparse_points is not None and len(sparse_points):
        keep = np.array([len(v) >= options.sparse_min_track for v in sparse_views])
        if sparse_errors is not None:
            keep &= np.asarray(sparse_errors) <= options.sparse_max_error_px
        keep &= _near_occupancy(sparse_points, carving, options.sparse_margin_voxels)
        chosen = sparse_points[keep]
        chosen_views = [v for v, k in zip(sparse_views, keep) if k]
        if len(chosen) >= 20:
            centers = camera_center(rotations, translations)
            towards = np.stack([_mean_direction(centers[v] - p) for p, v in zip(chosen, chosen_views)])
            occluding = occluding_points(points, chosen, chosen_views, intrinsics, rotations, translations,
                                         depth_margin=2 * carving.grid.voxel_size)
            points = np.concatenate([points[~occluding], chosen])
            normals = np.concatenate([normals[~occluding], estimate_normals(chosen, towards)])
            stats.update(sparse_points_used=len(chosen), hull_points_removed=int(occluding.sum()))
    if extra_points is not None:
        points = np.concatenate([points, extra_points[0]])
        normals = np.concatenate([normals, extra_points[1]])
    timings["fusion_s"] = time.perf_counter() - start

    start = time.perf_counter()
    vertices, faces = poisson_surface(points, normals, depth=options.poisson_depth,
                                      trim_density=options.trim_density)
    vertices, faces = largest_component(vertices, faces)
    stats["poisson_vertices"] = len(vertices)
    timings["poisson_s"] = time.perf_counter() - start

    start = time.perf_counter()
    target = min(depth_vertex_count(len(vertices), options.poisson_depth, options.target_depth),
                 options.max_vertices)
    vertices, faces = remesh_to_count(vertices, faces, target)
    vertices, faces = largest_component(vertices, faces)
    timings["remesh_s"] = time.perf_counter() - start
    stats.update(target_vertices=target, vertices=len(vertices), faces=len(faces), timings=timings)
    return InitialMesh(vertices, faces, vertex_normals(vertices, faces), carving, stats)


def _mean_direction(offsets: np.ndarray) -> np.ndarray:
    """Unit mean of the unit vectors (N, 3)."""
    units = offsets / np.linalg.norm(offsets, axis=1, keepdims=True)
    mean = units.sum(axis=0)
    return mean / np.linalg.norm(mean)


def _near_occupancy(points: np.ndarray, carving: Carving, margin_voxels: float) -> np.ndarray:
    """(N,) bool: points inside the occupancy grown by ``margin_voxels`` voxels."""
    grid = carving.grid
    grown = ndimage.binary_dilation(carving.occupancy, iterations=max(int(np.ceil(margin_voxels)), 1))
    index = np.rint((points - grid.origin) / grid.voxel_size).astype(np.int64)
    inside = np.all((index >= 0) & (index < np.array(grid.shape)), axis=1)
    result = np.zeros(len(points), bool)
    result[inside] = grown[tuple(index[inside].T)]
    return result


# --------------------------------------------------------------------------- a mesh the user supplies

UNIT_SIZES = {"millimetres": 1000.0, "centimetres": 100.0, "inches": 1 / 0.0254}
"""How many times larger a length is in these units than in metres: the size ratio (mesh / silhouettes)
of a mesh written in them (or its inverse, for cameras written in them)."""


def orient_outward(vertices: np.ndarray, faces: np.ndarray,
                   normals: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """Faces (F, 3) wound consistently and counter-clockwise seen from outside, and whether the winding could be
    made consistent (open3d ``orient_triangles`` needs an edge-manifold mesh; otherwise the winding is kept).

    Outward: the side the given vertex ``normals`` (V, 3) point to (a scanner's), else the winding with a positive
    signed volume about the centroid (right for closed surfaces and for scans open on one side).
    """
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    consistent = bool(mesh.is_edge_manifold() and mesh.orient_triangles())
    faces = np.asarray(mesh.triangles, np.int64)
    if normals is not None:
        outward = np.einsum("ij,ij->", vertex_normals(vertices, faces), normals) >= 0
    else:
        a, b, c = (vertices[faces[:, k]] - vertices.mean(axis=0) for k in range(3))
        outward = np.einsum("ij,ij->", a, np.cross(b, c)) >= 0
    return (faces if outward else faces[:, ::-1].copy()), consistent


def resample_to_count(vertices: np.ndarray, faces: np.ndarray, target_vertices: int,
                      decimate_above: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """A mesh of about ``target_vertices`` vertices by :func:`remesh_to_count` (isotropic remeshing collapses short
    edges and splits long ones, so it both simplifies and subdivides). A mesh with more than ``decimate_above``
    times the target is first reduced to twice the target by quadric decimation (open3d): remeshing a
    million-vertex scan directly takes minutes. Returns vertices (V, 3) float64 and faces (F, 3) int64."""
    import open3d as o3d

    if len(vertices) > decimate_above * target_vertices:
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                         o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
        mesh = mesh.simplify_quadric_decimation(4 * target_vertices)  # about two faces per vertex
        vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)
    return remesh_to_count(vertices, faces, target_vertices)


@dataclass
class MeshCheck:
    """How a mesh agrees with the silhouettes (see :func:`check_against_silhouettes`).

    inside_fraction (V,): per view, the share of the vertices that project inside its silhouette (grown by
    ``tolerance_px``; behind the camera or out of frame counts as outside); extent_ratio (V,): per view, the size
    of the vertices' projected bounding box over the silhouette's (square root of the areas), NaN where the
    mesh is not wholly in front of the camera or the silhouette is empty or touches the frame;
    median_inside_fraction and scale_ratio (the median extent ratio) decide; hull_size_ratio and hull_offset_m
    (3,) compare the mesh's bounding box with the silhouettes' visual hull (diagonal ratio, centre offset in
    metres) to say what is off; problems: one sentence per problem found, empty when the mesh fits.
    """

    inside_fraction: np.ndarray
    extent_ratio: np.ndarray
    median_inside_fraction: float
    scale_ratio: float
    hull_size_ratio: float
    hull_offset_m: np.ndarray
    problems: list[str]

    def stats(self, view_ids: list[str]) -> dict:
        """The figures for the stage's report (JSON-ready)."""
        finite = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {"inside_fraction": {v: float(f) for v, f in zip(view_ids, self.inside_fraction)},
                "extent_ratio": {v: finite(r) for v, r in zip(view_ids, self.extent_ratio)},
                "median_inside_fraction": self.median_inside_fraction, "scale_ratio": finite(self.scale_ratio),
                "hull_size_ratio": self.hull_size_ratio, "hull_offset_m": [float(x) for x in self.hull_offset_m],
                "problems": self.problems}


def _size_problem(ratio: float, measured: str) -> str:
    """The sentence for a mesh whose size is ``ratio`` times the silhouettes' (far from 1; ``measured`` says
    how): the unit it looks like it is written in, and the factor that would fit."""
    larger = max(ratio, 1 / ratio)
    unit, factor = min(UNIT_SIZES.items(), key=lambda item: abs(np.log(larger / item[1])))
    sizes = f"{ratio:.4g} times the size of the silhouettes ({measured})"
    if abs(np.log(larger / factor)) < np.log(1.5):
        which = (f"the mesh looks like {unit} and the cameras metres" if ratio > 1
                 else f"the cameras (poses.csv) look like {unit} and the mesh metres")
        scale = 1 / factor if ratio > 1 else factor
        return (f"wrong units? the mesh is {sizes}: {which}; scaling the mesh by {scale:.6g} "
                f"(a factor of {factor:.6g}) would fit")
    return f"wrong scale? the mesh is {sizes}: scaling it by about {1 / ratio:.3g} would fit"


def check_against_silhouettes(vertices: np.ndarray, masks: np.ndarray, intrinsics: np.ndarray,
                              rotations: np.ndarray, translations: np.ndarray, carving: Carving,
                              min_inside_fraction: float = 0.9, scale_range: tuple[float, float] = (0.8, 1.25),
                              tolerance_px: int = 2) -> MeshCheck:
    """Does a mesh (its vertices (N, 3), in the cameras' world) match the silhouettes (V, H, W) bool?

    It fits when the median over views of the inside fraction is at least ``min_inside_fraction`` and the
    median extent ratio lies in ``scale_range`` (see :class:`MeshCheck`). Otherwise the problems say what
    is off: a size ratio outside ``scale_range`` ("wrong units?" with the unit and factor that would fit, or
    "wrong scale?"; the median extent ratio, or where no camera has the whole mesh in front of it, the
    bounding-box diagonal against that of ``carving``, the silhouettes' visual hull), a centre away from the
    hull's ("wrong place?", the offset in metres), or neither (a rotated mesh or another world frame).
    """
    count, height, width = masks.shape
    k = np.broadcast_to(np.asarray(intrinsics, np.float64), (count, 3, 3))
    grow = _disk(tolerance_px) if tolerance_px else None
    inside = np.zeros(count)
    extent = np.full(count, np.nan)
    for view in range(count):
        pixels, depth = _project(np.asarray(vertices, np.float64), k[view], rotations[view], translations[view])
        col, row = np.rint(pixels[:, 0]).astype(np.int64), np.rint(pixels[:, 1]).astype(np.int64)
        seen = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        mask = ndimage.binary_dilation(masks[view], grow) if grow is not None else masks[view]
        inside[view] = mask[row[seen], col[seen]].sum() / max(len(vertices), 1)
        rows, cols = np.nonzero(masks[view])
        touches = len(rows) and (rows.min() == 0 or cols.min() == 0 or rows.max() == height - 1
                                 or cols.max() == width - 1)
        if len(rows) and not touches and np.all(depth > 0):
            mesh_area = np.prod(pixels.max(axis=0) - pixels.min(axis=0))
            mask_area = (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1)
            extent[view] = np.sqrt(mesh_area / mask_area)
    median_inside = float(np.median(inside))
    scale_ratio = float(np.nanmedian(extent)) if np.isfinite(extent).any() else float("nan")

    lo, hi = carving.grid.bounds_of(carving.occupancy, margin_voxels=0.0)
    mesh_lo, mesh_hi = vertices.min(axis=0), vertices.max(axis=0)
    size_ratio = float(np.linalg.norm(mesh_hi - mesh_lo) / np.linalg.norm(hi - lo))
    offset = 0.5 * (mesh_lo + mesh_hi) - 0.5 * (lo + hi)
    problems = []
    fits_scale = scale_range[0] <= scale_ratio <= scale_range[1]
    if median_inside >= min_inside_fraction and fits_scale:
        return MeshCheck(inside, extent, median_inside, scale_ratio, size_ratio, offset, problems)

    projected = (f"{scale_ratio:.3g} (median over views" if np.isfinite(scale_ratio)
                 else "undefined (no camera has the whole mesh in front of it")
    figures = (f"median share of its vertices inside the silhouettes {median_inside:.2f} (at least "
               f"{min_inside_fraction:.2f} needed), projected size / silhouette size {projected}; "
               f"{scale_range[0]:g}-{scale_range[1]:g} needed)")
    # The projected size is the sharper measure (the hull is larger than the object); without it (cameras
    # inside the mesh, as with a mesh in millimetres) the bounding boxes of mesh and hull are compared.
    if np.isfinite(scale_ratio):
        ratio, measured = scale_ratio, "median over views of its projected size over the silhouette's"
    else:
        ratio, measured = size_ratio, (f"its bounding-box diagonal {np.linalg.norm(mesh_hi - mesh_lo):.4g} in the "
                                       f"file's units, the silhouettes' visual hull's {np.linalg.norm(hi - lo):.4g} m")
    if not scale_range[0] <= ratio <= scale_range[1]:
        problems.append(_size_problem(ratio, measured))
    distance = float(np.linalg.norm(offset))
    if distance > max(0.1 * np.linalg.norm(hi - lo), 2 * carving.grid.voxel_size):
        problems.append(f"wrong place? the centre of its bounding box lies {distance:.3f} m from the centre of the "
                        f"silhouettes' visual hull (offset {offset[0]:+.3f}, {offset[1]:+.3f}, {offset[2]:+.3f} m "
                        "in the cameras' world)")
    if not problems:
        problems.append("its size and centre match the silhouettes, but it does not project onto them: rotated, "
                        "or in another world frame? It must be in the world of the poses (cameras.csv), in metres")
    problems.append(figures)
    return MeshCheck(inside, extent, median_inside, scale_ratio, size_ratio, offset, problems)


def user_initial_mesh(vertices: np.ndarray, faces: np.ndarray, masks: np.ndarray, intrinsics: np.ndarray,
                      rotations: np.ndarray, translations: np.ndarray, options: InitMeshOptions = InitMeshOptions(),
                      normals: np.ndarray | None = None) -> InitialMesh:
    """The initial mesh from a mesh the user supplies (a scan, in the cameras' world, metres), checked against
    the silhouettes (DESIGN §2 mesh_init, ``init.mode: mesh``).

    1. the largest connected component; faces wound consistently and outward (:func:`orient_outward`, by the
       scan's vertex ``normals`` (V, 3) when given);
    2. resampled to ``options.max_vertices`` (:func:`resample_to_count`), so the later stages cost what they
       cost with the hull; vertex normals from the faces;
    3. checked against the silhouettes (:func:`check_against_silhouettes`, against a visual hull of at most
       64 voxels a side): ``InitialMesh.check.problems`` is empty when it fits. Nothing is raised here.
    """
    timings = {}
    start = time.perf_counter()
    stats = {"source_vertices": len(vertices), "source_faces": len(faces)}
    # Per-vertex normals travel with the vertices through the component selection (it keeps rows).
    columns = np.asarray(vertices, np.float64) if normals is None else np.hstack([vertices, normals])
    columns, faces = largest_component(columns, np.asarray(faces, np.int64))
    vertices, normals = columns[:, :3], (None if normals is None else columns[:, 3:])
    faces, consistent = orient_outward(vertices, faces, normals)
    stats.update(component_vertices=len(vertices), component_faces=len(faces), consistent_winding=consistent)
    timings["orient_s"] = time.perf_counter() - start

    start = time.perf_counter()
    vertices, faces = largest_component(*resample_to_count(vertices, faces, options.max_vertices))
    timings["resample_s"] = time.perf_counter() - start

    start = time.perf_counter()
    carving = visual_hull(masks, intrinsics, rotations, translations, resolution=min(options.hull_resolution, 64),
                          min_inside_fraction=options.min_inside_fraction, min_views=options.min_views)
    check = check_against_silhouettes(vertices, masks, intrinsics, rotations, translations, carving,
                                      options.check_min_inside_fraction, options.check_scale_range)
    timings["check_s"] = time.perf_counter() - start
    stats.update(hull_voxels=int(carving.occupancy.sum()), voxel_size_m=carving.grid.voxel_size,
                 target_vertices=options.max_vertices, vertices=len(vertices), faces=len(faces), timings=timings)
    return InitialMesh(vertices, faces, vertex_normals(vertices, faces), carving, stats, check)
