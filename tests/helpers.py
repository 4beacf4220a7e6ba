"""Small shared constructors for tests."""

from __future__ import annotations

import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from sellip.model.pbrdf import PBRDFParams


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
    as_j = lambda v: jnp.asarray(np.broadcast_to(v, shape + (3,)), dtype)
    return dict(
        normal=as_j(normal),
        to_light=as_j(to_light),
        to_camera=as_j(to_camera),
        light_distance=jnp.asarray(np.full(shape, np.linalg.norm(flash - point)), dtype),
        light_axis=as_j(np.array([1.0, 0.0, 0.0])),
        camera_up=as_j(np.array([0.0, -1.0, 0.0])),
    )



def session_jax_cache(folder: Path) -> Path:
    """The XLA cache (and exported kernels) that every workflow run of the pytest session shares, for a test folder
    directly under pytest's base temporary folder (``tmp_path``, ``tmp_path_factory.mktemp(...)``): a later run loads
    the kernels an earlier one compiled, as a user's second run would. Under pytest-xdist (``make test``) each worker
    has its own base folder (``BASE/popen-gwN``): the cache sits in ``BASE``, one for all workers (concurrent jobs
    share it safely, as a run's fit shards do)."""
    base = Path(folder).parent
    return (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "jax_cache"
