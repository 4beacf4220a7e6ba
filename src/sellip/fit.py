"""Per-vertex polarimetric fit: batched Levenberg-Marquardt with variable projection (JAX).

Each vertex is an independent small problem (paper §4.3, DESIGN §5 and §7):

- nonlinear unknowns (5): the normal (2 degrees of freedom, a tangent-plane
  offset from the starting normal), eta, sigma_s and sigma_ss; bounds by
  reparameterization (scaled sigmoids; sigma_s <= sigma_ss keeps the two
  lobes apart);
- linear unknowns (7): rho_d (RGB), rho_s and rho_ss (RGB), solved in closed
  form with non-negativity inside the residual (exact small NNLS), so the
  solver sees only the nonlinear ones.

Loss per vertex (DESIGN §5), with view weights w_k = v_k / sum(v) and every
intensity divided by the vertex's own diffuse level (dimensionless, so the
weights lambda mean the same in every scene):

    lambda_psi  sum_k w_k (psi_hat(theta_o, eta) - psi_k)^2          (DoP)
  + lambda_d    sum_k w_k sum_c (I_d_hat - I_d)^2                   (diffuse)
  + lambda_s    sum_k w_k sum_c (I_s_hat - I_s)^2                   (specular)
  + lambda_phi  sum_k w_k [(I_a + G sin 2phi)^2 + (I_b - G cos 2phi)^2]   (azimuth)

where psi_k = G_k / I_d,k with G = sqrt(I_alpha^2 + I_beta^2) on the
colour-weighted mono signals and I_beta = I_s minus the predicted specular
lobes (both lobes, DESIGN §7). The azimuth term equals the paper's
2 w Gamma^2 (1 - cos(2 phi_hat - 2 phi_I)).

Arrays are batch-first: a batch of N vertices with K view slots each; unused
slots have weight 0.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sellip import polar
from sellip.conventions import observations_from_analyzers, stokes_to_analyzers
from sellip.fresnel import fresnel
from sellip.kernels import kernel
from sellip.pbrdf import (PBRDFParams, ViewFrames, diffuse_stokes, lobe_factor, lobe_stokes, reflection_stokes,
                          surface_terms, view_frames)

STATUS_FITTED = 0
STATUS_TOO_FEW_VIEWS = 1
STATUS_FAILED = 2
STATUS_NAMES = {STATUS_FITTED: "fitted", STATUS_TOO_FEW_VIEWS: "too few views", STATUS_FAILED: "failed"}

ETA_BOUNDS = (1.05, 3.0)
SIGMA_BOUNDS = (0.01, 1.0)
LOBE_GAP = 0.1  # sigma_ss >= sigma_s + LOBE_GAP
LOBE_SETS = ("diffuse", "specular", "full")
"""The reflection lobes a fit may use (DESIGN §7 model selection): none, the specular lobe, or
specular and single scattering (with sigma_ss free, or fixed by ``FitSettings.sigma_ss_fixed``)."""

MODELS = (0, 1, 2, 3)
"""The per-vertex model codes, simplest first (:data:`sellip.params.MODEL_NAMES`): 0 diffuse,
1 + specular, 2 + single scattering with sigma_ss fixed, 3 + single scattering (:mod:`sellip.models`)."""

DEFAULT_FIXED_SIGMA_SS = 0.9
"""Model 2's sigma_ss when the settings do not fix it (paper §6: 0.9 or 1.0)."""


@dataclass(frozen=True)
class FitSettings:
    """Settings of the per-vertex fit (config section ``fit``)."""

    lambda_psi: float = 100.0  # DESIGN §5 starts at 1; 100 with dimensionless residuals (docs/fit.md)
    lambda_d: float = 100.0
    lambda_s: float = 1.0
    lambda_phi: float = 100.0
    max_iterations: int = 30  # per stage
    normal_stage_iterations: int = 10  # the first stage (normal and eta, roughness held)
    tolerance: float = 1e-3  # relative loss decrease (of a near Gauss-Newton step) at which LM stops
    gradient_tolerance: float = 1e-3  # ... or when the residual is this close to orthogonal to the Jacobian
    min_views: int = 8
    dark_threshold: float = 0.02  # a view is too dark below this fraction of the vertex's median diffuse level
    chroma_threshold: float = 0.2  # colour outlier: distance of the unit-norm colour to the robust mean colour
    outlier_threshold: float = 4.0  # a view is an outlier when its residual exceeds this many robust sigmas ...
    outlier_floor: float = 0.05  # ... and this relative error
    shading_outlier_floor: float = 0.9  # a shading outlier is also > e^0.9 = 2.5x off the median apparent albedo
    sigma_ss_fixed: float | None = None  # fix sigma_ss (paper §6: 0.9 or 1.0) instead of fitting it
    lobes: str = "full"  # reflection lobes of the model: "diffuse" (none), "specular" (no single scattering), "full"
    round_iterations: int = 4  # LM iterations between compactions of the still-running vertices
    lm_batch: int = 512  # vertices advanced together by one compiled LM kernel
    chunk_size: int = 8192  # vertices prepared and finalized together (bounds memory)
    fit_normal: bool = True  # False holds the normal at normal0 (the augmented refit, docs/augment.md)
    lambda_g: float = 0.1  # weight of the virtual specular samples against the real views (paper Eq. 24)
    virtual_count: int = 180  # M virtual samples per vertex, at theta_h = 0, step, ..., (M - 1) step
    virtual_step_deg: float = 0.5  # their theta_h spacing (degrees)
    # The diffuse intensity's Fresnel transmissions use a held eta (the warm start's, then each LM stage's result),
    # so that eta is fitted from the polarization and the specular lobe, not from the diffuse shading's falloff,
    # which texture below the pixel and geometry errors bend (docs/fit.md). False: the fitted eta everywhere.
    hold_diffuse_eta: bool = True

    def __post_init__(self):
        if self.lobes not in LOBE_SETS:
            raise ValueError(f"FitSettings.lobes must be one of {LOBE_SETS}, got {self.lobes!r}")


def model_of(settings: FitSettings) -> int:
    """The model code (:data:`MODELS`) a FitSettings fits: its lobe set and whether sigma_ss is fixed."""
    if settings.lobes == "diffuse":
        return 0
    if settings.lobes == "specular":
        return 1
    return 2 if settings.sigma_ss_fixed is not None else 3


def model_arrays(models, sigma_ss_fixed: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex models (N,) (:data:`MODELS`) as the fit kernels take them: lobe_mask (N, 2), 1 where the
    model has the specular / single-scattering lobe, and the fixed sigma_ss (N,): ``sigma_ss_fixed``
    for model 2, NaN (free or absent) otherwise."""
    models = np.asarray(models)
    if models.size and (models.min() < 0 or models.max() > MODELS[-1]):
        raise ValueError(f"models must be in {MODELS}, got {np.unique(models).tolist()}")
    lobe_mask = np.stack([models >= 1, models >= 2], -1).astype(np.float64)
    return lobe_mask, np.where(models == 2, float(sigma_ss_fixed), np.nan)


class Observations(NamedTuple):
    """Observations of N vertices in K view slots (unused slots: weight 0).

    diffuse, diffuse_pol, specular: (N, K, 3) I_d, I_alpha, I_s (exposure-normalized linear RGB).
    to_light, to_camera, camera_up, light_axis: (N, K, 3) unit vectors (world): surface -> flash,
    surface -> camera, the camera's up axis, the flash polarizer axis; light_distance: (N, K) metres.
    usable: (N, K) bool, the view sees the vertex and its pixels are valid (not saturated).
    """

    diffuse: jnp.ndarray
    diffuse_pol: jnp.ndarray
    specular: jnp.ndarray
    to_light: jnp.ndarray
    to_camera: jnp.ndarray
    light_distance: jnp.ndarray
    camera_up: jnp.ndarray
    light_axis: jnp.ndarray
    usable: jnp.ndarray


class VirtualSamples(NamedTuple):
    """Virtual specular observations of N vertices (paper Eq. 24, docs/augment.md), M per vertex.

    Each is an exactly coaxial view (theta_i = theta_o = theta_h, theta_d = 0) at the vertex's
    median flash distance. theta_h: (N, M) radians. reflectance: (N, M, 3) the reflection lobes
    per unit shading, R+(0; eta) (rho_s kappa_s + rho_ss kappa_ss) (:func:`virtual_reflectance`),
    in the units of the fitted albedos. weight: (N, M) w^a, normalized cos theta_h (sum 1 per
    vertex; all 0 for a vertex without virtual samples); the fit scales it by ``lambda_g``.
    """

    theta_h: jnp.ndarray
    reflectance: jnp.ndarray
    weight: jnp.ndarray


class FitResult(NamedTuple):
    """Per-vertex results, each batch-first: normal (N, 3), params (PBRDFParams with batch N),
    status (N,) int, confidence (N,) in [0, 1], loss (N,), views_used (N,), iterations (N,), and the
    Gauss-Newton standard deviations normal_std_deg (N,) and eta_std (N,) the confidence comes from
    (inf where the vertex was not fitted or its Gauss-Newton matrix is singular; confidence 0 there),
    and sigma_s_std (N,), the same for the specular roughness (whether a vertex's lobe differs from
    its material's, :func:`sellip.augment.material_or_own`)."""

    normal: jnp.ndarray
    params: PBRDFParams
    status: jnp.ndarray
    confidence: jnp.ndarray
    loss: jnp.ndarray
    views_used: jnp.ndarray
    iterations: jnp.ndarray
    normal_std_deg: jnp.ndarray
    eta_std: jnp.ndarray
    sigma_s_std: jnp.ndarray


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


class _Frame(NamedTuple):
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


def _eta_from(z_eta):
    """eta from its unconstrained coordinate z[..., 2] (the scaled sigmoid of :func:`_decode`)."""
    return ETA_BOUNDS[0] + (ETA_BOUNDS[1] - ETA_BOUNDS[0]) * jax.nn.sigmoid(z_eta)


def _decode(z, frame: _Frame, sigma_ss_fixed):
    """Unconstrained z (5,) -> (normal (3,), eta, sigma_s, sigma_ss).

    sigma_s in [0.01, 1 - LOBE_GAP]; sigma_ss in [sigma_s + LOBE_GAP, 1]: single scattering is the
    broader lobe, and two lobes of equal roughness are one lobe (a flat, degenerate valley).
    sigma_ss_fixed: None (free), a number, or a traced scalar (a vertex's model: NaN = free).
    """
    normal = polar.safe_normalize(frame.normal0 + z[0] * frame.t1 + z[1] * frame.t2, fallback=frame.normal0)
    eta = _eta_from(z[2])
    sigma_s = SIGMA_BOUNDS[0] + (SIGMA_BOUNDS[1] - LOBE_GAP - SIGMA_BOUNDS[0]) * jax.nn.sigmoid(z[3])
    if isinstance(sigma_ss_fixed, (int, float)):
        return normal, eta, sigma_s, jnp.asarray(sigma_ss_fixed, z.dtype)
    low = sigma_s + LOBE_GAP
    sigma_ss = low + (SIGMA_BOUNDS[1] - low) * jax.nn.sigmoid(z[4])
    if sigma_ss_fixed is not None:
        fixed = jnp.asarray(sigma_ss_fixed, z.dtype)
        sigma_ss = jnp.where(jnp.isnan(fixed), sigma_ss, fixed)
    return normal, eta, sigma_s, sigma_ss


def _encode(eta, sigma_s, sigma_ss, dtype):
    """Inverse of :func:`_decode` for the scalar parameters (the normal offset starts at 0)."""
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


class _Virtual(NamedTuple):
    """One vertex's virtual samples, prepared (M of them)."""

    geom: object  # pbrdf geometry record, each field (M,): coaxial views at the vertex's flash distance
    target: jnp.ndarray  # (M, 3) virtual I_s / scale
    weight: jnp.ndarray  # (M,) lambda_g w^a


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


def _nnls_specular(a, b, y, weight, prior, ridge):
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
    """:func:`_nnls_specular` from its inner products: g_aa = sum w a^2, g_ab = sum w a b,
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

class _Vertex(NamedTuple):
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
    virtual: _Virtual | None = None  # virtual specular samples (augmentation), or none
    frames: ViewFrames | None = None  # (K,) the normal-independent frames (:func:`_prepare`), or computed on use
    lobe_mask: jnp.ndarray | None = None  # (2,) 1/0: the vertex's model has the specular, single-scattering lobe
    sigma_ss_fixed: jnp.ndarray | None = None  # () the model's fixed sigma_ss, NaN where it is free
    eta_diffuse: jnp.ndarray | None = None  # () eta of the diffuse intensity's transmissions (held), or the fitted eta


def _fixed_sigma_ss(v: _Vertex, settings: FitSettings):
    """sigma_ss_fixed for :func:`_decode`: the vertex's own model where it has one, else the settings'."""
    return settings.sigma_ss_fixed if v.sigma_ss_fixed is None else v.sigma_ss_fixed


def _view_frames(v: _Vertex) -> ViewFrames:
    if v.frames is not None:
        return v.frames
    return view_frames(v.to_light, v.to_camera, v.light_axis, v.camera_up)


def _surface(normal, v: _Vertex):
    """The normal-dependent geometry and frames (:class:`sellip.pbrdf.SurfaceTerms`) of the K views."""
    return surface_terms(normal, v.to_light, v.to_camera, v.light_distance, _view_frames(v))


def _view_terms(normal, eta, v: _Vertex, theta_h_offset=None, surface=None, reflection=None):
    """The roughness-independent per-view terms for unit albedos, from the full model (exact frames,
    3.5 deg flash offset included): the observations (I_d, I_alpha, I_s) of the diffuse lobe
    (``d_*``) and of the reflection lobe (``r_*``), each (K,), the diffuse DoP and azimuth
    direction, and the geometry record the lobe factors need. ``theta_h_offset`` (K,) radians,
    optional: the lobe factors will be evaluated at theta_h + offset (the per-sample Delta theta_h
    of the cluster fit, paper Eq. 25). ``surface`` (:func:`_surface` at ``normal``) and
    ``reflection`` (:func:`sellip.pbrdf.reflection_stokes` at ``eta``, normal-independent) may
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


def _lobe_terms(terms, sigma_s, sigma_ss, v: _Vertex, lobes: str = "full"):
    """``terms`` of :func:`_view_terms` with the two lobe factors D G / (4 cos_i cos_o) (K,) added
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


def _model_terms(normal, eta, sigma_s, sigma_ss, v: _Vertex, theta_h_offset=None, lobes: str = "full"):
    """Per-view design terms for unit albedos (:func:`_view_terms` and :func:`_lobe_terms`), each (K,)."""
    return _lobe_terms(_view_terms(normal, eta, v, theta_h_offset), sigma_s, sigma_ss, v, lobes)


def _linear_solution(terms, v: _Vertex, settings: FitSettings):
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


def _residuals_from_terms(terms, v: _Vertex, settings: FitSettings):
    """Weighted residual vector (9K,) (plus 3M with virtual samples) of one vertex from its
    :func:`_model_terms`; the albedos are solved in closed form inside."""
    rho_d, spec = _linear_solution(terms, v, settings)
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
        parts.append((jnp.sqrt(settings.lambda_s * v.virtual.weight)[:, None] * (pred_virtual - v.virtual.target)).ravel())
    return jnp.concatenate(parts)


def _residuals(z, v: _Vertex, frame: _Frame, settings: FitSettings):
    """Weighted residual vector (9K,) of one vertex; its squared norm is the loss."""
    normal, eta, sigma_s, sigma_ss = _decode(z, frame, _fixed_sigma_ss(v, settings))
    return _residuals_from_terms(_model_terms(normal, eta, sigma_s, sigma_ss, v, lobes=settings.lobes), v, settings)


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


def _residuals_and_jacobian(z, v: _Vertex, frame: _Frame, settings: FitSettings, free: tuple[int, ...]):
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
        return _decode(z if i is None else z + shift[i], frame, _fixed_sigma_ss(v, settings))

    def residual(terms, sigma_s, sigma_ss):
        return _residuals_from_terms(_lobe_terms(terms, sigma_s, sigma_ss, v, settings.lobes), v, settings)

    # Unrolled over the few points (a vmap over them measured 3x slower on CPU).
    frames = _view_frames(v)
    normal, eta, sigma_s, sigma_ss = decode(None)
    surface = _surface(normal, v)
    reflection = reflection_stokes(frames, eta)
    base = _view_terms(normal, eta, v, surface=surface, reflection=reflection)
    rows = [residual(base, sigma_s, sigma_ss)]
    for i in normal_cols:
        normal_i, _, _, _ = decode(i)
        rows.append(residual(_view_terms(normal_i, eta, v, reflection=reflection), sigma_s, sigma_ss))
    for i in eta_cols:
        _, eta_i, _, _ = decode(i)
        rows.append(residual(_view_terms(normal, eta_i, v, surface=surface, reflection=reflection_stokes(frames, eta_i)),
                             sigma_s, sigma_ss))
    for i in roughness:
        _, _, sigma_s_i, sigma_ss_i = decode(i)
        rows.append(residual(base, sigma_s_i, sigma_ss_i))
    r = jnp.stack(rows)
    h = jnp.asarray(steps[np.asarray(normal_cols + eta_cols + roughness, int)], z.dtype)
    return r[0], (r[1:] - r[:1]).T / h


def per_view_error(z, v: _Vertex, frame: _Frame, settings: FitSettings):
    """Relative RMS model error of each view (K,): diffuse and specular residuals over the diffuse level."""
    normal, eta, sigma_s, sigma_ss = _decode(z, frame, _fixed_sigma_ss(v, settings))
    terms = _model_terms(normal, eta, sigma_s, sigma_ss, v, lobes=settings.lobes)
    rho_d, spec = _linear_solution(terms, v, settings)
    (pred_d, _, pred_s), _ = _predictions(terms, rho_d, spec)
    return jnp.sqrt(jnp.sum((pred_d - v.obs_d) ** 2 + (pred_s - v.obs_s) ** 2, -1) / 6)


# --- Levenberg-Marquardt --------------------------------------------------------------------

class _LMState(NamedTuple):
    """Per-vertex solver state, batch-first. The normal equations (J^T J, J^T r) at z are carried:
    the Jacobian is computed at each trial point together with its residuals, and kept when the
    step is accepted."""

    z: jnp.ndarray  # (N, 5) unconstrained parameters
    loss: jnp.ndarray  # (N,)
    damping: jnp.ndarray  # (N,)
    iterations: jnp.ndarray  # (N,) int32, in the current stage
    done: jnp.ndarray  # (N,) bool
    hess: jnp.ndarray  # (N, F, F) J^T J over the free columns
    grad: jnp.ndarray  # (N, F) J^T r
    mark: jnp.ndarray  # (N,) the loss PROGRESS_ITERATIONS iterations ago (see _lm_rounds)
    fits: jnp.ndarray  # (N, F) 1 for the free columns this vertex moves in this stage (_fitted_columns)
    limit: jnp.ndarray  # (N,) int32 the stage's iteration cap


def _free_parameters(settings: FitSettings) -> tuple[int, ...]:
    """Indices into z of the parameters LM may move: normal (0, 1), eta (2), sigma_s (3), sigma_ss (4).

    A fixed sigma_ss is never moved, nor the roughness of a lobe the model (``settings.lobes``)
    leaves out; with ``settings.fit_normal`` False the normal stays at normal0. Which of these
    columns a vertex moves in a stage is data (:func:`_fitted_columns`).
    """
    normal = (0, 1) if settings.fit_normal else ()
    if settings.lobes == "diffuse":
        return normal + (2,)
    if settings.lobes == "specular" or settings.sigma_ss_fixed is not None:
        return normal + (2, 3)
    return normal + (2, 3, 4)


Z_LIMIT = 6.0
"""The largest |z| of the sigmoid-bounded parameters (eta, sigma_s, sigma_ss) LM moves to."""
PROGRESS_ITERATIONS = 4
STUCK_DAMPING = 10.0
"""LM stops a vertex whose loss fell by less than the tolerance over PROGRESS_ITERATIONS
iterations with its damping above STUCK_DAMPING (:func:`_lm_rounds`)."""


def _loss_tolerance(settings: FitSettings, dtype) -> float:
    """Relative loss decrease below which the fit has converged: settings.tolerance, but never
    below what the dtype resolves (float32 losses stop improving near 1e-6)."""
    return max(settings.tolerance, 30 * float(jnp.finfo(dtype).eps))


def _normal_equations(z, v: _Vertex, frame: _Frame, settings: FitSettings, free: tuple[int, ...], fits):
    """(loss, J^T J (F, F), J^T r (F,)) of one vertex at z; the columns it does not move (``fits`` (F,) 0) are 0."""
    r, jac = _residuals_and_jacobian(z, v, frame, settings, free)
    jac = jac * fits
    return jnp.sum(r * r), jac.T @ jac, jac.T @ r


def _lm_step(state: _LMState, v: _Vertex, frame: _Frame, settings: FitSettings, free: tuple[int, ...]):
    """One Levenberg-Marquardt step of one vertex (unbatched ``state``) over the parameters ``free``.

    A fresh state (loss +inf, :func:`_run_lm`) takes no step: its first "step" evaluates the normal
    equations at the start and always accepts them (and ends the fit if they are not finite), so
    that one compiled kernel serves the start and the iterations.
    Returns (z, loss, damping, hess, grad, converged, fresh)."""
    z, loss, damping, hess, grad = state.z, state.loss, state.damping, state.hess, state.grad
    fresh = jnp.isinf(loss)
    fitted = state.fits  # (F,) 0: a column held (a roughness the model lacks, or held in this stage)
    basis = jnp.eye(5, dtype=z.dtype)[np.asarray(free)]  # (F, 5)
    diag = jnp.diag(hess) + 1e-9

    def solve(moving):  # the damped step with the columns where ``moving`` is 0 held
        held = jnp.diag(1 - moving)
        return -solve_spd((hess + damping * jnp.diag(diag)) * moving[:, None] * moving[None, :] + held,
                          grad * moving) @ basis

    # Bounded parameters stay where their sigmoid still moves (|z| <= Z_LIMIT: within 0.25 % of
    # the range of a bound; a saturated one would leave a zero Jacobian column for good). A step
    # that would cross the limit is taken again with those parameters held (a projected step),
    # so that the quadratic model stays true to the step taken.
    step = solve(fitted)
    limit = jnp.asarray([np.inf, np.inf, Z_LIMIT, Z_LIMIT, Z_LIMIT], z.dtype)
    crossing = (jnp.abs(z + step) > limit).astype(z.dtype) @ basis.T  # (F,) 1 where the step crosses
    step = jnp.where(jnp.any(crossing > 0), solve(fitted * (1 - crossing)), step)
    z_new = jnp.where(fresh, z, jnp.clip(z + step, -limit, limit))
    loss_new, hess_new, grad_new = _normal_equations(z_new, v, frame, settings, free, fitted)
    better = (jnp.isfinite(loss_new) & (loss_new < loss) & jnp.all(jnp.isfinite(hess_new))
              & jnp.all(jnp.isfinite(grad_new)))
    tolerance = _loss_tolerance(settings, z.dtype)
    rel_gain = (loss - loss_new) / jnp.maximum(loss, jnp.finfo(z.dtype).tiny)
    # Stationarity at z (MINPACK's gtol): the largest cosine between the residual and a Jacobian column.
    cosine = jnp.max(jnp.abs(grad) / jnp.sqrt(diag * jnp.maximum(loss, jnp.finfo(z.dtype).tiny)))
    stationary = cosine < max(settings.gradient_tolerance, 10 * float(jnp.finfo(z.dtype).eps) ** 0.5)
    # Converged when the gain is small: the gain achieved by a near Gauss-Newton step (a heavily
    # damped step is small anyway), or the most the Gauss-Newton model at z can still give,
    # g^T H^-1 g (it ends the fits left crawling along a flat valley, e.g. a vanishing lobe whose
    # roughness runs to its bound, where steps fail by round-off and only the damping grows).
    model_gain = grad @ solve_spd(hess + 1e-6 * jnp.diag(diag) + jnp.diag(1 - fitted), grad) / jnp.maximum(
        loss, jnp.finfo(z.dtype).tiny)
    flat = (better & (rel_gain < tolerance) & (damping < 1e-2)) | (model_gain < tolerance)
    converged = stationary | flat | (loss_new < 1e-14)
    stalled = (~better) & (damping > 1e8)
    pick = lambda new, old: jnp.where(better, new, old)  # noqa: E731
    damping = jnp.where(fresh, damping, jnp.where(better, damping * 0.3, damping * 4.0))
    return (pick(z_new, z), pick(loss_new, loss), damping, pick(hess_new, hess), pick(grad_new, grad),
            jnp.where(fresh, ~better, converged | stalled), fresh)


@kernel(static_argnames=("settings", "steps", "free"))
def _lm_rounds(state: _LMState, records: _Vertex, frames: _Frame, settings: FitSettings, steps: int,
               free: tuple[int, ...]) -> _LMState:
    """Up to ``steps`` LM iterations for a batch, stopping early when every vertex is done. Which
    columns each vertex moves and its iteration cap are data (``state.fits``, ``state.limit``): both
    stages of a fit share one compiled kernel per batch shape."""
    step = jax.vmap(lambda st, v, f: _lm_step(st, v, f, settings, free))
    tolerance = _loss_tolerance(settings, state.z.dtype)

    def body(carry):
        st, count = carry
        z, loss, damping, hess, grad, converged, fresh = step(st, records, frames)
        active = ~st.done
        pick = lambda new, old: jnp.where(active.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)  # noqa: E731
        iterations = st.iterations + (active & ~fresh).astype(jnp.int32)
        loss = pick(loss, st.loss)
        # No progress: less than the tolerance gained over the last PROGRESS_ITERATIONS iterations
        # while the damping has grown past STUCK_DAMPING (a fit crawling along a flat valley, short
        # steps failing by round-off; a few failed steps at low damping only mean a poor model).
        check = active & (iterations % PROGRESS_ITERATIONS == 0)
        stuck = check & ((st.mark - loss) < tolerance * st.mark) & (damping > STUCK_DAMPING)
        st = _LMState(pick(z, st.z), loss, pick(damping, st.damping), iterations,
                      st.done | (active & (converged | stuck | (iterations >= st.limit))),
                      pick(hess, st.hess), pick(grad, st.grad), jnp.where(check, loss, st.mark), st.fits, st.limit)
        return st, count + 1

    def cond(carry):
        st, count = carry
        return (count < steps) & jnp.any(~st.done)

    return jax.lax.while_loop(cond, body, (state, jnp.asarray(0)))[0]


HOLD_ROUNDS = 2
"""With ``hold_diffuse_eta``: LM rounds after the second stage for the vertices whose eta moved by more than
HOLD_ETA_TOLERANCE from the one their diffuse transmissions held (each round holds the last result)."""
HOLD_ETA_TOLERANCE = 0.002

ROUGHNESS_GRID = ((0.05, 0.6), (0.1, 0.6), (0.2, 0.6), (0.3, 0.6), (0.45, 0.6),
                  (0.05, 0.9), (0.1, 0.9), (0.2, 0.9), (0.3, 0.9), (0.45, 0.9))
"""(sigma_s, sigma_ss) starting points tried besides the warm start: GGX lobes make the loss
non-convex in roughness."""


@kernel(static_argnames=("settings",))
def _best_start(z0, records: _Vertex, frames: _Frame, settings: FitSettings):
    """Per vertex, the lowest-loss start among the warm start and :data:`ROUGHNESS_GRID`. (N, 5).

    The starts differ in roughness only: the view terms are evaluated once per vertex."""
    grid = jnp.asarray(ROUGHNESS_GRID, z0.dtype)
    eta = _eta_from(z0[:, 2])
    grid_starts = jax.vmap(lambda e: _encode(jnp.full(len(ROUGHNESS_GRID), e), grid[:, 0], grid[:, 1], z0.dtype))(eta)
    starts = jnp.concatenate([z0[:, None], grid_starts.at[:, :, :2].set(z0[:, None, :2])], axis=1)

    def losses(zs, v, f):
        fixed = _fixed_sigma_ss(v, settings)
        normal, eta, _, _ = _decode(zs[0], f, fixed)
        view = _view_terms(normal, eta, v)
        _, _, sigma_s, sigma_ss = jax.vmap(lambda zz: _decode(zz, f, fixed))(zs)
        return jax.vmap(lambda s, ss: jnp.sum(_residuals_from_terms(_lobe_terms(view, s, ss, v, settings.lobes), v,
                                                                    settings) ** 2))(sigma_s, sigma_ss)

    loss = jax.vmap(losses)(starts, records, frames)
    loss = jnp.where(jnp.isfinite(loss), loss, jnp.inf)
    return jnp.take_along_axis(starts, jnp.argmin(loss, axis=1)[:, None, None], 1)[:, 0]


def _bucket(count: int, minimum: int = 64) -> int:
    """Sizes are rounded up to powers of two so that a few compiled shapes serve every call."""
    return max(minimum, 1 << int(np.ceil(np.log2(max(count, 1)))))


def _take(tree, index):
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def _to_host(tree):
    """Every leaf of ``tree`` as a numpy array: the LM's per-batch gathers are then numpy indexing
    (microseconds), not one dispatched JAX gather per field and batch."""
    return jax.tree_util.tree_map(np.asarray, tree)


_VIEW_FIELDS = ("obs_d", "obs_a", "obs_s", "to_light", "to_camera", "light_distance", "camera_up", "light_axis",
                "weight", "frames")
"""The fields of :class:`_Vertex` with a view axis (axis 1 of a batch)."""


def _batches(active: np.ndarray, views: np.ndarray, batch: int):
    """Batches of ``batch`` vertex indices from ``active`` and the view slots each needs.

    Vertices are ordered by their number of used views, so each batch can drop the slots none of
    its vertices uses (views are at the front, :func:`_compact_views`); widths are rounded by
    :func:`_view_bucket` (few compiled shapes). A last batch of at most a quarter of ``batch`` is
    padded to that quarter, any other to ``batch``: the vertices still running after most have
    converged are few, and two sizes compile half the kernels that every power of two down to 64
    would, for about 6 % more lanes stepped. Short batches repeat their vertices (identical work,
    harmless writes). Yields (index (size,), width)."""
    order = active[np.argsort(views[active], kind="stable")]
    for start in range(0, order.size, batch):
        size = batch if order.size - start > batch // 4 else batch // 4
        index = np.resize(order[start:start + size], size)
        yield index, _view_bucket(int(views[index].max(initial=1)))


def _take_records(records: _Vertex, index: np.ndarray, width: int) -> _Vertex:
    """Rows ``index`` of a batch of records, with only the first ``width`` view slots."""
    rows = _take(records, index)
    if width >= rows.obs_d.shape[1]:
        return rows
    return rows._replace(**{name: jax.tree_util.tree_map(lambda x: x[:, :width], getattr(rows, name))
                            for name in _VIEW_FIELDS if getattr(rows, name) is not None})


def _map_batches(kernel, rows: np.ndarray, records: _Vertex, frames: _Frame, batch: int, *per_vertex, out=None):
    """Apply a jitted batch ``kernel(*per_vertex_rows, records_rows, frames_rows)`` to the vertices
    ``rows``, in the view-width batches of :func:`_batches`, and scatter its outputs (a tuple or
    dict of per-vertex arrays) into ``out`` (same structure, full length; zeros when None). An output
    with a view axis narrower than ``out``'s is written to its first slots."""
    views = np.sum(np.asarray(records.weight) > 0, axis=1)
    for index, width in _batches(rows, views, batch):
        part = kernel(*[jnp.asarray(np.asarray(x)[index]) for x in per_vertex], _take_records(records, index, width),
                      _take(frames, index))
        part = jax.tree_util.tree_map(np.asarray, part)
        if out is None:
            n = len(records.weight)
            out = jax.tree_util.tree_map(lambda x: np.zeros((n,) + x.shape[1:], x.dtype), part)

        def scatter(full, new, index=index):
            full[(index,) + tuple(slice(0, k) for k in new.shape[1:])] = new
        jax.tree_util.tree_map(scatter, out, part)
    return out


def _fitted_columns(records: _Vertex, free: tuple[int, ...], hold_lobes: bool = False) -> np.ndarray:
    """(N, F) 1 for the columns of ``free`` each vertex moves: those its model fits (not the roughness
    of a lobe it lacks, nor a fixed sigma_ss; every column without per-vertex models), without the
    roughnesses when ``hold_lobes`` (the first stage, while the normal may still be a few degrees off:
    a sharp lobe would otherwise collapse onto one bright view)."""
    n = len(records.weight)
    dtype = np.asarray(records.weight).dtype
    if records.lobe_mask is None:
        per_parameter = [np.ones(n)] * 5
    else:
        lobe_mask = np.asarray(records.lobe_mask)
        per_parameter = [np.ones(n)] * 3 + [lobe_mask[:, 0], lobe_mask[:, 1] * np.isnan(records.sigma_ss_fixed)]
    if hold_lobes:
        per_parameter[3] = per_parameter[4] = np.zeros(n)
    return np.stack([per_parameter[i] for i in free], -1).astype(dtype)


def _run_lm(z, records: _Vertex, frames: _Frame, settings: FitSettings, run: np.ndarray, max_iterations: int,
            hold_lobes: bool = False):
    """LM over the parameters :func:`_free_parameters` ``(settings)`` (the roughnesses held when
    ``hold_lobes``) to convergence for the vertices where ``run`` is set, with compaction.

    The vertices still running are gathered into batches of one fixed size (one compiled shape
    per view width, :func:`_batches`) and advanced ``round_iterations`` steps at a time, so the
    cost follows the mean number of iterations, not the slowest vertex of a chunk, and the number
    of views each vertex uses, not the most any vertex uses. Returns (z, loss, iterations, hess)
    as numpy arrays; hess (N, F, F) is J^T J at z over the free columns (those held are 0).
    """
    free = _free_parameters(settings)
    z = np.asarray(z)
    n = z.shape[0]
    dtype = z.dtype
    run = np.asarray(run, bool)
    views = np.sum(np.asarray(records.weight) > 0, axis=1)
    batch = min(settings.lm_batch, _bucket(n))
    # A fresh state (loss +inf): the first step of each vertex evaluates its normal equations (_lm_step).
    loss = np.full(n, np.inf, dtype)
    hess = np.zeros((n, len(free), len(free)), dtype)
    grad = np.zeros((n, len(free)), dtype)
    state = _LMState(z, loss, np.full(n, 1e-3, dtype), np.zeros(n, np.int32), ~run, hess, grad, loss.copy(),
                     _fitted_columns(records, free, hold_lobes), np.full(n, max_iterations, np.int32))
    while True:
        active = np.flatnonzero(~state.done)
        if active.size == 0:
            return state.z, state.loss, state.iterations, state.hess
        fields = [x.copy() for x in state]
        for index, width in _batches(active, views, batch):
            part = _lm_rounds(_take(state, index), _take_records(records, index, width), _take(frames, index),
                              settings, steps=settings.round_iterations, free=free)
            for full, new in zip(fields, part):
                full[index] = np.asarray(new)
        state = _LMState(*fields)


# --- sample selection ---------------------------------------------------------------------

def select_views(obs: Observations, normal, settings: FitSettings):
    """Usable views per vertex: visible and valid, not too dark, not a colour or shading outlier. (N, K) bool.

    - too dark: mono I_d below ``dark_threshold`` times the vertex's median;
    - colour outliers: the unit-norm RGB of I_d far from the vertex's robust mean colour (more
      than ``chroma_threshold`` and ``outlier_threshold`` times the robust spread of the
      vertex's own colour distances), refined three times (anchor notes §2.2);
    - shading outliers: I_d divided by the shading cos(theta_i) / d^2 of the starting ``normal``
      (N, 3) is an apparent albedo, the same in every view up to the Fresnel terms and the
      normal's error; views whose log apparent albedo is more than ``outlier_threshold`` robust
      sigmas (MAD) and ``shading_outlier_floor`` from the median are dropped (inter-reflections,
      mis-registered pixels, corrupt frames).
    """
    usable = obs.usable & jnp.all(jnp.isfinite(obs.diffuse), -1)
    mono = jnp.mean(jnp.where(usable[..., None], obs.diffuse, 0), -1)
    level = _masked_median(mono, usable)
    usable = usable & (mono > settings.dark_threshold * level[:, None])
    unit_color = obs.diffuse / jnp.maximum(jnp.linalg.norm(obs.diffuse, axis=-1, keepdims=True), 1e-20)
    keep = usable
    for _ in range(4):
        mean = jnp.sum(jnp.where(keep[..., None], unit_color, 0), 1) / jnp.maximum(jnp.sum(keep, 1), 1)[:, None]
        mean = mean / jnp.maximum(jnp.linalg.norm(mean, axis=-1, keepdims=True), 1e-20)
        distance = jnp.linalg.norm(unit_color - mean[:, None, :], axis=-1)
        # The fixed threshold, widened where the vertex's own colours spread more (texture finer
        # than a pixel, noise in dark vertices): only outliers of its own distribution go.
        spread = 1.4826 * _masked_median(distance, keep)
        keep = usable & (distance < jnp.maximum(settings.chroma_threshold, settings.outlier_threshold * spread)[:, None])
    cos_i = jnp.clip(jnp.sum(normal[:, None, :] * obs.to_light, -1), 0.05, 1)
    distance = jnp.where(keep, obs.light_distance, 1)
    log_albedo = jnp.log(jnp.maximum(mono, 1e-30) * distance**2 / cos_i)
    center = _masked_median(log_albedo, keep)
    spread = 1.4826 * _masked_median(jnp.abs(log_albedo - center[:, None]), keep)
    limit = jnp.maximum(settings.outlier_threshold * spread, settings.shading_outlier_floor)
    return keep & (jnp.abs(log_albedo - center[:, None]) < limit[:, None])


def _masked_median(x, mask):
    """Median over the last axis of x where mask, per row (the lower middle of an even count); 0 for
    empty rows. Only the smaller half is ordered (``top_k``, 2.5x faster than a full sort on the CPU)."""
    big = jnp.where(mask, x, jnp.inf)
    half = x.shape[-1] // 2 + 1
    ordered = -jax.lax.top_k(-big, half)[0]  # the ``half`` smallest, ascending
    count = jnp.sum(mask, -1)
    idx = jnp.clip((count - 1) // 2, 0, half - 1)
    return jnp.where(count > 0, jnp.take_along_axis(ordered, idx[:, None], -1)[:, 0], 0)


# --- the batched fit ----------------------------------------------------------------------

def _prepare(obs: Observations, keep, prior: PBRDFParams, virtual: VirtualSamples | None = None,
             lambda_g: float = 0.0):
    """Normalize intensities by each vertex's diffuse level and build the per-vertex records.

    Virtual samples are placed at each vertex's median flash distance, so that they weigh like
    its real views in the dimensionless residuals."""
    mono = jnp.mean(obs.diffuse, -1)
    scale = jnp.maximum(_masked_median(mono, keep), 1e-12)
    count = jnp.sum(keep, -1)
    weight = keep / jnp.maximum(count, 1)[:, None]
    mean_color = jnp.sum(obs.diffuse * keep[..., None], 1)
    color = mean_color / jnp.maximum(jnp.sum(mean_color, -1, keepdims=True), 1e-20)
    color = jnp.where(jnp.sum(mean_color, -1, keepdims=True) > 0, color, 1.0 / 3)
    s = scale[:, None, None]
    # Unused slots may hold anything (NaN, zeros): give them harmless finite values; their weight is 0.
    clean = lambda x, fill: jnp.where(keep.reshape(keep.shape + (1,) * (x.ndim - 2)), jnp.nan_to_num(x), fill)  # noqa: E731
    obs = Observations(
        diffuse=clean(obs.diffuse, 0.0), diffuse_pol=clean(obs.diffuse_pol, 0.0), specular=clean(obs.specular, 0.0),
        to_light=clean(obs.to_light, 0.0), to_camera=clean(obs.to_camera, 0.0),
        light_distance=clean(obs.light_distance, 1.0), camera_up=clean(obs.camera_up, 0.0),
        light_axis=clean(obs.light_axis, 0.0), usable=keep)
    spec_prior = jnp.concatenate([prior.rho_s[:, None], prior.rho_ss], -1) / scale[:, None]
    prepared = None
    if virtual is not None:
        distance = jnp.where(count > 0, _masked_median(obs.light_distance, keep), 1.0)
        geom = virtual_geometry(virtual.theta_h.astype(scale.dtype), distance)
        prepared = _Virtual(geom, geom.shading[..., None] * virtual.reflectance / s,
                            (lambda_g * virtual.weight).astype(scale.dtype))
    return _Vertex(obs.diffuse / s, obs.diffuse_pol / s, obs.specular / s, obs.to_light, obs.to_camera,
                   obs.light_distance, obs.camera_up, obs.light_axis, weight.astype(obs.diffuse.dtype), color,
                   scale, spec_prior, prepared,
                   frames=view_frames(obs.to_light, obs.to_camera, obs.light_axis, obs.camera_up),
                   eta_diffuse=jnp.clip(prior.eta, *ETA_BOUNDS).astype(obs.diffuse.dtype))


def _robust_weights(z, v: _Vertex, frame: _Frame, settings: FitSettings):
    """View weights with outlier views removed: per-view error above the median by
    ``outlier_threshold`` robust sigmas (MAD) and above ``outlier_floor``. Returns (weight (K,), changed)."""
    err = per_view_error(z, v, frame, settings)
    used = v.weight > 0
    med = _masked_median(err[None], used[None])[0]
    mad = _masked_median(jnp.abs(err - med)[None], used[None])[0]
    outlier = used & (err > med + settings.outlier_threshold * 1.4826 * mad) & (err > settings.outlier_floor)
    keep = used & ~outlier
    return (keep / jnp.maximum(jnp.sum(keep), 1)).astype(v.weight.dtype), jnp.any(outlier)


def _finalize(z, loss, hess, fitted, v: _Vertex, frame: _Frame, settings: FitSettings):
    """Decoded parameters, linear solution and Gauss-Newton uncertainties at the solution of one vertex.

    hess: J^T J at z over :func:`_free_parameters` ``(settings)`` as the LM carried it, used when the
    normal was fitted (those are then every column); otherwise the Jacobian is evaluated here.
    fitted (F,): :func:`_fitted_columns` of the vertex over the columns with the normal free."""
    normal, eta, sigma_s, sigma_ss = _decode(z, frame, _fixed_sigma_ss(v, settings))
    terms = _model_terms(normal, eta, sigma_s, sigma_ss, v, lobes=settings.lobes)
    rho_d, spec = _linear_solution(terms, v, settings)
    # The uncertainties (hence the confidence) always treat the normal as unknown: holding it
    # fixed does not make it better known.
    free = _free_parameters(dataclasses.replace(settings, fit_normal=True))
    basis = jnp.eye(5, dtype=z.dtype)[np.asarray(free)]  # (F, 5)
    if not settings.fit_normal:
        _, jac = _residuals_and_jacobian(z, v, frame, settings, free)
        jac = jac * fitted
        hess = jac.T @ jac
    held = 1 - fitted @ basis  # (5,) 1 for the columns not fitted
    views = jnp.sum(v.weight > 0)
    dof = jnp.maximum(9 * views - jnp.sum(fitted), 1)
    normal_matrix = basis.T @ hess @ basis
    regular = normal_matrix + 1e-9 * jnp.diag(jnp.diag(normal_matrix)) + jnp.diag(held)
    cov = (loss / dof) * solve_spd(regular + 1e-12 * jnp.eye(5, dtype=z.dtype), jnp.eye(5, dtype=z.dtype))
    deta_dz = (ETA_BOUNDS[1] - ETA_BOUNDS[0]) * jax.nn.sigmoid(z[2]) * (1 - jax.nn.sigmoid(z[2]))
    eta_std = jnp.sqrt(jnp.maximum(cov[2, 2], 0)) * deta_dz
    dsigma_dz = (SIGMA_BOUNDS[1] - LOBE_GAP - SIGMA_BOUNDS[0]) * jax.nn.sigmoid(z[3]) * (1 - jax.nn.sigmoid(z[3]))
    sigma_s_std = jnp.sqrt(jnp.maximum(cov[3, 3], 0)) * dsigma_dz
    # A tangent offset dz rotates the normal by about |dz| / (1 + |z|^2) radians.
    normal_std = jnp.sqrt(jnp.maximum(cov[0, 0] + cov[1, 1], 0)) / (1 + z[0] ** 2 + z[1] ** 2)
    return dict(normal=normal, eta=eta, sigma_s=sigma_s, sigma_ss=sigma_ss, rho_d=rho_d * v.scale,
                rho_s=spec[0] * v.scale, rho_ss=spec[1:] * v.scale,
                eta_std=eta_std, sigma_s_std=sigma_s_std, normal_std_deg=jnp.degrees(normal_std))


@kernel(static_argnames=("settings",))
def _robust_weights_batch(z, records, frames, settings):
    return jax.vmap(lambda zz, v, f: _robust_weights(zz, v, f, settings))(z, records, frames)


@kernel(static_argnames=("settings",))
def _finalize_batch(z, loss, hess, fitted, records, frames, settings):
    return jax.vmap(lambda zz, ll, hh, ff, v, f: _finalize(zz, ll, hh, ff, v, f, settings))(z, loss, hess, fitted,
                                                                                          records, frames)


@kernel(static_argnames=("settings",))
def _select(obs: Observations, normal0, settings: FitSettings):
    normal0 = polar.safe_normalize(normal0, fallback=jnp.array([0.0, 0.0, 1.0], obs.diffuse.dtype))
    return select_views(obs, normal0, settings)


@kernel(static_argnames=("lambda_g",))
def _prepare_batch(obs: Observations, keep, normal0, prior: PBRDFParams, virtual: VirtualSamples | None = None,
                   lambda_g: float = 0.0):
    dtype = obs.diffuse.dtype
    normal0 = polar.safe_normalize(normal0, fallback=jnp.array([0.0, 0.0, 1.0], dtype))
    t1, t2 = tangent_basis(normal0)
    z0 = _encode(prior.eta, prior.sigma_s, prior.sigma_ss, dtype)
    return _prepare(obs, keep, prior, virtual, lambda_g), _Frame(normal0, t1, t2), z0


def _select_and_prepare(obs: Observations, normal0, prior: PBRDFParams, settings: FitSettings,
                        virtual: VirtualSamples | None = None):
    """Select each vertex's views once, move them to the front (:func:`_compact_views`) and build
    the per-vertex records. Returns (keep (N, K'), records, frames, z0) with K' <= K view slots."""
    dtype = np.asarray(obs.diffuse).dtype
    normal0 = jnp.asarray(normal0, dtype)
    keep = np.asarray(_select(Observations(*[jnp.asarray(x) for x in obs]), normal0, settings))
    obs = _compact_views(Observations(*[np.asarray(x) for x in obs]), keep)
    if virtual is not None:
        virtual = VirtualSamples(*[jnp.asarray(x, dtype) for x in virtual])
    records, frames, z0 = _prepare_batch(Observations(*[jnp.asarray(x) for x in obs]), jnp.asarray(obs.usable),
                                         normal0, prior, virtual, lambda_g=float(settings.lambda_g))
    if not settings.hold_diffuse_eta:  # the diffuse transmissions at the fitted eta
        records = records._replace(eta_diffuse=None)
    return obs.usable, records, frames, z0


def _view_bucket(count: int) -> int:
    """16, 24, 32, 48, 64, 96, 128, ...: at most 50 % padding, few distinct shapes."""
    size = 16
    while size < count:
        size = size * 3 // 2 if (size & (size - 1)) == 0 else size * 4 // 3
    return size


def _compact_views(obs: Observations, usable: np.ndarray) -> Observations:
    """Move each vertex's usable views to the front and drop the slots no vertex uses.

    K shrinks to the largest usable count (rounded up to a few sizes to limit recompilation),
    e.g. from 100 views to ~64 when each vertex sees half of them.
    """
    order = np.argsort(~usable, axis=1, kind="stable")
    width = min(_view_bucket(int(usable.sum(1).max(initial=1))), usable.shape[1])
    order = order[:, :width]
    gather = lambda x: np.take_along_axis(np.asarray(x), order.reshape(order.shape + (1,) * (np.ndim(x) - 2)), 1)  # noqa: E731
    return Observations(*[gather(x) for x in obs._replace(usable=usable)])


def _fit_chunk(obs: Observations, normal0, prior: PBRDFParams, settings: FitSettings, lobe_mask, fixed,
               virtual: VirtualSamples | None = None, valid: int | None = None):
    """Fit one chunk with per-vertex models (lobe_mask (N, 2), fixed (N,), :func:`model_arrays`); rows
    from ``valid`` on are padding (copies of a real row): LM skips them, and the vertices with too few
    usable views."""
    keep, records, frames, z0 = _to_host(_select_and_prepare(obs, normal0, prior, settings, virtual))
    records = records._replace(lobe_mask=lobe_mask, sigma_ss_fixed=fixed)

    def hold(records, z):  # the diffuse transmissions at the eta of z (FitSettings.hold_diffuse_eta)
        return records if records.eta_diffuse is None else records._replace(eta_diffuse=np.asarray(_eta_from(z[:, 2])))

    n = z0.shape[0]
    enough = np.asarray(keep).sum(1) >= settings.min_views
    rows = np.flatnonzero(enough & (np.arange(n) < (n if valid is None else valid)))
    active = np.zeros(n, bool)
    active[rows] = True
    batch = min(settings.lm_batch, _bucket(n))
    # Every per-vertex kernel runs on the vertices fitted, in batches of similar view counts.
    best_start = lambda z: _map_batches(partial(_best_start, settings=settings), rows, records, frames, batch, z,  # noqa: E731
                                        out=np.array(z))
    z = best_start(z0)
    # Stage 1: normal and eta with the roughnesses held; stage 2: everything.
    z, _, it_normal, _ = _run_lm(z, records, frames, settings, active, settings.normal_stage_iterations,
                                 hold_lobes=True)
    records = hold(records, z)
    z = best_start(z)  # lobes again, now that the normal is close
    z, loss, it_all, hess = _run_lm(z, records, frames, settings, active, settings.max_iterations)
    iterations = it_normal + it_all
    for _ in range(HOLD_ROUNDS if records.eta_diffuse is not None else 0):  # again where eta moved from the held one
        held = records.eta_diffuse
        records = hold(records, z)
        moved = active & (np.abs(records.eta_diffuse - held) > HOLD_ETA_TOLERANCE)
        if not moved.any():
            break
        z_new, loss_new, it_new, hess_new = _run_lm(z, records, frames, settings, moved, settings.max_iterations)
        z, loss = np.where(moved[:, None], z_new, z), np.where(moved, loss_new, loss)
        hess, iterations = np.where(moved[:, None, None], hess_new, hess), iterations + it_new
    # Robust pass: drop outlier views and continue only the vertices that had any.
    weight, changed = _map_batches(partial(_robust_weights_batch, settings=settings), rows, records, frames, batch, z,
                                   out=(np.array(records.weight), np.zeros(n, bool)))
    records = records._replace(weight=weight)
    changed = changed & active
    if changed.any():
        z_new, loss_new, it_robust, hess_new = _run_lm(z, records, frames, settings, changed, settings.max_iterations)
        z = np.where(changed[:, None], z_new, z)
        loss = np.where(changed, loss_new, loss)
        hess = np.where(changed[:, None, None], hess_new, hess)
        iterations = iterations + it_robust
    records = hold(records, z)  # the loss and std below at the final eta, also after the last hold round's refit
    fitted = _fitted_columns(records, _free_parameters(dataclasses.replace(settings, fit_normal=True)))
    out = _map_batches(partial(_finalize_batch, settings=settings), rows, records, frames, batch, z, loss, hess,
                       fitted)
    if out is None:  # no vertex to fit: placeholders (every vertex keeps its prior, see fit_vertices)
        out = {k: np.zeros((n,) + shape, z.dtype) for k, shape in
               (("normal", (3,)), ("eta", ()), ("sigma_s", ()), ("sigma_ss", ()), ("rho_d", (3,)), ("rho_s", ()),
                ("rho_ss", (3,)), ("eta_std", ()), ("sigma_s_std", ()), ("normal_std_deg", ()))}
    out.update(loss=loss, iterations=iterations, enough=enough, views_used=np.sum(weight > 0, axis=1))
    return out


def confidence_from_uncertainty(normal_std_deg, eta_std, normal_scale_deg=3.0, eta_scale=0.15):
    """Confidence in [0, 1] from the Gauss-Newton standard deviations of the normal (deg) and eta.

    The scales are where each factor is exp(-1/2): 3 deg of normal, 0.15 (10 %) of eta. (0.03 left
    nearly every vertex of the demo at 0: sparse views leave eta uncertain by 0.1-0.2, median 0.16.)"""
    return jnp.exp(-0.5 * ((normal_std_deg / normal_scale_deg) ** 2 + (eta_std / eta_scale) ** 2))


def fit_vertices(obs: Observations, normal0, prior: PBRDFParams, settings: FitSettings = FitSettings(),
                 progress=None, virtual: VirtualSamples | None = None, models=None,
                 sigma_ss_fixed: float = DEFAULT_FIXED_SIGMA_SS) -> FitResult:
    """Fit the pBRDF and normal of N vertices.

    obs: :class:`Observations` with batch (N, K). normal0: (N, 3) starting normals (e.g. the mesh
    normals; held there when ``settings.fit_normal`` is False). prior: warm-start parameters (batch
    N): eta, sigma_s, sigma_ss start the LM; rho_s and rho_ss are the ridge target of the linear
    solve. virtual: optional :class:`VirtualSamples` (batch N), added to the specular loss with
    weight ``settings.lambda_g`` (specular augmentation); None fits the real views alone.
    models: (N,) per-vertex model codes (:data:`MODELS`), capped at :func:`model_of` ``(settings)``;
    None: every vertex has that model. Model 2 fixes sigma_ss at ``settings.sigma_ss_fixed`` when set,
    else at ``sigma_ss_fixed``; model-0 vertices take no virtual samples (no lobe to augment). The
    model is data to the compiled kernels, not a static setting: one compilation serves every mix
    of models (an unused lobe costs its Jacobian column, about a tenth of an LM step).
    Returns a :class:`FitResult` of numpy arrays;
    vertices with fewer than ``settings.min_views`` usable views keep the prior (status "too few
    views", confidence 0), non-finite fits keep the prior (status "failed", confidence 0). Never NaN.
    Vertices are processed in chunks of ``settings.chunk_size``; ``progress(done)`` is called after each.
    """
    dtype = np.asarray(obs.diffuse).dtype
    n = np.shape(obs.diffuse)[0]
    normal0 = np.asarray(normal0, dtype)
    prior = PBRDFParams(*[np.asarray(x, dtype) for x in prior])
    top = model_of(settings)
    models = np.full(n, top) if models is None else np.minimum(np.asarray(models, np.int64), top)
    if models.shape != (n,):
        raise ValueError(f"fit_vertices: {models.shape} models for {n} vertices")
    lobe_mask, fixed = model_arrays(models, sigma_ss_fixed if settings.sigma_ss_fixed is None
                                    else settings.sigma_ss_fixed)
    lobe_mask, fixed = lobe_mask.astype(dtype), fixed.astype(dtype)
    if virtual is not None:  # model 0 has no lobe to augment
        virtual = virtual._replace(weight=np.where((models > 0)[:, None], np.asarray(virtual.weight), 0))
    # The kernels fit the most complex model; each vertex's own model is data (lobe_mask, fixed).
    settings = dataclasses.replace(settings, lobes="full", sigma_ss_fixed=None)
    chunks = []
    for start in range(0, n, settings.chunk_size):
        stop = min(n, start + settings.chunk_size)
        # Pad every chunk to a power of two (repeating its last vertex): few compiled shapes.
        index = np.minimum(np.arange(start, start + _bucket(stop - start)), stop - 1)
        index = index[:min(index.size, settings.chunk_size)]
        out = _fit_chunk(Observations(*[np.asarray(x)[index] for x in obs]), normal0[index],
                         PBRDFParams(*[x[index] for x in prior]), settings, lobe_mask[index], fixed[index],
                         None if virtual is None else VirtualSamples(*[np.asarray(x)[index] for x in virtual]),
                         valid=stop - start)
        chunks.append({k: v[:stop - start] for k, v in out.items()})
        if progress is not None:
            progress(stop)
    if not chunks:
        raise ValueError("fit_vertices needs at least one vertex")
    out = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    values = [out[k] for k in ("normal", "eta", "sigma_s", "sigma_ss", "rho_d", "rho_s", "rho_ss")]
    finite = np.all(np.stack([np.all(np.isfinite(x.reshape(n, -1)), -1) for x in values]), 0)
    ok = out["enough"] & finite
    status = np.where(~out["enough"], STATUS_TOO_FEW_VIEWS, np.where(finite, STATUS_FITTED, STATUS_FAILED))
    pick = lambda new, old: np.where(ok.reshape((-1,) + (1,) * (new.ndim - 1)), new, old).astype(dtype)  # noqa: E731
    params = PBRDFParams(
        eta=pick(out["eta"], prior.eta), rho_d=pick(out["rho_d"], prior.rho_d), rho_s=pick(out["rho_s"], prior.rho_s),
        sigma_s=pick(out["sigma_s"], prior.sigma_s), rho_ss=pick(out["rho_ss"], prior.rho_ss),
        sigma_ss=pick(out["sigma_ss"], prior.sigma_ss))
    confidence = np.asarray(confidence_from_uncertainty(out["normal_std_deg"], out["eta_std"]))
    confidence = np.where(ok & np.isfinite(confidence), confidence, 0.0).astype(dtype)
    uncertain = lambda std: np.where(ok & np.isfinite(std), std, np.inf).astype(dtype)  # noqa: E731
    normal0 = np.asarray(polar.safe_normalize(jnp.asarray(normal0), fallback=jnp.array([0.0, 0.0, 1.0], dtype)))
    return FitResult(normal=pick(out["normal"], normal0), params=params, status=status.astype(np.int32),
                     confidence=confidence, loss=np.where(ok, out["loss"], 0.0).astype(dtype),
                     views_used=out["views_used"].astype(np.int32), iterations=out["iterations"],
                     normal_std_deg=uncertain(out["normal_std_deg"]), eta_std=uncertain(out["eta_std"]),
                     sigma_s_std=uncertain(out["sigma_s_std"]))


def default_prior(n, dtype=np.float32) -> PBRDFParams:
    """The starting parameters of the first iteration (DESIGN §5: eta = 1.5)."""
    full = lambda value, *shape: jnp.full((n,) + shape, value, dtype)  # noqa: E731
    return PBRDFParams(eta=full(1.5), rho_d=full(0.5, 3), rho_s=full(0.0), sigma_s=full(0.3),
                       rho_ss=full(0.0, 3), sigma_ss=full(0.6))
