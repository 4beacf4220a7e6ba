"""Coverage of the per-material eta intervals of materials.csv, replayed on finished runs with a ground truth.

    python benchmarks/replay_intervals.py RESULTS [RESULTS ...] [--rows rows.csv] [--json coverage.json]

RESULTS are finished runs' results folders (``results/<name>`` of a workflow run on a synthetic capture with known
poses, e.g. the stability suite's ``OUT/runs/<case>/results/<case>``, kept by ``sellip bench-stability``). Per
material cluster: the estimate, the true eta, and three 95 % intervals (:mod:`sellip.bench.intervals`): ``vertex``
(the vertex bootstrap materials.csv gave before), ``scatter`` (the spatial block bootstrap) and ``ci`` (what
materials.csv gives: the scatter widened by the shared error). It fits the shared-error factor on each renderer's
runs and validates it on the other's, then on all, and scores each run with the factor fitted on the other runs; it
prints the coverage (materials whose interval holds the truth, per renderer) and the median relative width of each
interval, and per run how the vertices' residuals correlate with distance (what the block bootstrap's patch size was
chosen from). docs/viewer.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    from sellip.bench.replay import ignore_snakemake_zarr_warnings

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, nargs="+", help="finished runs' results folders")
    parser.add_argument("--rows", type=Path, help="write the per-material rows (CSV) here")
    parser.add_argument("--json", type=Path, help="write the coverage figures (JSON) here")
    args = parser.parse_args(argv)
    ignore_snakemake_zarr_warnings()

    import numpy as np
    import pandas as pd

    from sellip.bench.intervals import coverage, fit_shared_factor, intervals, material_rows, residual_correlation
    from sellip.model.params import read_params
    from sellip.report.materials import SHARED_STD_FACTOR

    frames, correlations = [], {}
    for results in args.results:
        try:
            frames.append(material_rows(results))
        except FileNotFoundError as error:
            print(f"skipped {results}: {error}", file=sys.stderr)
            continue
        correlations[results.name] = residual_correlation(read_params(results / "final" / "params.zarr"))
        print(f"{results.name}: residual correlation by distance (fraction of the diagonal): "
              + " ".join(f"<{edge:g}: {value:.2f}" for edge, value in correlations[results.name].items()))
    if not frames:
        parser.error("no run could be read")
    rows = pd.concat(frames, ignore_index=True)
    report = {"vertex": coverage(rows, rows["vertex_low"], rows["vertex_high"]),
              "scatter": coverage(rows, rows["scatter_low"], rows["scatter_high"])}
    factors = {"module": SHARED_STD_FACTOR, "all": fit_shared_factor(rows)}
    for renderer in sorted(rows["renderer"].unique()):
        factors[f"fit_on_{renderer}"] = fit_shared_factor(rows[rows["renderer"] == renderer])
    for name, factor in factors.items():
        ci = intervals(rows, factor)
        report[f"ci_{name}"] = {"factor": factor, **coverage(rows, ci["low"], ci["high"])}
    # Each run's materials scored with the factor fitted on the other runs.
    held_low, held_high = np.empty(len(rows)), np.empty(len(rows))
    for run in rows["run"].unique():
        out = (rows["run"] == run).to_numpy()
        ci = intervals(rows[out], fit_shared_factor(rows[~out]))
        held_low[out], held_high[out] = ci["low"], ci["high"]
    report["ci_leave_one_run_out"] = coverage(rows, held_low, held_high)
    # The alternative error model: a fixed share of eta, fitted and validated the same way.
    for renderer in ["all", *sorted(rows["renderer"].unique())]:
        fit_rows = rows if renderer == "all" else rows[rows["renderer"] == renderer]
        factor = fit_shared_factor(fit_rows, grid=np.arange(0, 0.1, 0.0002), scale="eta")
        factors[f"relative_fit_on_{renderer}"] = factor
        ci = intervals(rows, factor, scale="eta")
        report[f"relative_fit_on_{renderer}"] = {"factor": factor, **coverage(rows, ci["low"], ci["high"])}
    ci = intervals(rows, SHARED_STD_FACTOR)
    rows["ci_low"], rows["ci_high"] = ci["low"], ci["high"]
    pd.set_option("display.width", 200)
    print(rows.to_string(index=False, float_format=lambda v: f"{v:.4f}"))
    for name, figures in report.items():
        factor = f" (factor {figures.pop('factor'):.3f})" if "factor" in figures else ""
        print(f"{name}{factor}: " + "; ".join(
            f"{group} {f['covered']}/{f['materials']} covered, median width {f['median_width_pct']:.2f} %"
            for group, f in figures.items()))
    if args.rows:
        rows.to_csv(args.rows, index=False, float_format="%.6g")
    if args.json:
        args.json.write_text(json.dumps({"factors": factors, "coverage": report, "residual_correlation": correlations},
                                        indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
