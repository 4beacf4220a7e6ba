"""The three-lobe polarimetric BRDF of Hwang et al. 2022 (JAX, batched, channels last).

Two forms:

- :func:`full_mueller` / :func:`full_stokes`: the complete model of docs/design.md §6
  (paper Eqs. 5-11): diffuse = exit transmission o depolarizer o entry
  transmission about the normal; specular and single scattering = Fresnel
  reflection about the half vector, each with its own GGX lobe. Exact
  incident and exitant frames, no coaxial shortcut. Used by the renderer and
  the simulator.
- :func:`coaxial_observations`: the practical model of docs/design.md §5 (paper
  Eqs. 12-18) that the fit inverts: I_d, I_alpha, I_s.

Geometry per (vertex, view): ``normal`` n, ``to_light`` w_i (surface -> flash),
``to_camera`` w_o (surface -> camera), all unit (..., 3) in world
coordinates; ``light_distance`` d (...,) in metres. The flash emits Stokes
[1, 1, 0, 0] in its own frame, x = its polarizer axis (``light_axis``,
projected orthogonal to the beam). Camera-side Stokes vectors are in the
camera frame of the ray (:mod:`sellip.model.conventions`). The shading term
S = (n . w_i) / d^2 is included (unit flash intensity); everything is 0 where
n . w_i <= 0 or n . w_o <= 0.

Shapes: RGB Stokes arrays are ``(..., 4, 3)`` (Stokes component, then colour
last); RGB Mueller matrices are ``(..., 3, 4, 4)``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from sellip.model import polar
from sellip.model.fresnel import fresnel, reflection_mueller, transmission_mueller
from sellip.model.microfacet import ggx_d, smith_g


class PBRDFParams(NamedTuple):
    """Per-point pBRDF parameters with a common batch shape (...)."""

    eta: jnp.ndarray  # (...,) refractive index
    rho_d: jnp.ndarray  # (..., 3) diffuse albedo (no 1/pi; relative: one global scale is free)
    rho_s: jnp.ndarray  # (...,) specular albedo (monochrome: dielectric reflection keeps the light's colour)
    sigma_s: jnp.ndarray  # (...,) specular GGX roughness (alpha = sigma)
    rho_ss: jnp.ndarray  # (..., 3) single-scattering albedo
    sigma_ss: jnp.ndarray  # (...,) single-scattering GGX roughness


class Observations(NamedTuple):
    """The three observations of docs/design.md §5, each (..., 3)."""

    diffuse: jnp.ndarray  # I_d = 2 I90
    diffuse_pol: jnp.ndarray  # I_alpha = I135 - I45
    specular: jnp.ndarray  # I_s = I0 - I90


class _Geometry(NamedTuple):
    cos_i: jnp.ndarray
    cos_o: jnp.ndarray
    cos_h: jnp.ndarray
    cos_d: jnp.ndarray
    lit: jnp.ndarray  # n.w_i > 0 and n.w_o > 0
    shading: jnp.ndarray  # S = cos_i / d^2, 0 where not lit


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _geometry(normal, to_light, to_camera, light_distance) -> _Geometry:
    half = polar.safe_normalize(to_light + to_camera, fallback=normal)
    cos_i = _dot(normal, to_light)
    cos_o = _dot(normal, to_camera)
    lit = (cos_i > 0) & (cos_o > 0)
    shading = jnp.where(lit, cos_i / (light_distance * light_distance), 0)
    return _Geometry(
        cos_i=jnp.clip(cos_i, 0, 1),
        cos_o=jnp.clip(cos_o, 0, 1),
        cos_h=jnp.clip(_dot(normal, half), 0, 1),
        cos_d=jnp.clip(_dot(half, to_light), 0, 1),
        lit=lit,
        shading=shading,
    )


def _lobe_weight(geom: _Geometry, rho, sigma):
    """The lobe term kappa = rho D G / (4 cos_i cos_o), 0 where unlit; rho (...,) or (..., 3) like the result."""
    safe_i = jnp.where(geom.lit, geom.cos_i, 1)
    safe_o = jnp.where(geom.lit, geom.cos_o, 1)
    dg = ggx_d(geom.cos_h, sigma) * smith_g(geom.cos_i, geom.cos_o, sigma) / (4 * safe_i * safe_o)
    dg = jnp.where(geom.lit, dg, 0)
    return dg[..., None] * rho if rho.ndim == dg.ndim + 1 else dg * rho


class _Frames(NamedTuple):
    """The Stokes bases of one (vertex, view): x axes, each (..., 3)."""

    beam_in: jnp.ndarray  # propagation direction of the flash's beam (towards the surface)
    light: jnp.ndarray  # flash frame: its polarizer axis
    camera: jnp.ndarray  # camera frame of the ray: camera up made orthogonal, x = y x w_o
    diffuse_in: jnp.ndarray  # s axis of the plane (n, w_i)
    diffuse_out: jnp.ndarray  # s axis of the plane (n, w_o)
    reflection: jnp.ndarray  # s axis of the plane (w_i, w_o), incoming and outgoing


def _frames(normal, to_light, to_camera, light_axis, camera_up) -> _Frames:
    beam_in = -to_light
    x_light = polar.orthogonal_x_axis(beam_in, light_axis)
    x_camera = polar.frame_x_axis(to_camera, camera_up)
    # At normal incidence (or exact retro-reflection) a plane is undefined and any axis
    # orthogonal to the beam gives the same result: fall back to the flash/camera axis.
    return _Frames(
        beam_in=beam_in, light=x_light, camera=x_camera,
        diffuse_in=polar.safe_normalize(jnp.cross(normal, to_light), fallback=x_light),
        diffuse_out=polar.safe_normalize(jnp.cross(normal, to_camera), fallback=x_camera),
        reflection=polar.safe_normalize(jnp.cross(to_camera, to_light), fallback=x_light),
    )


def _unit_muellers(normal, to_light, to_camera, light_axis, camera_up, eta, geom: _Geometry):
    """Mueller matrices (..., 4, 4) of the diffuse and the reflection lobes for unit albedo,
    from the flash frame to the camera frame, without shading or lobe weights."""
    f = _frames(normal, to_light, to_camera, light_axis, camera_up)
    # Diffuse: exit transmission o depolarizer o entry transmission; only s0 survives the depolarizer.
    entry = transmission_mueller(geom.cos_i, eta) @ polar.frame_rotation(f.beam_in, f.light, f.diffuse_in)
    exit_column = transmission_mueller(geom.cos_o, eta)[..., :, 0]
    diffuse = (polar.frame_rotation(to_camera, f.diffuse_out, f.camera)
               @ (exit_column[..., :, None] * entry[..., None, 0, :]))
    # Reflection about the half vector, in the s/p frame of the plane (w_i, w_o).
    reflection = (polar.frame_rotation(to_camera, f.reflection, f.camera)
                  @ reflection_mueller(geom.cos_d, eta)
                  @ polar.frame_rotation(f.beam_in, f.light, f.reflection))
    return diffuse, reflection


class ViewFrames(NamedTuple):
    """The normal-independent terms of the reflection lobe and the light/camera frames of one
    (vertex, view) (:func:`view_frames`): a fit evaluates them once, not at every normal."""

    half: jnp.ndarray  # (..., 3) half vector of w_i and w_o
    cos_d: jnp.ndarray  # (...,) cos theta_d = h . w_i
    light: jnp.ndarray  # (..., 3) x axis of the flash frame (its polarizer axis)
    camera: jnp.ndarray  # (..., 3) x axis of the camera frame of the ray
    light_to_reflection: tuple  # (cos 2theta, sin 2theta) flash frame -> reflection plane, each (...,)
    reflection_to_camera: tuple  # (cos 2theta, sin 2theta) reflection plane -> camera frame


def view_frames(to_light, to_camera, light_axis, camera_up) -> ViewFrames:
    """:class:`ViewFrames` of views (..., 3) (the arguments of :func:`lobe_stokes`)."""
    beam_in = -to_light
    x_light = polar.orthogonal_x_axis(beam_in, light_axis)
    x_camera = polar.frame_x_axis(to_camera, camera_up)
    reflection = polar.safe_normalize(jnp.cross(to_camera, to_light), fallback=x_light)
    half = polar.safe_normalize(to_light + to_camera)
    return ViewFrames(half=half, cos_d=jnp.clip(_dot(half, to_light), 0, 1), light=x_light, camera=x_camera,
                      light_to_reflection=polar.frame_rotation_terms(beam_in, x_light, reflection),
                      reflection_to_camera=polar.frame_rotation_terms(to_camera, reflection, x_camera))


class SurfaceTerms(NamedTuple):
    """The normal-dependent terms of one (vertex, view) (:func:`surface_terms`), all (...,)."""

    geometry: _Geometry
    entry_cos: jnp.ndarray  # cos 2theta of the flash frame -> plane (n, w_i)
    exit_rotation: tuple  # (cos 2theta, sin 2theta) plane (n, w_o) -> camera frame


def surface_terms(normal, to_light, to_camera, light_distance, frames: ViewFrames) -> SurfaceTerms:
    """:class:`SurfaceTerms` of a surface with ``normal`` (..., 3) seen in views with ``frames``."""
    cos_i = _dot(normal, to_light)
    cos_o = _dot(normal, to_camera)
    lit = (cos_i > 0) & (cos_o > 0)
    half = jnp.where(jnp.sum(frames.half * frames.half, -1, keepdims=True) > 0, frames.half, normal)
    geom = _Geometry(cos_i=jnp.clip(cos_i, 0, 1), cos_o=jnp.clip(cos_o, 0, 1), cos_h=jnp.clip(_dot(normal, half), 0, 1),
                     cos_d=frames.cos_d, lit=lit,
                     shading=jnp.where(lit, cos_i / (light_distance * light_distance), 0))
    diffuse_in = polar.safe_normalize(jnp.cross(normal, to_light), fallback=frames.light)
    diffuse_out = polar.safe_normalize(jnp.cross(normal, to_camera), fallback=frames.camera)
    entry_cos, _ = polar.frame_rotation_terms(-to_light, frames.light, diffuse_in)
    return SurfaceTerms(geom, entry_cos, polar.frame_rotation_terms(to_camera, diffuse_out, frames.camera))


def reflection_stokes(frames: ViewFrames, eta):
    """The reflection lobe's unit Stokes vector (s0, s1, s2) (..., 3) in the camera frame, before the
    shading and the lobe factor: normal-independent (Fresnel at theta_d about the half vector)."""
    f_d = fresnel(frames.cos_d, eta)
    cos_r, sin_r = frames.light_to_reflection
    r0 = f_d.r_plus + f_d.r_minus * cos_r
    r1 = f_d.r_minus + f_d.r_plus * cos_r
    r2 = -f_d.r_s_r_p * sin_r
    r1, r2 = polar.rotate_linear_stokes(r1, r2, *frames.reflection_to_camera)
    return jnp.stack([r0, r1, r2], axis=-1)


def diffuse_stokes(surface: SurfaceTerms, eta):
    """The diffuse lobe's unit Stokes vector (s0, s1, s2) (..., 3) in the camera frame, before the
    shading: entry transmission, depolarization, exit transmission about the normal. s3 stays 0:
    dielectric interfaces without total internal reflection introduce no retardance but 0 or pi."""
    f_i = fresnel(surface.geometry.cos_i, eta)
    f_o = fresnel(surface.geometry.cos_o, eta)
    inside = f_i.t_plus + f_i.t_minus * surface.entry_cos
    s1, s2 = polar.rotate_linear_stokes(f_o.t_minus, jnp.zeros_like(inside), *surface.exit_rotation)
    return inside[..., None] * jnp.stack([f_o.t_plus, s1, s2], axis=-1)


def full_mueller(normal, to_light, to_camera, light_distance, light_axis, camera_up, params: PBRDFParams):
    """The full pBRDF as RGB Mueller matrices S * P, (..., 3, 4, 4), flash frame -> camera frame.

    normal, to_light, to_camera, light_axis, camera_up: (..., 3) world coordinates (the first
    three unit); light_distance: (...,) metres. params: batch shape (...).
    """
    geom = _geometry(normal, to_light, to_camera, light_distance)
    diffuse, reflection = _unit_muellers(normal, to_light, to_camera, light_axis, camera_up, params.eta, geom)
    shading = geom.shading[..., None]
    w_diffuse = shading * params.rho_d  # (..., 3)
    w_reflect = shading * (
        _lobe_weight(geom, params.rho_s, params.sigma_s)[..., None]
        + _lobe_weight(geom, params.rho_ss, params.sigma_ss)
    )
    return (
        w_diffuse[..., :, None, None] * diffuse[..., None, :, :]
        + w_reflect[..., :, None, None] * reflection[..., None, :, :]
    )


def lobe_stokes(normal, to_light, to_camera, light_distance, light_axis, camera_up, eta):
    """Stokes vectors (..., 4) of the two lobe shapes for unit albedo and unit lobe factor, with S.

    Returns ``(diffuse, reflection, geometry)``: the diffuse lobe for rho_d = 1; the reflection
    lobe (specular and single scattering share it) before its factor kappa / rho = D G / (4 cos_i cos_o),
    which :func:`lobe_factor` gives; and the geometry record for :func:`lobe_factor`.
    The full model is ``rho_d diffuse + (rho_s kappa_s + rho_ss kappa_ss) reflection``.
    Composed of :func:`view_frames`, :func:`surface_terms`, :func:`diffuse_stokes` and
    :func:`reflection_stokes` (the same chain of frames and Fresnel terms as :func:`full_mueller`,
    applied to the flash's [1, 1, 0, 0] instead of composing 4x4 matrices).
    """
    frames = view_frames(to_light, to_camera, light_axis, camera_up)
    surface = surface_terms(normal, to_light, to_camera, light_distance, frames)
    shading = surface.geometry.shading[..., None]
    zero = jnp.zeros_like(shading)
    return (jnp.concatenate([shading * diffuse_stokes(surface, eta), zero], -1),
            jnp.concatenate([shading * reflection_stokes(frames, eta), zero], -1), surface.geometry)


def lobe_factor(geom: _Geometry, sigma):
    """D G / (4 cos_i cos_o) of a GGX lobe of roughness sigma at the geometry of :func:`lobe_stokes`; (...,)."""
    return _lobe_weight(geom, jnp.ones_like(sigma), sigma)


def full_stokes(normal, to_light, to_camera, light_distance, light_axis, camera_up, params: PBRDFParams):
    """Stokes vectors (..., 4, 3) reaching the camera from a unit flash emitting [1, 1, 0, 0].

    Same arguments as :func:`full_mueller`. Cheaper than forming the Mueller matrices.
    """
    stokes_d, stokes_r, geom = lobe_stokes(normal, to_light, to_camera, light_distance, light_axis, camera_up,
                                           params.eta)
    w_reflect = lobe_factor(geom, params.sigma_s)[..., None] * params.rho_s[..., None] + (
        lobe_factor(geom, params.sigma_ss)[..., None] * params.rho_ss)
    return stokes_d[..., :, None] * params.rho_d[..., None, :] + stokes_r[..., :, None] * w_reflect[..., None, :]


def normal_azimuth_terms(normal, to_camera, camera_up):
    """(sin 2phi_o, cos 2phi_o) of the normal's azimuth phi_o in the camera frame of the ray.

    phi_o = atan2(n . y, n . x) with (x, y) the camera Stokes frame of w_o. Where the normal
    points straight at the camera the azimuth is undefined; (0, 1) is returned there (every
    term it multiplies vanishes at normal exitance). Each (...,).
    """
    x_camera = polar.frame_x_axis(to_camera, camera_up)
    y_camera = jnp.cross(to_camera, x_camera)
    a = _dot(normal, x_camera)
    b = _dot(normal, y_camera)
    r2 = a * a + b * b
    ok = r2 > jnp.finfo(r2.dtype).eps ** 2
    r2_safe = jnp.where(ok, r2, 1)
    return jnp.where(ok, 2 * a * b / r2_safe, 0), jnp.where(ok, (a * a - b * b) / r2_safe, 1)


def coaxial_observations(normal, to_light, to_camera, light_distance, camera_up, params: PBRDFParams) -> Observations:
    """The practical near-coaxial model of docs/design.md §5 (paper Eqs. 15-18).

    I_d = S rho_d T+_i T+_o;  I_alpha = S rho_d T-_o T+_i sin 2phi_o;
    I_s = S (kappa_s R+ + kappa_ss R+ - rho_d T-_o T+_i cos 2phi_o),
    with T at the incident and exitant angles, R+ at theta_d, and kappa_x = rho_x D G / (4 cos_i cos_o).
    Same geometry arguments as :func:`full_mueller` (no light axis: the flash is assumed co-polarized
    with the camera's 0-degree analyzer). Returns :class:`Observations`, each (..., 3).
    """
    geom = _geometry(normal, to_light, to_camera, light_distance)
    f_i = fresnel(geom.cos_i, params.eta)
    f_o = fresnel(geom.cos_o, params.eta)
    r_plus = fresnel(geom.cos_d, params.eta).r_plus
    sin_2phi, cos_2phi = normal_azimuth_terms(normal, to_camera, camera_up)
    shading = geom.shading[..., None]
    diffuse = shading * params.rho_d * (f_i.t_plus * f_o.t_plus)[..., None]
    polarized = shading * params.rho_d * (f_o.t_minus * f_i.t_plus)[..., None]
    specular = shading * r_plus[..., None] * (
        _lobe_weight(geom, params.rho_s, params.sigma_s)[..., None]
        + _lobe_weight(geom, params.rho_ss, params.sigma_ss)
    )
    return Observations(
        diffuse=diffuse,
        diffuse_pol=polarized * sin_2phi[..., None],
        specular=specular - polarized * cos_2phi[..., None],
    )
