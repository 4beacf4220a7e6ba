"""Fit one true material's cluster lobe again, with each model, on its vertices and on halves of them.

    python benchmarks/replay_lobes.py RUN --iteration N --truth CAPTURE/ground_truth/model.ply --material K \
        [--models 1 3]

RUN is a workflow's results folder (``results/<name>``) whose pass N kept its observations: run the workflow
with ``snakemake --notemp`` (``iter/N/observations.zarr`` is temporary otherwise), e.g. up to the target
``results/<name>/iter/0/clusters``. The replay takes the confident vertices of pass N's fit (the ones the
clustering uses) whose nearest true vertex is of material K, and fits :func:`sellip.fit.lobes.fit_cluster_lobe`
with the settings the pass used (``clusters.json``: ``settings`` and ``fit_settings``) on: all of them, a random half,
and the halves below and above the median true albedo brightness (a checker texture's dark and light bands). Per subset
the fitted rho_d against the truth's (the fit holds it), then one row per subset and model: eta, sigma_s, sigma_ss,
rho_s, rho_ss, samples, loss. docs/augment.md ("On by default") quotes it: on
stability ``baseline``'s first pass the rough material's light band alone swaps the lobes under model 3.
"""

from __future__ import annotations

import json
import sys


def main(argv=None) -> int:
    from sellip.bench.replay import ignore_snakemake_zarr_warnings, replay_parser

    parser = replay_parser(__doc__)
    parser.add_argument("--material", type=int, required=True, help="the true material label")
    parser.add_argument("--models", type=int, nargs="+", default=[1, 3], help="models to fit (sellip.fit.selection)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    ignore_snakemake_zarr_warnings()

    import numpy as np
    from scipy.spatial import cKDTree

    from sellip.fit import lobes as fit_lobes
    from sellip.fit import selection as fit_selection
    from sellip.fit.lobe_store import clustering_settings, load_rows, recorded_fit_settings
    from sellip.fit.observe import open_observations
    from sellip.model.params import read_params
    from sellip.model.ply import read_param_mesh

    folder = args.run / "iter" / str(args.iteration)
    observations = folder / "observations.zarr"
    if not observations.exists():
        parser.error(f"{observations} is missing: run the workflow with snakemake --notemp to keep it")
    info = json.loads((folder / "clusters" / "clusters.json").read_text())
    settings = clustering_settings(info)
    try:
        fit_settings = recorded_fit_settings(info, folder / "clusters" / "clusters.json")
    except ValueError as error:
        parser.error(str(error))
    store = read_params(folder / "fit.zarr")
    group = open_observations(observations)
    truth = read_param_mesh(args.truth)
    if truth.material is None:
        parser.error(f"{args.truth}: the ground truth has no material labels")
    nearest = cKDTree(np.asarray(truth.vertices)).query(np.asarray(store["vertices"]))[1]
    material = np.asarray(truth.material)[nearest]
    rho_d_true = np.asarray(truth.params.rho_d, np.float64)[nearest]
    brightness = rho_d_true.sum(1)
    used = (np.asarray(store["status"]) == 0) & (np.asarray(store["confidence"]) >= settings.min_confidence)
    rows = np.flatnonzero(used & (material == args.material))
    if rows.size < 10:
        parser.error(f"material {args.material}: {rows.size} confident vertices (labels: {np.unique(material)})")
    rng = np.random.default_rng(args.seed)
    median = np.median(brightness[rows])
    subsets = {"all": rows, "random half": np.sort(rng.permutation(rows)[: rows.size // 2]),
               "darker half": rows[brightness[rows] < median], "lighter half": rows[brightness[rows] >= median]}
    print(f"{args.run.name}, pass {args.iteration}, material {args.material}: {rows.size} confident vertices")
    # The albedo the cluster fit holds, against the truth's (the ratio is the capture's exposure scale where right).
    for name, subset in subsets.items():
        ratio = np.median(np.asarray(store["rho_d"])[subset] / rho_d_true[subset], 0)
        print(f"{name}: fitted rho_d / true rho_d, median per channel: {', '.join(f'{x:.0f}' for x in ratio)}")
    print("| subset | vertices | model | eta | sigma_s | sigma_ss | rho_s | rho_ss (RGB) | samples | loss |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, subset in subsets.items():
        if subset.size == 0:
            continue
        obs = load_rows(group, subset)
        eta0 = float(np.median(np.asarray(store["eta"])[subset]))
        for model in args.models:
            lobe = fit_lobes.fit_cluster_lobe(obs, np.asarray(store["normals"])[subset],
                                              np.asarray(store["rho_d"])[subset], eta0,
                                              fit_selection.settings_for_model(fit_settings, model), settings,
                                              seed=args.seed)
            print(f"| {name} | {subset.size} | {model} | {lobe.eta:.3f} | {lobe.sigma_s:.3f} | {lobe.sigma_ss:.3f} | "
                  f"{lobe.rho_s:.0f} | {', '.join(f'{abs(x):.0f}' for x in lobe.rho_ss)} | {lobe.samples} | "
                  f"{lobe.loss:.4f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
