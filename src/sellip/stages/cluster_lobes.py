"""``sellip cluster-lobes``: material clusters and per-cluster specular lobes (rule ``cluster_lobes``).

    sellip cluster-lobes --params results/NAME/iter/0/fit.zarr
                         --observations results/NAME/iter/0/observations.zarr
                         --output results/NAME/iter/0/clusters --seed 0
                         [--k-max 8] [--max-samples 20000] [--min-cluster-vertices 50] [--min-coherence 0.5]
                         [--set lambda_psi=100 ...]
                         [--no-model-selection] [--candidates 0 1 2 3] [--held-out-fraction 0.25]
                         [--selection-tolerance 0.01] [--selection-standard-errors 1]
                         [--fixed-sigma-ss 0.9] [--selection-max-samples 4096] [--inherit-models]

Writes the directory ``--output`` (built under a temporary name, then renamed) with

- ``labels.npy``: (N,) int32, the cluster of every vertex of the params store;
- ``models.npy``: (N,) uint8, the model of every vertex (its cluster's; :data:`sellip.model.params.MODEL_NAMES`);
- ``lobes.csv``: one row per cluster (:func:`lobes_schema`): cluster, vertices, eta, sigma_s,
  sigma_ss, rho_s, rho_ss_r, rho_ss_g, rho_ss_b, samples, loss, model;
- ``lobes.png``: each cluster's lobe against its samples as a function of theta_h (paper Fig. 7b);
- ``clusters.json``: K, the BIC per K, the merges, the regions added (:func:`sellip.fit.clusters.cluster_materials`),
  ``degenerate``: what could not be computed on these data and what was done instead (a cluster without a
  confident vertex or a usable sample, albedos without spread; the run goes on, lower in confidence),
  the settings (``settings``: the clustering's; ``fit_settings``: the lobe fit's) and the seed, and under ``model_selection`` per cluster the chosen model, the held-out loss of
  every candidate and why.

Model selection (DESIGN §7, :mod:`sellip.fit.selection`, on unless ``--no-model-selection``): per cluster,
the simplest model whose held-out loss is within the tolerance of the best; the cluster's lobe is
then fitted with that model. Without it every cluster gets the model of the fit settings (3, or 2
with ``--set sigma_ss_fixed=...``). The fit settings (``--set``) are also the most complex model allowed.
With ``--inherit-models`` (iterations between selections, config ``model_selection.every``) no candidate
is fitted: each cluster takes the model most of its vertices have in ``--params`` (their ``model``, from
the previous iteration), capped by what the settings allow; a store without models selects as usual.

The numerics are :mod:`sellip.fit` and :mod:`sellip.fit.selection`; ``sellip fit --lobes DIR`` turns
the result into virtual samples and fits every vertex with its model. ``--set`` overrides
:class:`sellip.fit.records.FitSettings` (view selection, lambda_psi, lambda_s, lobes, sigma_ss_fixed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

LOBE_COLUMNS = ("cluster", "vertices", "eta", "sigma_s", "sigma_ss", "rho_s", "rho_ss_r", "rho_ss_g", "rho_ss_b",
                "samples", "loss", "model")


def lobes_schema():
    """pandera schema of lobes.csv."""
    import pandera.pandas as pa

    from sellip.model.params import MODEL_NAMES

    finite = pa.Check(np.isfinite, element_wise=True)
    nonnegative = [pa.Check.ge(0), finite]
    return pa.DataFrameSchema(
        {
            "cluster": pa.Column(int, [pa.Check.ge(0)], unique=True, coerce=True),
            "vertices": pa.Column(int, pa.Check.ge(0), coerce=True),
            "eta": pa.Column(float, [pa.Check.ge(1.0), pa.Check.le(3.0)], coerce=True),
            "sigma_s": pa.Column(float, [pa.Check.gt(0), pa.Check.le(1.0)], coerce=True),
            "sigma_ss": pa.Column(float, [pa.Check.gt(0), pa.Check.le(1.0)], coerce=True),
            "rho_s": pa.Column(float, nonnegative, coerce=True),
            **{f"rho_ss_{c}": pa.Column(float, nonnegative, coerce=True) for c in "rgb"},
            "samples": pa.Column(int, pa.Check.ge(0), coerce=True),  # 0: a cluster without a usable sample
            "loss": pa.Column(float, nonnegative, coerce=True),
            "model": pa.Column(int, pa.Check.isin(sorted(MODEL_NAMES)), coerce=True),
        },
        strict=True, ordered=True, name="lobes.csv",
    )


def read_lobes(directory: Path):
    """The cluster labels (N,) and lobes (list of :class:`sellip.fit.lobes.ClusterLobe`, cluster order) of a
    ``cluster-lobes`` output directory. ValueError naming the file when it is missing or invalid."""
    import pandas as pd
    import pandera.pandas as pa

    from sellip.fit.lobes import ClusterLobe

    directory = Path(directory)
    labels_path, lobes_path = directory / "labels.npy", directory / "lobes.csv"
    for path in (labels_path, lobes_path):
        if not path.is_file():
            raise ValueError(f"{path}: missing; run `sellip cluster-lobes` first")
    labels = np.load(labels_path)
    try:
        table = lobes_schema().validate(pd.read_csv(lobes_path), lazy=True)
    except pa.errors.SchemaErrors as error:
        first = error.failure_cases.iloc[0]
        raise ValueError(f"{lobes_path}: invalid ({len(error.failure_cases)} problems; first: column "
                         f"{first['column']!r}, check {first['check']!r}, value {first['failure_case']!r})") from None
    table = table.sort_values("cluster")
    if list(table["cluster"]) != list(range(len(table))):
        raise ValueError(f"{lobes_path}: clusters must be numbered 0..K-1, got {list(table['cluster'])}")
    if labels.ndim != 1 or labels.dtype.kind != "i" or (labels.size and (labels.min() < 0 or labels.max() >= len(table))):
        raise ValueError(f"{labels_path}: expected (N,) integer labels in 0..{len(table) - 1}")
    lobes = [ClusterLobe(eta=row.eta, sigma_s=row.sigma_s, sigma_ss=row.sigma_ss, rho_s=row.rho_s,
                         rho_ss=np.array([row.rho_ss_r, row.rho_ss_g, row.rho_ss_b]), samples=int(row.samples),
                         loss=row.loss, theta_h_deg=np.zeros(0), value=np.zeros(0))
             for row in table.itertuples(index=False)]
    return labels, lobes


def read_models(directory: Path, count: int | None = None) -> np.ndarray:
    """The model of every vertex (N,) uint8 (``models.npy``) of a ``cluster-lobes`` output directory.
    ValueError naming the file when it is missing, not (N,) codes of :data:`sellip.model.params.MODEL_NAMES`,
    or (with ``count``) not ``count`` long."""
    from sellip.model.params import MODEL_NAMES

    path = Path(directory) / "models.npy"
    if not path.is_file():
        raise ValueError(f"{path}: missing; run `sellip cluster-lobes` first")
    models = np.load(path)
    if models.ndim != 1 or models.dtype.kind not in "iu" or not np.isin(models, sorted(MODEL_NAMES)).all():
        raise ValueError(f"{path}: expected (N,) integer model codes in {sorted(MODEL_NAMES)}")
    if count is not None and len(models) != count:
        raise ValueError(f"{path}: {len(models)} models for {count} vertices")
    return models.astype(np.uint8)


def recorded_fit_settings(clusters_json: dict, path: Path | str = "clusters.json"):
    """The :class:`sellip.fit.records.FitSettings` of a pass's lobe fits, as its ``clusters.json`` (parsed, read from ``path``)
    records them: the workflow's ``fit.settings`` for that pass. Raises ValueError for a file written before they were
    recorded (2026-11-26), naming the job to run again."""
    from sellip.fit.records import FitSettings

    if "fit_settings" not in clusters_json:
        raise ValueError(f"{path} has no fit_settings (written before 2026-11-26): run its cluster_lobes job again "
                         f"(snakemake --forcerun cluster_lobes --notemp ...)")
    return FitSettings(**clusters_json["fit_settings"])


def clustering_settings(clusters_json: dict, overrides: dict | None = None):
    """The :class:`sellip.fit.clusters.AugmentSettings` a ``clusters.json`` (its parsed dict) was made with, ``overrides``
    (field: value) over them: how a replay re-runs a pass's clustering or lobe fit as the workflow ran it (the
    :class:`sellip.fit.records.FitSettings` of the lobe fit are its ``fit_settings``)."""
    from sellip.fit.clusters import AugmentSettings

    fields = {f.name for f in dataclasses.fields(AugmentSettings)}
    unknown = set(overrides or {}) - fields
    if unknown:
        raise ValueError(f"not AugmentSettings fields: {sorted(unknown)}; expected some of {sorted(fields)}")
    return AugmentSettings(**{**{k: v for k, v in clusters_json["settings"].items() if k in fields},
                              **(overrides or {})})


def load_rows(group, rows: np.ndarray):
    """Observations (:class:`sellip.fit.records.Observations`) of the store rows ``rows`` (sorted), reading only their chunks."""
    from sellip.fit.observe import PER_VIEW_ARRAYS, VIEW_AXES
    from sellip.fit.records import Observations

    data = {name: np.asarray(group[name].oindex[rows]) for name in PER_VIEW_ARRAYS}
    for name in VIEW_AXES:
        data[name] = np.repeat(np.asarray(group[name][...])[None], len(rows), axis=0)
    return Observations(**data)


def plot_lobes(path: Path, lobes, color_of, models=None) -> None:
    """lobes.png: per cluster, its samples and its lobe (mono, per unit shading) against theta_h;
    ``models`` (K,) the clusters' model codes, shown in the titles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sellip.fit.lobes import lobe_curve

    columns = min(len(lobes), 4)
    rows = -(-len(lobes) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3.2 * rows), squeeze=False)
    theta = np.linspace(0, 89.5, 180)
    for k, (axis, lobe) in enumerate(zip(axes.ravel(), lobes)):
        axis.scatter(lobe.theta_h_deg, lobe.value, s=2, color="k", alpha=0.3, label="samples")
        axis.plot(theta, lobe_curve(theta, lobe, color_of(k)), color="r", label="cluster lobe")
        axis.set_yscale("symlog", linthresh=1e-3)
        lobes_text = {0: "no lobe", 1: f"σs {lobe.sigma_s:.3f}"}.get(
            -1 if models is None else int(models[k]), f"σs {lobe.sigma_s:.3f}, σss {lobe.sigma_ss:.2f}")
        model_text = "" if models is None else f" (model {int(models[k])})"
        axis.set_title(f"cluster {k}{model_text}: {lobes_text}, η {lobe.eta:.2f}", fontsize=9)
        axis.set_xlabel("θh (deg)")
        axis.set_xlim(0, 90)
    for axis in axes.ravel()[len(lobes):]:
        axis.axis("off")
    axes[0, 0].set_ylabel("reflectance per unit shading")
    axes[0, 0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def run_stage(params: Path, observations: Path, output: Path, seed: int = 0, settings=None,
              fit_settings=None, compilation_cache: str | None = None, selection=None,
              inherit_models: bool = False) -> dict:
    """Cluster the vertices of ``params``, choose each cluster's model (``selection``:
    :class:`sellip.fit.selection.SelectionSettings`, default on), fit the cluster lobes on ``observations``,
    write ``output``."""
    from sellip.report.timing import mark

    mark("imports")
    import jax

    from sellip.stages.fit import enable_compilation_cache

    jax.config.update("jax_enable_x64", True)  # one small problem per cluster: float64 costs little
    enable_compilation_cache(compilation_cache)
    import pandas as pd

    from sellip.fit.clusters import AugmentSettings, cluster_materials
    from sellip.fit.lobes import fit_cluster_lobe, no_lobe
    from sellip.fit.observe import ObserveError, open_observations
    from sellip.fit.records import FitSettings, model_of
    from sellip.fit.selection import SelectionSettings, allowed_models, select_model, settings_for_model
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
    clustering = cluster_materials(store["eta"], store["rho_d"], store["status"], store["confidence"], settings, seed,
                                   vertices=store["vertices"])
    k = len(clustering.centres)
    log.info("K = %d clusters (BIC over K: %s), %d merges, %d regions", k,
             {key: round(value, 1) for key, value in clustering.bic.items()}, len(clustering.merges),
             len(clustering.regions))
    allowed = allowed_models(fit_settings, selection.candidates)
    if selection.enabled:
        log.info("model selection: candidates %s, %.0f %% of each cluster's vertices held out, tolerance %g + %g SE",
                 allowed, 100 * selection.held_out_fraction, selection.tolerance, selection.standard_errors)
    inherited = None
    if selection.enabled and inherit_models:
        if "model" in store:
            inherited = np.asarray(store["model"], np.int64)
            log.info("models inherited from %s (no candidate fits this iteration)", params)
        else:
            log.warning("%s has no models to inherit: selecting", params)
    rng = np.random.default_rng(seed)
    lobes, rows_out, colors, models, choices = [], [], [], [], []
    notes = list(clustering.notes)
    for cluster in range(k):
        members = np.flatnonzero((clustering.labels == cluster) & clustering.used)
        if members.size == 0:  # its lobe comes from what its vertices have: lower confidence, said so
            members = np.flatnonzero(clustering.labels == cluster)
            notes.append(f"cluster {cluster} has no confidently fitted vertex: its lobe is fitted on all its "
                         f"{members.size} vertices")
            log.warning("%s", notes[-1])
        # Enough vertices for max_samples samples at >= 8 usable views each, a seeded subset.
        limit = max(64, settings.max_samples // 8)
        rows = np.sort(rng.choice(members, limit, replace=False)) if members.size > limit else members
        mark("read")
        obs = load_rows(group, rows)
        mark("select")
        eta0 = float(np.median(store["eta"][members]))
        if not np.isfinite(eta0):
            eta0 = 1.5  # DESIGN §5's start
        began, lobe = time.perf_counter(), None
        if not np.asarray(obs.usable).any():
            model, lobe = 0, no_lobe(eta0)
            reason = "no usable (vertex, view) sample: no lobe (model 0)"
            notes.append(f"cluster {cluster}: {reason}")
            log.warning("%s", notes[-1])
            choices.append({"cluster": cluster, "model": model, "name": MODEL_NAMES[model], "reason": reason,
                            "candidates": {}, "seconds": 0.0})
        elif inherited is not None:
            counts_here = np.bincount(inherited[clustering.labels == cluster], minlength=len(MODEL_NAMES))
            # The most common model, or the most complex allowed one below it.
            model = max((m for m in allowed if m <= int(np.argmax(counts_here))), default=allowed[0])
            reason = (f"model {model}: inherited, most of its vertices had it in {Path(params).name} "
                      f"({', '.join(f'model {m}: {c}' for m, c in enumerate(counts_here) if c)})")
            log.info("cluster %d: %s", cluster, reason)
            choices.append({"cluster": cluster, "model": model, "name": MODEL_NAMES[model], "reason": reason,
                            "inherited": True, "candidates": {}, "seconds": time.perf_counter() - began})
        elif selection.enabled:
            choice = select_model(obs, store["normals"][rows], store["rho_d"][rows], eta0, fit_settings, selection,
                                  settings, seed=seed + cluster)
            model = choice.model
            log.info("cluster %d: %s (%.1f s)", cluster, choice.reason, time.perf_counter() - began)
            choices.append({"cluster": cluster, "model": model, "name": MODEL_NAMES[model], "reason": choice.reason,
                            "best": choice.best, "train_vertices": choice.train_vertices,
                            "held_out_vertices": choice.held_out_vertices,
                            "held_out_samples": choice.held_out_samples,
                            "candidates": {str(m): row for m, row in choice.candidates.items()},
                            "seconds": time.perf_counter() - began})
        else:
            model = model_of(fit_settings)
        mark("fit")
        if lobe is None:
            lobe = fit_cluster_lobe(obs, store["normals"][rows], store["rho_d"][rows], eta0,
                                    settings_for_model(fit_settings, model, selection.sigma_ss_fixed), settings,
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
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(output.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    np.save(tmp / "labels.npy", clustering.labels.astype(np.int32))
    np.save(tmp / "models.npy", vertex_models)
    table.to_csv(tmp / "lobes.csv", index=False)
    plot_lobes(tmp / "lobes.png", lobes, lambda i: colors[i], models)
    summary = {"k": k, "bic": {str(key): value for key, value in clustering.bic.items()},
               "k_bic": int(min(clustering.bic, key=clustering.bic.get)) if clustering.bic else k,
               "merges": clustering.merges, "regions": clustering.regions, "degenerate": notes,
               "clustered_vertices": int(clustering.used.sum()), "vertices": n, "seed": seed,
               "settings": dataclasses.asdict(settings), "fit_settings": dataclasses.asdict(fit_settings),
               "model_selection": {"enabled": selection.enabled, "settings": dataclasses.asdict(selection),
                                   "allowed": allowed, "inherited": inherited is not None,
                                   "models": [int(m) for m in models], "vertices_per_model": counts,
                                   "clusters": choices}}
    (tmp / "clusters.json").write_text(json.dumps(summary, indent=2))
    shutil.rmtree(output, ignore_errors=True)
    tmp.rename(output)
    return summary


def configure_parser(parser: argparse.ArgumentParser) -> None:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.selection import SelectionSettings

    defaults = AugmentSettings()
    selection = SelectionSettings()
    parser.add_argument("--params", type=Path, required=True, help="this iteration's first-pass params store")
    parser.add_argument("--observations", type=Path, required=True, help="this iteration's observations.zarr")
    parser.add_argument("--output", type=Path, required=True, help="output directory (clusters)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--k-max", type=int, default=defaults.k_max)
    parser.add_argument("--max-samples", type=int, default=defaults.max_samples)
    parser.add_argument("--min-cluster-vertices", type=int, default=defaults.min_cluster_vertices)
    parser.add_argument("--min-coherence", type=float, default=defaults.min_coherence,
                        help="merge a cluster whose vertices' nearest neighbours lie in it less often than this "
                             "(a cut through one material's noise, not a material; 0: no test)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a FitSettings field (repeatable)")
    parser.add_argument("--compilation-cache", default=None, help="directory for XLA's persistent compilation cache")
    parser.add_argument("--model-selection", action=argparse.BooleanOptionalAction, default=selection.enabled,
                        help="choose each cluster's model on held-out vertices (default on)")
    parser.add_argument("--inherit-models", action="store_true",
                        help="no candidate fits: each cluster takes its vertices' most common model in --params")
    parser.add_argument("--candidates", type=int, nargs="+", default=list(selection.candidates),
                        help="model codes tried (sellip.model.params.MODEL_NAMES)")
    parser.add_argument("--held-out-fraction", type=float, default=selection.held_out_fraction)
    parser.add_argument("--selection-tolerance", type=float, default=selection.tolerance,
                        help="relative held-out loss a simpler model may lose")
    parser.add_argument("--selection-standard-errors", type=float, default=selection.standard_errors,
                        help="plus this many standard errors of the difference")
    parser.add_argument("--fixed-sigma-ss", type=float, default=selection.sigma_ss_fixed,
                        help="sigma_ss of model 2 when --set sigma_ss_fixed is not given")
    parser.add_argument("--selection-max-samples", type=int, default=selection.max_samples,
                        help="training samples per candidate fit")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.observe import ObserveError
    from sellip.fit.selection import SelectionSettings
    from sellip.model.params import ParamsError
    from sellip.stages.fit import settings_from_pairs

    try:
        if args.k_max < 1 or args.max_samples < 1 or args.min_cluster_vertices < 1 or args.selection_max_samples < 1:
            raise ValueError("--k-max, --max-samples, --min-cluster-vertices and --selection-max-samples must be >= 1")
        if not 0 <= args.min_coherence <= 1:
            raise ValueError(f"--min-coherence must be in [0, 1], got {args.min_coherence}")
        settings = AugmentSettings(k_max=args.k_max, max_samples=args.max_samples,
                                   min_cluster_vertices=args.min_cluster_vertices, min_coherence=args.min_coherence)
        selection = SelectionSettings(enabled=args.model_selection, candidates=tuple(args.candidates),
                                      held_out_fraction=args.held_out_fraction, tolerance=args.selection_tolerance,
                                      standard_errors=args.selection_standard_errors,
                                      sigma_ss_fixed=args.fixed_sigma_ss, max_samples=args.selection_max_samples)
        run_stage(args.params, args.observations, args.output, args.seed, settings,
                  settings_from_pairs(args.overrides), args.compilation_cache, selection, args.inherit_models)
    except (ObserveError, ParamsError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
