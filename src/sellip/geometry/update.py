"""The geometry update (docs/design.md §2, docs/geometry_update.md): the surface moved to agree with the
confident fitted normals by normal integration (a sparse least-squares problem), held by the photographs'
silhouettes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sellip.geometry.hull import project
from sellip.geometry.meshes import blend_normals, mesh_edges, vertex_normals
from sellip.geometry.silhouettes import Silhouette, boundary_distance, signed_distance


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
    pixels, depth = project(vertices, k, rotation, translation)
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
                        silhouette_weight: float = 0.01, smoothness_unconfident: float = 1.0,
                        keep_surface: bool = True) -> np.ndarray:
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
    ``keep_surface``: each round's step is shortened where it would fold the mesh (:func:`step_without_folds`).
    Long: the rounds of one sparse least-squares problem (normal targets, smoothness, anchor, silhouettes).
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
        step = offsets[:, None] * normals
        vertices = vertices + step if not keep_surface else step_without_folds(vertices, faces, step, measured_at)[0]
    return vertices


def step_without_folds(vertices: np.ndarray, faces: np.ndarray, step: np.ndarray, start: np.ndarray | None = None,
                       max_halvings: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``vertices + s_i step_i`` (V, 3) with each vertex's share s_i in [0, 1] as large as keeps the mesh a surface:
    where the full step makes a triangle cross another, flip (against the triangle before the step) or degenerate
    (:func:`sellip.geometry.meshes.surface_defects`), the step of that triangle's vertices and their neighbours is
    halved, and so on (at most ``max_halvings`` times, then withheld). A flip is measured against ``start`` (V, 3),
    the same mesh before the whole update (default: ``vertices``), so that rounds of small turns do not add up to
    one. Triangles that were folded before the step do not count. Returns (the moved vertices, s (V,)).

    A line search per vertex: a step that would fold the surface is longer than the local feature size (a thin
    part, a concavity the normals fitted on another surface), and nothing the rest of the update does can undo a
    fold once made."""
    from sellip.geometry.meshes import surface_defects

    faces = np.asarray(faces, np.int64)
    start = vertices if start is None else start
    folded_before = surface_defects(vertices, faces, start).folding_faces
    share = np.ones(len(vertices))
    for attempt in range(max_halvings + 2):
        moved = vertices + share[:, None] * step
        new = surface_defects(moved, faces, start).folding_faces & ~folded_before
        if not new.any():
            return moved, share
        touched = np.zeros(len(vertices), bool)
        touched[faces[new].ravel()] = True
        ring = np.any(touched[faces], axis=1)
        touched[faces[ring].ravel()] = True
        share[touched] *= 0.5 if attempt < max_halvings else 0.0
    return vertices + share[:, None] * step, share


