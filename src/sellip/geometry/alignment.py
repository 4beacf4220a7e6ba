"""Sim(3) alignment of camera sets and pose errors (docs/design.md §8: SfM poses are compared after a
similarity alignment).

Poses are COLMAP cam_from_world ``x_cam = R x_world + t`` (:mod:`sellip.model.conventions`), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sellip.model.conventions import camera_center

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


def refine_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, start: Similarity,
                      distances: tuple[float, ...] = (0.05, 0.02, 0.01), samples: int = 100000, seed: int = 0,
                      iterations: int = 50) -> Similarity:
    """``start`` (a similarity from the points' world to the surface's, e.g. :func:`align_cameras`) refined by ICP.

    points (N, 3), e.g. a reconstruction's vertices; the surface a triangle mesh (vertices (V, 3), faces (F, 3)),
    e.g. the ground truth. open3d's point-to-point ICP with scale, onto the surface's vertices and ``samples``
    area-uniform points of it (seeded), correspondences within ``distances`` (fractions of the surface's
    bounding-box diagonal, coarse to fine). Returns the refined similarity, points' world -> surface's world.
    Why the evaluation needs it: docs/benchmarks.md, "The painted cow from SfM".
    """
    import open3d as o3d

    from sellip.geometry.meshes import surface_samples

    vertices = np.asarray(vertices, np.float64)
    # The surface's own vertices among the targets: a model that is the surface moved stays exactly where it is.
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.concatenate([vertices, surface_samples(vertices, np.asarray(faces), samples, seed)])))
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(start.apply(np.asarray(points, np.float64))))
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True)
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    transform = np.eye(4)
    for fraction in distances:
        transform = o3d.pipelines.registration.registration_icp(source, target, fraction * diagonal, transform,
                                                                estimation, criteria).transformation
    linear = transform[:3, :3]
    scale = float(np.cbrt(np.linalg.det(linear)))
    return Similarity(scale, linear / scale, transform[:3, 3]).compose(start)


def pose_errors(rotations: np.ndarray, translations: np.ndarray, ref_rotations: np.ndarray,
                ref_translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per camera: rotation error (deg, angle of R R_ref^T) and camera-centre distance (world units). (N,) each."""
    # ||R - R_ref||_F = 2 sqrt(2) sin(angle / 2): accurate for small angles, unlike arccos of the trace.
    chord = np.linalg.norm(rotations - ref_rotations, axis=(-2, -1)) / (2 * np.sqrt(2))
    centers = camera_center(rotations, translations)
    ref_centers = camera_center(ref_rotations, ref_translations)
    return np.degrees(2 * np.arcsin(np.clip(chord, 0.0, 1.0))), np.linalg.norm(centers - ref_centers, axis=-1)


