"""GGX microfacet distribution and separable Smith shadowing (JAX, batched).

The roughness ``sigma`` is the GGX alpha itself (not alpha^2), as in the
paper and the authors' code (anchor notes §3.2-3.3). Both functions are
written without tan() so they stay finite at theta_h = 0 and at grazing
angles; sigma must be > 0 (the fit keeps it above a small floor).
"""

from __future__ import annotations

import jax.numpy as jnp


def ggx_d(cos_theta_h, sigma):
    """GGX normal distribution D(theta_h; sigma) = sigma^2 / (pi cos^4 (sigma^2 + tan^2)^2).

    Written as sigma^2 / (pi (1 + (sigma^2 - 1) cos^2)^2); D(0) = 1 / (pi sigma^2).
    Normalized: the integral of D cos(theta_h) over the hemisphere is 1. 0 for cos <= 0.
    cos_theta_h, sigma: broadcastable (...,).
    """
    c = jnp.clip(cos_theta_h, 0, 1)
    s2 = sigma * sigma
    denom = 1 + (s2 - 1) * c * c
    return jnp.where(cos_theta_h > 0, s2 / (jnp.pi * denom * denom), 0)


def smith_g1(cos_theta, sigma):
    """Smith masking for one direction: 2 / (1 + sqrt(1 + sigma^2 tan^2)) = 2c / (c + sqrt(c^2 + sigma^2 (1 - c^2)))."""
    c = jnp.clip(cos_theta, 0, 1)
    s2 = sigma * sigma
    root = jnp.sqrt(c * c + s2 * (1 - c * c))
    return 2 * c / (c + root)


def smith_g(cos_theta_i, cos_theta_o, sigma):
    """Separable (uncorrelated) Smith shadowing-masking G(theta_i, theta_o; sigma) in [0, 1]."""
    return smith_g1(cos_theta_i, sigma) * smith_g1(cos_theta_o, sigma)
