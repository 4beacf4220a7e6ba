"""Carving what the visual hull bridges: for each vertex, the depth along its inward normal at which the
photographs agree (multi-view photo-consistency), and how sure that is (docs/geometry_update.md, "Concavities").

A hull bridges a hollow that no silhouette shows (the bowl of a cup, the gap between legs): its vertices float
above the true surface, each view sees a different part of the hollow through them, and the fit finds no normal
that explains all views (the vertices are unconfident, and the normal integration holds them where they are). Along
the inward normal of such a vertex lies the depth at which the views see the same texture. For candidate depths
``delta`` the point ``x - delta n`` is given a small patch in the plane perpendicular to ``n`` (3 x 3 points,
``spacing`` apart); each view where the vertex faces the camera and is not hidden by the current mesh samples the
patch's colours (bilinear, every channel); the views' patch vectors, each centred and scaled to unit length (the
flash's shading changes each view's gain, not the pattern), are compared by their mean pairwise correlation
(normalised cross-correlation: 1 where all views agree). The best depth is kept where it beats the current
surface by ``margin`` and scores at least ``min_score``, with textured patches (relative contrast at least
``min_contrast``) in at least ``min_views`` views. A textureless surface gives no target: its concavity is not
seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATCH = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], np.float64)
"""The patch's points in units of ``spacing`` along two tangent directions (9 points)."""


@dataclass(frozen=True)
class CarveView:
    """One photograph for photo-consistency: ``image`` (H, W, C) float (I_d), ``valid`` (H, W) bool, ``intrinsics``
    (3, 3) of the image's pixel grid, ``rotation`` (3, 3) and ``translation`` (3,): cam_from_world."""

    image: np.ndarray
    valid: np.ndarray
    intrinsics: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        return -self.rotation.T @ self.translation


@dataclass(frozen=True)
class CarveTargets:
    """Per-vertex carving targets: ``vertex`` (K,) indices, ``depth`` (K,) metres inward along the normal from the
    vertices measured, ``weight`` (K,) in (0, 1], ``score`` (K,) the correlation at that depth, ``score_here`` (K,)
    at the current surface."""

    vertex: np.ndarray
    depth: np.ndarray
    weight: np.ndarray
    score: np.ndarray
    score_here: np.ndarray

    def __len__(self) -> int:
        return len(self.vertex)

    @staticmethod
    def none() -> CarveTargets:
        empty = np.zeros(0)
        return CarveTargets(np.zeros(0, np.int64), empty, empty, empty, empty)


def _tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) perpendicular to unit ``normals`` (N, 3) and to each other."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    first = np.cross(normals, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return first, np.cross(normals, first)


def _bilinear(image: np.ndarray, valid: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Colours (..., C) of ``image`` at pixel coordinates (u, v) (...,) and whether all four neighbours are valid."""
    height, width = valid.shape
    inside = (u >= 0) & (v >= 0) & (u <= width - 1.001) & (v <= height - 1.001)
    u, v = np.clip(u, 0, width - 1.001), np.clip(v, 0, height - 1.001)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - u0)[..., None], (v - v0)[..., None]
    colour = ((1 - fu) * (1 - fv) * image[v0, u0] + fu * (1 - fv) * image[v0, u0 + 1]
              + (1 - fu) * fv * image[v0 + 1, u0] + fu * fv * image[v0 + 1, u0 + 1])
    ok = inside & valid[v0, u0] & valid[v0, u0 + 1] & valid[v0 + 1, u0] & valid[v0 + 1, u0 + 1]
    return colour, ok


def photo_consistency(points: np.ndarray, normals: np.ndarray, visible: np.ndarray, views: list[CarveView],
                      depths: np.ndarray, spacing: float, max_views: int = 8, min_contrast: float = 0.05):
    """Mean pairwise correlation of the views' patches at each candidate depth: points (N, 3), unit outward normals
    (N, 3), ``visible`` (N, V) bool (the views that see each point), ``depths`` (D,) metres inward, ``spacing``
    metres between patch points. Each point uses its ``max_views`` most frontal visible views. Returns (score (N, D)
    in [-1, 1], NaN where fewer than 2 views have a textured patch; views (N, D) the count of views compared;
    contrast (N, D) the median relative contrast of the views' patches)."""
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    n, d = len(points), len(depths)
    first, second = _tangents(normals)
    offsets = PATCH[None, :, :1] * first[:, None, :] + PATCH[None, :, 1:] * second[:, None, :]  # (N, P, 3)
    samples = (points[:, None, None, :] - np.asarray(depths)[None, :, None, None] * normals[:, None, None, :]
               + spacing * offsets[:, None, :, :])  # (N, D, P, 3): the patch at every depth
    facing = np.stack([np.sum(normals * (view.centre - points), 1) / np.linalg.norm(view.centre - points, axis=1)
                       for view in views], 1)
    rank = np.argsort(np.argsort(-np.where(visible, facing, -np.inf), axis=1), axis=1)
    chosen = visible & (rank < max_views)
    total = None
    count = np.zeros((n, d))
    contrast_sum = np.zeros((n, d))
    for k, view in enumerate(views):
        rows = np.flatnonzero(chosen[:, k])
        if rows.size == 0:
            continue
        flat = samples[rows].reshape(-1, 3)
        cam = flat @ view.rotation.T + view.translation
        z = np.where(cam[:, 2] > 1e-9, cam[:, 2], np.nan)
        u = view.intrinsics[0, 0] * cam[:, 0] / z + view.intrinsics[0, 1] * cam[:, 1] / z + view.intrinsics[0, 2]
        v = view.intrinsics[1, 1] * cam[:, 1] / z + view.intrinsics[1, 2]
        ok_z = np.isfinite(z)
        colour, ok = _bilinear(view.image, view.valid, np.nan_to_num(u, nan=-1.0), np.nan_to_num(v, nan=-1.0))
        colour = colour.reshape(rows.size, d, len(PATCH), -1)
        ok = (ok & ok_z).reshape(rows.size, d, len(PATCH)).all(-1)
        vector = colour.reshape(rows.size, d, -1).astype(np.float64)
        mean = vector.mean(-1, keepdims=True)
        centred = vector - mean
        norm = np.linalg.norm(centred, axis=-1)
        contrast = norm / np.sqrt(vector.shape[-1]) / np.maximum(mean[..., 0], 1e-12)
        usable = ok & (contrast >= min_contrast)
        unit = np.where(usable[..., None], centred / np.maximum(norm, 1e-30)[..., None], 0.0)
        if total is None:
            total = np.zeros((n, d, unit.shape[-1]))
        total[rows] += unit
        count[rows] += usable
        contrast_sum[rows] += np.where(ok, contrast, 0.0)
    if total is None:
        return np.full((n, d), np.nan), count, np.zeros((n, d))
    squared = np.sum(total ** 2, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(count >= 2, (squared - count) / (count * (count - 1)), np.nan)
    seen = np.maximum(chosen.sum(1), 1)[:, None]
    return score, count, contrast_sum / seen


def carve_targets(vertices: np.ndarray, normals: np.ndarray, candidates: np.ndarray, visible: np.ndarray,
                  views: list[CarveView], max_depth: float, step: float, spacing: float, min_score: float = 0.6,
                  margin: float = 0.15, min_views: int = 3, max_views: int = 8,
                  min_contrast: float = 0.05) -> CarveTargets:
    """The carving targets of the ``candidates`` (K,) among ``vertices`` (V, 3) with unit outward ``normals`` (V, 3):
    depths 0, ``step``, ... up to ``max_depth`` (metres) inward searched by :func:`photo_consistency` (``visible``
    (V, views) bool, ``spacing`` its patch spacing). A vertex gets a target where its best depth is at least one
    step in, scores at least ``min_score`` with at least ``min_views`` textured views, and beats the current surface
    by ``margin``; its weight grows from 0 at that margin to 1 at twice it."""
    candidates = np.asarray(candidates, np.int64)
    if candidates.size == 0 or max_depth < step:
        return CarveTargets.none()
    depths = np.arange(0.0, max_depth + 0.5 * step, step)
    score, count, _ = photo_consistency(vertices[candidates], normals[candidates], visible[candidates], views,
                                        depths, spacing, max_views=max_views, min_contrast=min_contrast)
    usable = np.where(count >= min_views, score, np.nan)
    filled = np.where(np.isfinite(usable), usable, -np.inf)
    best = np.argmax(filled, axis=1)
    best_score = filled[np.arange(len(best)), best]
    here = np.where(np.isfinite(score[:, 0]), score[:, 0], -1.0)
    gain = best_score - here
    keep = (best > 0) & (best_score >= min_score) & (gain >= margin)
    weight = np.clip((gain - margin) / margin, 0.0, 1.0)
    keep &= weight > 0
    return CarveTargets(candidates[keep], depths[best[keep]], weight[keep], best_score[keep], here[keep])
