"""Re-run the per-cluster model selection of a pass on its stored fit and observations, with other settings.

    python benchmarks/replay_selection.py RUN --iteration N --truth CAPTURE/ground_truth/model.ply \
        [--set max_theta_error_deg=5 tolerance=0.02 ...]

RUN is a workflow's results folder (``results/<name>``) whose pass N kept its observations: run the workflow
with ``snakemake --notemp`` up to the target ``results/<name>/iter/N/clusters`` (``iter/N/observations.zarr`` is
temporary otherwise). The replay clusters ``iter/N/fit.zarr`` as the pass did (its settings and seed, from
``clusters.json``), takes each cluster's rows as ``cluster_lobes`` does (:func:`sellip.fit.augment_pass.cluster_rows`)
and runs :func:`sellip.fit.selection.select_model` with the pass's selection settings and ``--set``
(SelectionSettings fields) over them. With the run's own settings it gives the pass's choices again. Per cluster:
its vertices, their true material, the chosen model, its margin and the reason; then, as if every vertex had its
cluster's model, the share of vertices with single scattering where the truth has none (all, per true material)
and where it has some (recall): the figures of :mod:`sellip.bench.renderers` for that pass, before the refit.
docs/model_selection.md quotes it.
"""

from __future__ import annotations

import json
import sys
import time


def main(argv=None) -> int:
    from sellip.bench.replay import ignore_snakemake_zarr_warnings, replay_parser

    parser = replay_parser(__doc__)
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="SelectionSettings fields over the pass's own (e.g. max_theta_error_deg=5)")
    args = parser.parse_args(argv)
    ignore_snakemake_zarr_warnings()

    import dataclasses

    import jax
    import numpy as np
    from scipy.spatial import cKDTree

    from sellip.bench.renderers import single_scattering_shares
    from sellip.fit import selection as fit_selection
    from sellip.fit.augment_pass import cluster_rows
    from sellip.fit.clusters import cluster_materials
    from sellip.fit.lobe_store import clustering_settings, load_rows, previous_labels, recorded_fit_settings
    from sellip.fit.observe import open_observations
    from sellip.fit.shard import overrides_from_pairs
    from sellip.model.params import read_params
    from sellip.model.ply import read_param_mesh

    jax.config.update("jax_enable_x64", True)  # as cluster_lobes
    folder = args.run / "iter" / str(args.iteration)
    if not (folder / "observations.zarr").exists():
        parser.error(f"{folder / 'observations.zarr'} is missing: run the workflow with snakemake --notemp")
    info = json.loads((folder / "clusters" / "clusters.json").read_text())
    settings = clustering_settings(info)
    fit_settings = recorded_fit_settings(info, folder / "clusters" / "clusters.json")
    recorded = dict(info["model_selection"]["settings"])
    if "sigma_ss_fixed" in recorded:  # written before the key was renamed model2_sigma_ss
        recorded["model2_sigma_ss"] = recorded.pop("sigma_ss_fixed")
    known = {f.name for f in dataclasses.fields(fit_selection.SelectionSettings)}
    selection = fit_selection.SelectionSettings(**{k: tuple(v) if isinstance(v, list) else v
                                                   for k, v in recorded.items() if k in known})
    try:
        selection = dataclasses.replace(selection, **overrides_from_pairs(args.set, fit_selection.SelectionSettings))
    except (ValueError, TypeError) as error:
        parser.error(str(error))
    store = read_params(folder / "fit.zarr")
    group = open_observations(folder / "observations.zarr")
    truth = read_param_mesh(args.truth)
    nearest = cKDTree(np.asarray(truth.vertices)).query(np.asarray(store["vertices"]))[1]
    material = None if truth.material is None else np.asarray(truth.material)[nearest]
    truth_ss = np.asarray(truth.params.rho_ss, np.float64).reshape(truth.num_vertices, -1).max(1)[nearest] > 0
    seed = int(info.get("seed", 0))
    clustering = cluster_materials(store["eta"], store["rho_d"], store["status"], store["confidence"], settings, seed,
                                   vertices=store["vertices"],
                                   previous_labels=previous_labels(args.run, args.iteration))
    print(f"{args.run.name}, pass {args.iteration}: K = {len(clustering.centres)}; selection {selection}")
    print("| cluster | vertices | true material (share) | model | margin (runner-up) | s | reason |")
    print("|---|---|---|---|---|---|---|")
    models = np.zeros(len(clustering.centres), np.int64)
    for cluster, (members, rows) in enumerate(cluster_rows(clustering, settings, seed, vertices=store["vertices"])):
        began = time.perf_counter()
        eta0 = float(np.median(store["eta"][members]))
        picked = fit_selection.select_model(load_rows(group, rows), store["normals"][rows], store["rho_d"][rows],
                                            eta0 if np.isfinite(eta0) else 1.5, fit_settings, selection, settings,
                                            seed=seed + cluster)
        models[cluster] = picked.model
        label = clustering.labels == cluster
        if material is not None:
            values, counts = np.unique(material[label], return_counts=True)
            true = f"{values[np.argmax(counts)]} ({counts.max() / counts.sum():.0%})"
        else:
            true = "–"
        print(f"| {cluster} | {int(label.sum())} | {true} | {picked.model} | {picked.margin:.2f} "
              f"({picked.runner_up}) | {time.perf_counter() - began:.1f} | {picked.reason} |", flush=True)
    shares = single_scattering_shares(models[clustering.labels] >= 2, truth_ss, material)
    def pct(x):
        return "–" if x is None else f"{100 * x:.1f} %"

    print(f"single scattering where the truth has none: {pct(shares['share'])} "
          f"({', '.join(f'{k}: {pct(v)}' for k, v in shares['per_material'].items())}); "
          f"recall: {pct(shares['recall'])} "
          f"({', '.join(f'{k}: {pct(v)}' for k, v in shares['recall_per_material'].items())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
