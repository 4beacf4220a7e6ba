"""How often the material clustering's decisions of a finished run come out the same under perturbations that carry
no information (issue #49; docs/reproducibility.md).

    python benchmarks/reproducibility.py RUN --truth CAPTURE/ground_truth/model.ply \
        [--iterations 0 3 10] [--replicates 10] [--kinds exact noise permute subsample seed] \
        [--set min_coherence=0.5 ...] [--no-previous] [--json OUT.json]

RUN is a workflow's results folder (``results/<name>``). Per pass (``iter/N``, every pass with a clusters.json by
default) the run's clustering is replayed on its stored first-pass fit (``iter/N/fit.zarr``) with the run's own
settings and seed (``clusters.json``; ``--set`` overrides AugmentSettings fields) and, after the first pass, the
previous pass's clusters (``iter/N-1/clusters/labels.npy``, the hysteresis; ``--no-previous``: without), once per
replicate of each
perturbation (:data:`sellip.bench.reproducibility.KINDS`). It prints, per pass and perturbation, the
distribution of K, of the merge sequence (by rule), of the regions added, and per true material the share of
replays in which it has a cluster of its own and its eta error (min / median / max over replays, the cluster's
median own eta). ``--json`` writes every replay's decisions and the summaries.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    import argparse

    from sellip.bench.replay import clustering_overrides_and_truth, ignore_snakemake_zarr_warnings

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the run's results folder (results/<name>)")
    parser.add_argument("--truth", type=Path, required=True, help="the capture's ground_truth/model.ply")
    parser.add_argument("--iterations", type=int, nargs="*", default=None, help="passes (default: every one)")
    parser.add_argument("--replicates", type=int, default=10, help="replays per perturbation (exact: one)")
    parser.add_argument("--kinds", nargs="*", default=["exact", "noise", "permute", "subsample", "seed"])
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="AugmentSettings fields over the run's own")
    parser.add_argument("--no-previous", dest="previous", action="store_false",
                        help="replay without the previous pass's clusters (no hysteresis; the workflow gives them)")
    parser.add_argument("--json", type=Path, default=None, help="write every replay and the summaries here")
    args = parser.parse_args(argv)
    ignore_snakemake_zarr_warnings()

    import numpy as np
    from scipy.spatial import cKDTree

    from sellip.bench import reproducibility as rep
    from sellip.fit.lobe_store import clustering_settings, previous_labels
    from sellip.model.params import read_params

    overrides, truth = clustering_overrides_and_truth(parser, args.set, args.truth)
    iterations = args.iterations
    if iterations is None:
        iterations = sorted(int(p.parent.parent.name) for p in (args.run / "iter").glob("*/clusters/clusters.json"))
    if not iterations:
        parser.error(f"{args.run}: no iter/N/clusters/clusters.json")
    report = {"run": str(args.run), "settings_overrides": overrides, "passes": {}}
    for iteration in iterations:
        folder = args.run / "iter" / str(iteration)
        info = json.loads((folder / "clusters" / "clusters.json").read_text())
        settings = clustering_settings(info, overrides)
        store = read_params(folder / "fit.zarr")
        # The previous pass's clusters, as the workflow gives them (hysteresis); --no-previous: without.
        previous = previous_labels(args.run, iteration) if args.previous else None
        nearest = cKDTree(np.asarray(truth.vertices)).query(np.asarray(store["vertices"]))[1]
        material = np.asarray(truth.material)[nearest]
        eta_true = np.asarray(truth.params.eta, np.float64)[nearest]
        rows, start = [], time.perf_counter()
        for kind in args.kinds:
            for replicate in range(1 if kind == "exact" else args.replicates):
                labels, clustering, used = rep.replay(store, settings, info.get("seed", 0), kind, replicate,
                                                      previous)
                rows.append({"kind": kind, "replicate": replicate,
                             "decisions": rep.decisions(clustering, labels, used, store["eta"], material, eta_true),
                             "merge_reasons": [m["reason"] for m in clustering.merges],
                             "regions": list(clustering.regions)})
        summary = rep.summarise(rows)
        report["passes"][str(iteration)] = {"recorded_k": info["k"], "rows": rows, "summary": summary}
        print(f"pass {iteration}: the run's K {info['k']}; {len(rows)} replays in {time.perf_counter() - start:.0f} s")
        for kind, s in summary.items():
            materials = "; ".join(f"{label} (eta {m['eta_true']:.3f}): own {100 * m['own_share']:.0f} %, error "
                                  f"{m['error_pct'][0]:.2f}/{m['error_pct'][1]:.2f}/{m['error_pct'][2]:.2f} %"
                                  for label, m in s["materials"].items())
            print(f"  {kind:9s} n={s['replays']:3d} K {s['k']} regions {s['regions']} merges {s['merges']}")
            print(f"            {materials}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
