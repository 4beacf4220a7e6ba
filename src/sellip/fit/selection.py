"""Model selection (DESIGN §7): which lobes a material cluster needs, and fitting vertices by model.

The models (:data:`sellip.model.params.MODEL_NAMES`, the ``model`` of every vertex in model.ply), from
the simplest:

    0 diffuse                                   FitSettings(lobes="diffuse")
    1 diffuse + specular                        FitSettings(lobes="specular")
    2 + single scattering, sigma_ss fixed       FitSettings(lobes="full", sigma_ss_fixed=value)
    3 + single scattering                       FitSettings(lobes="full", sigma_ss_fixed=None)

Each is nested in the next (2 in 3: sigma_ss free includes the fixed value), so "simpler" is the
lower code. The fit settings of a pass are the most complex model allowed (:func:`model_of`): a
run with ``sigma_ss_fixed`` set never selects 3, one with ``lobes="specular"`` never 2 or 3.

The rule (:func:`select_model`, per cluster): the cluster's vertices are split (seeded, by
vertex) into a training and a held-out part; every candidate's cluster lobe
(:func:`sellip.fit.lobes.fit_cluster_lobe`) is fitted on the training part and scored by the
cluster loss on the held-out samples (:func:`sellip.fit.lobes.lobe_sample_losses`). The simplest
candidate whose held-out loss exceeds the best one's by at most ``tolerance`` (relative) plus
``standard_errors`` standard errors of the paired per-vertex difference is chosen.

:func:`fit_by_model` fits N vertices with per-vertex models: one :func:`sellip.fit.vertex_fit.fit_vertices`
call, the models being data to its compiled kernels (one compilation for every mix of models).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from sellip.fit import clusters
from sellip.fit import lobes as fit_lobes
from sellip.fit.records import MODELS, FitResult, FitSettings, Observations, VirtualSamples, model_of
from sellip.fit.vertex_fit import fit_vertices
from sellip.model.pbrdf import PBRDFParams

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SelectionSettings:
    """Settings of the per-cluster model selection (config section ``model_selection``)."""

    enabled: bool = True
    candidates: tuple[int, ...] = MODELS  # models tried (capped by the fit settings, see model_of)
    held_out_fraction: float = 0.25  # of the cluster's vertices (seeded split by vertex)
    tolerance: float = 0.01  # a simpler model may lose this fraction of the best held-out loss ...
    standard_errors: float = 1.0  # ... plus this many standard errors of the paired difference
    sigma_ss_fixed: float = 0.9  # sigma_ss of model 2 when the fit settings do not fix it (paper §6)
    max_samples: int = 4096  # training (and at most as many held-out) samples per candidate fit
    min_held_out_vertices: int = 8  # fewer in either part: no selection, the most complex candidate

    def __post_init__(self):
        if not self.candidates or any(m not in MODELS for m in self.candidates):
            raise ValueError(f"model_selection candidates must be a non-empty subset of {MODELS}, "
                             f"got {self.candidates}")
        if not 0 < self.held_out_fraction < 1:
            raise ValueError(f"model_selection held_out_fraction must be in (0, 1), got {self.held_out_fraction}")
        if self.tolerance < 0 or self.standard_errors < 0:
            raise ValueError("model_selection tolerance and standard_errors must be >= 0")
        if not 0.02 <= self.sigma_ss_fixed <= 1:
            raise ValueError(f"model_selection sigma_ss_fixed must be in [0.02, 1], got {self.sigma_ss_fixed}")


def settings_for_model(settings: FitSettings, model: int, sigma_ss_fixed: float = 0.9) -> FitSettings:
    """``settings`` fitting model ``model``. Model 2 fixes sigma_ss at ``settings.sigma_ss_fixed``
    when set, else at ``sigma_ss_fixed``; the other fields are kept."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model}")
    if model == 0:
        return dataclasses.replace(settings, lobes="diffuse")
    if model == 1:
        return dataclasses.replace(settings, lobes="specular")
    if model == 2:
        fixed = settings.sigma_ss_fixed if settings.sigma_ss_fixed is not None else sigma_ss_fixed
        return dataclasses.replace(settings, lobes="full", sigma_ss_fixed=fixed)
    return dataclasses.replace(settings, lobes="full", sigma_ss_fixed=None)


def allowed_models(settings: FitSettings, candidates=MODELS) -> list[int]:
    """The candidates a pass with ``settings`` may choose from: those not more complex than
    :func:`model_of` (``settings``), and never 3 when sigma_ss is fixed there. Sorted."""
    top = model_of(settings)
    return sorted({m for m in candidates if m <= top} or {top})


def cap_models(models, settings: FitSettings) -> np.ndarray:
    """Per-vertex models (N,) capped at what ``settings`` allow (:func:`model_of`), uint8."""
    return np.minimum(np.asarray(models, np.int64), model_of(settings)).astype(np.uint8)


class Selection(NamedTuple):
    """The model of one cluster and why. model: the chosen code. candidates: per tried code a dict
    held_out_loss (the cluster loss summed over the held-out samples), excess (over the best),
    standard_error (of that excess, from the per-vertex paired differences) and allowed (the rule's
    bound). best: the code of the lowest held-out loss. reason: a sentence. train_vertices,
    held_out_vertices, held_out_samples: the split."""

    model: int
    candidates: dict
    best: int | None
    reason: str
    train_vertices: int
    held_out_vertices: int
    held_out_samples: int


def split_vertices(n: int, fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Seeded split of n vertices into (train, held_out) sorted index arrays; round(fraction n) held out."""
    held = int(round(fraction * n))
    order = rng.permutation(n)
    return np.sort(order[held:]), np.sort(order[:held])


def choose(losses: dict, tolerance: float, standard_errors: float) -> tuple[int, int, dict]:
    """The rule on per-vertex held-out losses {model: (V,)}: the simplest model whose summed loss
    exceeds the best's by at most tolerance x best + standard_errors x SE, where SE is the
    standard error of the sum of the paired per-vertex differences (sqrt(V) x their std).
    Returns (chosen, best, {model: {held_out_loss, excess, standard_error, allowed}})."""
    totals = {m: float(np.sum(v)) for m, v in losses.items()}
    best = min(totals, key=lambda m: (totals[m], m))
    table, chosen = {}, None
    for m in sorted(losses):
        difference = np.asarray(losses[m]) - np.asarray(losses[best])
        se = float(np.sqrt(difference.size) * difference.std(ddof=1)) if difference.size > 1 else 0.0
        allowed = tolerance * totals[best] + standard_errors * se
        table[m] = {"held_out_loss": totals[m], "excess": totals[m] - totals[best], "standard_error": se,
                    "allowed": allowed}
        if chosen is None and totals[m] - totals[best] <= allowed:
            chosen = m
    return chosen, best, table


def select_model(obs: Observations, normals, rho_d, eta0: float, fit_settings: FitSettings | None = None,
                 selection: SelectionSettings = SelectionSettings(),
                 augment_settings: clusters.AugmentSettings = clusters.AugmentSettings(), seed: int = 0) -> Selection:
    """Choose the model of one cluster from the observations of its n vertices (DESIGN §7).

    obs: :class:`sellip.fit.records.Observations` (n, K); normals (n, 3), rho_d (n, 3): the vertices'
    fitted normals and albedos (held, as in :func:`sellip.fit.lobes.fit_cluster_lobe`); eta0: the
    start of eta. The candidates are ``selection.candidates`` allowed by ``fit_settings``
    (:func:`allowed_models`). Each candidate's lobe is fitted on the training vertices (at most
    ``selection.max_samples`` samples) and scored on the same held-out samples; the rule is
    :func:`choose`. Deterministic for a seed.
    """
    fit_settings = fit_settings or FitSettings()
    candidates = allowed_models(fit_settings, selection.candidates)
    n = len(normals)
    rng = np.random.default_rng(seed)
    train, held = split_vertices(n, selection.held_out_fraction, rng)
    if len(candidates) == 1:
        return Selection(candidates[0], {}, None, "one candidate", len(train), len(held), 0)
    if min(len(train), len(held)) < selection.min_held_out_vertices:
        top = candidates[-1]
        return Selection(top, {}, None, f"{n} vertices: too few to hold {selection.min_held_out_vertices} out "
                                        f"(kept the most complex candidate, {top})", len(train), len(held), 0)
    lobe_settings = dataclasses.replace(augment_settings, max_samples=selection.max_samples)
    take = lambda rows: Observations(*[np.asarray(x)[rows] for x in obs])  # noqa: E731
    normals, rho_d = np.asarray(normals), np.asarray(rho_d)
    train_pool = fit_lobes._pool_samples(take(train), normals[train], rho_d[train], fit_settings,
                                       selection.max_samples, np.random.default_rng(seed + 1))
    held_pool = fit_lobes._pool_samples(take(held), normals[held], rho_d[held], fit_settings,
                                      selection.max_samples, np.random.default_rng(seed + 2))
    if train_pool.count == 0 or held_pool.count == 0:
        top = candidates[-1]
        return Selection(top, {}, None, f"no usable samples in the training or held-out part (kept {top})",
                         len(train), len(held), held_pool.count)
    losses = {}
    for m in candidates:
        settings = settings_for_model(fit_settings, m, selection.sigma_ss_fixed)
        lobe = fit_lobes._fit_pool(train_pool, eta0, settings, lobe_settings)
        per_sample = fit_lobes.lobe_sample_losses(lobe, held_pool, settings, lobe_settings)
        losses[m] = np.bincount(held_pool.vertex, weights=per_sample, minlength=len(held))
    chosen, best, table = choose(losses, selection.tolerance, selection.standard_errors)
    percent = lambda x: 100 * x / max(table[best]["held_out_loss"], 1e-300)  # noqa: E731
    reason = (f"model {chosen}: held-out loss {table[chosen]['held_out_loss']:.4g}, "
              f"{percent(table[chosen]['excess']):+.2f} % over the best (model {best}), "
              f"allowed {percent(table[chosen]['allowed']):.2f} %")
    if chosen > candidates[0]:
        reason += "; simpler: " + ", ".join(f"model {m} {percent(table[m]['excess']):+.2f} % "
                                            f"(allowed {percent(table[m]['allowed']):.2f} %)"
                                            for m in candidates if m < chosen)
    return Selection(chosen, table, best, reason, len(train), len(held), held_pool.count)


def fit_by_model(obs: Observations, normal0, prior: PBRDFParams, models, settings: FitSettings = FitSettings(),
                 sigma_ss_fixed: float = 0.9, progress=None, virtual: VirtualSamples | None = None) -> FitResult:
    """:func:`sellip.fit.vertex_fit.fit_vertices` of N vertices, each with its own model (N,) (:data:`MODELS`).

    Model 2 fixes sigma_ss at ``settings.sigma_ss_fixed`` when set, else at ``sigma_ss_fixed``; models
    are capped at what ``settings`` allow; model-0 vertices get no virtual samples (they have no lobe
    to augment). ``progress(done)`` counts all vertices.
    """
    models = np.asarray(models)
    n = np.shape(obs.diffuse)[0]
    if models.shape != (n,):
        raise ValueError(f"fit_by_model: {models.shape} models for {n} vertices")
    if n == 0:
        raise ValueError("fit_by_model needs at least one vertex")
    return fit_vertices(obs, normal0, prior, settings, progress=progress, virtual=virtual, models=models,
                        sigma_ss_fixed=sigma_ss_fixed)
