"""Stokes/Mueller algebra (JAX, batched, channels last).

Stokes vectors are ``(..., 4)`` (s0, s1, s2, s3), Mueller matrices ``(..., 4, 4)``.
A Stokes vector is meaningful only with its reference frame: a unit basis
vector x orthogonal to the propagation direction ("forward"), with
y = forward x x, so (x, y, forward) is right-handed and angles grow from x
towards y, counter-clockwise as seen looking back along the beam
(:mod:`sellip.model.conventions`). This matches Mitsuba 3's ``mueller.h``.
"""

from __future__ import annotations

import jax.numpy as jnp


def safe_sqrt(x):
    """sqrt with a finite gradient at 0 (the double-``where`` pattern)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1)), 0)


def safe_normalize(v, fallback=None):
    """Unit vectors along the last axis; where ``v`` is ~0, ``fallback`` (or 0), with finite gradients."""
    sq = jnp.sum(v * v, axis=-1, keepdims=True)
    tiny = jnp.finfo(v.dtype).tiny ** 0.5
    ok = sq > tiny
    unit = v / jnp.sqrt(jnp.where(ok, sq, 1))
    if fallback is None:
        fallback = jnp.zeros_like(v)
    return jnp.where(ok, unit, fallback)


def rotator_from_cos_sin(cos_2theta, sin_2theta):
    """Mueller matrix of a frame rotation given cos 2theta and sin 2theta; (...,) -> (..., 4, 4).

    Same as :func:`rotator` but without trigonometry, so callers that have the
    double-angle terms from dot products keep exact, finite gradients.
    """
    one = jnp.ones_like(cos_2theta)
    zero = jnp.zeros_like(cos_2theta)
    rows = [
        [one, zero, zero, zero],
        [zero, cos_2theta, sin_2theta, zero],
        [zero, -sin_2theta, cos_2theta, zero],
        [zero, zero, zero, one],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def rotator(theta):
    """The paper's C(theta) (Eq. 1; Mitsuba's ``rotator``): rotates the reference frame by +theta.

    Horizontally polarized light [1, 1, 0, 0] becomes [1, cos 2theta, -sin 2theta, 0].
    theta: (...,) radians -> (..., 4, 4).
    """
    return rotator_from_cos_sin(jnp.cos(2 * theta), jnp.sin(2 * theta))


def linear_polarizer(theta):
    """Mueller matrix of an ideal linear polarizer with its axis at ``theta`` (radians). (...,) -> (..., 4, 4)."""
    half = 0.5 * jnp.ones_like(theta)
    zero = jnp.zeros_like(theta)
    horizontal = jnp.stack(
        [jnp.stack(r, axis=-1) for r in (
            [half, half, zero, zero], [half, half, zero, zero],
            [zero, zero, zero, zero], [zero, zero, zero, zero])],
        axis=-2,
    )
    rot = rotator(theta)
    return jnp.swapaxes(rot, -1, -2) @ horizontal @ rot


def depolarizer(value):
    """Mueller matrix of an ideal depolarizer scaling s0 by ``value``. (...,) -> (..., 4, 4)."""
    return value[..., None, None] * jnp.zeros(value.shape + (4, 4), value.dtype).at[..., 0, 0].set(1)


def dolp(stokes):
    """Degree of linear polarization sqrt(s1^2 + s2^2) / s0 of (..., 4) or (..., 3) Stokes; 0 where s0 <= 0."""
    s0 = stokes[..., 0]
    linear = safe_sqrt(stokes[..., 1] ** 2 + stokes[..., 2] ** 2)
    ok = s0 > 0
    return jnp.where(ok, linear / jnp.where(ok, s0, 1), 0)


def aolp(stokes):
    """Angle of linear polarization 0.5 atan2(s2, s1), radians in (-pi/2, pi/2]."""
    return 0.5 * jnp.arctan2(stokes[..., 2], stokes[..., 1])


def frame_rotation_terms(forward, basis_current, basis_target):
    """(cos 2theta, sin 2theta) of the rotation from one Stokes basis to another; each (...,).

    theta is the angle from ``basis_current`` to ``basis_target``, positive counter-clockwise
    about ``forward`` (all (..., 3), unit, bases orthogonal to ``forward``).
    """
    cos_t = jnp.sum(basis_current * basis_target, axis=-1)
    sin_t = jnp.sum(forward * jnp.cross(basis_current, basis_target), axis=-1)
    return cos_t * cos_t - sin_t * sin_t, 2 * sin_t * cos_t


def frame_rotation(forward, basis_current, basis_target):
    """Mueller matrix re-expressing a Stokes vector from one frame in another (Mitsuba's ``rotate_stokes_basis``).

    forward: (..., 3) unit propagation direction; basis_current, basis_target:
    (..., 3) unit x axes of the two frames, both orthogonal to ``forward``.
    Returns (..., 4, 4) M with ``s_target = M @ s_current``.
    """
    return rotator_from_cos_sin(*frame_rotation_terms(forward, basis_current, basis_target))


def rotate_linear_stokes(s1, s2, cos_2theta, sin_2theta):
    """The linear components (s1, s2) after a frame rotation (the middle block of C(theta))."""
    return cos_2theta * s1 + sin_2theta * s2, -sin_2theta * s1 + cos_2theta * s2


def frame_x_axis(forward, reference_y):
    """x axis of the frame with y closest to ``reference_y`` for a beam along ``forward``.

    y = reference_y with its ``forward`` component removed (normalized), x = y x forward.
    Used for the camera frame (reference_y = camera up). (..., 3) -> (..., 3).
    """
    y = safe_normalize(reference_y - jnp.sum(reference_y * forward, axis=-1, keepdims=True) * forward)
    return jnp.cross(y, forward)


def orthogonal_x_axis(forward, reference_x):
    """x axis closest to ``reference_x`` orthogonal to ``forward`` (e.g. a polarizer axis). (..., 3) -> (..., 3)."""
    return safe_normalize(reference_x - jnp.sum(reference_x * forward, axis=-1, keepdims=True) * forward)
