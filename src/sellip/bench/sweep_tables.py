"""The sweep's results: Pareto front, the table (one row per run, pandera-checked), the
speed-accuracy chart, the paper's comparisons (Table 1 eta, augmentation, sigma_ss, model selection) and
markdown tables.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from sellip.bench.sweep_plan import PRESETS, Variant, value_label

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- Pareto front


def pareto_front(cost, loss) -> np.ndarray:
    """(N,) bool: the points that no other point dominates, both ``cost`` and ``loss`` (N,) minimized.

    A point is dominated when another is no worse in both and strictly better in one; equal points do
    not dominate each other. Points with a NaN are never on the front and dominate nothing.
    """
    cost, loss = np.asarray(cost, np.float64), np.asarray(loss, np.float64)
    if cost.shape != loss.shape or cost.ndim != 1:
        raise ValueError(f"cost and loss must be (N,) arrays of one length, got {cost.shape} and {loss.shape}")
    finite = np.isfinite(cost) & np.isfinite(loss)
    c, e = cost[finite], loss[finite]
    no_worse = (c[None, :] <= c[:, None]) & (e[None, :] <= e[:, None])  # [i, j]: j no worse than i
    better = (c[None, :] < c[:, None]) | (e[None, :] < e[:, None])
    dominated = np.any(no_worse & better, axis=1)
    front = np.zeros(cost.shape, bool)
    front[np.flatnonzero(finite)[~dominated]] = True
    return front


# --------------------------------------------------------------------------- the table


TIME_RULES = {"fit_s": "fit_pbrdf", "cluster_s": "cluster_lobes", "observe_s": "gather_observations",
              "gather_s": "gather_fit", "refine_s": "refine_geometry", "render_s": "render_outputs",
              "evaluate_s": "evaluate_model", "init_mesh_s": "init_mesh"}
"""Per-rule job-time columns of sweep.csv and their rules (metrics.json timings, summed over jobs)."""

FIGURES = {
    "normal_median_deg": (("normal_error_deg", "all", "median"), "normal error, median (deg)", False),
    "normal_mean_deg": (("normal_error_deg", "all", "mean"), "normal error, mean (deg)", False),
    "eta_median_pct": (("eta_relative_error_pct", "median"), "η error, median (%)", False),
    "eta_mean_pct": (("eta_relative_error_pct", "mean"), "η error, mean (%)", False),
    "eta_material_mean_pct": (("eta_per_material", "mean_error_pct"), "η per material, mean error (%)", False),
    "eta_material_max_pct": (("eta_per_material", "max_error_pct"), "η per material, worst error (%)", False),
    "rho_d_rmse": (("rho_d_relative_rmse", "relative_rmse"), "ρd relative RMSE", False),
    "sigma_s_median": (("sigma_s_abs_error", "median"), "σs abs. error, median", False),
    "chamfer_mm": (("geometry", "chamfer_mm"), "Chamfer (mm)", False),
    "psnr_held_out_db": (("psnr_held_out", "mean_db"), "held-out PSNR (dB)", True),
    "psnr_new_light_db": (("psnr_new_light", "mean_db"), "new-light PSNR (dB)", True),
}
"""Figure-of-merit columns: (path in metrics.json, axis label, higher is better)."""

SWEEP_COLUMNS = ("preset", "scene", "factor", "value", "label", "name", "cpu_s", "fit_cpu_s", "total_s",
                 "upstream_s", "run_s", "cold_cpu_s", "cold_run_s", "jobs_s", *TIME_RULES, "new_programs", "compiled",
                 "compile_s", "cold_compiled", "deterministic",
                 "vertices", "confident", *FIGURES)
"""Columns of sweep.csv, one row per variant: cpu_s the CPU time (user + system, core-seconds) of the shared
upstream run plus the variant's own run (snakemake and every job); fit_cpu_s that of the fit_pbrdf jobs as
the Snakemake benchmark files sample it (``cpu_time``: sampled every 30 s after a job's first 15 s, so an
undercount for long jobs); compiled, compile_s the XLA compilations in the variant's jobs (not from the
cache) and their wall time; cold_* the same of the variant's first run (when repeated); deterministic:
1 when the repeated runs gave the same figures (0 if not, empty for one run); the other ``*_s`` wall-clock seconds;
figures as in metrics.json."""

TIME_AXIS = "cpu_s"
"""The cost axis of the chart and the Pareto fronts: CPU time is what a variant costs, and unlike wall time
it hardly depends on what else the (shared) machine runs."""


def metric_at(metrics: dict, path: tuple[str, ...]):
    node = metrics
    for part in path:
        if not isinstance(node, dict) or node.get(part) is None:
            return None
        node = node[part]
    return node


def job_cpu_seconds(benchmarks_dir: str | Path) -> dict[str, float]:
    """CPU time (s, user + system) per rule, summed over the Snakemake benchmark files under ``benchmarks_dir``
    (:func:`sellip.bench.scale.job_costs`: the ``cpu_time`` column, mean over repeats). Files without the column count
    0; no files, {}."""
    from sellip.bench.scale import job_costs

    if not any(Path(benchmarks_dir).rglob("*.tsv")):
        return {}
    jobs = job_costs(benchmarks_dir)
    per_rule = jobs["cpu_s"].fillna(0.0).groupby(jobs["rule"], sort=False).sum()
    return {rule: float(cpu) for rule, cpu in per_rule.items()}


def _number(value) -> float:
    return np.nan if value is None else float(value)


def sweep_row(variant: Variant, metrics: dict, record: dict, preset: str, cpu: dict[str, float] | None = None) -> dict:
    """One sweep.csv row from a variant, its metrics.json, its run record (:func:`run_variant`; ``run_s`` is
    required) and its CPU time per rule (:func:`job_cpu_seconds`; None: NaN). Missing figures are NaN."""
    timings = metrics.get("timings") or {}
    rules = timings.get("rules") or {}
    vertices = metrics.get("vertices") or {}
    value = "base" if variant.factor == "base" else value_label(variant.value)
    row = {"preset": preset, "scene": variant.scene, "factor": variant.factor, "value": value,
           "label": variant.label, "name": variant.name, "upstream_s": float(record.get("upstream_s", 0.0)),
           "run_s": float(record["run_s"]), "cold_run_s": _number(record.get("cold_run_s")),
           "cold_cpu_s": _number(record.get("cold_cpu_s")), "cold_compiled": _number(record.get("cold_compiled")),
           "deterministic": _number(record.get("deterministic")),
           "jobs_s": float(timings.get("total_s", np.nan)), "new_programs": int(record.get("new_programs", 0)),
           "vertices": vertices.get("model", np.nan), "confident": vertices.get("confident", np.nan)}
    row["total_s"] = row["upstream_s"] + row["run_s"]
    row["cpu_s"] = _number(record.get("cpu_s"))
    row["fit_cpu_s"] = _number(cpu.get("fit_pbrdf")) if cpu else np.nan
    row["compile_s"] = _number(record.get("compile_s"))
    row["compiled"] = _number(record.get("compiled"))
    for column, rule in TIME_RULES.items():
        row[column] = float(rules[rule]["s"]) if rule in rules else np.nan
    for column, (path, _, _) in FIGURES.items():
        value = metric_at(metrics, path)
        row[column] = np.nan if value is None else float(value)
    return {column: row[column] for column in SWEEP_COLUMNS}


def sweep_schema():
    """pandera schema of sweep.csv (SWEEP_COLUMNS, in order)."""
    import pandera.pandas as pa

    seconds = pa.Column(float, pa.Check.ge(0), coerce=True)
    optional_seconds = pa.Column(float, pa.Check.ge(0), nullable=True, coerce=True)
    columns = {
        "preset": pa.Column(str, pa.Check.isin(sorted(PRESETS))),
        "scene": pa.Column(str),
        "factor": pa.Column(str),
        "value": pa.Column(str, coerce=True),
        "label": pa.Column(str),
        "name": pa.Column(str, unique=True),
        "cpu_s": optional_seconds, "fit_cpu_s": optional_seconds,
        "total_s": seconds, "upstream_s": seconds, "run_s": seconds, "cold_run_s": optional_seconds,
        "cold_cpu_s": optional_seconds,
        "cold_compiled": pa.Column(float, pa.Check.ge(0), nullable=True, coerce=True),
        "deterministic": pa.Column(float, pa.Check.isin([0.0, 1.0]), nullable=True, coerce=True),
        "jobs_s": optional_seconds,
        **{column: optional_seconds for column in TIME_RULES},
        "new_programs": pa.Column(int, pa.Check.ge(0), coerce=True),
        "compiled": pa.Column(float, pa.Check.ge(0), nullable=True, coerce=True),
        "compile_s": optional_seconds,
        "vertices": pa.Column(float, pa.Check.ge(0), nullable=True, coerce=True),
        "confident": pa.Column(float, pa.Check.ge(0), nullable=True, coerce=True),
        **{column: pa.Column(float, nullable=True, coerce=True) for column in FIGURES},
    }
    assert set(columns) == set(SWEEP_COLUMNS)
    return pa.DataFrameSchema({c: columns[c] for c in SWEEP_COLUMNS}, strict=True, ordered=True, name="sweep.csv")


def sweep_table(rows: list[dict]):
    """sweep.csv as a validated DataFrame (ValueError naming the first problem)."""
    import pandas as pd
    import pandera.pandas as pa

    frame = pd.DataFrame(rows, columns=list(SWEEP_COLUMNS))
    try:
        return sweep_schema().validate(frame, lazy=True)
    except pa.errors.SchemaErrors as error:
        first = error.failure_cases.iloc[0]
        raise ValueError(f"sweep table invalid ({len(error.failure_cases)} problems; first: column "
                         f"{first['column']!r}, check {first['check']!r}, value {first['failure_case']!r})") from None


# --------------------------------------------------------------------------- the chart


CHART_FIGURES = ("normal_median_deg", "eta_material_mean_pct", "psnr_held_out_db")
"""The accuracy axes of the chart, one column each (η: per material, the paper's Table 1 figure)."""


def sweep_figure(table, figures: tuple[str, ...] = CHART_FIGURES):
    """Accuracy against CPU time (:data:`TIME_AXIS`), one row per scene and one column per figure: every
    variant labelled, the Pareto front (less time and better accuracy) joined by a step line and ringed."""
    from matplotlib.figure import Figure

    scenes = list(dict.fromkeys(table["scene"]))
    factors = list(dict.fromkeys(table["factor"]))
    colours = {f: f"C{k % 10}" for k, f in enumerate(factors)}
    fig = Figure(figsize=(4.3 * len(figures), 3.4 * max(len(scenes), 1) + 0.5), dpi=90, layout="constrained")
    axes = np.atleast_2d(fig.subplots(max(len(scenes), 1), len(figures), squeeze=False))
    for r, scene in enumerate(scenes):
        part = table[table["scene"] == scene]
        time_s = part[TIME_AXIS].to_numpy(float)
        for c, column in enumerate(figures):
            ax = axes[r, c]
            _, label, higher = FIGURES[column]
            value = part[column].to_numpy(float)
            front = pareto_front(time_s, -value if higher else value)
            for factor in dict.fromkeys(part["factor"]):
                rows = (part["factor"] == factor).to_numpy()
                ax.scatter(time_s[rows], value[rows], s=28, color=colours[factor], label=factor, zorder=3)
            order = np.argsort(time_s[front])
            ax.step(time_s[front][order], value[front][order], where="post", color="0.3", lw=1, zorder=2,
                    label="Pareto front")
            ax.scatter(time_s[front], value[front], s=110, facecolors="none", edgecolors="0.2", lw=1, zorder=4)
            for x, y, text in zip(time_s, value, part["label"]):
                if np.isfinite(x) and np.isfinite(y):
                    ax.annotate(text, (x, y), xytext=(3, 3), textcoords="offset points", fontsize=7)
            ax.set_xlabel("CPU time of all jobs (core-s)" if TIME_AXIS == "cpu_s" else TIME_AXIS)
            ax.set_ylabel(label + (" ↑" if higher else " ↓"))
            ax.set_title(f"{scene}", fontsize=10)
            ax.grid(alpha=0.3)
    legend = {}
    for ax in axes.flat:
        for handle, text in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(text, handle)
    fig.legend(list(legend.values()), list(legend), loc="outside lower center", ncol=min(len(legend), 9),
               fontsize=8)
    return fig


def front_marks(table, figures: tuple[str, ...] = CHART_FIGURES):
    """Per row of ``table``: which charted figures (1-based: 1 normal, 2 eta, 3 PSNR) its variant is on the
    Pareto front of (against :data:`TIME_AXIS`), within its scene, e.g. "1 3"; "" when none."""
    marks = [[] for _ in range(len(table))]
    for scene in dict.fromkeys(table["scene"]):
        rows = np.flatnonzero((table["scene"] == scene).to_numpy())
        part = table.iloc[rows]
        for k, column in enumerate(figures, 1):
            value = part[column].to_numpy(float)
            front = pareto_front(part[TIME_AXIS].to_numpy(float), -value if FIGURES[column][2] else value)
            for row in rows[front]:
                marks[row].append(str(k))
    return [" ".join(m) for m in marks]


# --------------------------------------------------------------------------- the paper's comparisons


PAPER_TABLE1 = (
    ("White billiard", 1.463, 1.465, 0.10),
    ("Red billiard", 1.485, 1.476, 0.61),
    ("Green billiard", 1.503, 1.476, 1.80),
    ("POM", 1.462, 1.457, 0.34),
    ("Fake pearl", 2.295, 2.244, 2.22),
    ("Yellow silicone", 1.303, 1.337, 2.61),
    ("PEEK", 1.663, 1.617, 2.77),
)
"""Paper Table 1 (tab:refractive_index): material, measured eta, the paper's fitted eta, its error (%).
In the order of :data:`sellip.capture.scenes.SPHERE_IOR_ETAS` (the wedges of the sphere_ior scene)."""

PAPER_TABLE1_AVERAGE_PCT = 1.49

PAPER_AUGMENTATION_PSNR_DB = {"on": 34.0, "off": 30.8}
"""Paper §5.4, the owl: PSNR with and without specular augmentation."""

PAPER_SIGMA_SS_PSNR_DB = {"free": 34.0, "0.9": 34.2, "1": 33.9}
"""Paper §6, the owl: PSNR with sigma_ss fitted, fixed at 0.9, fixed at 1; fixing saves "up to an estimated
56 %" of the computation time (not measured in the paper)."""

PAPER_SIGMA_SS_SAVING_PCT = 56.0


def ior_table(model, truth, confident, paper=PAPER_TABLE1):
    """Fitted refractive index per ground-truth material (the sphere_ior scene) next to the paper's Table 1.

    model, truth: :class:`sellip.model.render.ParamMesh` in one world (truth with ``material``: (M,) int indexing
    ``paper``'s rows); confident: (N,) bool model vertices. Each confident model vertex belongs to the
    material of its nearest ground-truth vertex. Columns: material, eta_true, vertices, eta_ours (median of
    the vertices' eta), error_pct (|eta_ours - eta_true| / eta_true), vertex_error_pct (median of the
    per-vertex |eta - eta_true| / eta_true), eta_paper, paper_error_pct. ValueError when ``truth`` has no
    material or its indices do not fit ``paper``.
    """
    import pandas as pd
    from scipy.spatial import cKDTree

    if truth.material is None:
        raise ValueError("the ground truth has no per-vertex material")
    material = np.asarray(truth.material, np.int64)
    if material.min() < 0 or material.max() >= len(paper):
        raise ValueError(f"ground-truth materials {np.unique(material).tolist()} do not index the {len(paper)} "
                         f"rows of the paper's table")
    confident = np.asarray(confident, bool)
    _, nearest = cKDTree(np.asarray(truth.vertices, np.float64)).query(np.asarray(model.vertices, np.float64))
    eta = np.asarray(model.params.eta, np.float64)
    eta_true = np.asarray(truth.params.eta, np.float64)
    rows = []
    for index, (name, _eta_m, eta_paper, paper_error) in enumerate(paper):
        members = confident & (material[nearest] == index)
        truth_eta = float(np.median(eta_true[material == index])) if np.any(material == index) else np.nan
        if members.any():
            ours = float(np.median(eta[members]))
            vertex_error = float(np.median(100 * np.abs(eta[members] - truth_eta) / truth_eta))
        else:
            ours, vertex_error = np.nan, np.nan
        rows.append({"material": name, "eta_true": truth_eta, "vertices": int(members.sum()), "eta_ours": ours,
                     "error_pct": 100 * abs(ours - truth_eta) / truth_eta, "vertex_error_pct": vertex_error,
                     "eta_paper": eta_paper, "paper_error_pct": paper_error})
    return pd.DataFrame(rows)


def _pair(table, scene: str, factor: str, value: str):
    rows = table[(table["scene"] == scene) & (table["factor"] == factor) & (table["value"] == value)]
    return None if rows.empty else rows.iloc[0]


def augmentation_table(table):
    """Per scene: the base (augmentation on) against the augment-off variant: held-out and new-light PSNR,
    sigma_s error, refit cost; the paper's owl numbers alongside. Empty when no scene has both."""
    import pandas as pd

    rows = []
    for scene in dict.fromkeys(table["scene"]):
        on, off = _pair(table, scene, "base", "base"), _pair(table, scene, "augment", "off")
        if on is None or off is None:
            continue
        for state, row in (("on", on), ("off", off)):
            rows.append({"scene": scene, "augmentation": state, "psnr_held_out_db": row["psnr_held_out_db"],
                         "psnr_new_light_db": row["psnr_new_light_db"], "sigma_s_median": row["sigma_s_median"],
                         "normal_median_deg": row["normal_median_deg"], "cpu_s": row["cpu_s"],
                         "total_s": row["total_s"], "paper_psnr_db": PAPER_AUGMENTATION_PSNR_DB[state]})
    return pd.DataFrame(rows)


def sigma_ss_table(table):
    """Per scene: sigma_ss fitted (the base) against fixed at each swept value: the fit jobs' summed wall time
    (fit_s) and its saving against the free fit, the whole pipeline's CPU time (cpu_s, exact) and its saving,
    the fit jobs' sampled CPU time, accuracy; the paper's owl PSNR alongside."""
    import pandas as pd

    rows = []
    for scene in dict.fromkeys(table["scene"]):
        free = _pair(table, scene, "base", "base")
        fixed = table[(table["scene"] == scene) & (table["factor"] == "sigma_ss")]
        if free is None or fixed.empty:
            continue
        for _, row in [(None, free), *fixed.iterrows()]:
            value = "free" if row["factor"] == "base" else row["value"]
            rows.append({"scene": scene, "sigma_ss": value, "fit_s": row["fit_s"],
                         "fit_saving_pct": 100 * (1 - row["fit_s"] / free["fit_s"]), "fit_cpu_s": row["fit_cpu_s"],
                         "cpu_s": row["cpu_s"], "cpu_saving_pct": 100 * (1 - row["cpu_s"] / free["cpu_s"]),
                         "total_s": row["total_s"], "psnr_held_out_db": row["psnr_held_out_db"],
                         "normal_median_deg": row["normal_median_deg"], "eta_median_pct": row["eta_median_pct"],
                         "eta_material_mean_pct": row["eta_material_mean_pct"],
                         "paper_psnr_db": PAPER_SIGMA_SS_PSNR_DB.get(value, np.nan)})
    return pd.DataFrame(rows)


def model_selection_table(table, vertex_models: dict[str, dict[int, int]]):
    """Per scene: the base (model selection on) against the selection-off variant: the final vertices per
    model (``vertex_models`` {variant name: {model code: vertices}}, from final/params.zarr), the fit and
    cluster_lobes job times, the pipeline CPU time and its saving, accuracy. Empty when no scene has both."""
    import pandas as pd

    rows = []
    for scene in dict.fromkeys(table["scene"]):
        on, off = _pair(table, scene, "base", "base"), _pair(table, scene, "model_selection", "off")
        if on is None or off is None:
            continue
        for state, row in (("on", on), ("off", off)):
            counts = vertex_models.get(row["name"], {})
            total = max(sum(counts.values()), 1)
            rows.append({"scene": scene, "selection": state,
                         "models": ", ".join(f"{m}: {100 * c / total:.0f} %" for m, c in sorted(counts.items()) if c),
                         "fit_s": row["fit_s"], "cluster_s": row["cluster_s"], "cpu_s": row["cpu_s"],
                         "cpu_saving_pct": 100 * (1 - row["cpu_s"] / off["cpu_s"]),
                         "fit_saving_pct": 100 * (1 - row["fit_s"] / off["fit_s"]),
                         "psnr_held_out_db": row["psnr_held_out_db"], "psnr_new_light_db": row["psnr_new_light_db"],
                         "normal_median_deg": row["normal_median_deg"], "eta_median_pct": row["eta_median_pct"],
                         "eta_material_mean_pct": row["eta_material_mean_pct"],
                         "rho_d_rmse": row["rho_d_rmse"]})
    return pd.DataFrame(rows)


def markdown_table(frame, columns: dict[str, tuple[str, str]]) -> str:
    """A GitHub markdown table of ``frame``: columns {column: (header, format spec)}; NaN shows as "–"."""
    def cell(value, spec):
        if value is None or (isinstance(value, (float, np.floating)) and not np.isfinite(value)):
            return "–"
        if spec.endswith("d"):
            value = int(value)
        return format(value, spec) if spec else str(value)

    lines = ["| " + " | ".join(header for header, _ in columns.values()) + " |",
             "|" + "|".join("---" for _ in columns) + "|"]
    for _, row in frame.iterrows():
        lines.append("| " + " | ".join(cell(row[c], spec) for c, (_, spec) in columns.items()) + " |")
    return "\n".join(lines) + "\n"


