"""Fresnel terms of a smooth dielectric interface between air and index ``eta`` (JAX, batched).

All angles are air-side: ``cos_theta`` is the cosine between the surface (or
microfacet) normal and the air-side ray. Exit transmission at an air-side
angle theta_o equals entry transmission at theta_o (reciprocity), so one
function serves the incident and the exitant sides (anchor notes §3.1).

Amplitude coefficients use the convention in which, below Brewster's angle,
r_s < 0 < r_p, so the retardance of reflection is cos(delta) = -1 there and +1
above it (paper §3.1); at normal incidence the reflected Stokes vector keeps
s1 and flips s2, s3 (a mirror image), as in Mitsuba 3.

Mueller matrices are expressed in the s/p frame: x = s (perpendicular to the
plane of incidence) for both the incoming and the outgoing beam, so s1 > 0
means s-polarized (paper Eq. 2: the (0, 1) element is (F_perp - F_par) / 2).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from sellip.model.polar import safe_sqrt


class FresnelTerms(NamedTuple):
    """Intensity coefficients for one interface crossing; each (...,)."""

    r_perp: jnp.ndarray  # R_s, reflectance of s-polarized light
    r_par: jnp.ndarray  # R_p, reflectance of p-polarized light
    r_s_r_p: jnp.ndarray  # signed product of the amplitude coefficients r_s * r_p (= R_x cos(delta))

    @property
    def t_perp(self):
        return 1 - self.r_perp

    @property
    def t_par(self):
        return 1 - self.r_par

    @property
    def r_plus(self):
        """R+ = (R_s + R_p) / 2."""
        return 0.5 * (self.r_perp + self.r_par)

    @property
    def r_minus(self):
        """R- = (R_s - R_p) / 2 (>= 0 for a dielectric)."""
        return 0.5 * (self.r_perp - self.r_par)

    @property
    def r_cross(self):
        """R_x = sqrt(R_s R_p) = |r_s r_p|."""
        return jnp.abs(self.r_s_r_p)

    @property
    def cos_delta(self):
        """Retardance of reflection: -1 below Brewster's angle, +1 above (0 exactly at it)."""
        return jnp.sign(self.r_s_r_p)

    @property
    def t_plus(self):
        """T+ = (T_s + T_p) / 2."""
        return 1 - self.r_plus

    @property
    def t_minus(self):
        """T- = (T_s - T_p) / 2 (<= 0: transmission favours p)."""
        return -self.r_minus

    @property
    def t_cross(self):
        """sqrt(T_s T_p)."""
        return safe_sqrt(self.t_perp * self.t_par)


def fresnel(cos_theta, eta) -> FresnelTerms:
    """Fresnel coefficients of air -> dielectric of index ``eta`` (> 1) at air-side angle theta.

    cos_theta: (...,) clipped to [0, 1]; eta: broadcastable to (...,).
    Gradients are finite for cos_theta in [0, 1] (normal and grazing incidence).
    """
    cos_i = jnp.clip(cos_theta, 0, 1)
    sin2_t = (1 - cos_i * cos_i) / (eta * eta)
    cos_t = jnp.sqrt(1 - sin2_t)  # sin2_t < 1 for eta > 1: no singularity
    r_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    r_p = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return FresnelTerms(r_perp=r_s * r_s, r_par=r_p * r_p, r_s_r_p=r_s * r_p)


def brewster_angle(eta):
    """Brewster's angle atan(eta), radians."""
    return jnp.arctan(eta)


def diffuse_dop(cos_theta, eta):
    """Degree of polarization of diffuse light leaving at air-side angle theta: |T-/T+| (paper Eq. 20).

    Equals the Atkinson-Hancock formula; 0 at normal incidence, grows with the zenith angle.
    """
    f = fresnel(cos_theta, eta)
    return -f.t_minus / f.t_plus


def _mueller_from(a, b, c):
    """[[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, 0], [0, 0, 0, c]] for (...,) arrays."""
    zero = jnp.zeros_like(a)
    rows = [[a, b, zero, zero], [b, a, zero, zero], [zero, zero, c, zero], [zero, zero, zero, c]]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def reflection_mueller(cos_theta_d, eta):
    """Mueller matrix F^R of specular reflection in the s/p frame (paper Eq. 2 with sin(delta) = 0).

    cos_theta_d: (...,) cosine between the microfacet normal and the incident ray. -> (..., 4, 4).
    """
    f = fresnel(cos_theta_d, eta)
    return _mueller_from(f.r_plus, f.r_minus, f.r_s_r_p)


def transmission_mueller(cos_theta, eta):
    """Mueller matrix F^T of transmission through the interface in the s/p frame (paper Eq. 2, delta = 0).

    cos_theta: (...,) air-side angle cosine (entry or exit). -> (..., 4, 4).
    """
    f = fresnel(cos_theta, eta)
    return _mueller_from(f.t_plus, f.t_minus, f.t_cross)
