"""Model selection (docs/design.md §7): which lobes a material cluster needs, and fitting vertices by model.

The models (:data:`sellip.model.params.MODEL_NAMES`, the ``model`` of every vertex in model.ply), from
the simplest:

    0 diffuse                                   FitSettings(lobes="diffuse")
    1 diffuse + specular                        FitSettings(lobes="specular")
    2 + single scattering, sigma_ss fixed       FitSettings(lobes="full", sigma_ss_fixed=value)
    3 + single scattering                       FitSettings(lobes="full", sigma_ss_fixed=None)

Each is nested in the next (2 in 3: sigma_ss free includes the fixed value), so "simpler" is the
lower code. The fit settings of a pass are the most complex model allowed (:func:`model_of`): a
run with ``sigma_ss_fixed`` set never selects 3, one with ``lobes="specular"`` never 2 or 3.

The rule (:func:`select_model`, per cluster): the cluster's vertices are cut (seeded, by vertex) into
``folds`` parts (:func:`fold_splits`; one training and one held-out part with ``folds`` 1); each part is held out
once, every candidate's cluster lobe (:func:`sellip.fit.lobes.fit_cluster_lobe`) fitted on the others, the fits
nested (:func:`nested_fits`: each model takes the best training fit it can express), and scored by the cluster
loss on the held-out samples (:func:`sellip.fit.lobes.lobe_sample_losses`). The simplest
candidate whose held-out loss exceeds the best one's by at most ``tolerance`` (relative) plus
``standard_errors`` standard errors of the paired per-vertex difference is chosen (:func:`choose`), in two
questions: a reflection lobe or not, then which lobes.

The candidate fits and their held-out scores that decide which lobes a cluster has (models 1, 2, 3) have no
per-sample half-angle error Delta theta_h (``max_theta_error_deg`` 0; the chosen model's lobe is then fitted with
it, as before); whether it has a reflection lobe at all (model 0 against the simplest with one) is decided
first, with it, as before 2026-11-26 (without it, a weak rough lobe such as pplastic_set's eta 1.33, sigma_s 0.4
was dropped altogether). That nuisance, one
per sample and re-fitted on the held-out samples too, rewards a lobe that is steep in theta_h: a narrow
specular lobe moves each sample onto its flank, and a broad single-scattering lobe fills in what is left.
On the stability suite's rough material (sigma_s 0.35, no single scattering) model 1 came out at sigma_s
0.17 with it and 0.33 without, and model 3 (sigma_s 0.09 + sigma_ss 0.49) won by 8 %; without it, by
0.03 %, within the tolerance (docs/model_selection.md, "Why no Delta theta_h").

:func:`decision_margin` says how far a choice is from the rule's boundary; :func:`cluster_margins` reads it back
from clusters.json and :func:`margin_confidence` turns it into the final model's confidence factor (materials.csv
reports it per material).

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
from sellip.fit.records import (
    DEFAULT_FIXED_SIGMA_SS,
    MODELS,
    FitResult,
    FitSettings,
    Observations,
    VirtualSamples,
    model_of,
)
from sellip.fit.vertex_fit import fit_vertices
from sellip.model.pbrdf import PBRDFParams
from sellip.settings import setting

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SelectionSettings:
    """Settings of the per-cluster model selection (config section ``model_selection``)."""

    enabled: bool = setting(True, "choose each cluster's model on held-out vertices; false: every vertex gets the fit "
                            "settings' model (3, or 2 when fit.settings.sigma_ss_fixed is set)")
    candidates: tuple[int, ...] = setting(MODELS, "models tried: 0 diffuse, 1 + specular, 2 + single scattering with "
                                          "sigma_ss fixed, 3 + single scattering (capped by the fit settings)",
                                          choices=MODELS, min_items=1)
    held_out_fraction: float = setting(0.25, "share of a cluster's vertices held out (a seeded split by vertex) when "
                                       "folds is 1", exclusive_minimum=0, exclusive_maximum=1)
    folds: int = setting(4, "k >= 2: k-fold cross-validation, every vertex held out once (docs/model_selection.md, "
                         "'Cross-validation and nested fits'); 1: one held-out part of held_out_fraction", minimum=1)
    tolerance: float = setting(0.01, "a simpler model may lose this fraction of the best held-out loss ...", minimum=0)
    standard_errors: float = setting(1.0, "... plus this many standard errors of the paired per-vertex difference",
                                     minimum=0)
    model2_sigma_ss: float = setting(DEFAULT_FIXED_SIGMA_SS, "sigma_ss of model 2 (single scattering with sigma_ss "
                                     "fixed), unless fit.settings.sigma_ss_fixed fixes every vertex's (paper §6: 0.9 "
                                     "or 1.0)", minimum=0.02, maximum=1)
    max_samples: int = setting(4096, "training (and at most as many held-out) samples per candidate fit (a power of "
                               "two: one compiled shape)", minimum=1)
    min_held_out_vertices: int = setting(8, "fewer vertices in either part: no selection, the most complex candidate",
                                         minimum=1)
    max_theta_error_deg: float = setting(0.0, "|Delta theta_h| bound of the candidate fits and their held-out scores "
                                         "among models 1, 2, 3 (0: none; model 0 against a lobe keeps augment's "
                                         "bound; docs/model_selection.md)", unit="degrees", minimum=0)

    def __post_init__(self):
        if not self.candidates or any(m not in MODELS for m in self.candidates):
            raise ValueError(f"model_selection candidates must be a non-empty subset of {MODELS}, "
                             f"got {self.candidates}")
        if not 0 < self.held_out_fraction < 1:
            raise ValueError(f"model_selection held_out_fraction must be in (0, 1), got {self.held_out_fraction}")
        if not isinstance(self.folds, (int, np.integer)) or self.folds < 1:
            raise ValueError(f"model_selection folds must be an integer >= 1, got {self.folds}")
        if self.tolerance < 0 or self.standard_errors < 0:
            raise ValueError("model_selection tolerance and standard_errors must be >= 0")
        if not 0.02 <= self.model2_sigma_ss <= 1:
            raise ValueError(f"model_selection model2_sigma_ss must be in [0.02, 1], got {self.model2_sigma_ss}")
        if self.max_theta_error_deg < 0:
            raise ValueError(f"model_selection max_theta_error_deg must be >= 0, got {self.max_theta_error_deg}")

    def lobe_settings(self, augment_settings: clusters.AugmentSettings) -> clusters.AugmentSettings:
        """The lobe-fit settings of the candidate fits: ``augment_settings`` with ``max_samples`` and the
        Delta theta_h bound of these settings (no alternations without a Delta theta_h to alternate with)."""
        return dataclasses.replace(augment_settings, max_samples=self.max_samples,
                                   max_theta_error_deg=self.max_theta_error_deg,
                                   alternations=augment_settings.alternations if self.max_theta_error_deg > 0 else 0)


def settings_for_model(settings: FitSettings, model: int,
                       sigma_ss_fixed: float = DEFAULT_FIXED_SIGMA_SS) -> FitSettings:
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
    bound). best: the code of the lowest held-out loss. reason: a sentence. train_vertices (a fold's, the mean
    over folds), held_out_vertices, held_out_samples (all folds'): the split. margin, runner_up:
    :func:`decision_margin` (NaN and None where no candidates were scored)."""

    model: int
    candidates: dict
    best: int | None
    reason: str
    train_vertices: int
    held_out_vertices: int
    held_out_samples: int
    margin: float = float("nan")
    runner_up: int | None = None


def split_vertices(n: int, fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Seeded split of n vertices into (train, held_out) sorted index arrays; round(fraction n) held out."""
    held = int(round(fraction * n))
    order = rng.permutation(n)
    return np.sort(order[held:]), np.sort(order[:held])


def fold_splits(n: int, selection: SelectionSettings, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (train, held_out) sorted index arrays of ``selection``: one :func:`split_vertices` of
    ``held_out_fraction`` when ``folds`` is 1; else ``folds`` parts of a seeded permutation of the n vertices (sizes
    differing by at most one), each held out once with the others as its training part."""
    if selection.folds == 1:
        return [split_vertices(n, selection.held_out_fraction, rng)]
    parts = np.array_split(rng.permutation(n), selection.folds)
    return [(np.sort(np.concatenate(parts[:k] + parts[k + 1:])), np.sort(part)) for k, part in enumerate(parts)]


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


def decision_margin(table: dict, chosen: int) -> tuple[float, int | None]:
    """How far the choice of :func:`choose` is from the rule's boundary, in units of the allowance, and the
    model nearest to taking its place: (margin in [0, 1], runner_up).

    For the chosen model its unused allowance, (allowed - excess) / allowed (1 when it is the best); for each
    simpler model how far its excess went past its allowance, (excess - allowed) / allowed. The margin is the
    smallest of these, capped at 1: 0 is a choice on the boundary (a little more noise or another split would
    flip it), 1 a choice no candidate came near. The runner-up is the model of the smallest term (a simpler
    model, or the best one when the chosen is not the best); where that is the chosen model's own slack as the
    best, the model of the next lowest held-out loss. ``table``: ``choose``'s ({} gives (NaN, None))."""
    if not table or chosen not in table:
        return float("nan"), None
    def unit(row):
        return max(row["allowed"], 1e-12 * max(row["held_out_loss"], 1e-300))

    row = table[chosen]
    best = min(table, key=lambda m: (table[m]["excess"], m))
    terms = {(best if best != chosen else None): (row["allowed"] - row["excess"]) / unit(row)}
    for m, other in table.items():
        if m < chosen:
            terms[m] = (other["excess"] - other["allowed"]) / unit(other)
    nearest = min(terms, key=lambda m: terms[m])
    runner_up = nearest
    if nearest is None:
        others = sorted((m for m in table if m != chosen), key=lambda m: (table[m]["excess"], m))
        runner_up = others[0] if others else None
    return float(np.clip(terms[nearest], 0.0, 1.0)), runner_up


MARGIN_FULL_CONFIDENCE = 0.5
"""A cluster whose :func:`decision_margin` is below this has its vertices' confidence lowered in the final model
(:func:`margin_confidence`): at 0 (the choice on the rule's boundary) by half."""


def margin_confidence(margin) -> np.ndarray:
    """The factor (...,) in [0.5, 1] on a vertex's confidence from its cluster's selection margin (...,):
    0.5 + min(margin, :data:`MARGIN_FULL_CONFIDENCE`) / (2 MARGIN_FULL_CONFIDENCE): 0.5 on the boundary, 1 at
    and above MARGIN_FULL_CONFIDENCE; 1 where no choice was scored (NaN: one candidate, too few vertices)."""
    margin = np.asarray(margin, np.float64)
    factor = 0.5 + 0.5 * np.clip(margin, 0.0, MARGIN_FULL_CONFIDENCE) / MARGIN_FULL_CONFIDENCE
    return np.where(np.isfinite(margin), factor, 1.0)


def cluster_margins(summary: dict, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cluster of a ``cluster-lobes`` summary (clusters.json), (margin (k,) float, runner_up (k,) int): the
    recorded :func:`decision_margin` and runner-up of each cluster's choice; NaN and -1 where the pass scored no
    candidates for it (inherited models, one candidate, too few vertices, no usable sample, selection off, or a
    clusters.json written before margins were recorded)."""
    margins, runner_up = np.full(k, np.nan), np.full(k, -1, np.int64)
    for choice in (summary.get("model_selection") or {}).get("clusters") or []:
        cluster = int(choice.get("cluster", -1))
        if 0 <= cluster < k and choice.get("margin") is not None:
            margins[cluster] = float(choice["margin"])
            runner_up[cluster] = -1 if choice.get("runner_up") is None else int(choice["runner_up"])
    return margins, runner_up


def in_family(lobe: fit_lobes.ClusterLobe, model: int, sigma_ss_fixed: float) -> bool:
    """Whether a fitted cluster lobe predicts what a lobe of ``model`` can: every lobe is in model 3's family;
    model 2's has no single scattering or sigma_ss at ``sigma_ss_fixed``; model 1's no single scattering; model
    0's no lobe at all (albedos at 0: the fit's closed-form non-negative solve gives exact zeros)."""
    no_ss = not np.any(np.asarray(lobe.rho_ss) > 0)
    if model >= 3:
        return True
    if model == 2:
        return no_ss or abs(lobe.sigma_ss - sigma_ss_fixed) < 1e-9
    return no_ss and (model == 1 or not lobe.rho_s > 0)


def nested_fits(fits: dict, sigma_ss_fixed: float) -> dict:
    """The candidates' training fits {model: ClusterLobe} with nesting restored: each model takes the lowest
    training loss among its own fit and the other models' fits in its family (:func:`in_family`; a simpler
    model's always is). The lobe fits are local (least squares from the best grid start), so a richer model can
    end in a worse optimum than a simpler one, or a simpler one miss the optimum a richer one found with its extra
    lobe at 0; the two then differ on held-out samples by what the optimizer did, not by what the extra lobe
    explains (on the stability suite's near-mirror, model 3 ended at sigma_s 0.050 with no single scattering,
    model 1 at 0.031 with a lower training loss, and five held-out vertices made model 3 "win" by 39 %;
    docs/model_selection.md, "Cross-validation and nested fits")."""
    return {m: min((lobe for j, lobe in fits.items() if j <= m or in_family(lobe, m, sigma_ss_fixed)),
                   key=lambda lobe: lobe.loss) for m in fits}


def _held_out_losses(models, folds, eta0: float, fit_settings: FitSettings, selection: SelectionSettings,
                     lobe_settings: clusters.AugmentSettings) -> dict:
    """{model: (held-out vertices of every fold,) summed held-out loss} of each model's lobe fitted on each fold's
    training pool (:func:`nested_fits` over ``models``) and scored on its held-out pool (``folds``: a list of
    (train, held, held-out vertex count); the vertices in fold order), with the Delta theta_h bound of
    ``lobe_settings`` (0: none, and no Delta theta_h fitted on the held-out samples either)."""
    delta_rounds = 2 if lobe_settings.max_theta_error_deg > 0 else 0
    settings = {m: settings_for_model(fit_settings, m, selection.model2_sigma_ss) for m in models}
    model_2_sigma_ss = settings_for_model(fit_settings, 2, selection.model2_sigma_ss).sigma_ss_fixed
    per_fold = {m: [] for m in models}
    for train_pool, held_pool, held in folds:
        fits = nested_fits({m: fit_lobes.fit_pool(train_pool, eta0, settings[m], lobe_settings) for m in models},
                           model_2_sigma_ss)
        for m in models:
            per_sample = fit_lobes.lobe_sample_losses(fits[m], held_pool, settings[m], lobe_settings, delta_rounds)
            per_fold[m].append(np.bincount(held_pool.vertex, weights=per_sample, minlength=held))
    return {m: np.concatenate(parts) for m, parts in per_fold.items()}


def _describe(chosen: int, best: int, table: dict, question: str) -> str:
    """The sentence of one comparison of :func:`select_model`."""
    def percent(x):
        return 100 * x / max(table[best]["held_out_loss"], 1e-300)

    reason = (f"{question}: model {chosen}, held-out loss {table[chosen]['held_out_loss']:.4g}, "
              f"{percent(table[chosen]['excess']):+.2f} % over the best (model {best}), "
              f"allowed {percent(table[chosen]['allowed']):.2f} %")
    simpler = [m for m in sorted(table) if m < chosen]
    if simpler:
        reason += "; simpler: " + ", ".join(f"model {m} {percent(table[m]['excess']):+.2f} % "
                                            f"(allowed {percent(table[m]['allowed']):.2f} %)" for m in simpler)
    return reason


def select_model(obs: Observations, normals, rho_d, eta0: float, fit_settings: FitSettings | None = None,
                 selection: SelectionSettings = SelectionSettings(),
                 augment_settings: clusters.AugmentSettings = clusters.AugmentSettings(), seed: int = 0) -> Selection:
    """Choose the model of one cluster from the observations of its n vertices (docs/design.md §7).

    obs: :class:`sellip.fit.records.Observations` (n, K); normals (n, 3), rho_d (n, 3): the vertices'
    fitted normals and albedos (held, as in :func:`sellip.fit.lobes.fit_cluster_lobe`); eta0: the
    start of eta. The candidates are ``selection.candidates`` allowed by ``fit_settings``
    (:func:`allowed_models`). Each candidate's lobe is fitted on the training vertices (at most
    ``selection.max_samples`` samples) and scored on the same held-out samples, by :func:`choose`, in two
    questions: a reflection lobe or none (model 0 against the simplest model with one), with the cluster lobe
    fit's Delta theta_h (``augment_settings``), as before 2026-11-26; then, if a lobe, which (the models from 1
    up) with ``selection.max_theta_error_deg`` (0: none; the module docstring says why). The table holds model
    0's row of the first question and the rows of the second (fitted and recorded even when the first says
    none); the margin is the smaller of the questions' that decided (:func:`decision_margin`). With
    ``selection.folds`` k >= 2 the training and held-out parts are the k folds of :func:`fold_splits`: every
    candidate is fitted k times and every vertex scored once, on the lobe fitted without it. Deterministic
    for a seed.
    """
    fit_settings = fit_settings or FitSettings()
    candidates = allowed_models(fit_settings, selection.candidates)
    n = len(normals)
    splits = fold_splits(n, selection, np.random.default_rng(seed))
    train_count = sum(len(train) for train, _ in splits) // len(splits)
    held_count = sum(len(held) for _, held in splits)
    if len(candidates) == 1:
        return Selection(candidates[0], {}, None, "one candidate", train_count, held_count, 0)
    if min(min(len(train), len(held)) for train, held in splits) < selection.min_held_out_vertices:
        top = candidates[-1]
        return Selection(top, {}, None, f"{n} vertices: too few to hold {selection.min_held_out_vertices} out "
                                        f"(kept the most complex candidate, {top})", train_count, held_count, 0)
    take = lambda rows: Observations(*[np.asarray(x)[rows] for x in obs])
    normals, rho_d = np.asarray(normals), np.asarray(rho_d)
    pools = []
    for fold, (train, held) in enumerate(splits):  # fold 0's generators are those of the single split
        train_pool = fit_lobes.pool_samples(take(train), normals[train], rho_d[train], fit_settings,
                                           selection.max_samples, np.random.default_rng(seed + 1 + 2 * fold))
        held_pool = fit_lobes.pool_samples(take(held), normals[held], rho_d[held], fit_settings,
                                          selection.max_samples, np.random.default_rng(seed + 2 + 2 * fold))
        pools.append((train_pool, held_pool, len(held)))
    held_samples = sum(held_pool.count for _, held_pool, _ in pools)
    if any(train_pool.count == 0 or held_pool.count == 0 for train_pool, held_pool, _ in pools):
        top = candidates[-1]
        return Selection(top, {}, None, f"no usable samples in a training or held-out part (kept {top})",
                         train_count, held_count, held_samples)
    lobed = [m for m in candidates if m >= 1]
    reasons, margins, table, chosen, best = [], [], {}, None, None
    if 0 in candidates and lobed:  # a reflection lobe at all: the lobe fit's own Delta theta_h
        lobe_fit = dataclasses.replace(augment_settings, max_samples=selection.max_samples)
        losses = _held_out_losses([0, lobed[0]], pools, eta0, fit_settings, selection, lobe_fit)
        chosen, best, first = choose(losses, selection.tolerance, selection.standard_errors)
        reasons.append(_describe(chosen, best, first, "a lobe"))
        margins.append(decision_margin(first, chosen))
        table.update(first)  # model 1's row is the which-lobes question's where that is asked
    if len(lobed) > 1:  # which lobes: no Delta theta_h (selection.max_theta_error_deg); recorded after a "none" too
        losses = _held_out_losses(lobed, pools, eta0, fit_settings, selection,
                                  selection.lobe_settings(augment_settings))
        which, which_best, second = choose(losses, selection.tolerance, selection.standard_errors)
        table.update(second)
        if chosen != 0:
            chosen, best = which, which_best
            reasons.append(_describe(chosen, best, second, "which lobes"))
            margins.append(decision_margin(second, chosen))
    elif chosen is None:  # no model 0 to compare and one lobed candidate cannot happen (len(candidates) > 1)
        chosen = lobed[0]
    margin, runner_up = min(margins, key=lambda pair: pair[0]) if margins else (float("nan"), None)
    reason = f"model {chosen} ({'; '.join(reasons)}); margin {margin:.2f}"
    reason += f" (model {runner_up})" if runner_up is not None else ""
    return Selection(chosen, table, best, reason, train_count, held_count, held_samples, margin, runner_up)


def fit_by_model(obs: Observations, normal0, prior: PBRDFParams, models, settings: FitSettings = FitSettings(),
                 sigma_ss_fixed: float = DEFAULT_FIXED_SIGMA_SS, progress=None,
                 virtual: VirtualSamples | None = None) -> FitResult:
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
