"""Both renderers side by side (issue #36): the figures of runs on captures of the same scenes rendered by sellip and
by Mitsuba 3 (stability-suite cases, :mod:`sellip.bench.stability`), with the share of vertices that got a
single-scattering lobe their ground truth does not have.

Public API::

    single_scattering_shares(has_ss, truth_ss, label=None) -> dict   # false share and recall from (N,) arrays
    false_single_scattering(model_ply, truth_ply) -> dict     # share of vertices with rho_ss > 0 (all, per material)
    renderer_row(workdir, case_name) -> dict                   # one run's figures (metrics.json + the share above)
    renderer_markdown(rows) -> str                              # the table of docs/benchmarks.md

    python -m sellip.bench.renderers RUNS_DIR CASE [CASE ...]   # prints the table of RUNS_DIR/<case> runs

A vertex has single scattering when any channel of its fitted rho_ss is above 0 (the model's choice, ``model``,
decides it per cluster). Known-pose runs only: model and ground truth share the world frame, so each model vertex
takes the material of its nearest ground-truth vertex.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np


def single_scattering_shares(has_ss, truth_ss, label=None) -> dict:
    """The single-scattering figures of N vertices from has_ss (N,) bool (the model gives the vertex rho_ss > 0),
    truth_ss (N,) bool (its ground truth has it) and optional true material labels (N,): {"share": has it where
    the truth has none, "vertices": how many have none, "per_material": {label: share} over the materials with
    such vertices, "recall": has it where the truth has it (None without such vertices), "recall_vertices",
    "recall_per_material"}."""
    has_ss, truth_ss = np.asarray(has_ss, bool), np.asarray(truth_ss, bool)
    out = {}
    for key, pool, hit in (("share", ~truth_ss, has_ss & ~truth_ss), ("recall", truth_ss, has_ss & truth_ss)):
        per_material = {}
        if label is not None:
            label = np.asarray(label)
            for value in np.unique(label[pool]):
                per_material[str(int(value))] = float(hit[pool & (label == value)].mean())
        out[key] = float(hit[pool].mean()) if pool.any() else None
        out["vertices" if key == "share" else "recall_vertices"] = int(pool.sum())
        out["per_material" if key == "share" else "recall_per_material"] = per_material
    return out


def false_single_scattering(model_ply: str | Path, truth_ply: str | Path) -> dict:
    """:func:`single_scattering_shares` of a model against its ground truth: each model vertex takes the truth of
    its nearest ground-truth vertex (per_material empty without ``material`` labels in the truth)."""
    from scipy.spatial import cKDTree

    from sellip.model.ply import read_param_mesh

    model, truth = read_param_mesh(model_ply), read_param_mesh(truth_ply)
    _, nearest = cKDTree(np.asarray(truth.vertices, np.float64)).query(np.asarray(model.vertices, np.float64))
    truth_ss = np.asarray(truth.params.rho_ss, np.float64).reshape(truth.num_vertices, -1).max(axis=1)[nearest] > 0
    has_ss = np.asarray(model.params.rho_ss, np.float64).reshape(model.num_vertices, -1).max(axis=1) > 0
    label = None if truth.material is None else np.asarray(truth.material)[nearest]
    return single_scattering_shares(has_ss, truth_ss, label)


def renderer_row(workdir: str | Path, case_name: str) -> dict:
    """The figures of the run of stability case ``case_name`` in ``workdir`` (results/<case>/, captures/<scene>/)."""
    import yaml

    workdir = Path(workdir)
    config = yaml.safe_load((workdir / "override.yaml").read_text())
    scene = config["demo"]["scene"]
    results = workdir / "results" / case_name
    metrics = json.loads((results / "metrics.json").read_text())
    per = (metrics.get("eta_per_material") or {}).get("materials") or {}
    ss = false_single_scattering(results / "final" / "model.ply",
                                 workdir / "captures" / scene / "ground_truth" / "model.ply")
    return {"case": case_name, "scene": scene, "renderer": config["demo"].get("renderer", "sellip"),
            "eta_per_material": {k: (v["eta_true"], v["eta"], v["error_pct"]) for k, v in per.items()},
            "normal_median_deg": metrics["normal_error_deg"]["all"]["median"],
            "normal_mean_deg": metrics["normal_error_deg"]["all"]["mean"],
            "psnr_held_out_db": (metrics.get("psnr_held_out") or {}).get("mean_db"),
            "false_ss_share": ss["share"], "false_ss_per_material": ss["per_material"], "ss_recall": ss["recall"]}


def _pct(value) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def renderer_markdown(rows: Sequence[Mapping]) -> str:
    """One line per run: η per material (true → fitted, error), normals, held-out PSNR, false ρ_ss share (all; per
    material), and the share of the vertices with a true ρ_ss that have one (recall; – where none has)."""
    header = ("| case | scene | renderer | η per material: true → fitted (error %) | normal median / mean (°) | "
              "held-out PSNR (dB) | ρ_ss > 0, all | ρ_ss > 0 per material | ρ_ss recall |")
    lines = [header, "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        eta = "; ".join(f"{t:.3f} → {f:.3f} ({e:.2f})" for t, f, e in row["eta_per_material"].values())
        per = ", ".join(f"{k}: {_pct(v)}" for k, v in row["false_ss_per_material"].items())
        psnr = "–" if row["psnr_held_out_db"] is None else f"{row['psnr_held_out_db']:.1f}"
        lines.append(f"| {row['case']} | {row['scene']} | {row['renderer']} | {eta} | "
                     f"{row['normal_median_deg']:.2f} / {row['normal_mean_deg']:.2f} | {psnr} | "
                     f"{_pct(row['false_ss_share'])} | {per} | {_pct(row.get('ss_recall'))} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str]) -> int:
    if len(argv) < 2:
        print("usage: python -m sellip.bench.renderers RUNS_DIR CASE [CASE ...]", file=sys.stderr)
        return 2
    runs = Path(argv[0])
    print(renderer_markdown([renderer_row(runs / case, case) for case in argv[1:]]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
