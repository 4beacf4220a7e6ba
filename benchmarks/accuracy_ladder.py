"""The accuracy ladder (docs/accuracy.md): one capture through rungs that each add one source of error.

    python benchmarks/accuracy_ladder.py --scene sphere_ior --views 24 --width 612 --height 512 [--renderer mitsuba] \
        [--rungs render sensor mesh hull] [--iterations 1] [--workdir results/bench/ladder] [--cores 2]
        [--ceiling-vertices 6000 30000] [--max-vertices 6000] [--hull-resolution 128] [--seed 3]

Rungs (each resumable: a rung whose result file exists is not run again; ``--edge-margin``, ``--max-slope`` and
``--min-cos`` other than their defaults give every rung a result of its own, e.g. ``render_slope0.4.json``):

- ``render``: the true mesh observed in noise-free images rendered at the HDR grid by the capture's renderer
  (sellip.bench.ladder);
- ``sensor``: the true mesh observed in the capture's HDR images (sensor noise, mosaic, ingest);
- ``mesh``: the whole workflow (``snakemake``) with ``init.mode: mesh`` from the true mesh;
- ``hull``: the whole workflow from the visual hull (the default);
- ``sfm``: the same without the capture's poses (``sfm.mode: sfm``: SfM's cameras, then refined against the object).

The workflow rungs hold four views out of the fit (spread evenly over the capture) for the held-out PSNR.
``--ceiling-vertices N ...`` also scores the held-out PSNR's ceilings (sellip.bench.ladder.psnr_ceiling): the ground
truth itself, and the ground truth resampled on meshes of N vertices (what a per-vertex model of N vertices can
score at best), in ``ceiling.json``.

Prints one table row per rung: eta per material (mean and worst error of the per-material medians),
eta per vertex (median, p90), normal error (median, p90), and for the workflow rungs the held-out
PSNR; then, for the true-mesh rungs, the eta of each material with a few true albedos (a checker texture) per
albedo (``sellip.bench.ladder.eta_by_albedo_mode``); writes ``ladder.json`` and ``ladder.md`` in the workdir.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def workflow_rung(capture: Path, name: str, results: Path, iterations: int, cores: int, overrides: dict) -> dict:
    """Run the workflow on ``capture`` (config.yaml, then ``overrides``; log in ``results/<name>.log``) and
    return the figures of its metrics.json."""
    from sellip.bench.sweep import SnakemakeRunner
    from sellip.report.metrics import headline_figures

    metrics = results / name / "metrics.json"
    if not metrics.is_file():
        log = results / f"{name}.log"
        print(f"{name}: snakemake, log {log}", flush=True)
        SnakemakeRunner(results.parent, cores=cores)(
            {"capture": str(capture), "name": name, "iterations": iterations, **overrides}, [], log)
    return headline_figures(json.loads(metrics.read_text()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="sphere_ior")
    parser.add_argument("--renderer", default="sellip", choices=["sellip", "mitsuba"],
                        help="the capture's renderer (sellip synth --renderer); the render rung renders the truth "
                             "noise-free with the same renderer")
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--width", type=int, default=612)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--seed", type=int, default=None,
                        help="the capture's seed (orbit and sensor noise; sellip synth --seed); default: the demo's")
    parser.add_argument("--rungs", nargs="+", default=["render", "sensor", "mesh", "hull"],
                        choices=["render", "sensor", "mesh", "hull", "sfm"])
    parser.add_argument("--iterations", type=int, default=1, help="outer iterations of the workflow rungs")
    parser.add_argument("--edge-margin", type=float, default=2.0, help="observe.edge_margin of every rung")
    parser.add_argument("--max-slope", type=float, default=0.0, help="observe.max_slope of every rung (0: off)")
    parser.add_argument("--min-cos", type=float, default=0.0, help="observe.min_cos of every rung")
    parser.add_argument("--workdir", type=Path, default=ROOT / "results/bench/ladder")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--max-vertices", type=int, default=None,
                        help="init.max_vertices of the workflow rungs (default: config.yaml's)")
    parser.add_argument("--hull-resolution", type=int, default=None,
                        help="init.hull_resolution of the workflow rungs, voxels (default: config.yaml's)")
    parser.add_argument("--ceiling-vertices", type=int, nargs="*", default=[],
                        help="also score the truth resampled on meshes of these vertex counts at the held-out views")
    args = parser.parse_args(argv)

    from sellip.bench.ladder import (
        WORKFLOW_RUNGS,
        albedo_mode_text,
        capture_tag,
        fit_true_mesh,
        psnr_ceiling,
        render_hdr,
        workflow_run_name,
    )
    from sellip.bench.stability import held_out_views
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.capture.hdr import merge_capture
    from sellip.capture.linearize import linearize_capture
    from sellip.capture.synthetic import DemoSettings, synthesize_capture
    from sellip.fit.observe import ObserveSettings

    seed = DemoSettings.seed if args.seed is None else args.seed
    tag = capture_tag(args.scene, args.views, args.width, args.height, args.renderer, args.seed)
    work = (args.workdir / tag).resolve()
    capture = work / "capture"
    if not (capture / "capture.yaml").is_file():
        synthesize_capture(args.scene, capture, views=args.views, width=args.width, height=args.height, progress=False,
                           renderer=args.renderer, seed=seed)
    hdr = work / "hdr.zarr"  # the true-mesh rungs' and the ceilings' own ingest (the workflow rungs ingest in the run)
    if not hdr.exists() and (args.ceiling_vertices or {"render", "sensor"} & set(args.rungs)):
        linearize_capture(capture, work / "linear.zarr", threads=args.cores)
        merge_capture(work / "linear.zarr", hdr, threads=args.cores)
    observe = ObserveSettings(edge_margin=args.edge_margin, max_slope=args.max_slope, min_cos=args.min_cos,
                              threads=args.cores)
    # Observation settings other than the ladder's defaults make every rung a run of its own (its own result file).
    observed = ((f"_edge{args.edge_margin:g}" if args.edge_margin != parser.get_default("edge_margin") else "")
                + (f"_slope{args.max_slope:g}" if args.max_slope else "")
                + (f"_mincos{args.min_cos:g}" if args.min_cos else ""))
    cache = str(work / "jax_cache")
    rows = {}
    for rung in args.rungs:
        # A workflow rung with other iterations or its own vertex count is a run of its own (render and sensor fit
        # the true mesh once per observation settings).
        suffix = observed
        if rung in WORKFLOW_RUNGS:
            name = workflow_run_name(tag, rung, args.iterations, args.max_vertices, args.hull_resolution, observed)
            suffix = name[len(f"{tag}_{rung}"):]
        out = work / f"{rung}{suffix}.json"
        if not out.is_file():
            if rung == "render":
                clean = render_hdr(capture, hdr, work / "render_hdr.zarr", renderer=args.renderer)
                figures = fit_true_mesh(capture, clean, work / f"render{suffix}", observe, cache)
            elif rung == "sensor":
                figures = fit_true_mesh(capture, hdr, work / f"sensor{suffix}", observe, cache)
            else:
                overrides = {"observe": {"edge_margin": args.edge_margin, "max_slope": args.max_slope,
                                         "min_cos": args.min_cos},
                             "evaluate": {"held_out_views": held_out_views(args.views, 4)}}
                overrides["init"] = {key: value for key, value in (("max_vertices", args.max_vertices),
                                                                   ("hull_resolution", args.hull_resolution)) if value}
                if rung == "sfm":
                    overrides["sfm"] = {"mode": "sfm"}
                if rung == "mesh":
                    overrides["init"] = {**overrides.get("init", {}), "mode": "mesh",
                                         "mesh_path": str(capture / GROUND_TRUTH_MESH)}
                figures = workflow_rung(capture, name, work / "results", args.iterations, args.cores, overrides)
            out.write_text(json.dumps(figures, indent=2))
        rows[rung] = json.loads(out.read_text())

    if args.ceiling_vertices:
        out = work / "ceiling.json"
        ceilings = json.loads(out.read_text()) if out.is_file() else {}
        views = held_out_views(args.views, 4)
        for count in [None, *args.ceiling_vertices]:
            key = "truth" if count is None else str(count)
            if key not in ceilings:
                ceilings[key] = psnr_ceiling(capture, hdr, views, count)
                out.write_text(json.dumps(ceilings, indent=2))
        for key, row in ceilings.items():
            print(f"held-out PSNR of the ground truth, {row['vertices']} vertices ({key}): {row['mean_db']:.2f} dB "
                  f"(views {', '.join(f'{v:.1f}' for v in row['views'].values())})")

    header = ("| rung | η per material mean / worst % | η per vertex median / p90 % | normal median / p90 ° "
              "| held-out PSNR dB |\n|---|---|---|---|---|")
    lines = [header]
    for rung, f in rows.items():
        per = f.get("eta_per_material") or {}
        psnr = f.get("held_out_psnr_db")
        lines.append(f"| {rung} | {per.get('mean_error_pct', float('nan')):.2f} / "
                     f"{per.get('max_error_pct', float('nan')):.2f} "
                     f"| {f['eta_vertex_median_pct']:.2f} / {f['eta_vertex_p90_pct'] or float('nan'):.2f} "
                     f"| {f['normal_median_deg']:.2f} / {f['normal_p90_deg'] or float('nan'):.2f} "
                     f"| {'–' if psnr is None else f'{psnr:.1f}'} |")
    table = "\n".join(lines)
    print(f"{tag}\n{table}")
    for rung, f in rows.items():  # a checker-textured material's eta per albedo mode (the fit's albedo dependence)
        for material, modes in (f.get("eta_by_albedo_mode") or {}).items():
            if len(modes) > 1:
                print(f"{rung}, material {material} by true albedo: {albedo_mode_text(modes)}")
    (work / "ladder.json").write_text(json.dumps(rows, indent=2))
    (work / "ladder.md").write_text(f"{tag}\n\n{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
