"""Per-vertex observations simulated with the full forward model: inputs with known answers
for the fit's tests and benchmark (no mesh, no images: one surface point per vertex)."""

from __future__ import annotations

import numpy as np

from sellip.model.pbrdf import PBRDFParams


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def vertex_observations(rng: np.random.Generator, params: PBRDFParams, normals, n_views: int = 40,
                        flash_offset_m: float = 0.05, distance: float = 0.9, max_zenith_deg: float = 75.0,
                        noise: float = 0.0, dtype=np.float64, view_axes=None, chunk: int = 4096):
    """Observations of N surface points (at the origin) seen by K cameras, from the full pBRDF.

    params: PBRDFParams with batch (N,); normals (N, 3). Cameras look at the point from
    ``distance`` metres, spread over directions within ``max_zenith_deg`` of each normal (or of
    ``view_axes`` (N, 3)) with a random roll; the flash sits ``flash_offset_m`` above the lens
    (camera up), polarized along the image x axis. ``noise``: Gaussian noise on the four analyzer
    intensities, relative to the point's mean intensity. Views from behind the surface (or
    unlit) are marked unusable. Returns a :class:`sellip.fit.records.Observations` of numpy arrays (N, K, ...).
    """
    import jax.numpy as jnp

    from sellip.fit.records import Observations
    from sellip.model import conventions
    from sellip.model.pbrdf import full_stokes

    normals = _unit(normals)
    n = normals.shape[0]
    axes = normals if view_axes is None else _unit(view_axes)
    t1 = _unit(np.cross(np.where(np.abs(axes[:, 2:3]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]]), axes))
    t2 = np.cross(axes, t1)
    zen = np.radians(rng.uniform(3, max_zenith_deg, (n, n_views)))
    azi = rng.uniform(0, 2 * np.pi, (n, n_views))
    to_camera = (np.cos(zen)[..., None] * axes[:, None] + np.sin(zen)[..., None] *
                 (np.cos(azi)[..., None] * t1[:, None] + np.sin(azi)[..., None] * t2[:, None]))
    forward = -to_camera
    right = _unit(np.cross(_unit(rng.normal(size=(n, n_views, 3))), forward))
    up = np.cross(forward, right)  # OpenCV: right x down = forward, so up = forward x right
    flash = distance * to_camera + flash_offset_m * up
    to_light = _unit(flash)
    light_distance = np.linalg.norm(flash, axis=-1)
    analyzers = np.empty((n, n_views, 4, 3), dtype)
    for start in range(0, n, chunk):
        rows = slice(start, min(n, start + chunk))
        as_j = lambda x: jnp.asarray(x[rows], dtype)  # noqa: B023 - called in this iteration
        point_params = PBRDFParams(*[jnp.broadcast_to(jnp.asarray(np.asarray(p)[rows], dtype)[:, None],
                                                      (rows.stop - rows.start, n_views) + np.shape(p)[1:])
                                     for p in params])
        normal = jnp.broadcast_to(as_j(normals)[:, None], (rows.stop - rows.start, n_views, 3))
        stokes = full_stokes(normal, as_j(to_light), as_j(to_camera), as_j(light_distance), as_j(right), as_j(up),
                             point_params)
        analyzers[rows] = np.asarray(conventions.stokes_to_analyzers(stokes, axis=-2))
    if noise:
        level = analyzers.mean(axis=(1, 2, 3), keepdims=True)
        analyzers = analyzers + (noise * level * rng.normal(size=analyzers.shape)).astype(dtype)
    i_d, i_a, i_s = conventions.observations_from_analyzers(analyzers)
    usable = (np.sum(normals[:, None] * to_camera, -1) > 0.05) & (np.sum(normals[:, None] * to_light, -1) > 0.05)
    cast = lambda x: np.asarray(x, dtype)
    return Observations(diffuse=cast(i_d), diffuse_pol=cast(i_a), specular=cast(i_s), to_light=cast(to_light),
                        to_camera=cast(to_camera), light_distance=cast(light_distance), camera_up=cast(up),
                        light_axis=cast(right), usable=usable)
