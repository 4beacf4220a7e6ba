"""The residuals of one vertex (docs/design.md §5): the linear parameters (rho_d RGB, rho_s, rho_ss RGB)
solved in closed form with non-negativity inside the residual (variable projection), then

    lambda_psi  sum_k w_k (psi_hat(theta_o, eta) - psi_k)^2          (DoP)
  + lambda_d    sum_k w_k sum_c (I_d_hat - I_d)^2                   (diffuse)
  + lambda_s    sum_k w_k sum_c (I_s_hat - I_s)^2                   (specular)
  + lambda_phi  sum_k w_k [(I_a + G sin 2phi)^2 + (I_b - G cos 2phi)^2]   (azimuth)

with view weights w_k = v_k / sum(v) and every intensity divided by the vertex's own diffuse level
(dimensionless). psi_k = G_k / I_d,k with G = sqrt(I_alpha^2 + I_beta^2) on the colour-weighted mono signals,
I_beta = I_s minus both predicted specular lobes (docs/design.md §7). The azimuth term equals the paper's
2 w Gamma^2 (1 - cos(2 phi_hat - 2 phi_I)).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from sellip.fit.parameterization import Frame, Virtual, decode_parameters
from sellip.fit.records import FitSettings
from sellip.model import polar
from sellip.model.conventions import observations_from_analyzers, stokes_to_analyzers
from sellip.model.fresnel import fresnel
from sellip.model.pbrdf import ViewFrames, diffuse_stokes, lobe_factor, reflection_stokes, surface_terms, view_frames

# --- closed-form linear parameters ---------------------------------------------------------

def solve_spd(matrix, rhs):
    """Solve ``matrix @ x = rhs`` for one small symmetric positive-definite (n, n) matrix.

    An unrolled Cholesky written with elementwise operations only: under ``vmap`` it becomes
    a few fused array operations instead of one LAPACK call per vertex. rhs: (n,) or (n, m).
    """
    n = matrix.shape[-1]
    tiny = jnp.finfo(matrix.dtype).tiny ** 0.5
    low = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            acc = matrix[i, j] - sum(low[i][k] * low[j][k] for k in range(j))
            low[i][j] = jnp.sqrt(jnp.maximum(acc, tiny)) if i == j else acc / low[j][j]
    y = []
    for i in range(n):
        y.append((rhs[i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i])
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return jnp.stack(x)


def nnls_specular(a, b, y, weight, prior, ridge):
    """Exact non-negative least squares for (rho_s, rho_ss RGB) with a small ridge towards ``prior``.

    Minimizes sum_k weight_k sum_c (rho_s a_k + rho_ss_c b_k - y_kc)^2 + ridge |x - prior|^2 over x >= 0.
    a, b: (K,), y: (K, 3), weight: (K,), prior: (4,). Returns (4,) = (rho_s, rho_ss RGB).

    The normal matrix has an arrow shape (rho_s couples to each channel, channels are independent),
    so every active set has a closed-form solution; the 9 candidates (rho_s = 0 with clamped
    channels, or rho_s free with any subset of free channels) are evaluated and the best feasible
    one is exact. Elementwise operations only.
    """
    wa, wb = weight * a, weight * b
    return _nnls_specular_gram(jnp.sum(wa * a), jnp.sum(wa * b), jnp.sum(wb * b), wa @ y, wb @ y, prior, ridge)


def _nnls_specular_gram(g_aa, g_ab, g_bb, y_a, y_b, prior, ridge):
    """:func:`nnls_specular` from its inner products: g_aa = sum w a^2, g_ab = sum w a b,
    g_bb = sum w b^2 (scalars), y_a = sum_k w_k a_k y_k, y_b = sum_k w_k b_k y_k ((3,) each)."""
    g00 = 3 * g_aa + ridge
    g0c = g_ab
    gcc = g_bb + ridge
    r0 = jnp.sum(y_a) + ridge * prior[0]
    rc = y_b + ridge * prior[1:]  # (3,)
    dtype = rc.dtype

    subsets = ((jnp.arange(8)[:, None] >> jnp.arange(3)[None, :]) & 1).astype(dtype)  # (8, 3), 1 = free
    n_free = jnp.sum(subsets, -1)
    rho_s = (r0 - g0c * (subsets @ rc) / gcc) / (g00 - n_free * g0c**2 / gcc)  # (8,)
    rho_ss = subsets * (rc[None, :] - g0c * rho_s[:, None]) / gcc  # (8, 3)
    feasible = (rho_s >= 0) & jnp.all(rho_ss >= 0, -1)
    rho_ss_only = jnp.maximum(rc / gcc, 0)  # rho_s = 0: channels independent
    cand_s = jnp.concatenate([jnp.zeros(1, dtype), rho_s])
    cand_ss = jnp.concatenate([rho_ss_only[None], rho_ss])
    cost = (g00 * cand_s**2 + 2 * g0c * cand_s * jnp.sum(cand_ss, -1) + gcc * jnp.sum(cand_ss**2, -1)
            - 2 * (r0 * cand_s + cand_ss @ rc))  # (9,) the objective up to a constant
    best = jnp.argmin(jnp.where(jnp.concatenate([jnp.ones(1, bool), feasible]), cost, jnp.inf))
    return jnp.concatenate([cand_s[best][None], cand_ss[best]])


# --- residuals ---------------------------------------------------------------------------

class Vertex(NamedTuple):
    """One vertex's prepared data (K view slots)."""

    obs_d: jnp.ndarray  # (K, 3) I_d / scale
    obs_a: jnp.ndarray  # (K, 3) I_alpha / scale
    obs_s: jnp.ndarray  # (K, 3) I_s / scale
    to_light: jnp.ndarray
    to_camera: jnp.ndarray
    light_distance: jnp.ndarray
    camera_up: jnp.ndarray
    light_axis: jnp.ndarray
    weight: jnp.ndarray  # (K,) view weights w_k (sum 1 over used views)
    color: jnp.ndarray  # (3,) channel weights for the mono DoP / azimuth signals (sum 1)
    scale: jnp.ndarray  # () the vertex's diffuse level (intensity units)
    prior: jnp.ndarray  # (4,) rho_s, rho_ss RGB warm start (already divided by scale)
    virtual: Virtual | None = None  # virtual specular samples (augmentation), or none
    frames: ViewFrames | None = None  # (K,) the normal-independent frames (:func:`_prepare`), or computed on use
    lobe_mask: jnp.ndarray | None = None  # (2,) 1/0: the vertex's model has the specular, single-scattering lobe
    sigma_ss_fixed: jnp.ndarray | None = None  # () the model's fixed sigma_ss, NaN where it is free
    eta_diffuse: jnp.ndarray | None = None  # () eta of the diffuse intensity's transmissions (held), or the fitted eta


def fixed_sigma_ss(v: Vertex, settings: FitSettings):
    """sigma_ss_fixed for :func:`decode_parameters`: the vertex's own model where it has one, else the settings'."""
    return settings.sigma_ss_fixed if v.sigma_ss_fixed is None else v.sigma_ss_fixed


def _view_frames(v: Vertex) -> ViewFrames:
    if v.frames is not None:
        return v.frames
    return view_frames(v.to_light, v.to_camera, v.light_axis, v.camera_up)


def _surface(normal, v: Vertex):
    """The normal-dependent geometry and frames (:class:`sellip.model.pbrdf.SurfaceTerms`) of the K views."""
    return surface_terms(normal, v.to_light, v.to_camera, v.light_distance, _view_frames(v))


def view_terms(normal, eta, v: Vertex, theta_h_offset=None, surface=None, reflection=None):
    """The roughness-independent per-view terms for unit albedos, from the full model (exact frames,
    3.5 deg flash offset included): the observations (I_d, I_alpha, I_s) of the diffuse lobe
    (``d_*``) and of the reflection lobe (``r_*``), each (K,), the diffuse DoP and azimuth
    direction, and the geometry record the lobe factors need. ``theta_h_offset`` (K,) radians,
    optional: the lobe factors will be evaluated at theta_h + offset (the per-sample Delta theta_h
    of the cluster fit, paper Eq. 25). ``surface`` (:func:`_surface` at ``normal``) and
    ``reflection`` (:func:`sellip.model.pbrdf.reflection_stokes` at ``eta``, normal-independent) may
    be passed when already known: the LM's difference Jacobian reuses them across its columns.
    """
    surface = _surface(normal, v) if surface is None else surface
    if reflection is None:
        reflection = reflection_stokes(_view_frames(v), eta)
    geom = surface.geometry
    shading = geom.shading[..., None]
    stokes_d = shading * diffuse_stokes(surface, eta)
    stokes_r = shading * reflection
    if theta_h_offset is not None:
        theta_h = jnp.arccos(jnp.clip(geom.cos_h, 0.0, 1.0))
        geom = geom._replace(cos_h=jnp.clip(jnp.cos(theta_h + theta_h_offset), 0.0, 1.0))
    d_id, d_ia, d_is = observations_from_analyzers(stokes_to_analyzers(stokes_d), axis=-1)
    r_id, r_ia, r_is = observations_from_analyzers(stokes_to_analyzers(stokes_r), axis=-1)
    lit = geom.lit & (geom.cos_i > 1e-4) & (geom.cos_o > 1e-4)
    gamma = polar.safe_sqrt(d_ia**2 + d_is**2)
    safe_gamma = jnp.where(gamma > 0, gamma, 1)
    dop = gamma / jnp.where(lit, d_id, 1)  # the diffuse DoP at the fitted eta
    if v.eta_diffuse is not None:  # the diffuse intensity at the held eta (its transmissions do not pull on eta)
        d_id = observations_from_analyzers(stokes_to_analyzers(shading * diffuse_stokes(surface, v.eta_diffuse)),
                                           axis=-1)[0]
    terms = {
        "d_id": d_id, "d_ia": d_ia, "d_is": d_is, "r_id": r_id, "r_ia": r_ia, "r_is": r_is,
        "dop": dop,
        "dir_a": jnp.where(gamma > 0, d_ia / safe_gamma, 0),  # unit direction of the diffuse (I_alpha, I_beta)
        "dir_b": jnp.where(gamma > 0, d_is / safe_gamma, 1),
        "lit": lit, "geom": geom,
    }
    if v.virtual is not None:  # S R+(0; eta) of the virtual coaxial views, (M,)
        terms["virt_shaded"] = v.virtual.geom.shading * fresnel(jnp.ones_like(eta), eta).r_plus
    return terms


def lobe_terms(terms, sigma_s, sigma_ss, v: Vertex, lobes: str = "full"):
    """``terms`` of :func:`view_terms` with the two lobe factors D G / (4 cos_i cos_o) (K,) added
    (``lobe_s``, ``lobe_ss``; 0 for a lobe the model ``lobes`` leaves out), and for virtual
    samples the virtual I_s of unit rho_s / rho_ss (``virt_s``, ``virt_ss``, (M,) each)."""
    geom = terms["geom"]
    on_s, on_ss = (1, 1) if v.lobe_mask is None else (v.lobe_mask[0], v.lobe_mask[1])  # the vertex's model
    zero = jnp.zeros_like(terms["d_id"])
    out = dict(terms, lobe_s=zero if lobes == "diffuse" else on_s * lobe_factor(geom, sigma_s),
               lobe_ss=on_ss * lobe_factor(geom, sigma_ss) if lobes == "full" else zero)
    if v.virtual is not None:
        shaded = terms["virt_shaded"]
        zero = jnp.zeros_like(shaded)
        out.update(virt_s=zero if lobes == "diffuse" else on_s * shaded * lobe_factor(v.virtual.geom, sigma_s),
                   virt_ss=on_ss * shaded * lobe_factor(v.virtual.geom, sigma_ss) if lobes == "full" else zero)
    return out


def model_terms(normal, eta, sigma_s, sigma_ss, v: Vertex, theta_h_offset=None, lobes: str = "full"):
    """Per-view design terms for unit albedos (:func:`view_terms` and :func:`lobe_terms`), each (K,)."""
    return lobe_terms(view_terms(normal, eta, v, theta_h_offset), sigma_s, sigma_ss, v, lobes)


def linear_solution(terms, v: Vertex, settings: FitSettings):
    """Closed-form rho_d (3,) and (rho_s, rho_ss RGB) (4,) for given nonlinear parameters.

    rho_d from the diffuse loss (non-negative, per channel), rho_s and rho_ss from the specular
    loss (exact small NNLS; only rho_s for ``lobes="specular"``, none for "diffuse"). The two
    couple weakly (the diffuse lobe's share of I_s, the reflection lobes' small share of I_d at
    the flash offset): two alternations settle them. Both solves need only inner products of the
    per-view terms, formed once: the alternations cost O(1), not O(K).
    """
    w = v.weight * terms["lit"]
    wa = w * terms["d_id"]
    norm_d = jnp.maximum(jnp.sum(wa * terms["d_id"]), 1e-20)
    diffuse_target = wa @ v.obs_d  # (3,) sum w a_d I_d
    if settings.lobes == "diffuse":
        return jnp.maximum(diffuse_target / norm_d, 0), jnp.zeros(4, norm_d.dtype)
    basis_s = terms["lobe_s"] * terms["r_is"]
    basis_ss = terms["lobe_ss"] * terms["r_is"]
    w_s, w_ss = w * basis_s, w * basis_ss
    # I_d = rho_d d_id + (lobe_s rho_s + lobe_ss rho_ss) r_id: the reflection's share of the diffuse target.
    share_s = jnp.sum(wa * terms["r_id"] * terms["lobe_s"])
    share_ss = jnp.sum(wa * terms["r_id"] * terms["lobe_ss"])
    # I_s = rho_d d_is + rho_s basis_s + rho_ss basis_ss: the specular normal equations.
    g_aa, g_ab, g_bb = jnp.sum(w_s * basis_s), jnp.sum(w_s * basis_ss), jnp.sum(w_ss * basis_ss)
    y_a, y_b = w_s @ v.obs_s, w_ss @ v.obs_s  # (3,) each
    d_a, d_b = jnp.sum(w_s * terms["d_is"]), jnp.sum(w_ss * terms["d_is"])  # the diffuse lobe's share of I_s
    if v.virtual is not None:  # the virtual samples are more rows of the specular loss (no diffuse part)
        wv_s, wv_ss = v.virtual.weight * terms["virt_s"], v.virtual.weight * terms["virt_ss"]
        g_aa, g_ab, g_bb = g_aa + jnp.sum(wv_s * terms["virt_s"]), g_ab + jnp.sum(wv_s * terms["virt_ss"]), \
            g_bb + jnp.sum(wv_ss * terms["virt_ss"])
        y_a, y_b = y_a + wv_s @ v.virtual.target, y_b + wv_ss @ v.virtual.target
    ridge = 1e-6 * jnp.maximum(g_aa + g_bb, 1e-12)
    spec = jnp.zeros(4, norm_d.dtype)
    # A lobe the vertex's model leaves out has albedo 0 (its basis is 0; the ridge alone would keep the prior).
    on = jnp.ones(4, norm_d.dtype) if v.lobe_mask is None else v.lobe_mask[jnp.array([0, 1, 1, 1])]
    for _ in range(2):
        rho_d = jnp.maximum((diffuse_target - share_s * spec[0] - share_ss * spec[1:]) / norm_d, 0)
        target_a, target_b = y_a - rho_d * d_a, y_b - rho_d * d_b
        if settings.lobes == "specular":  # one non-negative unknown: the clamped 1-D least squares
            rho_s = (jnp.sum(target_a) + ridge * v.prior[0]) / (3 * g_aa + ridge)
            spec = jnp.zeros(4, norm_d.dtype).at[0].set(jnp.maximum(rho_s, 0))
        else:
            spec = on * _nnls_specular_gram(g_aa, g_ab, g_bb, target_a, target_b, v.prior, ridge)
    return rho_d, spec


def _predictions(terms, rho_d, spec):
    """Predicted (I_d, I_alpha, I_s) (K, 3) and the reflection-lobe part (K, 3) of the weights."""
    reflect = terms["lobe_s"][:, None] * spec[0] + terms["lobe_ss"][:, None] * spec[None, 1:]
    pred = [rho_d[None, :] * terms[f"d_{o}"][:, None] + reflect * terms[f"r_{o}"][:, None] for o in ("id", "ia", "is")]
    return pred, reflect


def measured_dop(terms, i_d, i_alpha, i_beta):
    """The measured diffuse DoP (K,) that L_psi compares with the model's: the mono diffuse
    polarization (I_alpha, I_beta) (K,) each projected on the model's azimuth direction, over I_d (K,).

    Not the magnitude |(I_alpha, I_beta)| / I_d: the magnitude of a noisy vector is biased upwards
    (sensor noise and demosaicing's false polarization are rectified), and eta with it: +2 to +5 %
    per material on sphere_ior at 612x512 (docs/accuracy.md). The projection is linear in the
    observations, so zero-mean noise stays zero-mean; L_phi fits the direction.
    """
    return (i_alpha * terms["dir_a"] + i_beta * terms["dir_b"]) / jnp.maximum(i_d, 1e-6)


def residuals_from_terms(terms, v: Vertex, settings: FitSettings):
    """Weighted residual vector (9K,) (plus 3M with virtual samples) of one vertex from its
    :func:`model_terms`; the albedos are solved in closed form inside."""
    rho_d, spec = linear_solution(terms, v, settings)
    (pred_d, _, pred_s), reflect = _predictions(terms, rho_d, spec)
    w = v.weight * terms["lit"]
    # Mono diffuse signals: the observations minus the predicted reflection lobes (paper Eq. 22).
    i_d = (v.obs_d - reflect * terms["r_id"][:, None]) @ v.color
    i_alpha = (v.obs_a - reflect * terms["r_ia"][:, None]) @ v.color
    i_beta = (v.obs_s - reflect * terms["r_is"][:, None]) @ v.color
    gamma = polar.safe_sqrt(i_alpha**2 + i_beta**2)
    dop_measured = measured_dop(terms, i_d, i_alpha, i_beta)
    sqrt_w = jnp.sqrt(w)
    res_psi = jnp.sqrt(settings.lambda_psi) * sqrt_w * (terms["dop"] - dop_measured)
    res_d = jnp.sqrt(settings.lambda_d) * sqrt_w[:, None] * (pred_d - v.obs_d)
    res_s = jnp.sqrt(settings.lambda_s) * sqrt_w[:, None] * (pred_s - v.obs_s)
    res_phi = jnp.sqrt(settings.lambda_phi) * sqrt_w[:, None] * jnp.stack(
        [i_alpha - gamma * terms["dir_a"], i_beta - gamma * terms["dir_b"]], -1)
    parts = [res_psi, res_d.ravel(), res_s.ravel(), res_phi.ravel()]
    if v.virtual is not None:  # lambda_s lambda_g sum_m w^a_m sum_c (I_s_hat - I_s_virtual)^2 (paper Eq. 24)
        pred_virtual = terms["virt_s"][:, None] * spec[0] + terms["virt_ss"][:, None] * spec[None, 1:]
        sqrt_w_virtual = jnp.sqrt(settings.lambda_s * v.virtual.weight)[:, None]
        parts.append((sqrt_w_virtual * (pred_virtual - v.virtual.target)).ravel())
    return jnp.concatenate(parts)


def vertex_residuals(z, v: Vertex, frame: Frame, settings: FitSettings):
    """Weighted residual vector (9K,) of one vertex; its squared norm is the loss."""
    normal, eta, sigma_s, sigma_ss = decode_parameters(z, frame, fixed_sigma_ss(v, settings))
    return residuals_from_terms(model_terms(normal, eta, sigma_s, sigma_ss, v, lobes=settings.lobes), v, settings)


DIFFERENCE_STEPS = (7e-4, 7e-4, 3e-3, 3e-3, 1e-2)
"""Forward-difference steps in z (normal offsets, eta, sigma_s, sigma_ss) in float32, where the
truncation and round-off errors of each column balance (measured against forward-mode AD at
solutions of the benchmark problem: median column errors 0.1-0.5 %). The normal's columns need
the smallest step (the sharpest curvature: a narrow specular lobe), sigma_ss the largest (a broad,
weak lobe). Scaled by sqrt(eps) for other dtypes."""


def _difference_steps(dtype) -> np.ndarray:
    """(5,) forward-difference steps of :data:`DIFFERENCE_STEPS` for ``dtype``."""
    scale = (float(np.finfo(dtype).eps) / float(np.finfo(np.float32).eps)) ** 0.5
    return np.asarray(DIFFERENCE_STEPS) * scale


def residuals_and_jacobian(z, v: Vertex, frame: Frame, settings: FitSettings, free: tuple[int, ...]):
    """Residuals r (R,) at z and their forward-difference Jacobian (R, F) over the columns ``free``.

    Exploits the model's structure. The normal moves the surface terms (:func:`_surface`), eta
    the Fresnel terms, the roughnesses only the two lobe factors; the reflection lobe's Stokes
    vector does not depend on the normal at all. So: the surface terms at z and at each normal
    column, the reflection Fresnel terms at z and at the eta column, the view terms at every
    geometric point, and the roughness columns reuse the view terms at z; the closed-form
    albedos and the losses are evaluated at every point. About 3.5 residual evaluations for all
    5 columns, where forward-mode AD through the whole residual measured about 13 (docs/fit.md).
    """
    steps = _difference_steps(z.dtype)
    normal_cols = [i for i in free if i < 2]
    eta_cols = [i for i in free if i == 2]
    roughness = [i for i in free if i >= 3]
    shift = jnp.eye(5, dtype=z.dtype) * steps[:, None].astype(z.dtype)

    def decode(i):
        return decode_parameters(z if i is None else z + shift[i], frame, fixed_sigma_ss(v, settings))

    def residual(terms, sigma_s, sigma_ss):
        return residuals_from_terms(lobe_terms(terms, sigma_s, sigma_ss, v, settings.lobes), v, settings)

    # Unrolled over the few points (a vmap over them measured 3x slower on CPU).
    frames = _view_frames(v)
    normal, eta, sigma_s, sigma_ss = decode(None)
    surface = _surface(normal, v)
    reflection = reflection_stokes(frames, eta)
    base = view_terms(normal, eta, v, surface=surface, reflection=reflection)
    rows = [residual(base, sigma_s, sigma_ss)]
    for i in normal_cols:
        normal_i, _, _, _ = decode(i)
        rows.append(residual(view_terms(normal_i, eta, v, reflection=reflection), sigma_s, sigma_ss))
    for i in eta_cols:
        _, eta_i, _, _ = decode(i)
        rows.append(residual(view_terms(normal, eta_i, v, surface=surface, reflection=reflection_stokes(frames, eta_i)),
                             sigma_s, sigma_ss))
    for i in roughness:
        _, _, sigma_s_i, sigma_ss_i = decode(i)
        rows.append(residual(base, sigma_s_i, sigma_ss_i))
    r = jnp.stack(rows)
    h = jnp.asarray(steps[np.asarray(normal_cols + eta_cols + roughness, int)], z.dtype)
    return r[0], (r[1:] - r[:1]).T / h


def per_view_error(z, v: Vertex, frame: Frame, settings: FitSettings):
    """Relative RMS model error of each view (K,): diffuse and specular residuals over the diffuse level."""
    normal, eta, sigma_s, sigma_ss = decode_parameters(z, frame, fixed_sigma_ss(v, settings))
    terms = model_terms(normal, eta, sigma_s, sigma_ss, v, lobes=settings.lobes)
    rho_d, spec = linear_solution(terms, v, settings)
    (pred_d, _, pred_s), _ = _predictions(terms, rho_d, spec)
    return jnp.sqrt(jnp.sum((pred_d - v.obs_d) ** 2 + (pred_s - v.obs_s) ** 2, -1) / 6)


