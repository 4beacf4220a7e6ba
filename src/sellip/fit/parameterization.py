"""The fit's bounded parameterization (scaled sigmoids: eta in ETA_BOUNDS, sigma_s <= sigma_ss
- LOBE_GAP) and the geometry and reflectance of the virtual specular samples (paper Eq. 24).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sellip.fit.records import ETA_BOUNDS, LOBE_GAP, SIGMA_BOUNDS
from sellip.model import polar
from sellip.model.fresnel import fresnel
from sellip.model.pbrdf import lobe_factor, lobe_stokes

# --- reparameterization -------------------------------------------------------------------

def _to_unit_interval(x, lo, hi):
    return jnp.clip((x - lo) / (hi - lo), 1e-4, 1 - 1e-4)


def _logit(p):
    return jnp.log(p) - jnp.log1p(-p)


def tangent_basis(normal):
    """Two unit tangents (..., 3) orthogonal to ``normal`` and to each other (continuous away from -z)."""
    helper = jnp.where(jnp.abs(normal[..., 2:3]) < 0.9, jnp.array([0.0, 0.0, 1.0], normal.dtype),
                       jnp.array([1.0, 0.0, 0.0], normal.dtype))
    t1 = polar.safe_normalize(jnp.cross(helper, normal))
    return t1, jnp.cross(normal, t1)


class Frame(NamedTuple):
    """Per-vertex constants of the reparameterization."""

    normal0: jnp.ndarray  # (3,)
    t1: jnp.ndarray
    t2: jnp.ndarray


ETA_BOUND_MARGIN = 0.01
"""Of the eta range: a fitted eta this close to either bound is pinned there, not estimated (:func:`eta_at_bound`)."""


def eta_at_bound(eta) -> np.ndarray:
    """(N,) bool: the fitted eta (N,) sits within ETA_BOUND_MARGIN of the range of a bound of ETA_BOUNDS. The data
    pushed it out of the range (a diffuse DoP that is noise: stability ``dark_noisy``, half its vertices at 1.05),
    and its delta-method std collapses with the sigmoid's slope there: it is no estimate of eta."""
    eta = np.asarray(eta, np.float64)
    margin = ETA_BOUND_MARGIN * (ETA_BOUNDS[1] - ETA_BOUNDS[0])
    return (eta < ETA_BOUNDS[0] + margin) | (eta > ETA_BOUNDS[1] - margin)


def eta_from(z_eta):
    """eta from its unconstrained coordinate z[..., 2] (the scaled sigmoid of :func:`decode_parameters`)."""
    return ETA_BOUNDS[0] + (ETA_BOUNDS[1] - ETA_BOUNDS[0]) * jax.nn.sigmoid(z_eta)


def decode_parameters(z, frame: Frame, sigma_ss_fixed):
    """Unconstrained z (5,) -> (normal (3,), eta, sigma_s, sigma_ss).

    sigma_s in [0.01, 1 - LOBE_GAP]; sigma_ss in [sigma_s + LOBE_GAP, 1]: single scattering is the
    broader lobe, and two lobes of equal roughness are one lobe (a flat, degenerate valley).
    sigma_ss_fixed: None (free), a number, or a traced scalar (a vertex's model: NaN = free).
    """
    normal = polar.safe_normalize(frame.normal0 + z[0] * frame.t1 + z[1] * frame.t2, fallback=frame.normal0)
    eta = eta_from(z[2])
    sigma_s = SIGMA_BOUNDS[0] + (SIGMA_BOUNDS[1] - LOBE_GAP - SIGMA_BOUNDS[0]) * jax.nn.sigmoid(z[3])
    if isinstance(sigma_ss_fixed, (int, float)):
        return normal, eta, sigma_s, jnp.asarray(sigma_ss_fixed, z.dtype)
    low = sigma_s + LOBE_GAP
    sigma_ss = low + (SIGMA_BOUNDS[1] - low) * jax.nn.sigmoid(z[4])
    if sigma_ss_fixed is not None:
        fixed = jnp.asarray(sigma_ss_fixed, z.dtype)
        sigma_ss = jnp.where(jnp.isnan(fixed), sigma_ss, fixed)
    return normal, eta, sigma_s, sigma_ss


def encode_parameters(eta, sigma_s, sigma_ss, dtype):
    """Inverse of :func:`decode_parameters` for the scalar parameters (the normal offset starts at 0)."""
    z_eta = _logit(_to_unit_interval(eta, *ETA_BOUNDS))
    z_s = _logit(_to_unit_interval(sigma_s, SIGMA_BOUNDS[0], SIGMA_BOUNDS[1] - LOBE_GAP))
    sigma_s = jnp.clip(sigma_s, SIGMA_BOUNDS[0], SIGMA_BOUNDS[1] - LOBE_GAP)
    z_ss = _logit(_to_unit_interval(sigma_ss, sigma_s + LOBE_GAP, SIGMA_BOUNDS[1]))
    zeros = jnp.zeros_like(z_eta)
    return jnp.stack([zeros, zeros, z_eta, z_s, z_ss], axis=-1).astype(dtype)


# --- virtual samples (specular augmentation) ----------------------------------------------

def virtual_geometry(theta_h, light_distance):
    """The geometry record of exactly coaxial views at half angles theta_h (..., M) radians and flash
    distance light_distance (...,) metres: theta_i = theta_o = theta_h, theta_d = 0. Independent of
    the vertex's normal (a canonical frame), so virtual samples inform the lobes only."""
    theta_h = jnp.asarray(theta_h)
    sin, cos, zero = jnp.sin(theta_h), jnp.cos(theta_h), jnp.zeros_like(theta_h)
    direction = jnp.stack([sin, zero, cos], -1)
    normal = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], theta_h.dtype), direction.shape)
    distance = jnp.broadcast_to(jnp.asarray(light_distance, theta_h.dtype)[..., None], theta_h.shape)
    # Only the geometry record is used; the Stokes part is dead code under jit.
    _, _, geom = lobe_stokes(normal, direction, direction, distance, jnp.broadcast_to(
        jnp.array([0.0, 1.0, 0.0], theta_h.dtype), direction.shape), jnp.stack([-cos, zero, sin], -1),
        jnp.ones_like(theta_h))
    return geom


def virtual_reflectance(theta_h, eta, rho_s, sigma_s, rho_ss, sigma_ss):
    """Reflection lobes per unit shading at coaxial views, R+(0; eta) (rho_s kappa_s + rho_ss kappa_ss):
    the I_s of the lobes divided by S = cos(theta_i) / d^2. theta_h (..., M) radians; eta, rho_s,
    sigma_s, sigma_ss (...,); rho_ss (..., 3). Returns (..., M, 3)."""
    geom = virtual_geometry(theta_h, jnp.ones(jnp.shape(theta_h)[:-1], jnp.asarray(theta_h).dtype))
    r_plus = fresnel(jnp.ones_like(eta), eta).r_plus[..., None]
    lobe_s = lobe_factor(geom, sigma_s[..., None]) * r_plus
    lobe_ss = lobe_factor(geom, sigma_ss[..., None]) * r_plus
    return lobe_s[..., None] * rho_s[..., None, None] + lobe_ss[..., None] * rho_ss[..., None, :]


class Virtual(NamedTuple):
    """One vertex's virtual samples, prepared (M of them)."""

    geom: object  # pbrdf geometry record, each field (M,): coaxial views at the vertex's flash distance
    target: jnp.ndarray  # (M, 3) virtual I_s / scale
    weight: jnp.ndarray  # (M,) lambda_g w^a


