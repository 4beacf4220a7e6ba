"""The sweep's report (``sellip bench-sweep``): η per material of a run's results against the truth,
the vertices per model, and the markdown tables and files the sweep writes (:func:`write_outputs`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sellip.bench import sweep
from sellip.bench import sweep_tables as bench_sweep_tables
from sellip.jobs import atomic_file, write_text
from sellip.report.outputs import save_figure


def ior_of_results(results: Path, capture: Path):
    """bench_sweep_tables.ior_table of one finished run: results/NAME/final/{model.ply,params.zarr} against the
    capture's ground truth, in the ground truth's world (metrics.json ``alignment``)."""
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.geometry.alignment import Similarity
    from sellip.model.ply import read_param_mesh
    from sellip.report.figures_of_merit import transform_mesh
    from sellip.report.metrics import confident_vertices

    model_path, params_path = results / "final" / "model.ply", results / "final" / "params.zarr"
    model = read_param_mesh(model_path)
    truth = read_param_mesh(capture / GROUND_TRUTH_MESH)
    confident, _ = confident_vertices(model_path, params_path, model.num_vertices)
    alignment = json.loads((results / "metrics.json").read_text()).get("alignment") or {}
    if alignment.get("method") in ("sim3", "sim3+icp"):
        model = transform_mesh(model, Similarity(float(alignment["scale"]), np.asarray(alignment["rotation"]),
                                                 np.asarray(alignment["translation"])))
    return bench_sweep_tables.ior_table(model, truth, confident)



SWEEP_MD = {"label": ("variant", ""), "cpu_s": ("CPU s", ".0f"), "fit_cpu_s": ("fit CPU s", ".0f"),
            "total_s": ("wall s", ".0f"), "run_s": ("own run wall s", ".0f"),
            "normal_median_deg": ("normal med. °", ".2f"),
            "eta_median_pct": ("η per vertex med. %", ".2f"),
            "eta_material_mean_pct": ("η per material mean %", ".2f"),
            "eta_material_max_pct": ("η per material worst %", ".2f"), "rho_d_rmse": ("ρd RMSE", ".3f"),
            "sigma_s_median": ("σs err.", ".3f"), "chamfer_mm": ("Chamfer mm", ".3f"),
            "psnr_held_out_db": ("held-out PSNR dB", ".2f"), "psnr_new_light_db": ("new-light PSNR dB", ".2f"),
            "front": ("front", ""), "cold_cpu_s": ("first-run CPU s", ".0f"),
            "cold_compiled": ("first-run XLA compiles", "d")}



IOR_MD = {"material": ("material", ""), "eta_true": ("η true", ".3f"), "eta_ours": ("η ours (median)", ".3f"),
          "error_pct": ("error %", ".2f"), "vertex_error_pct": ("per-vertex error, median %", ".1f"),
          "vertices": ("vertices", "d"), "eta_paper": ("η paper", ".3f"), "paper_error_pct": ("paper error %", ".2f")}



AUG_MD = {"scene": ("scene", ""), "augmentation": ("augmentation", ""),
          "psnr_held_out_db": ("held-out PSNR dB", ".2f"), "psnr_new_light_db": ("new-light PSNR dB", ".2f"),
          "sigma_s_median": ("σs err.", ".3f"), "normal_median_deg": ("normal med. °", ".2f"),
          "cpu_s": ("CPU s", ".0f"), "total_s": ("wall s", ".0f"), "paper_psnr_db": ("paper (owl) PSNR dB", ".1f")}



SIGMA_MD = {"scene": ("scene", ""), "sigma_ss": ("σss", ""), "fit_s": ("fit jobs wall s", ".0f"),
            "fit_saving_pct": ("fit wall saved %", ".0f"), "fit_cpu_s": ("fit CPU s (sampled)", ".0f"),
            "cpu_s": ("pipeline CPU s", ".0f"), "cpu_saving_pct": ("CPU saved %", ".0f"), "total_s": ("wall s", ".0f"),
            "psnr_held_out_db": ("held-out PSNR dB", ".2f"), "normal_median_deg": ("normal med. °", ".2f"),
            "eta_median_pct": ("η per vertex med. %", ".2f"), "eta_material_mean_pct": ("η per material %", ".2f"),
            "paper_psnr_db": ("paper (owl) PSNR dB", ".1f")}



MODEL_MD = {"scene": ("scene", ""), "selection": ("model selection", ""), "models": ("final vertices per model", ""),
            "fit_s": ("fit jobs wall s", ".0f"), "fit_saving_pct": ("fit saved %", ".0f"),
            "cluster_s": ("cluster_lobes wall s", ".0f"), "cpu_s": ("pipeline CPU s", ".0f"),
            "cpu_saving_pct": ("CPU saved %", ".0f"), "psnr_held_out_db": ("held-out PSNR dB", ".2f"),
            "psnr_new_light_db": ("new-light PSNR dB", ".2f"), "normal_median_deg": ("normal med. °", ".2f"),
            "eta_median_pct": ("η per vertex med. %", ".2f"), "eta_material_mean_pct": ("η per material %", ".2f"),
            "rho_d_rmse": ("ρd RMSE", ".3f")}



def vertex_models(results: Path) -> dict[int, int]:
    """{model code: vertices} of a finished run's final/params.zarr."""
    from sellip.model.params import read_params

    codes, counts = np.unique(np.asarray(read_params(results / "final" / "params.zarr")["model"]), return_counts=True)
    return {int(m): int(c) for m, c in zip(codes, counts)}



def tables_markdown(table, ior, preset: str, models: dict | None = None) -> str:
    """tables.md: the sweep per scene, the IOR table, augmentation on/off, sigma_ss fixed/free, model
    selection on/off (``models``: {variant name: {model code: vertices}})."""
    table = table.assign(front=bench_sweep_tables.front_marks(table))
    parts = [f"# Speed-accuracy sweep ({preset} preset)\n",
             "CPU s: CPU time of all jobs (core-seconds, the chart's axis); wall s: the shared upstream run plus "
             "the variant's own run. front: on the Pareto front of 1 normal error, 2 η per material, 3 held-out PSNR "
             "against CPU time.\n"]
    for scene in dict.fromkeys(table["scene"]):
        parts += [f"\n## {scene}\n\n", bench_sweep_tables.markdown_table(table[table["scene"] == scene], SWEEP_MD)]
    if ior is not None and not ior.empty:
        mean = {"material": "average", "error_pct": ior["error_pct"].mean(),
                "vertex_error_pct": ior["vertex_error_pct"].mean(),
                "paper_error_pct": bench_sweep_tables.PAPER_TABLE1_AVERAGE_PCT}
        import pandas as pd

        shown = pd.concat([ior, pd.DataFrame([mean])], ignore_index=True)
        parts += ["\n## Refractive index (sphere_ior, base)\n\n", bench_sweep_tables.markdown_table(shown, IOR_MD)]
    aug = bench_sweep_tables.augmentation_table(table)
    if not aug.empty:
        parts += ["\n## Augmentation on/off\n\n", bench_sweep_tables.markdown_table(aug, AUG_MD)]
    sigma = bench_sweep_tables.sigma_ss_table(table)
    if not sigma.empty:
        saving = bench_sweep_tables.PAPER_SIGMA_SS_SAVING_PCT
        parts += [f"\n## σss free vs fixed (paper: fixing saves up to ~{saving:.0f} %)\n\n",
                  bench_sweep_tables.markdown_table(sigma, SIGMA_MD)]
    selection = bench_sweep_tables.model_selection_table(table, models or {})
    if not selection.empty:
        parts += ["\n## Model selection on/off (codes: 0 diffuse, 1 + specular, 2 + single scattering with σss "
                  "fixed, 3 + single scattering)\n\n", bench_sweep_tables.markdown_table(selection, MODEL_MD)]
    return "".join(parts)



def write_outputs(variants, records, preset: str, out: Path, workdir: Path) -> dict:
    """sweep.csv, sweep.png, ior.csv, tables.md in ``out`` from the finished runs; returns their paths."""
    import pandas as pd

    paths = sweep.SweepPaths(workdir)
    rows = []
    for variant, record in zip(variants, records):
        folder = paths.results / variant.name
        metrics = json.loads((folder / "metrics.json").read_text())
        rows.append(bench_sweep_tables.sweep_row(variant, metrics, record, preset,
                                                 bench_sweep_tables.job_cpu_seconds(folder / "benchmarks")))
    table = bench_sweep_tables.sweep_table(rows)
    iors = []
    for variant in variants:
        if variant.scene == "sphere_ior":
            ior = ior_of_results(paths.results / variant.name, paths.capture(variant.scene))
            iors.append(ior.assign(name=variant.name))
    ior_all = pd.concat(iors, ignore_index=True) if iors else None
    base_ior = None if ior_all is None else ior_all[ior_all["name"] == "sphere_ior__base"].drop(columns="name")
    models = {v.name: vertex_models(paths.results / v.name) for v in variants
              if v.factor in ("base", "model_selection")}
    written = {"csv": write_csv(table, out / "sweep.csv"),
               "png": save_figure(bench_sweep_tables.sweep_figure(table), out / "sweep.png"),
               "md": write_text(tables_markdown(table, base_ior, preset, models), out / "tables.md")}
    if ior_all is not None:
        written["ior"] = write_csv(ior_all, out / "ior.csv")
    return written


def write_csv(frame, path: str | Path) -> Path:
    """Write a DataFrame as CSV atomically (:func:`sellip.jobs.atomic_file`). Returns ``path``."""
    with atomic_file(path) as tmp:
        frame.to_csv(tmp, index=False)
    return Path(path)
