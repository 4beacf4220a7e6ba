"""Triangle-mesh utilities: surface samples and mesh-to-mesh distances (docs/design.md §8 Chamfer and
Hausdorff), point normals, screened Poisson, the largest component, isotropic remeshing to a vertex count,
vertex normals, edges. open3d and pymeshlab as numerical libraries; metres; pure functions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# --------------------------------------------------------------------------- mesh distances


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (N,) in degrees between direction vectors a and b (N, 3) (normalized here; atan2 form, exact near 0)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


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
    b_to_a_p95: 95th percentile of B-to-A distances; b_far_share: the share of B's samples farther than
    ``far`` from A (with B the truth: the share of the true surface the model misses by more than that).
    """

    a_to_b: float
    b_to_a: float
    chamfer: float
    hausdorff: float
    b_to_a_p95: float
    b_far_share: float


def mesh_distances(vertices_a: np.ndarray, faces_a: np.ndarray, vertices_b: np.ndarray, faces_b: np.ndarray,
                   count: int = 50000, seed: int = 0, far: float = 1e-3) -> MeshDistances:
    """Chamfer (mean of both directed mean distances) and Hausdorff distance between two meshes.

    ``count`` area-uniform samples per surface are measured against the other surface exactly; ``far`` (world
    units, default 1 mm in metres): the distance beyond which a sample of B counts in ``b_far_share``.
    """
    from_a = _distance_to_mesh(surface_samples(vertices_a, faces_a, count, seed), vertices_b, faces_b)
    from_b = _distance_to_mesh(surface_samples(vertices_b, faces_b, count, seed + 1), vertices_a, faces_a)
    return MeshDistances(a_to_b=float(from_a.mean()), b_to_a=float(from_b.mean()),
                         chamfer=float(0.5 * (from_a.mean() + from_b.mean())),
                         hausdorff=float(max(from_a.max(), from_b.max())),
                         b_to_a_p95=float(np.percentile(from_b, 95)), b_far_share=float(np.mean(from_b > far)))


@dataclass(frozen=True)
class SurfaceDefects:
    """Where a triangle mesh stops being a surface (:func:`surface_defects`).

    self_intersecting_pairs: pairs of triangles that cross each other without sharing a vertex; flipped: triangles
    whose normal turned by more than 90 degrees from the reference's (the same face of the previous mesh);
    degenerate: triangles whose height is below ``1e-3`` of their longest edge (zero area, a needle or a cap);
    folding_faces (F,) bool: the triangles of any of the three.
    """

    self_intersecting_pairs: int
    flipped: int
    degenerate: int
    folding_faces: np.ndarray

    @property
    def folds(self) -> int:
        """Self-intersecting pairs plus flipped triangles: 0 for a mesh that is still a surface."""
        return self.self_intersecting_pairs + self.flipped

    def as_dict(self) -> dict:
        return {"self_intersecting_pairs": self.self_intersecting_pairs, "flipped_triangles": self.flipped,
                "degenerate_triangles": self.degenerate}


DEGENERATE_HEIGHT = 1e-3


def surface_defects(vertices: np.ndarray, faces: np.ndarray, reference: np.ndarray | None = None) -> SurfaceDefects:
    """Count the folds of a triangle mesh: vertices (V, 3), faces (F, 3). ``reference`` (V, 3): the same mesh's
    vertices before it moved (the previous iteration's; the faces never change), against whose face normals a
    triangle counts as flipped; None: no flip count (0). Self-intersections by open3d
    (``TriangleMesh.get_self_intersecting_triangles``; pairs that share a vertex do not count) among the faces
    pymeshlab's grid finds crossing (``compute_selection_by_self_intersections_per_face``)."""
    import open3d as o3d
    import pymeshlab

    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    longest = np.max(np.stack([np.linalg.norm(e, axis=1) for e in (b - a, c - b, a - c)]), axis=0)
    # height over the longest edge = twice the area / longest^2
    degenerate = np.linalg.norm(cross, axis=1) < DEGENERATE_HEIGHT * np.maximum(longest, 1e-300) ** 2
    flipped = np.zeros(len(faces), bool)
    if reference is not None:
        reference = np.asarray(reference, np.float64)
        if reference.shape != vertices.shape:
            raise ValueError(f"reference vertices {reference.shape} do not match the mesh's {vertices.shape}")
        ra, rb, rc = (reference[faces[:, k]] for k in range(3))
        flipped = np.sum(cross * np.cross(rb - ra, rc - ra), axis=1) < 0
    # open3d tests every pair of triangles (8 s at 20k faces); pymeshlab's grid finds the crossing faces in a
    # fraction of a second, and open3d counts the pairs among them (the same faces, tested both ways).
    meshset = pymeshlab.MeshSet()
    meshset.add_mesh(pymeshlab.Mesh(vertices, faces.astype(np.int32)))
    meshset.compute_selection_by_self_intersections_per_face()
    crossing = np.flatnonzero(meshset.current_mesh().face_selection_array())
    pairs = np.zeros((0, 2), np.int64)
    if len(crossing):
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices),
                                         o3d.utility.Vector3iVector(faces[crossing].astype(np.int32)))
        pairs = crossing[np.asarray(mesh.get_self_intersecting_triangles(), np.int64).reshape(-1, 2)]
    folding = degenerate | flipped
    folding[pairs.ravel()] = True
    return SurfaceDefects(len(pairs), int(flipped.sum()), int(degenerate.sum()), folding)


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
    ``L = sqrt(2 A / (sqrt(3) V))``) and is corrected once from the count actually reached. The same arrays give
    the same mesh in every install: pymeshlab's surface-distance check of a collapse or flip (``checksurfdist``)
    is off, since its answer depends on the process's memory layout (where pymeshlab is installed); the vertices
    are reprojected onto the input surface at every step, which keeps them on it (docs/geometry.md).
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
                                                    featuredeg=180.0, checksurfdist=False)
        mesh = meshes.current_mesh()
        out_vertices = mesh.vertex_matrix().astype(np.float64)
        out_faces = mesh.face_matrix().astype(np.int64)
        ratio = len(out_vertices) / target_vertices
        if abs(ratio - 1) < 0.1:
            break
        length *= np.sqrt(ratio)
    return out_vertices, out_faces


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, area_weighted: bool = False) -> np.ndarray:
    """Unit vertex normals (V, 3) of a mesh with counter-clockwise faces seen from outside.

    ``area_weighted=False``: open3d's ``compute_vertex_normals`` (the sum of the unit normals of a vertex's faces),
    what the reconstruction uses; True: the sum of the face normals weighted by their areas (the synthetic scenes'
    ground truth, where faces differ in size)."""
    if area_weighted:
        a, b, c = (vertices[faces[:, k]] for k in range(3))
        face_normals = np.cross(b - a, c - a)  # length = twice the area
        normals = np.zeros_like(vertices)
        for k in range(3):
            np.add.at(normals, faces[:, k], face_normals)
        return normals / np.linalg.norm(normals, axis=1, keepdims=True)
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


