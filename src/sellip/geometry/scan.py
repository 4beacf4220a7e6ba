"""A mesh the user supplies (``init.mode: mesh``, a scan): oriented outward, resampled to a vertex
count and checked against the silhouettes (scale, units, placement), with a message that names the likely
problem.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage

from sellip.geometry.hull import Carving, InitialMesh, InitMeshOptions, MeshCheck, project, visual_hull
from sellip.geometry.meshes import largest_component, remesh_to_count, vertex_normals
from sellip.geometry.silhouettes import disk

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
    grow = disk(tolerance_px) if tolerance_px else None
    inside = np.zeros(count)
    extent = np.full(count, np.nan)
    for view in range(count):
        pixels, depth = project(np.asarray(vertices, np.float64), k[view], rotations[view], translations[view])
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
    the silhouettes (docs/design.md §2 mesh_init, ``init.mode: mesh``).

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
