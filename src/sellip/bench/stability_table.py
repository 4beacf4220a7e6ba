"""The stability suite's measurements: one row per case from its results folder (figures of
merit, non-finite outputs, how well confidence flags bad vertices), the table's schema, and the markdown tables
of docs/benchmarks.md.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Case:
    """One case of the suite.

    name: results/<name> and the table row; group: material, capture, geometry or baseline;
    breaks: what is broken, in words; config: merged over :func:`base_config` (deep);
    views: captured views (None: the base's); flash_offset_m: added to capture.yaml ``light.position_m``
    after synthesis (the capture keeps the true flash; the reconstruction believes the declared one);
    missing / corrupt / truncated: frame ids deleted, overwritten with random bytes, cut to a third
    after synthesis (the run uses ``ingest.bad_frames: skip``); perturb_m: standard deviation of the
    seeded displacement of the initial mesh's vertices along their normals; needs: optional packages the case
    needs (e.g. "mitsuba"); the suite skips the case, with a warning, where one is missing.
    """

    name: str
    group: str
    breaks: str
    config: Mapping = field(default_factory=dict)
    views: int | None = None
    flash_offset_m: tuple[float, float, float] | None = None
    missing: tuple[str, ...] = ()
    corrupt: tuple[str, ...] = ()
    truncated: tuple[str, ...] = ()
    perturb_m: float = 0.0
    needs: tuple[str, ...] = ()

    @property
    def edits_capture(self) -> bool:
        return self.flash_offset_m is not None or bool(self.missing or self.corrupt or self.truncated)


BAD_NORMAL_DEG = 10.0
"""A vertex whose normal is further than this from the ground truth's is bad."""

BAD_ETA_PCT = 10.0
"""A vertex whose η is further than this (relative, %) from the ground truth's is bad."""

LOW_CONFIDENCE = 0.5
"""A vertex whose confidence is below this is flagged."""

# --------------------------------------------------------------------------- measuring


def rank_auc(score: np.ndarray, positive: np.ndarray) -> float | None:
    """Probability that a random positive has a larger ``score`` than a random negative, ties one half
    (the Mann-Whitney U / ROC AUC). None when either class is empty."""
    from scipy.stats import rankdata

    score = np.asarray(score, np.float64)
    positive = np.asarray(positive, bool)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        return None
    ranks = rankdata(score)
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def confidence_flagging(error: np.ndarray, confidence: np.ndarray, bad_above: float,
                        low_below: float = LOW_CONFIDENCE) -> dict:
    """How well a low confidence marks large errors (definitions: module docstring).

    error, confidence: (N,). Returns bad_share, flagged_share, bad_flagged (recall), flagged_bad
    (precision), auc, and worst_auc: the AUC for the worst tenth of the vertices (error at or above its
    90th percentile), defined whatever the errors' scale; a ratio over an empty set is None.
    """
    error = np.asarray(error, np.float64)
    confidence = np.asarray(confidence, np.float64)
    if error.shape != confidence.shape or error.ndim != 1:
        raise ValueError(f"error and confidence must be (N,) of one length, got {error.shape}, {confidence.shape}")
    if error.size == 0:
        return {"bad_share": None, "flagged_share": None, "bad_flagged": None, "flagged_bad": None, "auc": None,
                "worst_auc": None}
    bad = error > bad_above
    flagged = ~(confidence >= low_below)  # NaN confidence counts as flagged

    def share(of, among):
        return float(np.mean(of[among])) if among.any() else None

    doubt = -np.nan_to_num(confidence, nan=-1.0)
    return {"bad_share": float(bad.mean()), "flagged_share": float(flagged.mean()),
            "bad_flagged": share(flagged, bad), "flagged_bad": share(bad, flagged), "auc": rank_auc(doubt, bad),
            "worst_auc": rank_auc(doubt, error >= np.percentile(error, 90))}


def _count_nonfinite(values) -> int:
    values = np.asarray(values)
    return int(np.size(values) - np.count_nonzero(np.isfinite(values))) if values.dtype.kind in "fc" else 0


INFINITE_WHEN_UNKNOWN = ("normal_std_deg", "eta_std", "sigma_s_std")
"""params.zarr arrays that are +inf by design where the uncertainty is unknown: a vertex not fitted
(status != 0), or fitted with a singular Gauss-Newton matrix (confidence 0; sellip.model.params)."""


def nonfinite_outputs(results_dir: str | Path) -> dict[str, int]:
    """Non-finite values per output array of a finished run: every vertex property of final/model.ply, every
    array of final/params.zarr (except +inf in INFINITE_WHEN_UNKNOWN where the uncertainty is unknown),
    every array of the .npz files under final/renders, and metrics.json (NaN or Infinity literals). Returns
    only the arrays with any ({} when all is finite); a missing output counts -1."""
    import warnings

    import zarr

    from sellip.model.ply import read_ply

    results_dir = Path(results_dir)
    bad: dict[str, int] = {}
    model = results_dir / "final" / "model.ply"
    if model.is_file():
        vertex, _ = read_ply(model)
        for name, values in vertex.items():
            if (count := _count_nonfinite(values)):
                bad[f"model.ply:{name}"] = count
    else:
        bad["model.ply"] = -1
    params = results_dir / "final" / "params.zarr"
    if (params / "zarr.json").is_file():
        with warnings.catch_warnings():  # Snakemake's .snakemake_timestamp in a directory output
            warnings.simplefilter("ignore")
            group = zarr.open_group(str(params), mode="r")
            arrays = {name: np.asarray(array[...]) for name, array in group.arrays()}
        unknown = np.zeros(0, bool)
        if "status" in arrays and "confidence" in arrays:
            unknown = (arrays["status"] != 0) | (arrays["confidence"] == 0)
        for name, values in arrays.items():
            if name in INFINITE_WHEN_UNKNOWN and values.shape == unknown.shape:
                values = np.where(unknown & (values == np.inf), 0.0, values)
            if (count := _count_nonfinite(values)):
                bad[f"params.zarr:{name}"] = count
    else:
        bad["params.zarr"] = -1
    renders = results_dir / "final" / "renders"
    if renders.is_dir():
        for path in sorted(renders.glob("*.npz")):
            with np.load(path) as data:
                for name in data.files:
                    if (count := _count_nonfinite(data[name])):
                        bad[f"renders/{path.name}:{name}"] = count
    else:
        bad["renders"] = -1
    metrics = results_dir / "metrics.json"
    if metrics.is_file():
        literals = []
        json.loads(metrics.read_text(), parse_constant=literals.append)
        if literals:
            bad["metrics.json"] = len(literals)
    else:
        bad["metrics.json"] = -1
    return bad


def _get(mapping, *keys):
    for key in keys:
        if not isinstance(mapping, Mapping) or mapping.get(key) is None:
            return None
        mapping = mapping[key]
    return mapping


COLUMNS: dict[str, str] = {
    # name: pandas dtype ("float" columns may be null)
    "case": "str", "group": "str", "breaks": "str", "status": "str", "error": "str",
    "wall_s": "float", "cpu_s": "float", "views": "float", "vertices": "float", "confident_share": "float",
    "normal_mean_deg": "float", "normal_median_deg": "float", "normal_p90_deg": "float",
    "eta_median_pct": "float", "eta_material_mean_pct": "float", "eta_material_max_pct": "float",
    "rho_d_rmse": "float", "sigma_s_median_err": "float",
    "chamfer_mm": "float", "hausdorff_mm": "float", "truth_far_share": "float", "folds_max": "float",
    "fold_first_mesh": "float", "psnr_held_out_db": "float", "psnr_new_light_db": "float",
    "true_materials": "float", "clusters_per_pass": "str", "fragile": "str", "found_before": "float",
    "outputs_finite": "bool", "nonfinite": "str",
    "confidence_median": "float", "bad_share": "float", "flagged_share": "float", "bad_flagged": "float",
    "flagged_bad": "float", "auc": "float", "worst_auc": "float", "eta_bad_share": "float",
    "eta_bad_flagged": "float", "eta_flagged_bad": "float", "eta_auc": "float", "eta_worst_auc": "float",
}
"""The columns of stability.csv, in order (definitions: docs/benchmarks.md)."""


def geometry_folds(iterations: Sequence[Mapping]) -> tuple[int, int | None, str] | None:
    """(the most folds of any mesh, the first mesh that folds or None, a one-line account) from metrics.json's
    ``geometry_iterations``; folds = self-intersecting triangle pairs + flipped triangles. None: no row counts
    them (a run from before they were measured)."""
    counted = [row for row in iterations if row.get("self_intersecting_pairs") is not None]
    if not counted:
        return None
    folds = [int(row["self_intersecting_pairs"]) + int(row.get("flipped_triangles") or 0) for row in counted]
    first = next((row["mesh"] for row, count in zip(counted, folds) if count), None)
    account = "; ".join(f"mesh {row['mesh']}: {row['self_intersecting_pairs']} self-intersecting pairs, "
                        f"{row.get('flipped_triangles') or 0} flipped" for row, count in zip(counted, folds) if count)
    return max(folds), first, account


def cluster_decisions(results: str | Path, metrics: Mapping | None = None) -> dict:
    """The clustering's decisions of the finished run ``results`` (``results/<name>``): ``clusters_per_pass`` (K of
    each pass, ``iter/<it>/clusters/clusters.json``, in order: "2 3 2"), ``found_before`` (regions kept by the
    hysteresis over all passes: their records say ``found_before``; docs/reproducibility.md), ``true_materials``
    (the truth's materials in metrics.json's ``eta_per_material``) and ``fragile`` (the final clusters whose support is
    below 1, each with its support: "2 (0.9), 4 (0.7)"; metrics.json's ``material_support``). Missing parts are
    None or ""."""
    from sellip.fit.lobe_store import pass_clusters

    records = [record for _, record in pass_clusters(Path(results))]
    out = {"clusters_per_pass": " ".join(str(int(r["k"])) for r in records),
           "found_before": float(sum("found_before" in region for r in records for region in r.get("regions") or []))
           if records else None, "true_materials": None, "fragile": ""}
    if metrics:
        materials = _get(metrics, "eta_per_material", "materials")
        out["true_materials"] = float(len(materials)) if materials else None
        support = metrics.get("material_support") or {}
        clusters = support.get("clusters") or {}
        out["fragile"] = ", ".join(f"{k} ({clusters.get(str(k), {}).get('support', float('nan')):.1f})"
                                   for k in support.get("fragile") or [])
    return out


def empty_row(case: Case) -> dict:
    row = {name: (None if kind == "float" else "") for name, kind in COLUMNS.items()}
    row.update(case=case.name, group=case.group, breaks=case.breaks, outputs_finite=False)
    return row


def case_row(case: Case, workdir: str | Path, wall_s: float, error: str | None = None,
             cpu_s: float | None = None) -> dict:
    """One table row from a case's finished run in ``workdir`` (results/<case.name>, captures/<scene>).

    wall_s, cpu_s: the run's wall time and the CPU time (user + system) of all its processes;
    ``error``: why the run failed (the row then has status "failed" and whatever outputs exist)."""
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.model.ply import read_param_mesh, read_ply
    from sellip.report.figures_of_merit import vertex_errors

    workdir = Path(workdir)
    results = workdir / "results" / case.name
    row = empty_row(case)
    row.update(status="failed" if error else "ok", error=error or "", wall_s=float(wall_s),
               cpu_s=None if cpu_s is None else float(cpu_s))
    hdr = results / "hdr.zarr" / "zarr.json"
    if hdr.is_file():
        row["views"] = float(len(json.loads(hdr.read_text()).get("attributes", {}).get("view_id", [])))
    nonfinite = nonfinite_outputs(results)
    row["outputs_finite"] = not nonfinite
    row["nonfinite"] = "; ".join(f"{k} {'missing' if v < 0 else v}" for k, v in nonfinite.items())
    metrics_path = results / "metrics.json"
    if metrics_path.is_file():
        m = json.loads(metrics_path.read_text())
        vertices = _get(m, "vertices", "model")
        row.update(
            vertices=vertices,
            confident_share=(_get(m, "vertices", "confident") / vertices) if vertices else None,
            normal_mean_deg=_get(m, "normal_error_deg", "all", "mean"),
            normal_median_deg=_get(m, "normal_error_deg", "all", "median"),
            normal_p90_deg=_get(m, "normal_error_deg", "all", "p90"),
            eta_median_pct=_get(m, "eta_relative_error_pct", "median"),
            eta_material_mean_pct=_get(m, "eta_per_material", "mean_error_pct"),
            eta_material_max_pct=_get(m, "eta_per_material", "max_error_pct"),
            rho_d_rmse=_get(m, "rho_d_relative_rmse", "relative_rmse"),
            sigma_s_median_err=_get(m, "sigma_s_abs_error", "median"),
            chamfer_mm=_get(m, "geometry", "chamfer_mm"), hausdorff_mm=_get(m, "geometry", "hausdorff_mm"),
            truth_far_share=_get(m, "geometry", "truth_farther_than_1mm"),
            psnr_held_out_db=_get(m, "psnr_held_out", "mean_db"),
            psnr_new_light_db=_get(m, "psnr_new_light", "mean_db"))
        row.update(cluster_decisions(results, m))
        folds = geometry_folds(m.get("geometry_iterations") or [])
        if folds is not None:
            row.update(folds_max=float(folds[0]), fold_first_mesh=None if folds[1] is None else float(folds[1]))
            if folds[0] and not error:
                row.update(status="failed", error=f"the surface folds: {folds[2]}")
    model_path = results / "final" / "model.ply"
    scene = (case.config.get("demo") or {}).get("scene", "tiny")
    truth_path = workdir / "captures" / scene / GROUND_TRUTH_MESH
    if model_path.is_file() and truth_path.is_file():
        vertex, _ = read_ply(model_path)
        confidence = np.asarray(vertex.get("confidence", np.zeros(len(vertex["x"]))), np.float64)
        errors = vertex_errors(read_param_mesh(model_path), read_param_mesh(truth_path))
        normal = confidence_flagging(errors["normal_error_deg"], confidence, BAD_NORMAL_DEG)
        eta = confidence_flagging(errors["eta_relative_error_pct"], confidence, BAD_ETA_PCT)
        row.update(confidence_median=float(np.nanmedian(confidence)), **normal,
                   **{f"eta_{k}": eta[k] for k in ("bad_share", "bad_flagged", "flagged_bad", "auc", "worst_auc")})
    return row


def _schema():
    import pandera.pandas as pa

    def column(kind: str):
        if kind == "float":
            return pa.Column(float, pa.Check.ge(0), nullable=True)
        return pa.Column(bool if kind == "bool" else str)

    columns = {name: column(kind) for name, kind in COLUMNS.items()}
    columns["status"] = pa.Column(str, pa.Check.isin(["ok", "failed"]))
    columns["case"] = pa.Column(str, unique=True)
    for name in ("bad_share", "flagged_share", "bad_flagged", "flagged_bad", "auc", "worst_auc", "eta_bad_share",
                 "eta_bad_flagged", "eta_flagged_bad", "eta_auc", "eta_worst_auc", "confident_share",
                 "confidence_median", "truth_far_share"):
        columns[name] = pa.Column(float, [pa.Check.in_range(0, 1)], nullable=True)
    return pa.DataFrameSchema(columns, strict=True, ordered=True)


def validate_table(rows: Sequence[Mapping]):
    """The rows as a DataFrame in COLUMNS order, checked against STABILITY_SCHEMA (pandera raises naming the
    column and row)."""
    import pandas as pd

    table = pd.DataFrame([{name: row.get(name) for name in COLUMNS} for row in rows], columns=list(COLUMNS))
    for name, kind in COLUMNS.items():
        table[name] = table[name].astype({"float": "float64", "bool": "bool", "str": "object"}[kind])
        if kind == "str":
            table[name] = table[name].fillna("").astype(str)
    return _schema().validate(table, lazy=True)


def format_cell(value, digits: int = 1, percent: bool = False) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return f"{100 * value:.0f} %" if percent else f"{value:.{digits}f}"


def _share_count(share, vertices) -> str:
    """'1.2 % (28)': a share of the vertices with its vertex count."""
    if share is None or not np.isfinite(share):
        return "–"
    count = f" ({round(share * vertices)})" if vertices is not None and np.isfinite(vertices) else ""
    return f"{100 * share:.1f} %{count}"


def _from_mesh(mesh) -> str:
    """' (from mesh 2)': the first mesh that folds, or '' when none does."""
    return "" if mesh is None or not np.isfinite(mesh) else f" (from mesh {mesh:.0f})"


def _markdown(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def stability_markdown(table) -> str:
    """The suite's tables in Markdown: the figures of merit per case, then finiteness and confidence flagging, then
    the clustering's decisions (:func:`cluster_decisions`)."""
    records = table.to_dict("records")
    merit, flags, decisions = [], [], []
    for row in records:
        status = "ok" if row["status"] == "ok" else f"**failed**: {row['error'][:160]}"
        merit.append([
            row["case"], row["breaks"], status, format_cell(row["views"], 0), format_cell(row["vertices"], 0),
            " / ".join(format_cell(row[k]) for k in ("normal_mean_deg", "normal_median_deg", "normal_p90_deg")),
            format_cell(row["eta_median_pct"]),
            " / ".join(format_cell(row[k], 2) for k in ("eta_material_mean_pct", "eta_material_max_pct")),
            format_cell(row["rho_d_rmse"], 2), format_cell(row["sigma_s_median_err"], 2),
            f"{format_cell(row['chamfer_mm'], 2)} / {format_cell(row['hausdorff_mm'], 1)}",
            format_cell(row["truth_far_share"], percent=True),
            format_cell(row["folds_max"], 0) + _from_mesh(row["fold_first_mesh"]),
            format_cell(row["psnr_held_out_db"]),
            format_cell(row["psnr_new_light_db"]), f"{format_cell(row['wall_s'], 0)} / {format_cell(row['cpu_s'], 0)}"])
        finite = "yes" if row["outputs_finite"] else f"**no**: {row['nonfinite'][:120]}"
        flags.append([
            row["case"], finite, format_cell(row["confident_share"], percent=True),
            format_cell(row["confidence_median"], 2), format_cell(row["flagged_share"], percent=True),
            f"{_share_count(row['bad_share'], row['vertices'])} / "
            + " / ".join(format_cell(row[k], percent=True) for k in ("bad_flagged", "flagged_bad")),
            format_cell(row["auc"], 2), format_cell(row["worst_auc"], 2),
            f"{_share_count(row['eta_bad_share'], row['vertices'])} / "
            + " / ".join(format_cell(row[k], percent=True) for k in ("eta_bad_flagged", "eta_flagged_bad")),
            format_cell(row["eta_auc"], 2), format_cell(row["eta_worst_auc"], 2)])
        decisions.append([row["case"], format_cell(row["true_materials"], 0), row["clusters_per_pass"] or "–",
                          format_cell(row["found_before"], 0), row["fragile"] or "–"])
    lines = ["Figures of merit (metrics.json of each run):", ""]
    lines += _markdown(["case", "broken", "status", "views", "vertices", "normal mean / median / p90 (°)",
                        "η per vertex, median (%)", "η per material, mean / worst (%)", "ρ_d rel. RMSE",
                        "σ_s err. (median)", "Chamfer / Hausdorff (mm)", "truth > 1 mm away",
                        "folds, most of any mesh",
                        "held-out PSNR (dB)", "new-light PSNR (dB)", "wall / CPU (s)"], merit)
    caption = (f"Outputs and confidence (bad: normal error > {BAD_NORMAL_DEG:g}°, η error > {BAD_ETA_PCT:g} %; "
               f"flagged: confidence < {LOW_CONFIDENCE:g}):")
    lines += ["", caption, ""]
    lines += _markdown(["case", "outputs finite", "confidence > 0", "median confidence", "flagged",
                        "normal bad (vertices) / bad flagged / flagged bad", "normal AUC", "normal worst-10 % AUC",
                        "η bad (vertices) / bad flagged / flagged bad", "η AUC", "η worst-10 % AUC"], flags)
    lines += ["", "The clustering's decisions (clusters.json of each pass; support: materials.csv):", ""]
    lines += _markdown(["case", "true materials", "clusters at each pass", "kept as found before (hysteresis)",
                        "fragile clusters (support)"], decisions)
    return "\n".join(lines) + "\n"


