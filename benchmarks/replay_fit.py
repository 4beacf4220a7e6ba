"""Fit a pass's observations again with other fit settings, and score eta and the normals against the truth.

    python benchmarks/replay_fit.py RUN --iteration N --truth CAPTURE/ground_truth/model.ply \
        [--set hold_diffuse_eta=false ...] [--out fit.npz]

RUN is a workflow's results folder (``results/<name>``) whose pass N kept its observations: run the workflow with
``snakemake --notemp`` up to ``results/<name>/iter/N/clusters`` (``observations.zarr`` is temporary otherwise). The
replay runs the fit stage (:func:`sellip.fit.shard.fit_shard`, one shard, the default prior: pass 0's start) with
the pass's fit settings as its ``clusters/clusters.json`` records them (the workflow's ``fit.settings`` for the
pass, :func:`sellip.fit.lobe_store.recorded_fit_settings`) and ``--set`` over them, then prints, over the fitted
vertices with confidence > 0.1: the normal error (median, p90) against the nearest true vertex's normal, and per true
material the median eta error, its median on the darker and brighter halves of the material (by the true albedo of the
12 true vertices nearest each vertex), the median absolute eta error and the correlation of eta with that albedo.
docs/fit.md ("Why the diffuse eta is held") is this script on stability ``fine_texture`` and ``baseline``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the run's results folder (results/<name>), run with --notemp")
    parser.add_argument("--iteration", type=int, default=0, help="the pass (iter/N)")
    parser.add_argument("--truth", type=Path, required=True, help="the capture's ground_truth/model.ply")
    parser.add_argument("--set", dest="pairs", action="append", default=[], metavar="KEY=VALUE",
                        help="a FitSettings field over the defaults (repeatable)")
    parser.add_argument("--out", type=Path, default=None, help="keep the fit here (.npz)")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore", message="Object at .snakemake_timestamp")
    import dataclasses
    import json

    import numpy as np
    import zarr
    from scipy.spatial import cKDTree

    from sellip.fit.lobe_store import recorded_fit_settings
    from sellip.fit.shard import fit_shard as run_stage
    from sellip.fit.shard import overrides_from_pairs
    from sellip.model.ply import read_param_mesh

    observations = args.run / "iter" / str(args.iteration) / "observations.zarr"
    if not observations.exists():
        sys.exit(f"{observations} does not exist: run the workflow with --notemp up to it")
    clusters_json = args.run / "iter" / str(args.iteration) / "clusters" / "clusters.json"
    try:
        recorded = recorded_fit_settings(json.loads(clusters_json.read_text()), clusters_json)
        settings = dataclasses.replace(recorded, **overrides_from_pairs(args.pairs, type(recorded)))
    except (OSError, ValueError) as error:
        parser.error(str(error))
    with tempfile.TemporaryDirectory() as folder:
        out = args.out or Path(folder) / "fit.npz"
        run_stage(observations, (0, 1), out, settings=settings)
        fit = dict(np.load(out))
    vertices = np.asarray(zarr.open(str(observations), mode="r")["vertices"])
    truth = read_param_mesh(args.truth)
    tree = cKDTree(truth.vertices)
    _, nearest = tree.query(vertices)
    _, around = tree.query(vertices, 12)
    albedo = np.asarray(truth.params.rho_d).sum(-1)[around].mean(1)
    material, eta_true = truth.material[nearest], np.asarray(truth.params.eta)[nearest]
    used = (fit["confidence"] > 0.1) & (fit["status"] == 0)
    angle = np.degrees(np.arccos(np.clip(np.sum(fit["normal"] * truth.normals[nearest], -1), -1, 1)))[used]
    print(f"{args.run.name} pass {args.iteration} ({' '.join(args.pairs) or 'as run'}): {used.sum()} of {len(used)} "
          f"vertices with confidence > 0.1; normal median {np.median(angle):.2f} deg, "
          f"p90 {np.percentile(angle, 90):.2f}")
    error = 100 * (fit["eta"] / eta_true - 1)
    for k in np.unique(material):
        mine = used & (material == k)
        dark = mine & (albedo < np.median(albedo[mine]))
        bright = mine & ~dark
        print(f"  material {k} (eta {eta_true[mine][0]:.3f}, {mine.sum()} vertices): "
              f"median {np.median(error[mine]):+.2f} %"
              f" (dark {np.median(error[dark]):+.2f} / bright {np.median(error[bright]):+.2f}), |error| median "
              f"{np.median(np.abs(error[mine])):.2f} %, eta-albedo correlation "
              f"{np.corrcoef(fit['eta'][mine], albedo[mine])[0, 1]:+.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
