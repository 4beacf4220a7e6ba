"""Coverage of the per-material η intervals of ``final/materials.csv`` (issue #49 item 4), replayed on finished runs.

A run's final store and its capture's ground truth give, per material cluster, the estimate, the true η (the
median truth over the cluster's vertices), three intervals and the figure the shared error scales with:

- ``vertex``: the bootstrap of the median over vertices resampled one by one (the interval materials.csv gave
  before: the scatter alone, vertices treated as independent; :func:`sellip.report.materials.median_interval`);
- ``scatter``: the spatial block bootstrap (patches of neighbouring vertices resampled;
  :func:`sellip.report.materials.block_median_interval`);
- ``ci``: the scatter widened by the shared error ``factor`` x the median ``eta_std`` (what materials.csv gives,
  :func:`sellip.report.materials.eta_interval`).

:func:`fit_shared_factor` fits the factor by maximum likelihood on some rows (a normal error of variance
scatter^2 + (factor x eta_std)^2 per material), :func:`coverage` counts the materials whose interval holds the
truth, per renderer, and their median relative width. ``benchmarks/replay_intervals.py`` is the command line;
docs/viewer.md quotes it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

ROW_COLUMNS = ("run", "renderer", "cluster", "vertices", "estimating", "eta", "gt_eta", "vertex_low", "vertex_high",
               "scatter_low", "scatter_high", "eta_std")


def run_renderer(capture: Path) -> str:
    """"mitsuba" or "sellip": the renderer of a synthetic capture (capture.yaml's ``synthetic.renderer``)."""
    import yaml

    synthetic = (yaml.safe_load((Path(capture) / "capture.yaml").read_text()) or {}).get("synthetic") or {}
    return "mitsuba" if str(synthetic.get("renderer", "")).startswith("mitsuba") else "sellip"


def capture_of(results: Path) -> Path:
    """The capture folder of a results folder (metrics.json's ``capture``; a relative one is the workflow's,
    relative to the folder above ``results/``)."""
    metrics = Path(results) / "metrics.json"
    if not metrics.is_file():
        raise FileNotFoundError(f"{metrics}: missing: the run did not finish (rule evaluate)")
    capture = Path(json.loads(metrics.read_text())["capture"])
    return capture if capture.is_absolute() else Path(results).resolve().parent.parent / capture


def material_rows(results: str | Path) -> pd.DataFrame:
    """One row per material cluster of ``results/final/params.zarr`` (columns :data:`ROW_COLUMNS`), against the
    capture's ground truth; FileNotFoundError where the run has no final store or its capture no truth."""
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.model.params import read_params
    from sellip.model.ply import read_param_mesh, read_ply
    from sellip.report import materials

    results = Path(results)
    capture = capture_of(results)
    truth_path = capture / GROUND_TRUTH_MESH
    if not truth_path.is_file():
        raise FileNotFoundError(f"{truth_path}: missing: the capture has no ground truth")
    store = read_params(results / "final" / "params.zarr")
    _, faces = read_ply(results / "final" / "model.ply")
    table = materials.material_table(store, faces, read_param_mesh(truth_path), shared_factor=0.0)
    estimating = materials.estimating_vertices(store)
    cluster = np.asarray(store.get("cluster", np.zeros(len(estimating))), np.int64)
    eta_own = np.asarray(store.get("eta_vertex", store["eta"]), np.float64)
    rows = []
    for row in table.itertuples():
        use = (cluster == row.cluster) & estimating
        low, high = materials.median_interval(eta_own[use], seed=materials.BOOTSTRAP_SEED + int(row.cluster)) \
            if use.any() else (row.eta, row.eta)
        rows.append({"run": results.name, "renderer": run_renderer(capture), "cluster": row.cluster,
                     "vertices": row.vertices, "estimating": row.confident_vertices, "eta": row.eta,
                     "gt_eta": row.gt_eta, "vertex_low": low, "vertex_high": high, "scatter_low": row.eta_scatter_low,
                     "scatter_high": row.eta_scatter_high,
                     "eta_std": row.eta_fit_std if np.isfinite(row.eta_fit_std) else 0.0})
    return pd.DataFrame(rows, columns=list(ROW_COLUMNS))


def intervals(rows: pd.DataFrame, factor: float, level: float = 0.95, scale: str = "eta_std") -> pd.DataFrame:
    """(low, high) of the materials.csv interval of each row with shared-error ``factor`` x the row's ``scale``
    column (``eta_std``: the formula of :func:`sellip.report.materials.eta_interval`; ``eta``: an error model
    that is a fixed share of eta, the alternative the replay compares)."""
    from scipy.stats import norm

    z = float(norm.ppf(0.5 + level / 2))
    shared = z * factor * rows[scale].to_numpy(np.float64)
    eta = rows["eta"].to_numpy(np.float64)
    return pd.DataFrame({"low": eta - np.hypot(eta - rows["scatter_low"].to_numpy(np.float64), shared),
                         "high": eta + np.hypot(rows["scatter_high"].to_numpy(np.float64) - eta, shared)},
                        index=rows.index)


def fit_shared_factor(rows: pd.DataFrame, level: float = 0.95, grid: np.ndarray | None = None,
                      scale: str = "eta_std") -> float:
    """The factor (of the ``scale`` column, >= 0) that maximises the normal likelihood of the rows' errors
    eta - gt_eta, each of variance s^2 + (factor x scale)^2, s the half-width of its scatter interval over the
    normal quantile of ``level``; a grid search (default 0 to 2 by 0.0025)."""
    from scipy.stats import norm

    z = float(norm.ppf(0.5 + level / 2))
    grid = np.arange(0, 2.0001, 0.0025) if grid is None else np.asarray(grid, np.float64)
    error = (rows["eta"] - rows["gt_eta"]).to_numpy(np.float64)
    scatter = ((rows["scatter_high"] - rows["scatter_low"]).to_numpy(np.float64) / (2 * z))
    std = rows[scale].to_numpy(np.float64)
    variance = scatter[None] ** 2 + (grid[:, None] * std[None]) ** 2 + 1e-12
    loglik = -0.5 * np.sum(np.log(variance) + error[None] ** 2 / variance, axis=1)
    return float(grid[int(np.argmax(loglik))])


def coverage(rows: pd.DataFrame, low: np.ndarray, high: np.ndarray) -> dict:
    """Per renderer and over all rows: {materials, covered, share, median_width_pct} of the intervals (low, high)
    against ``gt_eta`` (width relative to the estimate, in %)."""
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    inside = (low <= rows["gt_eta"].to_numpy()) & (rows["gt_eta"].to_numpy() <= high)
    width = 100 * (high - low) / rows["eta"].to_numpy(np.float64)
    out = {}
    for name, select in [("all", np.ones(len(rows), bool))] + [
            (renderer, (rows["renderer"] == renderer).to_numpy()) for renderer in sorted(rows["renderer"].unique())]:
        count = int(select.sum())
        out[name] = {"materials": count, "covered": int(inside[select].sum()),
                     "share": float(inside[select].mean()) if count else None,
                     "median_width_pct": float(np.median(width[select])) if count else None}
    return out


CORRELATION_EDGES = (0.0, 0.02, 0.04, 0.06, 0.1, 0.15, 0.2, 0.3)


def residual_correlation(store: dict, edges: tuple = CORRELATION_EDGES) -> dict:
    """How far apart two vertices' errors stop moving together: the correlation of the estimating vertices'
    residuals (own eta minus their material's median, over their std) between pairs of vertices at a distance in
    each bin (``edges``: fractions of the model's bounding-box diagonal). Returns {upper edge: correlation} (NaN
    where no pair). What :data:`sellip.report.materials.PATCH_FRACTION` was chosen from."""
    from scipy.spatial import cKDTree

    from sellip.report.materials import estimating_vertices

    vertices = np.asarray(store["vertices"], np.float64)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    eta_own = np.asarray(store.get("eta_vertex", store["eta"]), np.float64)
    cluster = np.asarray(store.get("cluster", np.zeros(len(eta_own))), np.int64)
    use = estimating_vertices(store)
    residual = np.full(len(eta_own), np.nan)
    for k in np.unique(cluster[use]):
        member = use & (cluster == k)
        residual[member] = eta_own[member] - np.median(eta_own[member])
    points, residual = vertices[use], residual[use]
    residual = residual / (residual.std() or 1.0)
    tree = cKDTree(points)
    out = {}
    for low, high in zip(edges[:-1], edges[1:]):
        pairs = tree.query_pairs(high * diagonal, output_type="ndarray")
        distance = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
        pairs = pairs[distance >= low * diagonal]
        out[float(high)] = float(np.mean(residual[pairs[:, 0]] * residual[pairs[:, 1]])) if len(pairs) else np.nan
    return out
