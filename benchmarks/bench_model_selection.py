"""Model selection on and off (DESIGN §7, docs/model_selection.md): real workflow runs, compared.

    python benchmarks/bench_model_selection.py [--scenes sphere_ior demo] [--workdir /tmp/sellip_msel]
                                               [--iterations 2] [--repeat 2] [--output results.json]

For each scene (a built-in synthetic capture, sellip.scenes), runs the whole Snakemake workflow
(`snakemake --cores 2`, in its own --directory, so nothing under this checkout is touched) twice:
with `model_selection.enabled` false (results/<scene>_nosel) and true (results/<scene>_sel), on a
reduced capture (24 views at 320x256, at most 3,000 vertices, 2 iterations). With --repeat 2 each
configuration is run again from scratch (its results removed) with the compilation cache of the
first runs: the second run's times are the warm ones a user sees after the first capture.
Prints per run the models chosen (vertices per model in final/params.zarr, and per cluster in
every iteration's clusters.json), the fit-stage times (sums of the Snakemake benchmark files of
rule fit_pbrdf, and of cluster_lobes) and the figures of merit of metrics.json; writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]


def run_config(scene: str, name: str, selection: bool, workdir: Path, iterations: int) -> dict:
    """The config overrides of one run (over config/config.yaml)."""
    return {
        "name": name,
        "iterations": iterations,
        "demo": {"scene": scene, "views": 24, "width": 320, "height": 256, "seed": 3},
        "init": {"hull_resolution": 64, "max_vertices": 3000},
        "fit": {"shards": 2, "compilation_cache": str(workdir / "jax_cache"), "settings": {"min_views": 6}},
        "evaluate": {"held_out_views": ["v005", "v017"], "render_views": ["v000"], "supersample": 1},
        "model_selection": {"enabled": selection},
    }


def snakemake(workdir: Path, config: dict) -> float:
    """Run the workflow in ``workdir`` with ``config`` on top of the defaults; returns the wall time (s)."""
    override = workdir / f"{config['name']}.yaml"
    override.write_text(yaml.safe_dump(config))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), "--cores", "2"]
    began = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - began
    (workdir / f"{config['name']}.snakemake.log").write_text(result.stdout + result.stderr)
    if result.returncode != 0:
        raise SystemExit(f"snakemake failed for {config['name']} (log: {workdir / config['name']}.snakemake.log):\n"
                         f"{result.stderr[-3000:]}")
    return seconds


def _benchmark_seconds(folder: Path) -> dict:
    """Summed wall time (s) of the benchmark files under ``folder``, by iteration/pass subfolder."""
    out = {}
    for path in sorted(folder.rglob("*.tsv")):
        key = str(path.parent.relative_to(folder))
        lines = path.read_text().splitlines()
        out[key] = out.get(key, 0.0) + float(lines[1].split("\t")[0])
    return out


def summarize(results: Path) -> dict:
    """Models, times and figures of merit of one finished run (results/<name>)."""
    import zarr

    metrics = json.loads((results / "metrics.json").read_text())
    store = zarr.open_group(str(results / "final" / "params.zarr"), mode="r")
    model = np.asarray(store["model"][:])
    clusters = {}
    for path in sorted((results / "iter").glob("*/clusters/clusters.json")):
        info = json.loads(path.read_text())["model_selection"]
        clusters[path.parent.parent.name] = {"models": info["models"], "enabled": info["enabled"],
                                             "reasons": [c["reason"] for c in info["clusters"]]}
    fit_times = _benchmark_seconds(results / "benchmarks" / "fit_pbrdf")
    rules = metrics["timings"]["rules"]
    return {
        "vertices": int(model.size),
        "vertices_per_model": {str(m): int(np.sum(model == m)) for m in range(4)},
        "clusters": clusters,
        "fit_pbrdf_s": rules["fit_pbrdf"]["s"],
        "fit_pbrdf_by_pass_s": fit_times,
        "cluster_lobes_s": rules["cluster_lobes"]["s"],
        "total_job_s": metrics["timings"]["total_s"],
        "normal_error_median_deg": metrics["normal_error_deg"]["all"]["median"],
        "normal_error_mean_deg": metrics["normal_error_deg"]["all"]["mean"],
        "eta_error_mean_pct": metrics["eta_relative_error_pct"]["mean"],
        "rho_d_relative_rmse": metrics["rho_d_relative_rmse"]["relative_rmse"],
        "sigma_s_abs_error_median": metrics["sigma_s_abs_error"]["median"],
        "psnr_held_out_db": metrics["psnr_held_out"]["mean_db"],
        "psnr_new_light_db": metrics["psnr_new_light"]["mean_db"],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["sphere_ior", "demo"])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/sellip_msel"))
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=2, help="runs per configuration (the last is reported)")
    parser.add_argument("--output", type=Path, default=None, help="write the summaries as JSON")
    args = parser.parse_args(argv)
    report = {}
    for scene in args.scenes:
        workdir = args.workdir / scene
        workdir.mkdir(parents=True, exist_ok=True)
        for repeat in range(args.repeat):
            for selection in (False, True):
                name = f"{scene}_{'sel' if selection else 'nosel'}"
                if repeat:
                    shutil.rmtree(workdir / "results" / name, ignore_errors=True)
                wall = snakemake(workdir, run_config(scene, name, selection, workdir, args.iterations))
                summary = {"wall_s": wall, "repeat": repeat, **summarize(workdir / "results" / name)}
                report.setdefault(name, []).append(summary)
                print(f"{name} (run {repeat + 1}): {json.dumps(summary)}", flush=True)
                if args.output:
                    args.output.write_text(json.dumps(report, indent=1))
    print("\n| run | wall | fit_pbrdf | cluster_lobes | vertices per model 0/1/2/3 | normal median | eta mean | "
          "albedo RMSE | sigma_s median | PSNR held-out | PSNR new light |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, runs in report.items():
        for s in runs:
            counts = "/".join(str(s["vertices_per_model"][str(m)]) for m in range(4))
            print(f"| {name} ({'warm' if s['repeat'] else 'cold'}) | {s['wall_s']:.0f} s | {s['fit_pbrdf_s']:.0f} s | "
                  f"{s['cluster_lobes_s']:.0f} s | {counts} | {s['normal_error_median_deg']:.2f}° | "
                  f"{s['eta_error_mean_pct']:.1f} % | {100 * s['rho_d_relative_rmse']:.1f} % | "
                  f"{s['sigma_s_abs_error_median']:.3f} | {s['psnr_held_out_db']:.1f} dB | {s['psnr_new_light_db']:.1f} dB |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
