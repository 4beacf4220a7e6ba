"""Small shared constructors for tests."""

from __future__ import annotations

import numpy as np
import jax.numpy as jnp

from sellip.pbrdf import PBRDFParams


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def make_params(shape=(), eta=1.5, rho_d=(0.5, 0.4, 0.3), rho_s=1.0, sigma_s=0.3,
                rho_ss=(0.2, 0.1, 0.05), sigma_ss=0.6, dtype=jnp.float64) -> PBRDFParams:
    """pBRDF parameters broadcast to a batch shape."""
    def full(value, channels=None):
        target = shape if channels is None else shape + (channels,)
        return jnp.broadcast_to(jnp.asarray(value, dtype), target)

    return PBRDFParams(eta=full(eta), rho_d=full(rho_d, 3), rho_s=full(rho_s), sigma_s=full(sigma_s),
                       rho_ss=full(rho_ss, 3), sigma_ss=full(sigma_ss))


def camera_geometry(theta_deg, azimuth_deg, flash_offset_deg=0.0, distance=0.9, dtype=jnp.float64):
    """A surface point on the optical axis of a camera at the origin (OpenCV axes, up = -y).

    The normal is tilted by ``theta_deg`` from the direction to the camera, with azimuth
    ``azimuth_deg`` in the camera's Stokes frame (x right, y up). The flash sits above the
    camera (image up) so that the light and view rays make ``flash_offset_deg`` at the point.
    Returns arrays for normal, to_light, to_camera, light_distance, light_axis, camera_up.
    """
    theta = np.radians(np.asarray(theta_deg, dtype=np.float64))
    azimuth = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    theta, azimuth = np.broadcast_arrays(theta, azimuth)
    point = np.array([0.0, 0.0, distance])
    flash = np.array([0.0, -distance * np.tan(np.radians(flash_offset_deg)), 0.0])
    to_camera = unit(-point)
    to_light = unit(flash - point)
    normal = np.stack([np.sin(theta) * np.cos(azimuth), -np.sin(theta) * np.sin(azimuth), -np.cos(theta)], -1)
    shape = theta.shape
    as_j = lambda v: jnp.asarray(np.broadcast_to(v, shape + (3,)), dtype)  # noqa: E731
    return dict(
        normal=as_j(normal),
        to_light=as_j(to_light),
        to_camera=as_j(to_camera),
        light_distance=jnp.asarray(np.full(shape, np.linalg.norm(flash - point)), dtype),
        light_axis=as_j(np.array([1.0, 0.0, 0.0])),
        camera_up=as_j(np.array([0.0, -1.0, 0.0])),
    )


def synthetic_observations(rng, params: PBRDFParams, normals, n_views=40, model="coaxial",
                           flash_offset_m=0.05, distance=0.9, max_zenith_deg=75.0, noise=0.0,
                           dtype=jnp.float64):
    """Observations of N vertices (at the origin) seen by K cameras spread over each normal's hemisphere.

    Cameras look at the vertex from ``distance`` metres with a random roll; the flash sits
    ``flash_offset_m`` above the lens (camera up). ``model``: "coaxial" (what the fit assumes)
    or "full" (the complete pBRDF through four analyzers). ``noise``: relative Gaussian noise on
    the four analyzer intensities (or on the three observations for "coaxial").
    Returns a :class:`sellip.fit.Observations`.
    """
    from sellip import conventions
    from sellip.fit import Observations
    from sellip.pbrdf import coaxial_observations, full_stokes

    normals = unit(np.asarray(normals))
    n = normals.shape[0]
    # View directions within max_zenith of the normal, spread in azimuth.
    t1 = unit(np.cross(np.where(np.abs(normals[:, 2:3]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]]), normals))
    t2 = np.cross(normals, t1)
    zen = np.radians(rng.uniform(3, max_zenith_deg, (n, n_views)))
    azi = rng.uniform(0, 2 * np.pi, (n, n_views))
    to_camera = (np.cos(zen)[..., None] * normals[:, None] + np.sin(zen)[..., None] *
                 (np.cos(azi)[..., None] * t1[:, None] + np.sin(azi)[..., None] * t2[:, None]))
    camera = distance * to_camera
    forward = -to_camera
    roll_ref = unit(rng.normal(size=(n, n_views, 3)))
    right = unit(np.cross(roll_ref, forward))
    up = np.cross(forward, right)  # right x up = -forward (OpenCV: y down = -up, z forward)
    flash = camera + flash_offset_m * up
    to_light = unit(flash)
    light_distance = np.linalg.norm(flash, axis=-1)
    as_j = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    nrm = as_j(np.broadcast_to(normals[:, None], (n, n_views, 3)))
    expand = PBRDFParams(*[jnp.broadcast_to(jnp.asarray(p, dtype)[:, None], (n, n_views) + jnp.shape(p)[1:])
                           for p in params])
    if model == "coaxial":
        obs = coaxial_observations(nrm, as_j(to_light), as_j(to_camera), as_j(light_distance), as_j(up), expand)
        i_d, i_a, i_s = obs.diffuse, obs.diffuse_pol, obs.specular
        if noise:
            level = jnp.mean(i_d, axis=(1, 2), keepdims=True)
            i_d, i_a, i_s = (x + noise * level * jnp.asarray(rng.normal(size=x.shape), dtype) for x in (i_d, i_a, i_s))
    else:
        stokes = full_stokes(nrm, as_j(to_light), as_j(to_camera), as_j(light_distance), as_j(right), as_j(up), expand)
        analyzers = conventions.stokes_to_analyzers(stokes, axis=-2)
        if noise:
            level = jnp.mean(analyzers, axis=(1, 2, 3), keepdims=True)
            analyzers = analyzers + noise * level * jnp.asarray(rng.normal(size=analyzers.shape), dtype)
        i_d, i_a, i_s = conventions.observations_from_analyzers(analyzers)
    return Observations(diffuse=i_d, diffuse_pol=i_a, specular=i_s, to_light=as_j(to_light),
                        to_camera=as_j(to_camera), light_distance=as_j(light_distance), camera_up=as_j(up),
                        light_axis=as_j(right), usable=jnp.ones((n, n_views), bool))
