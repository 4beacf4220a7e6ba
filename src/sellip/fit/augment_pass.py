"""One augmentation pass (rule ``cluster_lobes``; paper §4.3, docs/design.md §7): the material clusters, each
cluster's model chosen on held-out vertices, each cluster's lobe fitted, written to the cluster-lobes
directory (:func:`cluster_and_fit_lobes`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from sellip.fit.lobe_store import LOBE_COLUMNS, load_rows, lobes_schema, plot_lobes, read_labels
from sellip.jobs import atomic_directory

log = logging.getLogger(__name__)


def _choose_model(cluster: int, obs, store: dict, rows, eta0: float, clustering, inherited, allowed, params,
                  fit_settings, selection, settings, seed: int, notes: list):
    """(model, lobe or None, the choice's record for clusters.json or None) of one cluster: no lobe without a usable
    sample (a note), the model most of its vertices had (``inherited``), the model selection's, or the fit
    settings' model."""
    from sellip.fit.lobes import no_lobe
    from sellip.fit.records import model_of
    from sellip.fit.selection import select_model
    from sellip.model.params import MODEL_NAMES

    began, lobe, choice = time.perf_counter(), None, None
    if not np.asarray(obs.usable).any():
        model, lobe = 0, no_lobe(eta0)
        reason = "no usable (vertex, view) sample: no lobe (model 0)"
        notes.append(f"cluster {cluster}: {reason}")
        log.warning("%s", notes[-1])
        choice = {"cluster": cluster, "model": model, "name": MODEL_NAMES[model], "reason": reason,
                  "candidates": {}, "seconds": 0.0}
    elif inherited is not None:
        counts_here = np.bincount(inherited[clustering.labels == cluster], minlength=len(MODEL_NAMES))
        # The most common model, or the most complex allowed one below it.
        model = max((m for m in allowed if m <= int(np.argmax(counts_here))), default=allowed[0])
        reason = (f"model {model}: inherited, most of its vertices had it in {Path(params).name} "
                  f"({', '.join(f'model {m}: {c}' for m, c in enumerate(counts_here) if c)})")
        log.info("cluster %d: %s", cluster, reason)
        choice = {"cluster": cluster, "model": model, "name": MODEL_NAMES[model], "reason": reason,
                  "inherited": True, "candidates": {}, "seconds": time.perf_counter() - began}
    elif selection.enabled:
        picked = select_model(obs, store["normals"][rows], store["rho_d"][rows], eta0, fit_settings, selection,
                              settings, seed=seed + cluster)
        model = picked.model
        log.info("cluster %d: %s (%.1f s)", cluster, picked.reason, time.perf_counter() - began)
        choice = {"cluster": cluster, "model": model, "name": MODEL_NAMES[model], "reason": picked.reason,
                  "best": picked.best, "train_vertices": picked.train_vertices,
                  "held_out_vertices": picked.held_out_vertices, "held_out_samples": picked.held_out_samples,
                  "margin": None if np.isnan(picked.margin) else picked.margin, "runner_up": picked.runner_up,
                  "candidates": {str(m): row for m, row in picked.candidates.items()},
                  "seconds": time.perf_counter() - began}
    else:
        model = model_of(fit_settings)
    return model, lobe, choice


def cluster_rows(clustering, settings, seed: int, notes: list | None = None,
                 vertices: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per cluster of ``clustering`` (:func:`sellip.fit.clusters.cluster_materials`), (members, rows): its
    confidently fitted vertices (all its vertices where it has none; said in ``notes``) and the seeded subset of
    them whose observations its lobe fit and model selection read (enough for ``settings.max_samples`` samples at
    8 usable views each). With ``settings.pool_min_coherence`` > 0 and the ``vertices`` (N, 3), the rows are drawn
    from the members at least that coherent (:func:`sellip.fit.clusters.vertex_coherence`), where at least half of
    them are. The same ``seed`` gives the same rows (``benchmarks/replay_selection.py`` replays them)."""
    from sellip.fit.clusters import nearest_vertices, vertex_coherence

    rng = np.random.default_rng(seed)
    coherence = None
    if settings.pool_min_coherence > 0 and vertices is not None:
        coherence = vertex_coherence(clustering.labels, nearest_vertices(vertices, settings.coherence_neighbours))
    out = []
    for cluster in range(len(clustering.centres)):
        members = np.flatnonzero((clustering.labels == cluster) & clustering.used)
        if members.size == 0:  # its lobe comes from what its vertices have: lower confidence, said so
            members = np.flatnonzero(clustering.labels == cluster)
            if notes is not None:
                notes.append(f"cluster {cluster} has no confidently fitted vertex: its lobe is fitted on all its "
                             f"{members.size} vertices")
                log.warning("%s", notes[-1])
        pooled = members
        if coherence is not None:
            coherent = members[coherence[members] >= settings.pool_min_coherence]
            if 2 * coherent.size >= members.size:
                pooled = coherent
                log.info("cluster %d: %d of %d vertices pooled (coherence >= %g)", cluster, coherent.size,
                         members.size, settings.pool_min_coherence)
            else:
                log.info("cluster %d: all %d vertices pooled (only %d are coherent >= %g)", cluster, members.size,
                         coherent.size, settings.pool_min_coherence)
        limit = max(64, settings.max_samples // 8)
        rows = np.sort(rng.choice(pooled, limit, replace=False)) if pooled.size > limit else pooled
        out.append((members, rows))
    return out


def _write_directory(output: Path, labels, vertex_models, table, lobes, colors, models, summary: dict) -> None:
    """The cluster-lobes directory (:mod:`sellip.fit.lobe_store`), built under a temporary name, then renamed."""
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        np.save(tmp / "labels.npy", labels.astype(np.int32))
        np.save(tmp / "models.npy", vertex_models)
        table.to_csv(tmp / "lobes.csv", index=False)
        plot_lobes(tmp / "lobes.png", lobes, lambda i: colors[i], models)
        (tmp / "clusters.json").write_text(json.dumps(summary, indent=2))


def cluster_and_fit_lobes(params: Path, observations: Path, output: Path, seed: int = 0, settings=None,
              fit_settings=None, compilation_cache: str | None = None, selection=None,
              inherit_models: bool = False, previous_clusters: Path | None = None) -> dict:
    """Cluster the vertices of ``params``, choose each cluster's model (``selection``:
    :class:`sellip.fit.selection.SelectionSettings`, default on), fit the cluster lobes on ``observations``,
    write ``output``. ``previous_clusters``: the previous pass's cluster-lobes directory, whose ``labels.npy`` keeps
    a material found there on less evidence (:func:`sellip.fit.clusters.cluster_materials` ``previous_labels``;
    ignored, said so, when it labels other vertices).

    Long: the per-cluster loop gathers the lobes table, the plot's colours and the choices that clusters.json
    records side by side; the model choice and the writing are :func:`_choose_model` and :func:`_write_directory`."""
    from sellip.timing import mark

    mark("imports")
    import jax

    from sellip.fit.shard import enable_compilation_cache

    jax.config.update("jax_enable_x64", True)  # one small problem per cluster: float64 costs little
    enable_compilation_cache(compilation_cache)
    import pandas as pd

    from sellip.fit.cluster_support import clustering_support
    from sellip.fit.clusters import AugmentSettings, cluster_materials
    from sellip.fit.lobes import fit_cluster_lobe
    from sellip.fit.observe import ObserveError, open_observations
    from sellip.fit.records import FitSettings
    from sellip.fit.selection import (
        SelectionSettings,
        allowed_models,
        settings_for_model,
    )
    from sellip.model.params import MODEL_NAMES, read_params, same_vertices

    settings = settings or AugmentSettings()
    fit_settings = fit_settings or FitSettings()
    selection = selection or SelectionSettings()
    mark("read")
    store = read_params(params)
    group = open_observations(observations)
    total = int(group.attrs["num_vertices"])
    n = len(store["vertices"])
    if not same_vertices(np.asarray(group["vertices"][...]), store["vertices"]):
        raise ObserveError(observations, f"holds {total} vertices that are not the {n} vertices of {params} "
                                         "(cluster-lobes needs the params and observations of the same mesh)")
    mark("cluster")
    previous = None if previous_clusters is None else read_labels(previous_clusters, n)
    if previous is not None:
        log.info("the previous pass's clusters: %s (a material found there is kept on %g less coherence)",
                 previous_clusters, settings.keep_coherence_margin)
    elif previous_clusters is not None:
        log.warning("%s labels other vertices than the %d of %s: no hysteresis this pass", previous_clusters, n,
                    params)
    clustering = cluster_materials(store["eta"], store["rho_d"], store["status"], store["confidence"], settings, seed,
                                   vertices=store["vertices"], previous_labels=previous)
    k = len(clustering.centres)
    log.info("K = %d clusters (BIC over K: %s), %d merges, %d regions", k,
             {key: round(value, 1) for key, value in clustering.bic.items()}, len(clustering.merges),
             len(clustering.regions))
    support = None
    if settings.stability_resamples > 0:
        mark("support")
        support = clustering_support(store["eta"], store["rho_d"], store["status"], store["confidence"], clustering,
                                     settings, seed, vertices=store["vertices"], previous_labels=previous)
        log.info("support of each cluster over %d resamples: %s (K over them: %s)", support["resamples"],
                 [row["support"] for row in support["clusters"]], support["k"])
    allowed = allowed_models(fit_settings, selection.candidates)
    if selection.enabled:
        split = (f"{selection.folds}-fold cross-validation" if selection.folds > 1
                 else f"{100 * selection.held_out_fraction:.0f} % of each cluster's vertices held out")
        log.info("model selection: candidates %s, %s, tolerance %g + %g SE", allowed, split, selection.tolerance,
                 selection.standard_errors)
    inherited = None
    if selection.enabled and inherit_models:
        if "model" in store:
            inherited = np.asarray(store["model"], np.int64)
            log.info("models inherited from %s (no candidate fits this iteration)", params)
        else:
            log.warning("%s has no models to inherit: selecting", params)
    lobes, rows_out, colors, models, choices = [], [], [], [], []
    notes = list(clustering.notes)
    for cluster, (members, rows) in enumerate(cluster_rows(clustering, settings, seed, notes, store["vertices"])):
        mark("read")
        obs = load_rows(group, rows)
        mark("select")
        eta0 = float(np.median(store["eta"][members]))
        if not np.isfinite(eta0):
            eta0 = 1.5  # docs/design.md §5's start
        model, lobe, choice = _choose_model(cluster, obs, store, rows, eta0, clustering, inherited, allowed, params,
                                            fit_settings, selection, settings, seed, notes)
        if choice is not None:
            choices.append(choice)
        mark("fit")
        if lobe is None:
            lobe = fit_cluster_lobe(obs, store["normals"][rows], store["rho_d"][rows], eta0,
                                    settings_for_model(fit_settings, model, selection.model2_sigma_ss), settings,
                                    seed=seed + cluster)
        log.info("cluster %d: %d vertices (%d confident), %d samples, model %d: eta %.3f sigma_s %.3f sigma_ss %.3f "
                 "rho_s %.4g rho_ss %s", cluster, int(np.sum(clustering.labels == cluster)), members.size,
                 lobe.samples, model, lobe.eta, lobe.sigma_s, lobe.sigma_ss, lobe.rho_s, np.round(lobe.rho_ss, 4))
        lobes.append(lobe)
        models.append(model)
        mean_color = np.asarray(obs.diffuse)[np.asarray(obs.usable)].sum(0)
        colors.append(mean_color / mean_color.sum() if mean_color.sum() > 0 else np.full(3, 1 / 3))
        rows_out.append({"cluster": cluster, "vertices": int(np.sum(clustering.labels == cluster)), "eta": lobe.eta,
                         "sigma_s": lobe.sigma_s, "sigma_ss": lobe.sigma_ss, "rho_s": lobe.rho_s,
                         **{f"rho_ss_{c}": float(lobe.rho_ss[i]) for i, c in enumerate("rgb")},
                         "samples": lobe.samples, "loss": lobe.loss, "model": model})
    mark("write")
    table = lobes_schema().validate(pd.DataFrame(rows_out, columns=list(LOBE_COLUMNS)))
    vertex_models = np.asarray(models, np.uint8)[clustering.labels]
    counts = {str(m): int(np.sum(vertex_models == m)) for m in sorted(MODEL_NAMES)}
    log.info("vertices per model: %s", counts)
    summary = {"k": k, "bic": {str(key): value for key, value in clustering.bic.items()},
               "k_bic": int(min(clustering.bic, key=clustering.bic.get)) if clustering.bic else k,
               "merges": clustering.merges, "regions": clustering.regions, "support": support, "degenerate": notes,
               "clustered_vertices": int(clustering.used.sum()), "vertices": n, "seed": seed,
               "settings": dataclasses.asdict(settings), "fit_settings": dataclasses.asdict(fit_settings),
               "model_selection": {"enabled": selection.enabled, "settings": dataclasses.asdict(selection),
                                   "allowed": allowed, "inherited": inherited is not None,
                                   "models": [int(m) for m in models], "vertices_per_model": counts,
                                   "clusters": choices}}
    _write_directory(Path(output), clustering.labels, vertex_models, table, lobes, colors, models, summary)
    return summary
