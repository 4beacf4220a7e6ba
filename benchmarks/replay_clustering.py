"""Re-run the material clustering of a finished run on its stored fit, with other settings, against the truth.

    python benchmarks/replay_clustering.py RUN --iteration N --truth CAPTURE/ground_truth/model.ply \
        [--set min_coherence=0.5 ...]

RUN is a workflow's results folder (``results/<name>``). The replay reads ``iter/N/fit.zarr`` (the first pass's
fit that the clustering saw) and ``iter/N/clusters/clusters.json`` (its settings and seed), overrides settings with
``--set`` (AugmentSettings fields), and runs :func:`sellip.fit.clusters.cluster_materials` as the workflow does. It
prints K, the merges and regions, each cluster's size, spatial coherence, median eta and its vertices' true
materials, and eta per material (the figure of metrics.json,
:func:`sellip.report.figures_of_merit.eta_per_material`) when every
vertex takes its cluster's median: what the material eta of that pass would be with these settings, without the
refit and the per-vertex deviations. The replays of docs/augment.md and docs/accuracy.md are this script.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path


def replay(run: Path, iteration: int, overrides: dict | None = None):
    """The clustering of ``run``'s pass ``iteration`` re-run on its stored fit with the run's settings and seed
    (clusters.json), the previous pass's clusters (the hysteresis) and ``overrides`` (AugmentSettings fields) over
    them. Returns (clustering, settings, store)."""
    from sellip.fit import clusters as fit_clusters
    from sellip.fit.lobe_store import clustering_settings, previous_labels
    from sellip.model.params import read_params

    folder = run / "iter" / str(iteration)
    info = json.loads((folder / "clusters" / "clusters.json").read_text())
    settings = clustering_settings(info, overrides)
    store = read_params(folder / "fit.zarr")
    clustering = fit_clusters.cluster_materials(store["eta"], store["rho_d"], store["status"], store["confidence"],
                                           settings, info.get("seed", 0), vertices=store["vertices"],
                                           previous_labels=previous_labels(run, iteration))
    return clustering, dataclasses.asdict(settings), store


def main(argv=None) -> int:
    from sellip.bench.replay import clustering_overrides_and_truth, ignore_snakemake_zarr_warnings, replay_parser

    parser = replay_parser(__doc__, "the pass whose fit is clustered (iter/N)")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="AugmentSettings fields over the run's own (e.g. min_coherence=0.5)")
    args = parser.parse_args(argv)
    ignore_snakemake_zarr_warnings()

    import numpy as np
    from scipy.spatial import cKDTree

    from sellip.bench.ladder import albedo_mode_text, eta_by_albedo_mode
    from sellip.fit import clusters as fit_clusters
    from sellip.fit import lobes
    from sellip.report.figures_of_merit import eta_per_material

    overrides, truth = clustering_overrides_and_truth(parser, args.set, args.truth)
    start = time.perf_counter()
    try:
        clustering, settings, store = replay(args.run, args.iteration, overrides)
    except ValueError as error:
        parser.error(str(error))
    seconds = time.perf_counter() - start

    nearest = cKDTree(np.asarray(truth.vertices)).query(np.asarray(store["vertices"]))[1]
    material = np.asarray(truth.material)[nearest]
    eta_true = np.asarray(truth.params.eta, np.float64)[nearest]
    labels, used, eta = clustering.labels, clustering.used, np.asarray(store["eta"], np.float64)
    medians = lobes.cluster_medians(eta, labels, used, np.full(len(clustering.centres), np.nan))
    coherence = fit_clusters.spatial_coherence(labels, store["vertices"])

    print(f"{args.run.name}, pass {args.iteration}: K {len(clustering.centres)} (BIC took "
          f"{min(clustering.bic, key=clustering.bic.get)}), {len(clustering.regions)} regions, "
          f"{len(clustering.merges)} merges; {seconds:.1f} s; settings {settings}")
    for merge in clustering.merges:
        print(f"  merged: {merge['reason']}")
    for k in range(len(clustering.centres)):
        members = labels == k
        kinds, counts = np.unique(material[members & used], return_counts=True)
        composition = ", ".join(f"{int(m)}: {int(c)}" for m, c in zip(kinds, counts) if c >= 20)
        print(f"  cluster {k}: {int(members.sum())} vertices, coherence {coherence[k]:.2f}, eta {medians[k]:.4f}; "
              f"true materials {{{composition}}}")
    figures = eta_per_material(medians[labels][used], eta_true[used], material[used])
    errors = " ".join(f"{row['error_pct']:.2f}" for row in figures["materials"].values())
    print(f"eta per material (cluster medians): {errors} %; mean {figures['mean_error_pct']:.2f} %, "
          f"worst {figures['max_error_pct']:.2f} %")
    true_rho_d = np.asarray(truth.params.rho_d, np.float64)[nearest]
    for kind, modes in eta_by_albedo_mode(eta[used], eta_true[used], material[used], true_rho_d[used]).items():
        if len(modes) > 1:  # a checker-textured material: its vertices' own eta per true albedo
            print(f"  material {kind} by true albedo (its vertices' own eta): {albedo_mode_text(modes)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
