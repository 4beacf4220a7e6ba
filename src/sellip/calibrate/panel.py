"""The light panel behind the synthetic spheres (:mod:`sellip.calibrate.synthetic`), mirrored by them.

Public API::

    PANEL_DISTANCE_M, PANEL_HALF_SIZE_M                  # the panel: the plane z = 1 m, 2 m x 2 m about the axis
    panel_reflection(points, normals, eta, panel) -> analyzers (N, 4)   # the panel mirrored, Fresnel-polarized
"""

from __future__ import annotations

import numpy as np

PANEL_DISTANCE_M = 1.0
"""The light panel behind the spheres: the plane z = this (camera coordinates), 2 m x 2 m about the optical axis."""

PANEL_HALF_SIZE_M = 1.0


def panel_reflection(points: np.ndarray, normals: np.ndarray, eta: float, panel: float) -> np.ndarray:
    """Analyzer intensities (N, 4) of the light panel mirrored by a glossy dielectric at surface points (N, 3)
    with normals (N, 3) (camera coordinates): where the mirror ray of the camera ray meets the panel
    (:data:`PANEL_DISTANCE_M`), the panel's unpolarized radiance ``panel`` (s0) times the Fresnel reflectance,
    R+ = (Rs + Rp) / 2, polarized by R- = (Rs - Rp) / 2 across the plane of incidence (s-polarized: along d x n),
    in the ray's Stokes frame (sellip.conventions). On a sphere's limb that is tangential, perpendicular to the
    diffuse light's radial polarization; at grazing incidence Rs, Rp -> 1, so the limb mirrors the panel."""
    from sellip.model.conventions import stokes_to_analyzers

    d = points / np.linalg.norm(points, axis=-1, keepdims=True)
    cos_i = np.clip(-np.sum(d * normals, axis=-1), 0.0, 1.0)
    mirror = d + 2 * cos_i[:, None] * normals
    t = (PANEL_DISTANCE_M - points[:, 2]) / np.where(mirror[:, 2] > 1e-9, mirror[:, 2], np.nan)
    hit = points + t[:, None] * mirror
    on_panel = ((mirror[:, 2] > 1e-9) & (np.abs(hit[:, 0]) <= PANEL_HALF_SIZE_M)
                & (np.abs(hit[:, 1]) <= PANEL_HALF_SIZE_M))
    sin2_t = (1 - cos_i ** 2) / eta ** 2
    cos_t = np.sqrt(1 - sin2_t)
    r_s = ((cos_i - eta * cos_t) / (cos_i + eta * cos_t)) ** 2
    r_p = ((eta * cos_i - cos_t) / (eta * cos_i + cos_t)) ** 2
    # the ray's Stokes frame: z towards the camera, y the camera's up without its z part, x = y x z
    z = -d
    up = np.array([0.0, -1.0, 0.0])
    y_axis = up - (z @ up)[:, None] * z
    y_axis /= np.linalg.norm(y_axis, axis=-1, keepdims=True)
    x_axis = np.cross(y_axis, z)
    s_dir = np.cross(d, normals)
    s_dir /= np.maximum(np.linalg.norm(s_dir, axis=-1, keepdims=True), 1e-12)
    psi = np.arctan2(np.sum(s_dir * y_axis, -1), np.sum(s_dir * x_axis, -1))
    level = np.where(on_panel, panel, 0.0)
    plus, minus = level * (r_s + r_p) / 2, level * (r_s - r_p) / 2
    stokes = np.stack([plus, minus * np.cos(2 * psi), minus * np.sin(2 * psi)], axis=-1)
    return np.asarray(stokes_to_analyzers(stokes, axis=-1), np.float32)
