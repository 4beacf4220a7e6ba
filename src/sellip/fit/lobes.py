"""Per-cluster specular lobes and virtual samples (paper §4.3 "Specular and single scattering loss",
Eqs. 24-25): a cluster's eta, sigma_s, sigma_ss, rho_s, rho_ss fitted to the pooled observations of its
vertices with a per-sample half-angle error Delta theta_h and the regularizer lambda_theta Delta theta_h^2;
per vertex, M virtual specular samples rendered from its cluster's lobe; per-material values with per-vertex
deviations where a vertex's data demand them.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sellip.fit import parameterization as fit_parameterization
from sellip.fit import records as fit_records
from sellip.fit import residuals as fit_residuals
from sellip.fit import solver as fit_solver
from sellip.fit import vertex_fit as fit_vertex_fit
from sellip.fit.clusters import AugmentSettings
from sellip.fit.kernels import kernel
from sellip.fit.records import FitSettings, Observations, VirtualSamples
from sellip.model import fresnel as model_fresnel

log = logging.getLogger(__name__)


class ClusterLobe(NamedTuple):
    """One cluster's lobe: eta, sigma_s, sigma_ss, rho_s (floats), rho_ss (3,), samples (count), loss;
    theta_h_deg (J,) and value (J,) the samples of the plot (paper Fig. 7b): half angle with its fitted
    Delta theta_h, and the mono lobe value per unit shading, comparable to :func:`lobe_curve`."""

    eta: float
    sigma_s: float
    sigma_ss: float
    rho_s: float
    rho_ss: np.ndarray
    samples: int
    loss: float
    theta_h_deg: np.ndarray
    value: np.ndarray


# --- per-cluster lobe ----------------------------------------------------------------------------

class _Samples(NamedTuple):
    """Pooled (vertex, view) samples of one cluster as a one-vertex fit record (J slots) plus what the
    cluster fit adds: normal (J, 3) and rho_d (J, 3) / scale of each sample's vertex."""

    record: fit_residuals.Vertex
    normal: jnp.ndarray
    rho_d: jnp.ndarray


def _solve_spec(terms, target_s, w, prior):
    """Closed-form (rho_s, rho_ss RGB) (4,) of the cluster fit: exact NNLS (:func:`sellip.fit.residuals.nnls_specular`).
    A lobe the model leaves out has a zero basis (:func:`sellip.fit.residuals._lobe_terms`): its albedo comes out 0,
    and rho_s alone is the clamped 1-D least squares. target_s (J, 3): I_s minus its diffuse part."""
    basis_s, basis_ss = terms["lobe_s"] * terms["r_is"], terms["lobe_ss"] * terms["r_is"]
    ridge = 1e-6 * jnp.maximum(jnp.sum(w * (basis_s**2 + basis_ss**2)), 1e-12)
    return fit_residuals.nnls_specular(basis_s, basis_ss, target_s, w, prior, ridge)


def _cluster_residuals(z, delta, spec, samples: _Samples, settings: FitSettings, lambda_theta):
    """Residual matrix (J, 5) of the cluster fit: DoP, specular RGB, Delta theta_h (paper Eq. 25).

    z (5,) as :func:`sellip.fit.parameterization.decode_parameters` (the normal entries unused); delta (J,) radians;
    spec (4,) rho_s, rho_ss RGB, or None to solve them (closed form, variable projection). The lobes are
    those of the record's model (``lobe_mask``, ``sigma_ss_fixed``: :func:`_with_model`; a lobe left
    out contributes nothing). Returns (res, spec).
    """
    v = samples.record
    frame = fit_parameterization.Frame(*(jnp.array([0.0, 0.0, 1.0], z.dtype),) * 3)
    _, eta, sigma_s, sigma_ss = fit_parameterization.decode_parameters(z, frame,
                                                                       fit_residuals.fixed_sigma_ss(v, settings))
    terms = fit_residuals.model_terms(samples.normal, eta, sigma_s, sigma_ss, v, theta_h_offset=delta,
                                      lobes=settings.lobes)
    w = v.weight * terms["lit"]
    diffuse_s = samples.rho_d * terms["d_is"][:, None]
    if spec is None:
        spec = _solve_spec(terms, v.obs_s - diffuse_s, w, v.prior)
    reflect = terms["lobe_s"][:, None] * spec[0] + terms["lobe_ss"][:, None] * spec[None, 1:]
    i_d = (v.obs_d - reflect * terms["r_id"][:, None]) @ v.color
    i_alpha = (v.obs_a - reflect * terms["r_ia"][:, None]) @ v.color
    i_beta = (v.obs_s - reflect * terms["r_is"][:, None]) @ v.color
    dop_measured = fit_residuals.measured_dop(terms, i_d, i_alpha, i_beta)
    sqrt_w = jnp.sqrt(w)
    res_psi = jnp.sqrt(settings.lambda_psi) * sqrt_w * (terms["dop"] - dop_measured)
    res_s = jnp.sqrt(settings.lambda_s) * sqrt_w[:, None] * (diffuse_s + reflect * terms["r_is"][:, None] - v.obs_s)
    res_theta = jnp.sqrt(lambda_theta * v.weight) * delta
    return jnp.concatenate([res_psi[:, None], res_s, res_theta[:, None]], 1), spec


class _Pool(NamedTuple):
    """Pooled samples of a cluster (:func:`pool_samples`): the samples (J slots), the count of real
    ones, the intensity scale they are divided by, and vertex (count,) the row of each real sample."""

    samples: _Samples
    count: int
    scale: float
    vertex: np.ndarray


def pool_samples(obs: Observations, normals, rho_d, settings: FitSettings, max_samples: int,
                  rng: np.random.Generator) -> _Pool:
    """The usable views (:func:`sellip.fit.vertex_fit.select_views`) of n vertices as J <= max_samples samples,
    padded with weight-0 slots to the power of two at or above ``max_samples``: every cluster has
    the same shape, so the lobe fit compiles once per run (and once per machine with the persistent
    compilation cache)."""
    dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
    settings = _kernel_settings(settings)
    obs = Observations(*[np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else np.asarray(x) for x in obs])
    normals = np.asarray(normals, dtype) / np.linalg.norm(normals, axis=-1, keepdims=True)
    # Rows padded to 2048 or a power of two (repeats, cut off after): one compiled view selection serves clusters
    # and pools of any size (each size was a trace and a compile or cache load, 24 per demo job).
    n = len(normals)
    rows = np.minimum(np.arange(fit_solver.bucket(n, minimum=2048)), max(n - 1, 0))
    keep = np.asarray(fit_vertex_fit.select_for_normal(Observations(*[jnp.asarray(np.asarray(x)[rows]) for x in obs]),
                                  jnp.asarray(normals[rows]), settings))[:n]
    vertex, view = np.nonzero(keep)
    if vertex.size > max_samples:
        pick = np.sort(rng.choice(vertex.size, max_samples, replace=False))
        vertex, view = vertex[pick], view[pick]
    count = vertex.size
    size = fit_solver.bucket(max_samples, minimum=256)
    index_v = np.resize(vertex, size) if count else np.zeros(size, int)
    index_k = np.resize(view, size) if count else np.zeros(size, int)
    take = lambda x: np.asarray(x)[index_v, index_k]
    diffuse = take(obs.diffuse)
    valid = np.arange(size) < count
    scale = float(np.median(diffuse[:count].mean(-1))) if count else 1.0
    color = diffuse[:count].sum(0)
    color = color / color.sum() if count and color.sum() > 0 else np.full(3, 1 / 3)
    record = fit_residuals.Vertex(
        obs_d=diffuse / scale, obs_a=take(obs.diffuse_pol) / scale, obs_s=take(obs.specular) / scale,
        to_light=take(obs.to_light), to_camera=take(obs.to_camera), light_distance=take(obs.light_distance),
        camera_up=take(obs.camera_up), light_axis=take(obs.light_axis),
        weight=np.where(valid, 1.0 / max(count, 1), 0.0).astype(dtype), color=color.astype(dtype),
        scale=np.asarray(scale, dtype), prior=np.zeros(4, dtype))
    record = record._replace(**{name: jnp.asarray(getattr(record, name), dtype) for name in record._fields
                                if getattr(record, name) is not None})
    samples = _Samples(record, jnp.asarray(normals[index_v]), jnp.asarray(np.asarray(rho_d, dtype)[index_v] / scale))
    return _Pool(samples, count, scale, vertex)


def _stacked_residuals(z, delta, samples, settings, lambda_theta):
    return _cluster_residuals(z, delta, None, samples, settings, lambda_theta)[0].ravel()


_stacked = kernel(_stacked_residuals, static_argnames=("settings",))
_stacked_jacobian = kernel(jax.jacfwd(_stacked_residuals), static_argnames=("settings",),
                           name="sellip.fit.lobes._stacked_jacobian")


def _delta_step(z, delta, samples, settings: FitSettings, lambda_theta, max_delta, steps: int = 3, spec=None):
    """Gauss-Newton on each sample's Delta theta_h with the lobe parameters (and albedos) held:
    every sample's rows depend on its own Delta only. Accepts a step per sample only where it
    lowers that sample's cost. ``spec`` (4,) holds the albedos at given values (None: solved at the
    incoming delta)."""
    if spec is None:
        _, spec = _cluster_residuals(z, delta, None, samples, settings, lambda_theta)

    def rows(d):
        return _cluster_residuals(z, d, spec, samples, settings, lambda_theta)[0]

    for _ in range(steps):
        res, slope = jax.jvp(rows, (delta,), (jnp.ones_like(delta),))
        cost = jnp.sum(res**2, 1)
        new = jnp.clip(delta - jnp.sum(res * slope, 1) / (jnp.sum(slope**2, 1) + 1e-30), -max_delta, max_delta)
        better = jnp.sum(rows(new) ** 2, 1) < cost
        delta = jnp.where(better, new, delta)
    return delta


_delta_step_jit = kernel(_delta_step, static_argnames=("settings", "steps"))


@kernel(static_argnames=("settings",))
def _pool_solution(z, delta, samples: _Samples, settings: FitSettings, lambda_theta):
    """At the solution z of a cluster fit: its loss, albedos (4,), eta, sigma_s, sigma_ss, and per sample
    the measured lobe value (J,) and its shading R+(theta_d)/R+(0) x S (J,) (their ratio is comparable to
    :func:`lobe_curve`, plotted against theta_h + delta). One compiled kernel, not op-by-op dispatch."""
    res, spec = _cluster_residuals(z, delta, None, samples, settings, lambda_theta)
    frame = fit_parameterization.Frame(*(jnp.array([0.0, 0.0, 1.0], z.dtype),) * 3)
    _, eta, sigma_s, sigma_ss = fit_parameterization.decode_parameters(
        z, frame, fit_residuals.fixed_sigma_ss(samples.record, settings))
    terms = fit_residuals.model_terms(samples.normal, eta, sigma_s, sigma_ss, samples.record, theta_h_offset=delta)
    measured = (samples.record.obs_s - samples.rho_d * terms["d_is"][:, None]) @ samples.record.color
    shading = terms["r_is"] / model_fresnel.fresnel(jnp.ones((), z.dtype), eta).r_plus
    return jnp.sum(res**2), spec, eta, sigma_s, sigma_ss, measured, shading


@kernel(static_argnames=("settings",))
def _sample_losses(z, delta, spec, samples: _Samples, settings: FitSettings, lambda_theta):
    """The cluster loss of each sample (J,) with the lobe (z, albedos ``spec``) and deltas held."""
    res, _ = _cluster_residuals(z, delta, spec, samples, settings, lambda_theta)
    return jnp.sum(res**2, 1)


def lobe_fit_settings(settings: FitSettings) -> FitSettings:
    """The fields of ``settings`` the cluster fit uses (loss weights, lobe set, view selection), the
    others at their defaults: the jitted lobe kernels take the settings as a static argument, so
    passes that differ only in, e.g., ``fit_normal`` or ``max_iterations`` share one compilation."""
    keep = ("lambda_psi", "lambda_s", "lobes", "sigma_ss_fixed", "dark_threshold", "chroma_threshold",
            "outlier_threshold", "shading_outlier_floor")
    return FitSettings(**{name: getattr(settings, name) for name in keep})


def _kernel_settings(settings: FitSettings) -> FitSettings:
    """The static settings of the cluster kernels: :func:`lobe_fit_settings` with every lobe. The model
    (``settings.lobes``, ``sigma_ss_fixed``) travels as data in the samples' record (:func:`_with_model`),
    so that every candidate model of model selection runs one compiled program (four programs of five
    kernels each were 68 s of the demo's cold cluster_lobes job of 94 s)."""
    return dataclasses.replace(lobe_fit_settings(settings), lobes="full", sigma_ss_fixed=None)


def _with_model(samples: _Samples, settings: FitSettings) -> _Samples:
    """``samples`` whose record carries the model of ``settings`` (:func:`sellip.fit.records.model_of`) as the
    per-vertex fit's kernels take it: lobe_mask (2,) and the fixed sigma_ss (NaN: free)."""
    dtype = samples.record.obs_d.dtype
    lobe_mask, fixed = fit_records.model_arrays(np.array([fit_records.model_of(settings)]),
                                                settings.sigma_ss_fixed or 0.0)
    return samples._replace(record=samples.record._replace(lobe_mask=jnp.asarray(lobe_mask[0], dtype),
                                                           sigma_ss_fixed=jnp.asarray(fixed[0], dtype)))


def _free_lobe_parameters(settings: FitSettings) -> list[int]:
    """Indices into z of the cluster fit's nonlinear parameters: eta (2), and sigma_s (3), sigma_ss (4)
    where the lobe set fits them (:func:`sellip.fit.solver.free_parameters` without the normal)."""
    return list(fit_solver.free_parameters(dataclasses.replace(settings, fit_normal=False)))


def fit_cluster_lobe(obs: Observations, normals, rho_d, eta0: float, fit_settings: FitSettings | None = None,
                     settings: AugmentSettings = AugmentSettings(), seed: int = 0) -> ClusterLobe:
    """Fit one cluster's lobe to the pooled observations of its n vertices (paper Eq. 25).

    obs: :class:`sellip.fit.records.Observations` (n, K); normals (n, 3) and rho_d (n, 3): the vertices'
    fitted normals and albedos (held). eta0: the start of eta (e.g. the members' median).
    Minimizes lambda_psi L_psi + lambda_s L_s' + lambda_theta sum_j w_j Delta theta_h_j^2 over eta,
    sigma_s, sigma_ss (LM, scipy ``least_squares`` on the fit's bounded parameterization), rho_s
    and rho_ss (closed form) and Delta theta_h (J,) (per-sample Gauss-Newton), alternating
    ``settings.alternations`` times. Intensities are divided by the cluster's median diffuse level.
    Then up to ``settings.trim_rounds`` refits without the vertices the lobe fits worst (:func:`_worst_vertices`),
    until the lobe stops moving (eta by 0.1 %, a roughness by 0.01), and none where more than
    ``settings.trim_max_share`` of the vertices would go or fewer than ``settings.trim_min_vertices`` are pooled:
    a few vertices of another material with a brighter, narrower lobe otherwise pull the lobe to theirs
    (docs/augment.md, "Trimmed lobe fits"; off by default).
    The lobes are those of ``fit_settings.lobes`` and ``sigma_ss_fixed`` (the model, :mod:`sellip.fit.selection`):
    a lobe left out has albedo 0 (its roughness is then the start value, unused).
    """
    fit_settings = lobe_fit_settings(fit_settings or FitSettings())
    rng = np.random.default_rng(seed)
    pool = pool_samples(obs, normals, rho_d, fit_settings, settings.max_samples, rng)
    if pool.count == 0:
        raise ValueError("the cluster has no usable (vertex, view) sample")
    lobe = fit_pool(pool, eta0, fit_settings, settings)
    rows = np.arange(len(normals))  # the vertices the lobe is fitted to
    for _ in range(settings.trim_rounds if fit_settings.lobes != "diffuse" else 0):
        pooled = np.unique(pool.vertex).size
        if pooled < settings.trim_min_vertices:
            break
        worst = _worst_vertices(lobe, pool, len(rows), fit_settings, settings)
        share = worst.sum() / pooled
        if share > settings.trim_max_share:
            log.info("lobe not trimmed (further): %d of %d pooled vertices (%.0f %%) fit it worse than %g robust SD, "
                     "more than a few intruders", int(worst.sum()), pooled, 100 * share, settings.trim_z)
            break
        if not worst.any():
            break
        rows = rows[~worst]
        pool = pool_samples(Observations(*[np.asarray(x)[rows] for x in obs]), np.asarray(normals)[rows],
                             np.asarray(rho_d)[rows], fit_settings, settings.max_samples, rng)
        if pool.count == 0:
            break
        previous, lobe = lobe, fit_pool(pool, eta0, fit_settings, settings)
        log.info("lobe refit without the %d of %d pooled vertices (%.0f %%) it fit worst: eta %.4f sigma_s %.3f -> "
                 "eta %.4f sigma_s %.3f", int(worst.sum()), pooled, 100 * share, previous.eta, previous.sigma_s,
                 lobe.eta, lobe.sigma_s)
        if (abs(lobe.eta - previous.eta) < 1e-3 * previous.eta and abs(lobe.sigma_s - previous.sigma_s) < 0.01
                and abs(lobe.sigma_ss - previous.sigma_ss) < 0.01):
            break
    return lobe


def _worst_vertices(lobe: ClusterLobe, pool: _Pool, count: int, fit_settings: FitSettings,
                    settings: AugmentSettings) -> np.ndarray:
    """(count,) bool: the pooled vertices the lobe fits worst, those whose mean sample loss
    (:func:`lobe_sample_losses`) lies more than ``settings.trim_z`` robust standard deviations (1.4826 MAD) above
    the median vertex's. A vertex without a pooled sample is never among them."""
    losses = lobe_sample_losses(lobe, pool, fit_settings, settings)
    samples = np.bincount(pool.vertex, minlength=count)
    sampled = samples > 0
    mean = np.bincount(pool.vertex, weights=losses, minlength=count)[sampled] / samples[sampled]
    median = np.median(mean)
    spread = 1.4826 * np.median(np.abs(mean - median))
    worst = np.zeros(count, bool)
    if spread > 0:
        worst[np.flatnonzero(sampled)] = mean > median + settings.trim_z * spread
    return worst


def fit_pool(pool: _Pool, eta0: float, fit_settings: FitSettings, settings: AugmentSettings) -> ClusterLobe:
    """:func:`fit_cluster_lobe` on pooled samples."""
    from scipy.optimize import least_squares

    fit_settings = lobe_fit_settings(fit_settings)
    samples, count, scale = _with_model(pool.samples, fit_settings), pool.count, pool.scale
    static = _kernel_settings(fit_settings)  # the compiled kernels' (one program for every model)
    dtype = samples.record.obs_d.dtype
    lambda_theta = jnp.asarray(settings.lambda_theta, dtype)
    max_delta = jnp.asarray(np.radians(settings.max_theta_error_deg), dtype)
    delta = jnp.zeros(samples.normal.shape[0], dtype)
    free = _free_lobe_parameters(fit_settings)
    # Start: eta0 with the fit's roughness grid, the lowest loss.
    grid = np.asarray(fit_solver.ROUGHNESS_GRID)
    starts = np.asarray(fit_parameterization.encode_parameters(jnp.full(len(grid), eta0, dtype),
                                                               jnp.asarray(grid[:, 0], dtype),
                                                               jnp.asarray(grid[:, 1], dtype), dtype))
    if fit_settings.lobes == "diffuse":  # no roughness to start from: one start
        starts = starts[:1]
    costs = [float(jnp.sum(_stacked(jnp.asarray(s), delta, samples, static, lambda_theta) ** 2)) for s in starts]
    z = starts[int(np.argmin(costs))].astype(np.float64)

    def solve(z, delta):
        def residual(x):
            full = z.copy()
            full[free] = x
            return np.asarray(_stacked(jnp.asarray(full, dtype), delta, samples, static, lambda_theta), np.float64)

        def jacobian(x):
            full = z.copy()
            full[free] = x
            jac = _stacked_jacobian(jnp.asarray(full, dtype), delta, samples, static, lambda_theta)
            return np.asarray(jac, np.float64)[:, free]

        result = least_squares(residual, z[free], jac=jacobian, method="lm", xtol=1e-8, ftol=1e-8, max_nfev=100)
        z = z.copy()
        z[free] = result.x
        return z

    # Without a lobe, Delta theta_h changes nothing: one solve.
    for _ in range(settings.alternations if fit_settings.lobes != "diffuse" else 0):
        z = solve(z, delta)
        delta = _delta_step_jit(jnp.asarray(z, dtype), delta, samples, static, lambda_theta, max_delta)
    z = solve(z, delta)
    loss, spec, eta, sigma_s, sigma_ss, measured, shading = _pool_solution(jnp.asarray(z, dtype), delta, samples,
                                                                          static, lambda_theta)
    eta, sigma_s, sigma_ss = float(eta), float(sigma_s), float(sigma_ss)
    measured, shading = np.asarray(measured), np.asarray(shading)
    ok = (shading > 1e-6) & (np.arange(shading.shape[0]) < count)
    theta_h = np.degrees(np.arccos(np.clip(np.sum(np.asarray(samples.normal) * _unit(
        np.asarray(samples.record.to_light) + np.asarray(samples.record.to_camera)), -1), -1, 1)))
    return ClusterLobe(eta=eta, sigma_s=sigma_s, sigma_ss=sigma_ss, rho_s=float(spec[0]) * scale,
                       rho_ss=np.asarray(spec[1:], np.float64) * scale, samples=int(count),
                       loss=float(loss),
                       theta_h_deg=(theta_h + np.degrees(np.asarray(delta)))[ok],
                       value=(measured / np.where(shading > 1e-6, shading, 1) * scale)[ok])


def no_lobe(eta: float) -> ClusterLobe:
    """The lobe of a cluster without a usable sample: no specular and no single scattering (albedos 0), ``eta``,
    the roughness starts of the fit; ``samples`` 0. Its model is diffuse only (code 0)."""
    return ClusterLobe(eta=float(eta), sigma_s=float(fit_solver.ROUGHNESS_GRID[0][0]),
                       sigma_ss=float(fit_solver.ROUGHNESS_GRID[0][1]), rho_s=0.0, rho_ss=np.zeros(3), samples=0,
                       loss=0.0, theta_h_deg=np.zeros(0), value=np.zeros(0))


def lobe_sample_losses(lobe: ClusterLobe, pool: _Pool, fit_settings: FitSettings,
                       settings: AugmentSettings = AugmentSettings(), delta_rounds: int = 2) -> np.ndarray:
    """The cluster loss of each real sample of ``pool`` (count,) under a given lobe (held): the
    rows of :func:`_cluster_residuals` with the lobe's eta, roughnesses and albedos, and each
    sample's own Delta theta_h fitted (a per-sample nuisance, with its L_theta cost) by
    ``delta_rounds`` x 3 Gauss-Newton steps. Summed, it is the cluster fit's loss on these samples:
    the held-out error of model selection (:func:`sellip.fit.selection.select_model`)."""
    fit_settings = lobe_fit_settings(fit_settings)
    samples, static = _with_model(pool.samples, fit_settings), _kernel_settings(fit_settings)
    dtype = samples.record.obs_d.dtype
    lambda_theta = jnp.asarray(settings.lambda_theta, dtype)
    max_delta = jnp.asarray(np.radians(settings.max_theta_error_deg), dtype)
    z = fit_parameterization.encode_parameters(jnp.asarray(lobe.eta, dtype), jnp.asarray(lobe.sigma_s, dtype),
                    jnp.asarray(max(lobe.sigma_ss, lobe.sigma_s + fit_records.LOBE_GAP), dtype), dtype)
    spec = jnp.asarray(np.concatenate([[lobe.rho_s], np.asarray(lobe.rho_ss)]) / pool.scale, dtype)
    delta = jnp.zeros(samples.normal.shape[0], dtype)
    for _ in range(delta_rounds if fit_settings.lobes != "diffuse" else 0):
        delta = _delta_step_jit(z, delta, samples, static, lambda_theta, max_delta, spec=spec)
    return np.asarray(_sample_losses(z, delta, spec, samples, static, lambda_theta), np.float64)[:pool.count]


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def lobe_curve(theta_h_deg, lobe: ClusterLobe, color=(1 / 3, 1 / 3, 1 / 3)) -> np.ndarray:
    """The mono coaxial lobe value per unit shading (:func:`sellip.fit.parameterization.virtual_reflectance` weighted by
    ``color``) at half angles theta_h_deg (M,) degrees. Returns (M,)."""
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    theta_h = jnp.radians(jnp.asarray(theta_h_deg, dtype))
    values = fit_parameterization.virtual_reflectance(theta_h, *_lobe_arrays([lobe]))
    return np.asarray(values[0] @ jnp.asarray(color, values.dtype))


def _lobe_arrays(lobes):
    """(eta, rho_s, sigma_s, rho_ss, sigma_ss) arrays (K,), (K, 3) of cluster lobes."""
    dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
    return (jnp.asarray([lb.eta for lb in lobes], dtype), jnp.asarray([lb.rho_s for lb in lobes], dtype),
            jnp.asarray([lb.sigma_s for lb in lobes], dtype), jnp.asarray(np.stack([lb.rho_ss for lb in lobes]), dtype),
            jnp.asarray([lb.sigma_ss for lb in lobes], dtype))


# --- virtual samples -----------------------------------------------------------------------------

def virtual_theta_h(settings: FitSettings | None = None) -> np.ndarray:
    """The M half angles (radians) of the virtual samples: 0, step, ..., (M - 1) step (paper: 0..89.5 deg)."""
    settings = settings or FitSettings()
    theta = np.radians(settings.virtual_step_deg) * np.arange(settings.virtual_count)
    if settings.virtual_count < 1 or theta[-1] >= np.pi / 2:
        raise ValueError(f"virtual samples need 1 <= virtual_count and (virtual_count - 1) * virtual_step_deg < 90, "
                         f"got {settings.virtual_count} x {settings.virtual_step_deg} deg")
    return theta


def virtual_samples(labels, lobes: list[ClusterLobe] | None, settings: FitSettings | None = None,
                    dtype=np.float32) -> VirtualSamples:
    """Virtual specular samples of N vertices from their cluster labels (N,) and the clusters' lobes.

    Every vertex gets the M samples of its cluster's lobe (:func:`sellip.fit.parameterization.virtual_reflectance`)
    at :func:`virtual_theta_h`, weights w^a = cos theta_h / sum cos theta_h. A label < 0 (no
    cluster) gets weight 0. Returns :class:`sellip.fit.records.VirtualSamples` of numpy arrays (N, M, ...).
    """
    labels = np.asarray(labels)
    theta = virtual_theta_h(settings)
    if lobes:
        theta_k = jnp.asarray(np.broadcast_to(theta, (len(lobes), theta.size)))
        table = np.asarray(fit_parameterization.virtual_reflectance(theta_k, *_lobe_arrays(lobes)))  # (K, M, 3)
    else:
        table = np.zeros((0, theta.size, 3))
    if labels.size and labels.max(initial=-1) >= len(table):
        raise ValueError(f"cluster label {labels.max()} but only {len(table)} cluster lobes")
    weight = np.cos(theta) / np.cos(theta).sum()
    has = labels >= 0
    reflectance = np.zeros((labels.size, theta.size, 3))
    if len(table):
        reflectance[has] = table[labels[has]]
    return VirtualSamples(theta_h=np.broadcast_to(theta, (labels.size, theta.size)).astype(dtype),
                          reflectance=reflectance.astype(dtype),
                          weight=np.where(has[:, None], weight[None], 0.0).astype(dtype))


VALUE_SOURCES = {0: "material", 1: "vertex"}
"""Codes of ``eta_source`` and ``lobe_source`` in final/params.zarr and model.ply: the vertex carries its
material cluster's value, or its own (its data differ from the material's significantly)."""


def cluster_medians(value, labels, use, fallback) -> np.ndarray:
    """(K,) the median of ``value`` (N,) over each cluster's vertices (``labels`` (N,) in 0..K-1) where ``use`` (N,)
    bool; ``fallback`` (K,) for a cluster with no such vertex. A material's eta is the median of its vertices' own
    fits: on sphere_ior (24 views of 612x512, ten iterations) 0.59 / 0.88 % mean / worst per material against the
    cluster lobe fit's 0.75 / 2.33 %, on the demo's plumage and disc 0.63 / 1.01 % against 1.35 / 0.73 %."""
    value, labels, use = np.asarray(value, np.float64), np.asarray(labels, np.intp), np.asarray(use, bool)
    out = np.array(fallback, np.float64, copy=True)
    for k in np.unique(labels[use]):
        out[k] = np.median(value[use & (labels == k)])
    return out


def material_or_own(value, value_std, labels, cluster_value, deviation_sigmas: float = 3.0, std_floor: float = 0.01,
                    neighbours=None, min_support: int = 0):
    """A property of the material, not of the vertex (docs/design.md §7: no more model than the scene needs): each
    vertex takes its cluster's value unless its own fitted value differs from it by more than
    ``deviation_sigmas`` of its own uncertainty, and, with ``neighbours``, at least ``min_support`` of its
    neighbours differ from theirs the same way, by as much: a deviation the data demand is a spot, not one vertex.

    value, value_std (N,): the vertices' fitted value (eta, sigma_s) and its Gauss-Newton std (inf where
    unknown: such a vertex always takes the material's); labels (N,) int cluster of each vertex;
    cluster_value (K,). ``std_floor`` keeps an overconfident fit (a few views, a tiny std) from splitting
    off on noise. ``neighbours`` (N, k) int: each vertex's nearest vertices (:func:`nearest_vertices`). Isolated
    deviations are the per-vertex fits' outliers: on the tiny stability sphere 63 of 2,384 vertices passed 3 std
    alone, every one 18-30 % off (a fit pinned at eta's lower bound by a depolarized sample, or a highlight between
    the views), and together cost 1.5 dB of held-out PSNR (docs/accuracy.md, "A deviation is a spot").
    ``deviation_sigmas`` <= 0 keeps every vertex's own value. Returns (value (N,), source (N,) uint8 with
    :data:`VALUE_SOURCES` codes). The map is then piecewise constant where the object is, and keeps a real boundary or a
    deviating spot where the data demand it.
    """
    value = np.asarray(value, np.float64)
    if deviation_sigmas <= 0:
        return value.copy(), np.ones(len(value), np.uint8)
    cluster_value = np.asarray(cluster_value, np.float64)
    material = cluster_value[np.asarray(labels, np.intp)]
    scale = np.maximum(np.nan_to_num(np.asarray(value_std, np.float64), nan=np.inf, posinf=np.inf), std_floor)
    side = np.sign(value - material) * (np.isfinite(scale) & (np.abs(value - material) > deviation_sigmas * scale))
    if neighbours is not None and min_support > 0:
        neighbours = np.asarray(neighbours, np.intp)
        support = (side[neighbours] == side[:, None]).sum(axis=1) if neighbours.shape[1] else np.zeros(len(value))
        side = np.where(support >= min_support, side, 0)
    own = side != 0
    return np.where(own, value, material), own.astype(np.uint8)
