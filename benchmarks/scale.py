"""The whole workflow at several capture sizes: time per stage, peak memory, a fitted model of how each stage's
cost grows, and what it predicts for captures not run (issue #20; docs/speed.md, "Scale").

    python benchmarks/scale.py --sizes 24x612x512:10000:10 72x1224x1024:30000:3 100x1224x1024:100000:3 \\
        [--scene sphere_ior] [--workdir results/bench/scale] [--cores 2] [--predict-iterations 10]

A size is VIEWSxWIDTHxHEIGHT:VERTICES[:ITERATIONS] (raw sensor pixels; init.max_vertices; ITERATIONS default 3).
Each size is a synthetic capture (``sellip synth``) and one ``snakemake`` run of the repository's workflow on it
(known poses, the hull, four views held out), resumable: a size whose ``run.json`` exists is read, not run. The
capture's synthesis is timed apart (a user's capture is photographed, not rendered).

Prints, and writes to ``scale.md`` and ``scale.json`` in the workdir: per size the measured wall time and per rule
its one-off and per-iteration job time and peak memory (``sellip.bench.scale.rule_costs``), and each size's wall time
as a ratio to the first size's (the baseline, measured in the same benchmark); the cost model fitted to all
sizes (``sellip.bench.scale.fit_cost_model``) and, as a check, each size's wall time as the model predicts it from its
own costs and from the other sizes' (leave one out); then predictions at ``--predict-iterations`` for every
measured size, and for the paper's capture (200 views of 2448x2048, 500k vertices) on 2 cores and on a 32-core node
(32 fit shards, the SLURM profile: docs/hpc.md). Measured rows say "measured"; predictions say "predicted".
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER = ("paper capture", 200, 2448 * 2048, 500_000)
HELD_OUT = 4


def parse_size(text: str) -> dict:
    match = re.fullmatch(r"(\d+)x(\d+)x(\d+):(\d+)(?::(\d+))?", text)
    if not match:
        raise argparse.ArgumentTypeError(f"size {text!r}: expected VIEWSxWIDTHxHEIGHT:VERTICES[:ITERATIONS], "
                                         "e.g. 100x1224x1024:100000:3")
    views, width, height, vertices, iterations = match.groups()
    return {"views": int(views), "width": int(width), "height": int(height), "max_vertices": int(vertices),
            "iterations": int(iterations or 3)}


def run_size(scene: str, size: dict, work: Path, cores: int) -> dict:
    """Synthesize (once) and run one size; return its record (also ``work/<tag>/run.json``)."""
    from sellip.bench.stability import held_out_views
    from sellip.bench.sweep import SnakemakeRunner
    from sellip.capture.synthetic import synthesize_capture
    from sellip.report.metrics import headline_figures

    tag = f"{scene}_{size['views']}v_{size['width']}x{size['height']}_{size['max_vertices']}n_{size['iterations']}it"
    folder = work / tag
    record_path = folder / "run.json"
    if record_path.is_file():
        return json.loads(record_path.read_text())
    capture = folder / "capture"
    synth_s = None
    if not (capture / "capture.yaml").is_file():
        print(f"{tag}: synthesizing {size['views']} views of {size['width']}x{size['height']}", flush=True)
        started = time.perf_counter()
        synthesize_capture(scene, capture, views=size["views"], width=size["width"], height=size["height"],
                           progress=False)
        synth_s = time.perf_counter() - started
    # Every iteration runs (converge off): the cost model measures what one full iteration costs (docs/speed.md,
    # "Convergence": a converged run's later iterations cost a second each).
    config = {"capture": str(capture), "name": "run", "iterations": size["iterations"],
              "converge": {"enabled": False}, "init": {"max_vertices": size["max_vertices"]},
              "evaluate": {"held_out_views": held_out_views(size["views"], HELD_OUT)}}
    log = folder / "snakemake.log"
    print(f"{tag}: snakemake ({size['iterations']} iterations), log {log}", flush=True)
    wall, cpu = SnakemakeRunner(folder, cores=cores)(config, [], log)
    metrics = json.loads((folder / "results" / "run" / "metrics.json").read_text())
    record = {"tag": tag, **size, "views_fitted": size["views"] - HELD_OUT, "pixels": size["width"] * size["height"],
              "vertices": int(metrics["vertices"]["model"]), "wall_s": wall, "cpu_s": cpu, "synth_s": synth_s,
              "cores": cores, "benchmarks": str(folder / "results" / "run" / "benchmarks"),
              "figures": headline_figures(metrics)}
    record_path.write_text(json.dumps(record, indent=2))
    return record


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", type=parse_size, required=True)
    parser.add_argument("--scene", default="sphere_ior")
    parser.add_argument("--workdir", type=Path, default=ROOT / "results/bench/scale")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--predict-iterations", type=int, default=10)
    args = parser.parse_args(argv)
    from sellip.bench import scale

    work = args.workdir.resolve()
    records = [run_size(args.scene, size, work, args.cores) for size in args.sizes]
    runs = []
    for r in records:
        size = scale.CaptureSize(r["views_fitted"], r["pixels"], r["vertices"])
        runs.append((size, scale.rule_costs(scale.job_costs(r["benchmarks"]), r["iterations"])))
    model = scale.fit_cost_model(runs)

    lines = ["| size | V fitted | N | iterations | wall (measured) | ÷ the first size's | own costs (model) "
             "| from the other sizes | synthesis | η per material mean | normal median | held-out PSNR |",
             "|" + "---|" * 12]
    for i, (r, (size, _costs)) in enumerate(zip(records, runs)):
        own = scale.predict(scale.fit_cost_model([runs[i]]), size, r["iterations"], args.cores).attrs["wall_s"]
        others = [run for j, run in enumerate(runs) if j != i]
        loo = scale.predict(scale.fit_cost_model(others), size, r["iterations"], args.cores).attrs["wall_s"] \
            if others else float("nan")
        f = r["figures"]
        synth = "–" if r["synth_s"] is None else f"{r['synth_s'] / 60:.1f} min"
        lines.append(f"| {r['views']} × {r['width']}×{r['height']} | {r['views_fitted']} | {r['vertices']:,} "
                     f"| {r['iterations']} | {r['wall_s'] / 60:.1f} min | {r['wall_s'] / records[0]['wall_s']:.2f}× "
                     f"| {own / 60:.1f} min | {loo / 60:.1f} min "
                     f"| {synth} "
                     f"| {f['eta_per_material_mean_pct'] or float('nan'):.2f} % | {f['normal_median_deg']:.2f}° "
                     f"| {f['held_out_psnr_db'] or float('nan'):.1f} dB |")
    measured = "\n".join(lines)

    rules = list(model.index)
    head = "| rule | term | " + " | ".join(f"{r['views']}v {r['width']}: once / per it. s, MB" for r in records)
    rows = [head + " | model: once s | per iteration s |", "|" + "---|" * (len(records) + 4)]
    for rule in rules:
        cells = [f"{costs.loc[rule, 'once_s']:.0f} / {costs.loc[rule, 'per_iteration_s']:.1f}, "
                 f"{costs.loc[rule, 'max_rss_mb']:.0f}" for _, costs in runs]
        m = model.loc[rule]
        rows.append(f"| {rule} | {m['term']} | " + " | ".join(cells)
                    + f" | {m['once_s_a']:.1f} + {m['once_s_b']:.3g}·{m['term']} "
                    f"| {m['per_iteration_s_a']:.1f} + {m['per_iteration_s_b']:.3g}·{m['term']} |")
    per_rule = "\n".join(rows)

    targets = [(f"{r['views']} × {r['width']}×{r['height']}, {r['vertices']:,} vertices", size, args.cores, 2)
               for r, (size, _) in zip(records, runs)]
    paper = scale.CaptureSize(PAPER[1] - HELD_OUT, PAPER[2], PAPER[3])
    targets += [(f"{PAPER[0]} (200 × 2448×2048, 500k), 2 cores", paper, 2, 2),
                (f"{PAPER[0]}, a 32-core node, 32 fit shards", paper, 32, 32)]
    rows = [f"| predicted, {args.predict_iterations} iterations | wall | largest job memory "
            "| the three largest rules |",
            "|---|---|---|---|"]
    predictions = []
    for label, size, cores, shards in targets:
        p = scale.predict(model, size, args.predict_iterations, cores, shards)
        top = p["critical_s"].sort_values(ascending=False).head(3)
        rows.append(f"| {label} | {p.attrs['wall_s'] / 60:.0f} min | {p['max_rss_mb'].max() / 1024:.1f} GB "
                    f"| {', '.join(f'{k} {v / 60:.0f} min' for k, v in top.items())} |")
        predictions.append({"label": label, "size": size._asdict(), "cores": cores, "shards": shards,
                            "wall_s": p.attrs["wall_s"], "rules": p.to_dict(orient="index")})
    predicted = "\n".join(rows)

    text = f"Measured ({args.cores} cores):\n\n{measured}\n\nPer rule:\n\n{per_rule}\n\n{predicted}\n"
    print(text)
    (work / "scale.md").write_text(text)
    (work / "scale.json").write_text(json.dumps({"runs": records, "model": model.reset_index().to_dict("records"),
                                                 "predictions": predictions}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
