"""The per-material table of a final model (``final/materials.csv``; issue #40).

One row per material cluster of ``final/params.zarr`` (``cluster``; a store without one is one material):

    cluster, vertices, area_share, confident_vertices,
    eta, eta_ci_low, eta_ci_high, eta_scatter_low, eta_scatter_high, eta_shared_std, eta_spread, eta_fit_std,
    eta_own_vertices,
    rho_d_r, rho_d_g, rho_d_b, rho_s, sigma_s, rho_ss_r, rho_ss_g, rho_ss_b, sigma_ss,
    model, model_name, lobe_own_vertices, selection_margin, runner_up_model, cluster_support, cluster_alternative
    [+ with a ground truth: gt_material, gt_eta, gt_rho_d_r, gt_rho_d_g, gt_rho_d_b, gt_sigma_s, gt_sigma_ss]

Definitions (the cluster's vertices are those with its label; "estimating" vertices are the confident ones,
confidence > 0, whose own eta is not pinned at a bound of the fit, :func:`sellip.fit.eta_at_bound`):

- ``eta``: the median of the estimating vertices' own eta (``eta_vertex``, the per-vertex fit): the material's
  eta as ``sellip finalize`` sets it (:func:`sellip.augment.cluster_medians`); the median of the model's eta where
  no vertex estimates it.
- ``eta_ci_low``/``eta_ci_high``: a 95 % interval of the material's eta that includes what moves all its vertices
  together (issue #49; :func:`eta_interval`): the scatter interval below, each side widened in quadrature by 1.96 x
  ``eta_shared_std``. ``eta_shared_std`` = :data:`SHARED_STD_FACTOR` x ``eta_fit_std``: the 1-sigma error shared by
  the material's vertices (normal and geometry error, model mismatch, calibration), in units of the fits' own
  uncertainty, which grows where the polarization signal is weak (dark, rough, few views); the factor was fitted on
  the stability suite's scenes of both renderers and each renderer's fit validated on the other's (docs/viewer.md);
  0 where the store has no ``eta_std`` (the interval is then the scatter's alone).
- ``eta_scatter_low``/``eta_scatter_high``: the 95 % interval of the median from the spread of the vertices alone:
  the 2.5 / 97.5 percentiles of the median over :data:`BOOTSTRAP_ROUNDS` spatial block bootstrap resamples
  (:func:`block_median_interval`: patches of neighbouring vertices, cubes of :data:`PATCH_FRACTION` of the model's
  bounding-box diagonal, resampled, since neighbours share views and errors; seeded: the same store gives the same
  table).
  ``eta_spread`` = 1.4826 MAD of their own eta (how much vertices differ), ``eta_fit_std`` = the median of their
  Gauss-Newton std ``eta_std`` (the fit's own uncertainty per vertex; NaN where the store has none).
- ``rho_d_*``, ``rho_ss_*``: the mean over the cluster's vertices (relative: one global scale is free,
  docs/design.md §4); ``rho_s``, ``sigma_s``, ``sigma_ss``: the median over them.
- ``model``: the most common per-vertex ``model`` code (:data:`sellip.params.MODEL_NAMES`); ``eta_own_vertices``,
  ``lobe_own_vertices``: how many keep their own eta / specular lobe (``eta_source``/``lobe_source`` = 1).
- ``selection_margin``, ``runner_up_model``: how far the cluster's model choice was from the selection rule's
  boundary, in units of its allowance (0: on it, a little more noise would flip it; 1: no candidate came near), and
  the model nearest to taking its place (:func:`sellip.fit.selection.decision_margin`, from the final pass's
  ``clusters.json``, carried per vertex as ``selection_margin`` / ``selection_runner_up``); NaN and -1 where the
  pass scored no candidates (or the store predates them). Below 0.5 the vertices' ``confidence`` is lowered
  (:func:`sellip.fit.selection.margin_confidence`): a fragile lobe choice says so in both places.
- ``cluster_support``, ``cluster_alternative``: the share of repeats of the final pass's clustering on resampled
  vertices (:func:`sellip.fit.cluster_support.clustering_support`, config ``augment.stability_resamples``) that
  found this material again whole (nothing split off it), and the material it was merged into most often in the
  others (-1: none, never lost, or a material split off it); NaN and
  -1 where not measured. Below 1 the data do not settle whether this material is one of its own: a fragile
  material says so here, with its alternative.
- ``area_share``: the cluster's share of the surface, each vertex carrying a third of its triangles' area.
- Ground truth (``gt_*``): each model vertex's nearest ground-truth vertex (same world: a run on known poses) votes;
  ``gt_material`` is the most common true material label (-1: none), ``gt_eta`` etc. the medians of the true values
  there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sellip.jobs import atomic_file
from sellip.model.params import MODEL_NAMES

BOOTSTRAP_ROUNDS = 1000
BOOTSTRAP_SEED = 0
MAD_TO_SD = 1.4826
LEVEL = 0.95
# The edge of a spatial patch of the block bootstrap, as a fraction of the model's bounding-box diagonal. The
# residuals of neighbouring vertices' own eta correlate (0.2-0.5 within 0.02 of the diagonal) and stop doing so by
# 0.06-0.1 of it (docs/viewer.md, "The eta interval"): a patch of 0.1 holds what neighbours share.
PATCH_FRACTION = 0.1
# The 1-sigma error that moves all of a material's vertices together, in units of the median Gauss-Newton std of
# their own eta (``eta_std``): the maximum-likelihood fit (0.143) on 19 materials of eight runs of both renderers (the
# demo and stability scenes), each renderer's own fit validated on the other's and each run's on the others
# (0.145-0.15 without any one run but pplastic_set, 0.08 without it), rounded up (docs/viewer.md, "The eta
# interval"; benchmarks/replay_intervals.py). Over all 22 materials of ten runs it is 0.13 (same coverage, 3.4 % wide
# instead of 3.8 %): kept at 0.15 until more of the suite's runs refit it.
SHARED_STD_FACTOR = 0.15

COLUMNS = ("cluster", "vertices", "area_share", "confident_vertices", "eta", "eta_ci_low", "eta_ci_high",
           "eta_scatter_low", "eta_scatter_high", "eta_shared_std", "eta_spread", "eta_fit_std", "eta_own_vertices",
           "rho_d_r", "rho_d_g", "rho_d_b", "rho_s", "sigma_s",
           "rho_ss_r", "rho_ss_g", "rho_ss_b", "sigma_ss", "model", "model_name", "lobe_own_vertices",
           "selection_margin", "runner_up_model", "cluster_support", "cluster_alternative")
GT_COLUMNS = ("gt_material", "gt_eta", "gt_rho_d_r", "gt_rho_d_g", "gt_rho_d_b", "gt_sigma_s", "gt_sigma_ss")


class MaterialsError(ValueError):
    """A model or table that cannot make a materials table (the message names the file)."""


def materials_schema(ground_truth: bool = False):
    """pandera schema of materials.csv (with the ``gt_*`` columns when ``ground_truth``)."""
    import pandera.pandas as pa

    finite = pa.Check(np.isfinite, element_wise=True)
    nonnegative = [pa.Check.ge(0), finite]
    count = pa.Column(int, pa.Check.ge(0), coerce=True)
    eta = pa.Column(float, [pa.Check.ge(1.0), pa.Check.le(3.0)], coerce=True)
    columns = {
        "cluster": pa.Column(int, pa.Check.ge(0), unique=True, coerce=True),
        "vertices": pa.Column(int, pa.Check.gt(0), coerce=True),
        "area_share": pa.Column(float, [pa.Check.ge(0), pa.Check.le(1)], coerce=True),
        "confident_vertices": count,
        "eta": eta, "eta_ci_low": eta, "eta_ci_high": eta, "eta_scatter_low": eta, "eta_scatter_high": eta,
        "eta_shared_std": pa.Column(float, nonnegative, coerce=True),
        "eta_spread": pa.Column(float, nonnegative, coerce=True),
        "eta_fit_std": pa.Column(float, pa.Check.ge(0), nullable=True, coerce=True),
        "eta_own_vertices": count,
        **{f"rho_d_{c}": pa.Column(float, nonnegative, coerce=True) for c in "rgb"},
        "rho_s": pa.Column(float, nonnegative, coerce=True),
        "sigma_s": pa.Column(float, [pa.Check.gt(0), finite], coerce=True),
        **{f"rho_ss_{c}": pa.Column(float, nonnegative, coerce=True) for c in "rgb"},
        "sigma_ss": pa.Column(float, [pa.Check.gt(0), finite], coerce=True),
        "model": pa.Column(int, pa.Check.isin(sorted(MODEL_NAMES)), coerce=True),
        "model_name": pa.Column(str, pa.Check.isin(list(MODEL_NAMES.values()))),
        "lobe_own_vertices": count,
        "selection_margin": pa.Column(float, [pa.Check.ge(0), pa.Check.le(1)], nullable=True, coerce=True),
        "runner_up_model": pa.Column(int, pa.Check.isin([-1, *sorted(MODEL_NAMES)]), coerce=True),
        "cluster_support": pa.Column(float, [pa.Check.ge(0), pa.Check.le(1)], nullable=True, coerce=True),
        "cluster_alternative": pa.Column(int, pa.Check.ge(-1), coerce=True),
    }
    if ground_truth:
        columns.update({
            "gt_material": pa.Column(int, pa.Check.ge(-1), coerce=True),  # -1: the truth has no labels
            "gt_eta": pa.Column(float, [pa.Check.ge(1.0), pa.Check.le(3.0)], coerce=True),
            **{f"gt_rho_d_{c}": pa.Column(float, nonnegative, coerce=True) for c in "rgb"},
            "gt_sigma_s": pa.Column(float, pa.Check.ge(0), coerce=True),
            "gt_sigma_ss": pa.Column(float, pa.Check.ge(0), coerce=True),
        })
    checks = [pa.Check(lambda t: (t["eta_ci_low"] <= t["eta"] + 1e-9) & (t["eta"] <= t["eta_ci_high"] + 1e-9),
                       name="eta_ci_low <= eta <= eta_ci_high"),
              pa.Check(lambda t: (t["eta_ci_low"] <= t["eta_scatter_low"] + 1e-9)
                       & (t["eta_scatter_high"] <= t["eta_ci_high"] + 1e-9),
                       name="the interval holds the scatter-only interval")]
    return pa.DataFrameSchema(columns, checks=checks, strict=True, ordered=True, name="materials.csv")


def validate_materials(table: pd.DataFrame, label: str = "materials.csv") -> pd.DataFrame:
    """The table checked by :func:`materials_schema`; MaterialsError naming ``label``, the row and the column."""
    import pandera.pandas as pa

    schema = materials_schema(ground_truth="gt_eta" in table.columns)
    try:
        return schema.validate(table, lazy=True)
    except pa.errors.SchemaErrors as error:
        first = error.failure_cases.iloc[0]
        raise MaterialsError(f"{label}: {len(error.failure_cases)} problem(s); first: row {first['index']}, "
                             f"column {first['column']!r}, check {first['check']!r}, "
                             f"value {first['failure_case']!r}") from None


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) a third of the area of every triangle around each vertex (m^2). vertices (V, 3), faces (F, 3)."""
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.intp)
    area = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                         vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    return np.bincount(faces.ravel(), weights=np.repeat(area / 3, 3), minlength=len(vertices))


def median_interval(values: np.ndarray, rounds: int = BOOTSTRAP_ROUNDS, seed: int = BOOTSTRAP_SEED,
                    level: float = 0.95) -> tuple[float, float]:
    """The bootstrap percentile interval (low, high) of the median of ``values`` (n,), n >= 1; seeded."""
    values = np.asarray(values, np.float64)
    if values.size < 2:
        return float(values[0]), float(values[0])
    rng = np.random.default_rng(seed)
    medians = np.empty(rounds)
    for start in range(0, rounds, 100):  # bounded memory for large clusters
        stop = min(start + 100, rounds)
        medians[start:stop] = np.median(values[rng.integers(0, values.size, (stop - start, values.size))], axis=1)
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(medians, [tail, 100 - tail])
    return float(low), float(high)


def patch_labels(vertices: np.ndarray, edge_m: float) -> np.ndarray:
    """(V,) int: the spatial patch of each vertex: the cube of edge ``edge_m`` (m, > 0) of a grid from the
    vertices' lower corner that holds it, numbered 0.. in order of first appearance. vertices (V, 3) in metres."""
    vertices = np.asarray(vertices, np.float64)
    if edge_m <= 0 or not np.isfinite(edge_m):
        raise MaterialsError(f"patch edge {edge_m!r} m: expected a positive length")
    cells = np.floor((vertices - vertices.min(axis=0)) / edge_m).astype(np.int64)
    _, first, labels = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))  # renumber the cells in order of first appearance
    return order[labels.ravel()]


def block_median_interval(values: np.ndarray, patches: np.ndarray, rounds: int = BOOTSTRAP_ROUNDS,
                          seed: int = BOOTSTRAP_SEED, level: float = LEVEL) -> tuple[float, float]:
    """The spatial block bootstrap's percentile interval (low, high) of the median of ``values`` (n,), n >= 1:
    each round draws as many patches as ``values`` touches (``patches`` (n,), labels of
    :func:`patch_labels`), with replacement, and takes the median of all their vertices; seeded. Neighbours share
    views and errors, so resampling patches rather than vertices keeps what they share in the spread. With fewer
    than two patches it is :func:`median_interval` (the vertices resampled one by one)."""
    values = np.asarray(values, np.float64)
    _, patch = np.unique(np.asarray(patches), return_inverse=True)
    count = int(patch.max()) + 1 if patch.size else 0
    if values.size < 2 or count < 2:
        return median_interval(values, rounds, seed, level)
    order = np.argsort(values, kind="stable")
    sorted_values, sorted_patch = values[order], patch.ravel()[order]
    rng = np.random.default_rng(seed)
    medians = np.empty(rounds)
    for start in range(0, rounds, 100):  # bounded memory for large clusters
        stop = min(start + 100, rounds)
        drawn = rng.integers(0, count, (stop - start, count))
        times = np.zeros((stop - start, count))  # how often each patch was drawn, per round
        np.add.at(times, (np.arange(stop - start)[:, None], drawn), 1.0)
        weight = np.cumsum(times[:, sorted_patch], axis=1)
        half = weight[:, -1:] / 2
        below = np.argmax(weight >= half, axis=1)  # the weighted lower median ...
        above = np.argmax(weight > half, axis=1)  # ... and the upper one (they differ on an even total)
        medians[start:stop] = 0.5 * (sorted_values[below] + sorted_values[above])
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(medians, [tail, 100 - tail])
    return float(low), float(high)


def eta_interval(eta_own: np.ndarray, patches: np.ndarray, eta_std: np.ndarray, seed: int = BOOTSTRAP_SEED,
                 shared_factor: float = SHARED_STD_FACTOR, level: float = LEVEL) -> dict:
    """A material's eta and its interval (module docstring): eta_own (n,) the estimating vertices' own eta,
    n >= 1; patches (n,) their spatial patches (:func:`patch_labels`); eta_std (n,) their Gauss-Newton std (NaN
    where unknown). Returns {eta, low, high, scatter_low, scatter_high, shared_std}: the median; the spatial block
    bootstrap's interval of it (:func:`block_median_interval`, seeded by ``seed``); the 1-sigma shared error
    ``shared_factor`` x the median finite eta_std (0 where none is finite); and the interval: each side of the
    scatter interval widened in quadrature by the normal quantile of ``level`` x shared_std."""
    from scipy.stats import norm

    eta_own = np.asarray(eta_own, np.float64)
    eta = float(np.median(eta_own))
    scatter_low, scatter_high = block_median_interval(eta_own, patches, seed=seed, level=level)
    finite = np.asarray(eta_std, np.float64)
    finite = finite[np.isfinite(finite)]
    shared = float(shared_factor * np.median(finite)) if finite.size else 0.0
    z = float(norm.ppf(0.5 + level / 2))
    scatter_low, scatter_high = min(scatter_low, eta), max(scatter_high, eta)
    return {"eta": eta, "scatter_low": scatter_low, "scatter_high": scatter_high, "shared_std": shared,
            "low": eta - float(np.hypot(eta - scatter_low, z * shared)),
            "high": eta + float(np.hypot(scatter_high - eta, z * shared))}


def estimating_vertices(arrays: dict) -> np.ndarray:
    """(N,) bool: the vertices of a parameter store that estimate their material's eta: confidence > 0 (all where
    the store has none) and their own eta (``eta_vertex``, else ``eta``) finite and not pinned at a bound of the fit
    (:func:`sellip.fit.eta_at_bound`)."""
    from sellip.fit.parameterization import eta_at_bound

    eta_own = np.asarray(arrays.get("eta_vertex", arrays["eta"]), np.float64)
    confidence = np.asarray(arrays["confidence"], np.float64) if "confidence" in arrays else np.ones(len(eta_own))
    return (confidence > 0) & ~eta_at_bound(eta_own) & np.isfinite(eta_own)


def _mode(values: np.ndarray) -> int:
    codes, counts = np.unique(np.asarray(values, np.int64), return_counts=True)
    return int(codes[np.argmax(counts)])


def material_table(arrays: dict, faces: np.ndarray, ground_truth=None, shared_factor: float = SHARED_STD_FACTOR,
                   patch_fraction: float = PATCH_FRACTION) -> pd.DataFrame:
    """The materials table (module docstring) of a final parameter store.

    arrays: name -> (N, ...) arrays of final/params.zarr (:func:`sellip.params.read_params`); needs
    ``vertices`` and the pBRDF fields; uses ``cluster``, ``confidence``, ``eta_vertex``, ``eta_std``, ``model``,
    ``eta_source``, ``lobe_source``, ``selection_margin``, ``selection_runner_up``, ``cluster_support``,
    ``cluster_alternative`` where present. faces (F, 3) of the
    model (for the area shares).
    ground_truth: a :class:`sellip.render.ParamMesh` in the same world (its ``material`` labels used if present).
    shared_factor, patch_fraction: the interval's constants (:data:`SHARED_STD_FACTOR`, :data:`PATCH_FRACTION`;
    other values only for the replay that measures them, benchmarks/replay_intervals.py).
    """
    vertices = np.asarray(arrays["vertices"], np.float64)
    n = len(vertices)
    if n == 0:
        raise MaterialsError("the model has no vertex")

    def column(name, default):
        return np.asarray(arrays[name]) if name in arrays else np.full(n, default)

    cluster = column("cluster", 0).astype(np.int64)
    eta_final = np.asarray(arrays["eta"], np.float64)
    eta_own = np.asarray(arrays.get("eta_vertex", eta_final), np.float64)
    eta_std = column("eta_std", np.nan).astype(np.float64)
    models = column("model", 3).astype(np.int64)
    margin = column("selection_margin", np.nan).astype(np.float64)
    runner_up = column("selection_runner_up", -1).astype(np.int64)
    support = column("cluster_support", np.nan).astype(np.float64)
    alternative = column("cluster_alternative", -1).astype(np.int64)
    estimating = estimating_vertices(arrays)
    area = vertex_areas(vertices, faces)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    patches = patch_labels(vertices, patch_fraction * diagonal) if diagonal > 0 else np.zeros(n, np.int64)
    total_area = area.sum() or 1.0
    truth = _truth_per_vertex(vertices, ground_truth) if ground_truth is not None else None
    rows = []
    for k in np.unique(cluster):
        member = cluster == k
        use = member & estimating
        if use.any():
            interval = eta_interval(eta_own[use], patches[use], eta_std[use], seed=BOOTSTRAP_SEED + int(k),
                                    shared_factor=shared_factor)
            eta, low, high, shared = interval["eta"], interval["low"], interval["high"], interval["shared_std"]
            scatter_low, scatter_high = interval["scatter_low"], interval["scatter_high"]
            spread = MAD_TO_SD * float(np.median(np.abs(eta_own[use] - eta)))
            finite_std = eta_std[use][np.isfinite(eta_std[use])]
            fit_std = float(np.median(finite_std)) if finite_std.size else np.nan
        else:
            eta = low = high = scatter_low = scatter_high = float(np.median(eta_final[member]))
            spread, fit_std, shared = 0.0, np.nan, 0.0
        rho_d = np.asarray(arrays["rho_d"], np.float64)[member].mean(0)
        rho_ss = np.asarray(arrays["rho_ss"], np.float64)[member].mean(0)
        model = _mode(models[member])
        row = {"cluster": int(k), "vertices": int(member.sum()), "area_share": float(area[member].sum() / total_area),
               "confident_vertices": int(use.sum()), "eta": eta, "eta_ci_low": low, "eta_ci_high": high,
               "eta_scatter_low": scatter_low, "eta_scatter_high": scatter_high, "eta_shared_std": shared,
               "eta_spread": spread, "eta_fit_std": fit_std,
               "eta_own_vertices": int(column("eta_source", 0)[member].astype(np.int64).sum()),
               "rho_d_r": rho_d[0], "rho_d_g": rho_d[1], "rho_d_b": rho_d[2],
               "rho_s": float(np.median(np.asarray(arrays["rho_s"], np.float64)[member])),
               "sigma_s": float(np.median(np.asarray(arrays["sigma_s"], np.float64)[member])),
               "rho_ss_r": rho_ss[0], "rho_ss_g": rho_ss[1], "rho_ss_b": rho_ss[2],
               "sigma_ss": float(np.median(np.asarray(arrays["sigma_ss"], np.float64)[member])),
               "model": model, "model_name": MODEL_NAMES[model],
               "lobe_own_vertices": int(column("lobe_source", 0)[member].astype(np.int64).sum()),
               "selection_margin": float(np.median(margin[member])) if np.isfinite(margin[member]).all() else np.nan,
               "runner_up_model": _mode(runner_up[member]),
               "cluster_support": float(np.median(support[member])) if np.isfinite(support[member]).all() else np.nan,
               "cluster_alternative": _mode(alternative[member])}
        if truth is not None:
            row.update(_truth_row(truth, member))
        rows.append(row)
    return validate_materials(pd.DataFrame(rows, columns=list(COLUMNS + (GT_COLUMNS if truth is not None else ()))))


def _truth_per_vertex(vertices: np.ndarray, truth) -> dict:
    """The ground truth's values at each model vertex's nearest ground-truth vertex."""
    from scipy.spatial import cKDTree

    nearest = cKDTree(np.asarray(truth.vertices, np.float64)).query(vertices, k=1)[1]
    p = truth.params
    return {"material": None if truth.material is None else np.asarray(truth.material)[nearest],
            "eta": np.asarray(p.eta)[nearest], "rho_d": np.asarray(p.rho_d)[nearest],
            "sigma_s": np.asarray(p.sigma_s)[nearest], "sigma_ss": np.asarray(p.sigma_ss)[nearest]}


def _truth_row(truth: dict, member: np.ndarray) -> dict:
    rho_d = np.median(truth["rho_d"][member], axis=0)
    return {"gt_material": -1 if truth["material"] is None else _mode(truth["material"][member]),
            "gt_eta": float(np.median(truth["eta"][member])),
            "gt_rho_d_r": rho_d[0], "gt_rho_d_g": rho_d[1], "gt_rho_d_b": rho_d[2],
            "gt_sigma_s": float(np.median(truth["sigma_s"][member])),
            "gt_sigma_ss": float(np.median(truth["sigma_ss"][member]))}


def write_materials(path: str | Path, table: pd.DataFrame) -> Path:
    """Write the table as CSV atomically (temporary name, then rename), after checking it."""
    path = Path(path)
    validate_materials(table, str(path))
    with atomic_file(path) as tmp:
        table.to_csv(tmp, index=False, float_format="%.6g")
    return path


def read_materials(path: str | Path) -> pd.DataFrame:
    """A materials.csv, checked (MaterialsError naming the file, row and column)."""
    path = Path(path)
    if not path.is_file():
        raise MaterialsError(f"{path}: missing; run `sellip view` first")
    return validate_materials(pd.read_csv(path), str(path))
