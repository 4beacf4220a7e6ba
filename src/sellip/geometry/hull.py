"""The visual hull and the initial mesh (docs/design.md §2 mesh_init): voxel carving from the silhouettes,
the surface points of the occupancy, fusion with SfM's sparse points, screened Poisson at a depth and
remeshing to a vertex count.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from sellip.geometry.meshes import (
    depth_vertex_count,
    estimate_normals,
    largest_component,
    poisson_surface,
    remesh_to_count,
    vertex_normals,
)
from sellip.model.conventions import camera_center, camera_forward
from sellip.settings import setting

# --------------------------------------------------------------------------- visual hull


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
        finite = lambda x: float(x) if np.isfinite(x) else None
        return {"inside_fraction": {v: float(f) for v, f in zip(view_ids, self.inside_fraction)},
                "extent_ratio": {v: finite(r) for v, r in zip(view_ids, self.extent_ratio)},
                "median_inside_fraction": self.median_inside_fraction, "scale_ratio": finite(self.scale_ratio),
                "hull_size_ratio": self.hull_size_ratio, "hull_offset_m": [float(x) for x in self.hull_offset_m],
                "problems": self.problems}


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


class EmptyHullError(ValueError):
    """The silhouettes leave no voxel: they and the cameras disagree about where the object is."""


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


def project(points: np.ndarray, intrinsics: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """Pixel coordinates (N, 2) and depth (N,) of world points (N, 3) in one camera."""
    cam = points @ rotation.T.astype(points.dtype) + translation.astype(points.dtype)
    depth = cam[:, 2]
    safe = np.where(depth > 0, depth, 1.0)
    k = intrinsics.astype(points.dtype)
    u = k[0, 0] * cam[:, 0] / safe + k[0, 1] * cam[:, 1] / safe + k[0, 2]
    v = k[1, 1] * cam[:, 1] / safe + k[1, 2]
    return np.stack([u, v], axis=-1), depth


def silhouette_coverage(vertices: np.ndarray, faces: np.ndarray, masks: np.ndarray, intrinsics: np.ndarray,
                        rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """(V,) per view the fraction of the silhouette's pixels that the mesh's projection covers: near 1 where the
    cameras describe the photographs; a hull carved by cameras that are not the capture's shrinks to the part that
    every cone shares, and covers less. vertices (N, 3) world metres, faces (F, 3), masks (V, H, W) bool,
    intrinsics (3, 3) in the masks' pixels, rotations (V, 3, 3) and translations (V, 3) cam_from_world. The
    projection is the vertices' pixels grown by the longest projected edge and filled (a coarse footprint)."""
    coverage = np.ones(len(masks))
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    for view, mask in enumerate(masks):
        if not mask.any():
            continue
        pixels, depth = project(vertices, intrinsics, rotations[view], translations[view])
        ahead = depth > 0
        lengths = np.linalg.norm(pixels[edges[:, 0]] - pixels[edges[:, 1]], axis=1)[ahead[edges].all(1)]
        reach = int(np.ceil(np.percentile(lengths, 99))) if len(lengths) else 1
        footprint = np.zeros(mask.shape, bool)
        inside = ahead & (pixels[:, 0] >= 0) & (pixels[:, 1] >= 0) & (pixels[:, 0] < mask.shape[1] - 0.5) \
            & (pixels[:, 1] < mask.shape[0] - 0.5)
        rows, cols = np.rint(pixels[inside, 1]).astype(int), np.rint(pixels[inside, 0]).astype(int)
        footprint[rows, cols] = True
        footprint = ndimage.binary_fill_holes(ndimage.binary_dilation(footprint, iterations=max(reach, 1)))
        coverage[view] = float((footprint & mask).sum() / mask.sum())
    return coverage


@dataclass(frozen=True)
class Carving:
    """Result of silhouette carving.

    grid: the VoxelGrid; occupancy: (X, Y, Z) bool, kept voxels; inside_fraction: (X, Y, Z) float32,
    fraction of the views that see a voxel in frame and have it inside their silhouette;
    disagreement: (V,) float, per view the fraction of kept voxels it sees in frame but outside its mask.
    others_disagreement: (V,) float, per view the fraction of the hull of the OTHER views (the same carving
    without this view) that it sees in frame but outside its mask (computed on request, else zeros): a view whose
    photograph is not where its camera says (swapped, misplaced) disagrees with what the others share, while the
    kept voxels (``min_inside_fraction`` near 1) have already been carved by it, so ``disagreement`` cannot see it.
    """

    grid: VoxelGrid
    occupancy: np.ndarray
    inside_fraction: np.ndarray
    disagreement: np.ndarray
    others_disagreement: np.ndarray


def carve(masks: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
          grid: VoxelGrid, min_inside_fraction: float = 0.9, min_views: int = 3, others: bool = False) -> Carving:
    """Keep the voxels whose centre projects inside the silhouette in at least ``min_inside_fraction``
    of the views that see it in frame (and that at least ``min_views`` views see in frame).

    masks (V, H, W) bool; intrinsics (V, 3, 3) or (3, 3); rotations (V, 3, 3); translations (V, 3).
    A fraction below 1 makes the hull robust to a few bad masks (a dark patch cut out of one view).
    ``others``: also each view's disagreement with the other views' hull (``Carving.others_disagreement``; keeps
    two (V, voxels) bool arrays: use it on a coarse grid).
    """
    count, height, width = masks.shape
    k = np.broadcast_to(np.asarray(intrinsics, np.float64), (count, 3, 3))
    centers = grid.centers().reshape(-1, 3).astype(np.float32)
    in_frame = np.zeros(len(centers), np.int32)
    inside = np.zeros(len(centers), np.int32)
    per_view = []
    for view in range(count):
        pixels, depth = project(centers, k[view], rotations[view], translations[view])
        col, row = np.rint(pixels[:, 0]).astype(np.int64), np.rint(pixels[:, 1]).astype(np.int64)
        seen = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        in_mask = np.zeros(len(centers), bool)
        in_mask[seen] = masks[view][row[seen], col[seen]]
        in_frame += seen
        inside += in_mask
        if others:
            per_view.append((seen, in_mask))
    fraction = inside / np.maximum(in_frame, 1)
    occupancy = (in_frame >= min(min_views, count)) & (fraction >= min_inside_fraction - 1e-9)
    disagreement = np.zeros(count)
    kept = centers[occupancy]
    for view in range(count):
        pixels, depth = project(kept, k[view], rotations[view], translations[view])
        col, row = np.rint(pixels[:, 0]).astype(np.int64), np.rint(pixels[:, 1]).astype(np.int64)
        seen = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        if seen.any():
            disagreement[view] = 1.0 - masks[view][row[seen], col[seen]].mean()
    others_disagreement = np.zeros(count)
    for view, (seen, in_mask) in enumerate(per_view):
        frame_rest, inside_rest = in_frame - seen, inside - in_mask
        hull_rest = (frame_rest >= min(min_views, count - 1)) & (
            inside_rest >= (min_inside_fraction - 1e-9) * np.maximum(frame_rest, 1))
        looked = hull_rest & seen
        if looked.any():
            others_disagreement[view] = 1.0 - in_mask[looked].mean()
    return Carving(grid, occupancy.reshape(grid.shape), fraction.reshape(grid.shape).astype(np.float32),
                   disagreement, others_disagreement)


def visual_hull(masks: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                resolution: int = 128, coarse_resolution: int = 48, min_inside_fraction: float = 0.9,
                min_views: int = 3, bounds: tuple[np.ndarray, np.ndarray] | None = None,
                margin_voxels: float = 2.0) -> Carving:
    """Silhouette carving in two passes: a coarse grid over ``bounds`` (default: the cameras' common
    view volume), then ``resolution`` voxels along the longest side of the coarse hull's box.

    See :func:`carve` for the arguments. Raises ValueError when nothing survives the coarse pass. The
    ``others_disagreement`` is the coarse pass's (the fine grid covers only the kept voxels' box).
    """
    height, width = masks.shape[1:]
    lo, hi = bounds if bounds is not None else view_volume_bounds(intrinsics, rotations, translations, width, height)
    coarse = carve(masks, intrinsics, rotations, translations, VoxelGrid.from_bounds(lo, hi, coarse_resolution),
                   min_inside_fraction, min_views, others=True)
    if not coarse.occupancy.any():
        raise EmptyHullError("silhouette carving removed every voxel: the masks and the poses disagree")
    lo, hi = coarse.grid.bounds_of(coarse.occupancy, margin_voxels)
    fine = carve(masks, intrinsics, rotations, translations, VoxelGrid.from_bounds(lo, hi, resolution),
                 min_inside_fraction, min_views)
    # The other views' hull reaches beyond the kept voxels' box: its disagreement is the coarse grid's, which holds it.
    return replace(fine, others_disagreement=coarse.others_disagreement)


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
        sparse_px, sparse_depth = project(sparse_points[index], k[view], rotations[view], translations[view])
        px, depth = project(points, k[view], rotations[view], translations[view])
        tree = cKDTree(sparse_px)
        neighbours = tree.query_ball_point(px, radius_px)
        nearest_depth = np.array([sparse_depth[n].max() if n else -np.inf for n in neighbours])
        votes += (depth > 0) & (depth < nearest_depth - depth_margin)
    return votes >= min_views


# --------------------------------------------------------------------------- the initial mesh


INIT_MODES = ("hull", "mvs", "mesh")
"""How the initial mesh is made (config ``init.mode``; :func:`sellip.geometry.initial.make_initial_mesh`)."""


@dataclass(frozen=True)
class InitMeshOptions:
    """Settings of the initial mesh (config section ``init``; each setting declared once here,
    :mod:`sellip.settings`): :func:`sellip.geometry.initial.make_initial_mesh` and :func:`hull_mesh`.

    The other fields are the library's own: trim_density: Poisson density trim (see :func:`poisson_surface`);
    sparse_max_error_px / sparse_min_track: which SfM points are fused; sparse_margin_voxels: SfM points farther
    outside the hull are background; check_min_inside_fraction / check_scale_range: when a mesh the user supplies
    fits the silhouettes (:func:`check_against_silhouettes`); threads: the job's (-1: all cores).
    """

    mode: str = setting("hull", "visual hull of the silhouettes fused with the SfM points (hull, CPU), COLMAP "
                        "PatchMatch stereo (mvs: pycolmap with CUDA and an SfM model, sfm.mode sfm or verify), or the "
                        "mesh in init.mesh_path resampled to max_vertices and checked against the silhouettes (mesh)",
                        choices=INIT_MODES)
    hull_resolution: int = setting(128, "voxels along the longest side of the hull's box", minimum=16)
    min_inside_fraction: float = setting(0.9, "a voxel stays when this fraction of the views that see it have it "
                                         "inside their silhouette", exclusive_minimum=0, maximum=1)
    min_views: int = 3
    poisson_depth: int = setting(7, "screened Poisson octree depth", minimum=4, maximum=12)
    target_depth: int = setting(9, "the mesh is remeshed to the vertex density of a solve at this depth (4x the "
                                "vertices per level), at most max_vertices", minimum=4, maximum=12)
    max_vertices: int = setting(30000, "vertex budget of the initial mesh (every vertex is fitted later: keep it "
                                "laptop-sized)", minimum=100)
    outlier_view_z: float = setting(6.0, "a view whose silhouette disagrees with the other views' hull this many "
                                    "robust standard deviations above the views' median (and by more than 5 %) is "
                                    "named in a warning as a likely swapped or misplaced view (docs/reliability.md)",
                                    unit="robust standard deviations", minimum=2)
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


def hull_mesh(masks: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                 options: InitMeshOptions = InitMeshOptions(), sparse_points: np.ndarray | None = None,
                 sparse_views: list[np.ndarray] | None = None, sparse_errors: np.ndarray | None = None,
                 extra_points: tuple[np.ndarray, np.ndarray] | None = None) -> InitialMesh:
    """The initial mesh of docs/design.md §2 mesh_init from silhouettes, fused with SfM points.

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


