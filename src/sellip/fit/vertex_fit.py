"""The per-vertex polarimetric fit (:func:`fit_vertices`): view selection, batching by view count,
the solver, the robust pass, the diffuse eta hold, finalize (status, confidence, std), and the default prior.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from sellip.fit.kernels import kernel
from sellip.fit.parameterization import (
    Frame,
    Virtual,
    decode_parameters,
    encode_parameters,
    eta_from,
    tangent_basis,
    virtual_geometry,
)
from sellip.fit.records import (
    DEFAULT_FIXED_SIGMA_SS,
    ETA_BOUNDS,
    LOBE_GAP,
    SIGMA_BOUNDS,
    STATUS_FAILED,
    STATUS_FITTED,
    STATUS_TOO_FEW_VIEWS,
    FitResult,
    FitSettings,
    Observations,
    VirtualSamples,
    model_arrays,
    model_of,
)
from sellip.fit.residuals import (
    Vertex,
    fixed_sigma_ss,
    linear_solution,
    model_terms,
    per_view_error,
    residuals_and_jacobian,
    solve_spd,
)
from sellip.fit.solver import (
    HOLD_ETA_TOLERANCE,
    HOLD_ROUNDS,
    bucket,
    fitted_columns,
    free_parameters,
    map_batches,
    pick_best_start,
    run_lm,
    to_host,
    view_bucket,
)
from sellip.model import polar
from sellip.model.pbrdf import PBRDFParams, view_frames

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
        threshold = jnp.maximum(settings.chroma_threshold, settings.outlier_threshold * spread)
        keep = usable & (distance < threshold[:, None])
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
    clean = lambda x, fill: jnp.where(keep.reshape(keep.shape + (1,) * (x.ndim - 2)), jnp.nan_to_num(x), fill)
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
        prepared = Virtual(geom, geom.shading[..., None] * virtual.reflectance / s,
                            (lambda_g * virtual.weight).astype(scale.dtype))
    return Vertex(obs.diffuse / s, obs.diffuse_pol / s, obs.specular / s, obs.to_light, obs.to_camera,
                   obs.light_distance, obs.camera_up, obs.light_axis, weight.astype(obs.diffuse.dtype), color,
                   scale, spec_prior, prepared,
                   frames=view_frames(obs.to_light, obs.to_camera, obs.light_axis, obs.camera_up),
                   eta_diffuse=jnp.clip(prior.eta, *ETA_BOUNDS).astype(obs.diffuse.dtype))


def robust_weights(z, v: Vertex, frame: Frame, settings: FitSettings):
    """View weights with outlier views removed: per-view error above the median by
    ``outlier_threshold`` robust sigmas (MAD) and above ``outlier_floor``. Returns (weight (K,), changed)."""
    err = per_view_error(z, v, frame, settings)
    used = v.weight > 0
    med = _masked_median(err[None], used[None])[0]
    mad = _masked_median(jnp.abs(err - med)[None], used[None])[0]
    outlier = used & (err > med + settings.outlier_threshold * 1.4826 * mad) & (err > settings.outlier_floor)
    keep = used & ~outlier
    return (keep / jnp.maximum(jnp.sum(keep), 1)).astype(v.weight.dtype), jnp.any(outlier)


def _finalize(z, loss, hess, fitted, v: Vertex, frame: Frame, settings: FitSettings):
    """Decoded parameters, linear solution and Gauss-Newton uncertainties at the solution of one vertex.

    hess: J^T J at z over :func:`free_parameters` ``(settings)`` as the LM carried it, used when the
    normal was fitted (those are then every column); otherwise the Jacobian is evaluated here.
    fitted (F,): :func:`fitted_columns` of the vertex over the columns with the normal free."""
    normal, eta, sigma_s, sigma_ss = decode_parameters(z, frame, fixed_sigma_ss(v, settings))
    terms = model_terms(normal, eta, sigma_s, sigma_ss, v, lobes=settings.lobes)
    rho_d, spec = linear_solution(terms, v, settings)
    # The uncertainties (hence the confidence) always treat the normal as unknown: holding it
    # fixed does not make it better known.
    free = free_parameters(dataclasses.replace(settings, fit_normal=True))
    basis = jnp.eye(5, dtype=z.dtype)[np.asarray(free)]  # (F, 5)
    if not settings.fit_normal:
        _, jac = residuals_and_jacobian(z, v, frame, settings, free)
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
    return jax.vmap(lambda zz, v, f: robust_weights(zz, v, f, settings))(z, records, frames)


@kernel(static_argnames=("settings",))
def _finalize_batch(z, loss, hess, fitted, records, frames, settings):
    return jax.vmap(lambda zz, ll, hh, ff, v, f: _finalize(zz, ll, hh, ff, v, f, settings))(z, loss, hess, fitted,
                                                                                          records, frames)


@kernel(static_argnames=("settings",))
def select_for_normal(obs: Observations, normal0, settings: FitSettings):
    normal0 = polar.safe_normalize(normal0, fallback=jnp.array([0.0, 0.0, 1.0], obs.diffuse.dtype))
    return select_views(obs, normal0, settings)


@kernel(static_argnames=("lambda_g",))
def _prepare_batch(obs: Observations, keep, normal0, prior: PBRDFParams, virtual: VirtualSamples | None = None,
                   lambda_g: float = 0.0):
    dtype = obs.diffuse.dtype
    normal0 = polar.safe_normalize(normal0, fallback=jnp.array([0.0, 0.0, 1.0], dtype))
    t1, t2 = tangent_basis(normal0)
    z0 = encode_parameters(prior.eta, prior.sigma_s, prior.sigma_ss, dtype)
    return _prepare(obs, keep, prior, virtual, lambda_g), Frame(normal0, t1, t2), z0


def select_and_prepare(obs: Observations, normal0, prior: PBRDFParams, settings: FitSettings,
                        virtual: VirtualSamples | None = None):
    """Select each vertex's views once, move them to the front (:func:`_compact_views`) and build
    the per-vertex records. Returns (keep (N, K'), records, frames, z0) with K' <= K view slots."""
    dtype = np.asarray(obs.diffuse).dtype
    normal0 = jnp.asarray(normal0, dtype)
    keep = np.asarray(select_for_normal(Observations(*[jnp.asarray(x) for x in obs]), normal0, settings))
    obs = _compact_views(Observations(*[np.asarray(x) for x in obs]), keep)
    if virtual is not None:
        virtual = VirtualSamples(*[jnp.asarray(x, dtype) for x in virtual])
    records, frames, z0 = _prepare_batch(Observations(*[jnp.asarray(x) for x in obs]), jnp.asarray(obs.usable),
                                         normal0, prior, virtual, lambda_g=float(settings.lambda_g))
    if not settings.hold_diffuse_eta:  # the diffuse transmissions at the fitted eta
        records = records._replace(eta_diffuse=None)
    return obs.usable, records, frames, z0




def _compact_views(obs: Observations, usable: np.ndarray) -> Observations:
    """Move each vertex's usable views to the front and drop the slots no vertex uses.

    K shrinks to the largest usable count (rounded up to a few sizes to limit recompilation),
    e.g. from 100 views to ~64 when each vertex sees half of them.
    """
    order = np.argsort(~usable, axis=1, kind="stable")
    width = min(view_bucket(int(usable.sum(1).max(initial=1))), usable.shape[1])
    order = order[:, :width]
    gather = lambda x: np.take_along_axis(np.asarray(x), order.reshape(order.shape + (1,) * (np.ndim(x) - 2)), 1)
    return Observations(*[gather(x) for x in obs._replace(usable=usable)])


def _fit_chunk(obs: Observations, normal0, prior: PBRDFParams, settings: FitSettings, lobe_mask, fixed,
               virtual: VirtualSamples | None = None, valid: int | None = None):
    """Fit one chunk with per-vertex models (lobe_mask (N, 2), fixed (N,), :func:`model_arrays`); rows
    from ``valid`` on are padding (copies of a real row): LM skips them, and the vertices with too few
    usable views."""
    keep, records, frames, z0 = to_host(select_and_prepare(obs, normal0, prior, settings, virtual))
    records = records._replace(lobe_mask=lobe_mask, sigma_ss_fixed=fixed)

    def hold(records, z):  # the diffuse transmissions at the eta of z (FitSettings.hold_diffuse_eta)
        return records if records.eta_diffuse is None else records._replace(eta_diffuse=np.asarray(eta_from(z[:, 2])))

    n = z0.shape[0]
    enough = np.asarray(keep).sum(1) >= settings.min_views
    rows = np.flatnonzero(enough & (np.arange(n) < (n if valid is None else valid)))
    active = np.zeros(n, bool)
    active[rows] = True
    batch = min(settings.lm_batch, bucket(n))
    # Every per-vertex kernel runs on the vertices fitted, in batches of similar view counts.
    best_start = lambda z: map_batches(partial(pick_best_start, settings=settings), rows, records, frames, batch, z,
                                        out=np.array(z))
    z = best_start(z0)
    # Stage 1: normal and eta with the roughnesses held; stage 2: everything.
    z, _, it_normal, _ = run_lm(z, records, frames, settings, active, settings.normal_stage_iterations,
                                 hold_lobes=True)
    records = hold(records, z)
    z = best_start(z)  # lobes again, now that the normal is close
    z, loss, it_all, hess = run_lm(z, records, frames, settings, active, settings.max_iterations)
    iterations = it_normal + it_all
    for _ in range(HOLD_ROUNDS if records.eta_diffuse is not None else 0):  # again where eta moved from the held one
        held = records.eta_diffuse
        records = hold(records, z)
        moved = active & (np.abs(records.eta_diffuse - held) > HOLD_ETA_TOLERANCE)
        if not moved.any():
            break
        z_new, loss_new, it_new, hess_new = run_lm(z, records, frames, settings, moved, settings.max_iterations)
        z, loss = np.where(moved[:, None], z_new, z), np.where(moved, loss_new, loss)
        hess, iterations = np.where(moved[:, None, None], hess_new, hess), iterations + it_new
    # Robust pass: drop outlier views and continue only the vertices that had any.
    weight, changed = map_batches(partial(_robust_weights_batch, settings=settings), rows, records, frames, batch, z,
                                   out=(np.array(records.weight), np.zeros(n, bool)))
    records = records._replace(weight=weight)
    changed = changed & active
    if changed.any():
        z_new, loss_new, it_robust, hess_new = run_lm(z, records, frames, settings, changed, settings.max_iterations)
        z = np.where(changed[:, None], z_new, z)
        loss = np.where(changed, loss_new, loss)
        hess = np.where(changed[:, None, None], hess_new, hess)
        iterations = iterations + it_robust
    records = hold(records, z)  # the loss and std below at the final eta, also after the last hold round's refit
    fitted = fitted_columns(records, free_parameters(dataclasses.replace(settings, fit_normal=True)))
    out = map_batches(partial(_finalize_batch, settings=settings), rows, records, frames, batch, z, loss, hess,
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
        index = np.minimum(np.arange(start, start + bucket(stop - start)), stop - 1)
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
    pick = lambda new, old: np.where(ok.reshape((-1,) + (1,) * (new.ndim - 1)), new, old).astype(dtype)
    params = PBRDFParams(
        eta=pick(out["eta"], prior.eta), rho_d=pick(out["rho_d"], prior.rho_d), rho_s=pick(out["rho_s"], prior.rho_s),
        sigma_s=pick(out["sigma_s"], prior.sigma_s), rho_ss=pick(out["rho_ss"], prior.rho_ss),
        sigma_ss=pick(out["sigma_ss"], prior.sigma_ss))
    confidence = np.asarray(confidence_from_uncertainty(out["normal_std_deg"], out["eta_std"]))
    confidence = np.where(ok & np.isfinite(confidence), confidence, 0.0).astype(dtype)
    uncertain = lambda std: np.where(ok & np.isfinite(std), std, np.inf).astype(dtype)
    normal0 = np.asarray(polar.safe_normalize(jnp.asarray(normal0), fallback=jnp.array([0.0, 0.0, 1.0], dtype)))
    return FitResult(normal=pick(out["normal"], normal0), params=params, status=status.astype(np.int32),
                     confidence=confidence, loss=np.where(ok, out["loss"], 0.0).astype(dtype),
                     views_used=out["views_used"].astype(np.int32), iterations=out["iterations"],
                     normal_std_deg=uncertain(out["normal_std_deg"]), eta_std=uncertain(out["eta_std"]),
                     sigma_s_std=uncertain(out["sigma_s_std"]))


def default_prior(n, dtype=np.float32) -> PBRDFParams:
    """The starting parameters of the first iteration (docs/design.md §5: eta = 1.5)."""
    full = lambda value, *shape: jnp.full((n,) + shape, value, dtype)
    return PBRDFParams(eta=full(1.5), rho_d=full(0.5, 3), rho_s=full(0.0), sigma_s=full(0.3),
                       rho_ss=full(0.0, 3), sigma_ss=full(0.6))
