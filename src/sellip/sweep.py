"""Speed-accuracy sweep of the whole workflow (issue #9): one factor at a time from a base configuration.

Public API::

    Factor, FACTORS, PRESETS, Variant
    plan_variants(scenes, preset, only=None) -> list[Variant]     # per scene: the base, then each factor value
    variant_overrides(variant, preset, capture, cache) -> dict      # the config file of one snakemake run
    pareto_front(cost, loss) -> (N,) bool                          # non-dominated points, both minimized
    front_marks(table) -> list[str]                                # which charted figures a row is on the front of
    job_cpu_seconds(benchmarks_dir) -> {rule: CPU s}
    sweep_row(variant, metrics, record, preset, cpu) -> dict; SWEEP_COLUMNS; sweep_schema()
    sweep_figure(table) -> matplotlib Figure                       # accuracy against time, fronts marked
    PAPER_TABLE1; ior_table(model, truth, confident) -> DataFrame  # fitted eta per Table-1 material
    augmentation_table(table), sigma_ss_table(table), model_selection_table(table, vertex_models)
    markdown_table(frame, columns)
    link_upstream(source, target); cache_entries(directory) -> int
    SnakemakeRunner(workdir, cores); run_sweep(scenes, preset, workdir, runner, ...) -> list of records

Every variant is a real ``snakemake`` run of the repository's Snakefile with a config file on top of
config/config.yaml: the base of its preset and scene, plus the one key its factor changes. Variants whose
factor does not touch the capture, ingest, poses or initial mesh (all of FACTORS) reuse one upstream run
per scene: its outputs are hard-linked into the variant's results folder (mtimes kept) and snakemake runs
with ``--rerun-triggers mtime``, so only the reconstruction loop and the evaluation run again.

Times (seconds). Wall clock: ``upstream_s`` the shared upstream run (ingest, poses, initial mesh,
previews); ``run_s`` the variant's own snakemake run; ``total_s`` = upstream_s + run_s, what the whole
pipeline takes with this setting; per-rule job times from metrics.json ``timings``. CPU: ``cpu_s``, the
user + system time of snakemake and every job of the upstream run and of the variant's run
(``getrusage``), is the chart's cost axis (:data:`TIME_AXIS`): on a machine shared with other work, wall
time measures the neighbours as much as the variant.

XLA compilation: every job compiles its JAX kernels or loads them from the persistent cache that all jobs
share. The fit's settings are static arguments and its batch shapes follow the data, so a variant compiles
kernels no other run needed. With ``repeat=2`` (the default) a variant whose run spent more than
:data:`RECOMPILE_FRACTION` of its CPU time compiling runs again, and the second run, which finds its
kernels in the cache, is the one timed: the steady-state cost of a setting, as on a machine that has run
it before. The first run's times are kept (``cold_*``): their difference is what compiling costs the
first time. ``compiled``/``compile_s`` of the timed run say what compilation is left in its time.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
"""The checkout this module lives in (its Snakefile and config/config.yaml drive the runs)."""


class SweepError(RuntimeError):
    """A sweep run failed or its inputs are inconsistent (the message names the run and its log)."""


# --------------------------------------------------------------------------- what is swept


@dataclass(frozen=True)
class Factor:
    """One swept setting: the dotted config ``key`` and the ``values`` tried besides the base's own.

    values: a tuple for every preset, or {preset: tuple}. label: format of a value in the chart ("{}" gets
    on/off for booleans, "free" for None). upstream: the values change the capture, ingest, poses or
    initial mesh, so the variant runs everything itself instead of reusing the scene's upstream run.
    """

    name: str
    key: str
    values: tuple | dict
    label: str = "{}"
    upstream: bool = False

    def values_for(self, preset: str) -> tuple:
        values = self.values.get(preset, ()) if isinstance(self.values, dict) else self.values
        return tuple(values)


FACTORS: tuple[Factor, ...] = (
    Factor("iterations", "iterations", {"quick": (1, 3), "full": (2, 4)}, "{} it"),
    Factor("views", "observe.max_views", {"quick": (12,), "full": (24,)}, "{} views"),
    Factor("augment", "augment.enabled", (False,), "aug {}"),
    Factor("sigma_ss", "fit.settings.sigma_ss_fixed", {"quick": (0.9, 1.0), "full": (0.9,)}, "σss {}"),
    Factor("model_selection", "model_selection.enabled", (False,), "selection {}"),
    Factor("lm_cap", "fit.settings.max_iterations", (10,), "LM {}"),
    Factor("dtype", "fit.dtype", {"quick": ("float64",)}, "{}"),
)
"""The factors, in sweep order. Adding one is one line here. The quick preset tries every factor of issue #9
around its small base (iterations 1 and 3 of 2, 12 of 24 views, σ_ss fixed at 0.9 and 1, LM cap 10 of 30,
float64); the full one, at the demo's size, the values that the quick sweep found to matter or that change
the fit's cost (iterations 2 and 4 of 6, 24 of 36 views, augmentation and model selection off, σ_ss 0.9,
LM cap 10): 10 variants, about 50 minutes on 2 cores (docs/benchmarks.md)."""

SCENE_FACTORS: dict[str, dict[str, tuple[str, ...]]] = {"quick": {"sphere_ior": ("model_selection",)},
                                                        "full": {"sphere_ior": ("model_selection",)}}
"""Per preset and scene, the only factors swept there (a scene not named: every factor). sphere_ior runs its
base (the refractive-index table) and model selection off (a scene without single scattering)."""


_QUICK = {
    "iterations": 2,
    "demo": {"views": 24, "width": 320, "height": 256, "seed": 0},
    "init": {"hull_resolution": 64, "max_vertices": 1500},
    # Shards are whole observation chunks: 256-vertex chunks split ~1.5k vertices evenly over both shards.
    "observe": {"vertex_chunk": 256},
    "fit": {"shards": 2, "settings": {"min_views": 6}},
    "augment": {"max_samples": 4096, "settings": {"virtual_count": 45, "virtual_step_deg": 2.0}},
    "evaluate": {"held_out_views": ["v005", "v017"], "render_views": ["v000"], "supersample": 1},
}

_FULL = {
    "iterations": 6,
    "demo": {"views": 36, "width": 612, "height": 512, "seed": 0},
    "init": {"max_vertices": 6000},
    "observe": {"max_slope": 0.4},
    "fit": {"shards": 2},
    "augment": {"settings": {"virtual_count": 45, "virtual_step_deg": 2.0}},
    "evaluate": {"held_out_views": ["v004", "v013", "v022", "v031"], "render_views": ["v000"], "supersample": 1},
}

PRESETS: dict[str, dict] = {"quick": _QUICK, "full": _FULL}
"""Base configuration of each preset (over config/config.yaml; the same for every scene).

quick: 24 views at 320x256 (2 held out), ~1.5k vertices, 2 iterations, 6 usable views
per vertex suffice, cluster lobes from at most 4096 samples, 45 virtual samples 2 deg apart, observation chunks
that split the vertices over both fit shards. full: the built-in demo's own settings (config/config.yaml
``demo``: 36 views at 612x512, 4 held out, 6k vertices, and its ``overrides``: 6 iterations, the slope test,
45 virtual samples), with one rendered view instead of four."""


# --------------------------------------------------------------------------- config helpers


def get_key(config: dict, key: str):
    """The value at a dotted ``key`` of a nested dict (KeyError naming the key when absent)."""
    node = config
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(key)
        node = node[part]
    return node


def set_key(config: dict, key: str, value) -> dict:
    """A deep copy of ``config`` with the dotted ``key`` set to ``value`` (intermediate dicts created)."""
    out = copy.deepcopy(config)
    node = out
    *parents, last = key.split(".")
    for part in parents:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ValueError(f"cannot set {key!r}: {part!r} is not a mapping")
    node[last] = copy.deepcopy(value)
    return out


def merge(base: dict, over: dict) -> dict:
    """``base`` updated by ``over`` recursively (nested dicts key by key), as Snakemake merges config files."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_defaults(repo: Path = REPO) -> dict:
    """config/config.yaml of the checkout."""
    import yaml

    path = Path(repo) / "config" / "config.yaml"
    if not path.is_file():
        raise SweepError(f"{path} does not exist: run the sweep from a checkout of sellip")
    return yaml.safe_load(path.read_text())


def value_label(value) -> str:
    """A config value as text for names and labels: on/off, free (None), 0.9, float64, 12."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "free"
    return f"{value:g}" if isinstance(value, float) else str(value)


# --------------------------------------------------------------------------- the plan


@dataclass(frozen=True)
class Variant:
    """One run of the sweep: ``factor`` "base" is the scene's base configuration (value None)."""

    scene: str
    factor: str
    value: object = None
    label: str = "base"
    key: str | None = None
    upstream: bool = False

    @property
    def name(self) -> str:
        """Results folder name (config ``name``): scene__base, scene__factor-value."""
        if self.factor == "base":
            return f"{self.scene}__base"
        return f"{self.scene}__{self.factor}-{re.sub(r'[^A-Za-z0-9_.-]', '_', value_label(self.value))}"


def plan_variants(scenes: list[str], preset: str, only: list[str] | None = None,
                  factors: tuple[Factor, ...] = FACTORS, defaults: dict | None = None) -> list[Variant]:
    """Per scene: the base, then every value of every factor (``only``: these factors; :data:`SCENE_FACTORS`
    may narrow them per scene) that differs from the base's own value (base of ``preset`` over ``defaults``,
    config/config.yaml when None)."""
    if preset not in PRESETS:
        raise SweepError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
    known = {f.name for f in factors}
    unknown = sorted(set(only or ()) - known)
    if unknown:
        raise SweepError(f"unknown factor(s) {unknown}; expected some of {sorted(known)}")
    if not scenes:
        raise SweepError("no scene to sweep")
    base = merge(load_defaults() if defaults is None else defaults, PRESETS[preset])
    variants = []
    for scene in scenes:
        variants.append(Variant(scene, "base"))
        allowed = SCENE_FACTORS.get(preset, {}).get(scene)
        for factor in factors:
            if (only and factor.name not in only) or (allowed is not None and factor.name not in allowed):
                continue
            try:
                own = get_key(base, factor.key)
            except KeyError:
                own = None
            for value in factor.values_for(preset):
                if value == own and type(value) is type(own):
                    continue
                shown = value_label(value)
                variants.append(Variant(scene, factor.name, value, factor.label.format(shown), factor.key,
                                        factor.upstream))
    return variants


def variant_overrides(variant: Variant, preset: str, capture: str | Path, cache: str | Path,
                      name: str | None = None) -> dict:
    """The config file of ``variant``'s snakemake run (over config/config.yaml): the preset's base, the
    scene, the capture folder (absolute: the built-in demo overrides then do not apply), the shared XLA
    cache, the results name (default ``variant.name``) and the factor's value."""
    config = merge(PRESETS[preset], {"name": name or variant.name, "capture": str(Path(capture).resolve()),
                                     "demo": {"scene": variant.scene},
                                     "fit": {"compilation_cache": str(Path(cache).resolve())}})
    if variant.key is not None:
        config = set_key(config, variant.key, variant.value)
    return config


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
    c, l = cost[finite], loss[finite]
    no_worse = (c[None, :] <= c[:, None]) & (l[None, :] <= l[:, None])  # [i, j]: j no worse than i
    better = (c[None, :] < c[:, None]) | (l[None, :] < l[:, None])
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
1 when the repeated runs gave the same figures (0 if not, empty for one run); the other ``*_s`` wall-clock seconds; figures as in metrics.json."""

TIME_AXIS = "cpu_s"
"""The cost axis of the chart and the Pareto fronts: CPU time is what a variant costs, and unlike wall time
it hardly depends on what else the (shared) machine runs."""


def _dig(metrics: dict, path: tuple[str, ...]):
    node = metrics
    for part in path:
        if not isinstance(node, dict) or node.get(part) is None:
            return None
        node = node[part]
    return node


def job_cpu_seconds(benchmarks_dir: str | Path) -> dict[str, float]:
    """CPU time (s, user + system) per rule, summed over the Snakemake benchmark files under ``benchmarks_dir``
    (:func:`sellip.scale.job_costs`: the ``cpu_time`` column, mean over repeats). Files without the column count
    0; no files, {}."""
    from sellip.scale import job_costs

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
        value = _dig(metrics, path)
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


def save_figure_atomic(fig, path: str | Path) -> Path:
    """Write a figure as PNG under a temporary name, then rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        fig.savefig(tmp, format="png")
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_csv_atomic(frame, path: str | Path) -> Path:
    """Write a DataFrame as CSV under a temporary name, then rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        frame.to_csv(tmp, index=False)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text_atomic(text: str, path: str | Path) -> Path:
    """Write text under a temporary name, then rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


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
In the order of :data:`sellip.scenes.SPHERE_IOR_ETAS` (the wedges of the sphere_ior scene)."""

PAPER_TABLE1_AVERAGE_PCT = 1.49

PAPER_AUGMENTATION_PSNR_DB = {"on": 34.0, "off": 30.8}
"""Paper §5.4, the owl: PSNR with and without specular augmentation."""

PAPER_SIGMA_SS_PSNR_DB = {"free": 34.0, "0.9": 34.2, "1": 33.9}
"""Paper §6, the owl: PSNR with sigma_ss fitted, fixed at 0.9, fixed at 1; fixing saves "up to an estimated
56 %" of the computation time (not measured in the paper)."""

PAPER_SIGMA_SS_SAVING_PCT = 56.0


def ior_table(model, truth, confident, paper=PAPER_TABLE1):
    """Fitted refractive index per ground-truth material (the sphere_ior scene) next to the paper's Table 1.

    model, truth: :class:`sellip.render.ParamMesh` in one world (truth with ``material``: (M,) int indexing
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
    for index, (name, eta_m, eta_paper, paper_error) in enumerate(paper):
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


# --------------------------------------------------------------------------- running the workflow


UPSTREAM_RULES = ("linearize_frames", "merge_hdr", "plot_hdr_previews", "run_sfm", "init_mesh")
"""The rules before the reconstruction loop; none of them reads a swept setting."""

UPSTREAM_OUTPUTS = ("hdr.zarr", "previews", "cameras.csv", "sfm", "mesh")
"""Their outputs under results/NAME/ (linearize_frames' linear.zarr is temporary and gone)."""


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def link_upstream(source: str | Path, target: str | Path) -> None:
    """Hard-link the upstream outputs, benchmark files and logs of results folder ``source`` into ``target``
    (created), keeping every mtime (files share the inode; folders get their source's stat), so that
    ``snakemake --rerun-triggers mtime`` finds them up to date. SweepError when an output is missing."""
    source, target = Path(source), Path(target)
    for name in UPSTREAM_OUTPUTS:
        if not (source / name).exists():
            raise SweepError(f"{source / name} is missing: the upstream run did not finish")
    target.mkdir(parents=True, exist_ok=True)
    pairs = [(source / n, target / n) for n in UPSTREAM_OUTPUTS]
    pairs += [(source / "benchmarks" / f"{r}.tsv", target / "benchmarks" / f"{r}.tsv") for r in UPSTREAM_RULES]
    pairs += [(source / "logs" / f"{r}.log", target / "logs" / f"{r}.log") for r in UPSTREAM_RULES]
    for src, dst in pairs:
        if not src.exists():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst, copy_function=_link_or_copy, dirs_exist_ok=True)
        else:
            _link_or_copy(str(src), str(dst))


def cache_entries(directory: str | Path) -> int:
    """Files in the persistent XLA compilation cache (one per compiled program; 0 when it does not exist)."""
    directory = Path(directory)
    return sum(1 for p in directory.rglob("*") if p.is_file()) if directory.is_dir() else 0


class SnakemakeRunner:
    """Runs the repository's workflow in ``workdir``: ``runner(config, targets, log_path) -> (wall s, CPU s)``.

    The command is ``python -m snakemake TARGETS --snakefile REPO/Snakefile --directory WORKDIR --cores N
    --rerun-triggers mtime [EXTRA] --configfile REPO/config/config.yaml CONFIG`` (the config written to
    WORKDIR/configs/NAME.yaml; the targets first, as --rerun-triggers and --configfile take several values);
    its output goes to ``log_path``. CPU s: user + system time of snakemake and every job it ran
    (``getrusage(RUSAGE_CHILDREN)`` before and after; exact, whatever else the machine runs). JAX logs
    its compilations into the job logs (``JAX_LOG_COMPILES=1``, see :func:`xla_compile_seconds`).
    SweepError with the log's tail on failure.
    """

    def __init__(self, workdir: str | Path, cores: int = 2, repo: str | Path = REPO, python: str = sys.executable,
                 extra: tuple[str, ...] = ()):
        self.workdir, self.cores, self.repo, self.python = Path(workdir).resolve(), int(cores), Path(repo), python
        self.extra = tuple(extra)
        if not (self.repo / "Snakefile").is_file():
            raise SweepError(f"{self.repo / 'Snakefile'} does not exist: run the sweep from a checkout of sellip")

    def __call__(self, config: dict, targets: list[str], log_path: str | Path) -> float:
        import yaml

        config_path = self.workdir / "configs" / f"{config['name']}.yaml"
        config_path.parent.mkdir(parents=True, exist_ok=True)
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        command = [self.python, "-m", "snakemake", *targets, "--snakefile", str(self.repo / "Snakefile"),
                   "--directory", str(self.workdir), "--cores", str(self.cores), "--rerun-triggers", "mtime",
                   *self.extra, "--configfile", str(self.repo / "config" / "config.yaml"), str(config_path)]
        env = {**os.environ, "PATH": f"{Path(self.python).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               "JAX_LOG_COMPILES": "1"}
        log_path = Path(log_path)
        log_path.parent.mkdir(parents=True, exist_ok=True)
        before = _children_cpu()
        started = time.perf_counter()
        with open(log_path, "w") as out:
            result = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, env=env, check=False)
        wall = time.perf_counter() - started
        cpu = _children_cpu() - before
        if result.returncode != 0:
            tail = "".join(log_path.read_text().splitlines(keepends=True)[-25:])
            raise SweepError(f"snakemake for {config['name']} failed (exit {result.returncode}); log {log_path}:\n{tail}")
        return wall, cpu


def _children_cpu() -> float:
    """User + system CPU seconds of this process's finished (waited-for) descendants."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


_XLA_HIT = re.compile(r"Persistent compilation cache hit for '")
_XLA_DONE = re.compile(r"Finished XLA compilation of .* in ([0-9.eE+-]+) sec")


def xla_compile_seconds(logs_dir: str | Path) -> tuple[float, int]:
    """XLA compilations in the job logs under ``logs_dir`` (written with ``JAX_LOG_COMPILES=1``): their summed
    wall time (s) and count, not counting executables loaded from the persistent cache (a "Finished XLA
    compilation" line right after a "Persistent compilation cache hit" line)."""
    seconds, count = 0.0, 0
    for path in sorted(Path(logs_dir).rglob("*.log")):
        hit = False
        for line in path.read_text(errors="replace").splitlines():
            if _XLA_HIT.search(line):
                hit = True
                continue
            done = _XLA_DONE.search(line)
            if done:
                if not hit:
                    seconds += float(done.group(1))
                    count += 1
                hit = False
    return seconds, count


RECOMPILE_FRACTION = 0.1
"""A run whose XLA compilations took more than this fraction of its CPU time is repeated (up to ``repeat``)."""

RECORD = "sweep_record.json"
"""Per results folder: what the sweep ran there (config, times); a finished variant is not run again."""


@dataclass
class SweepPaths:
    """Where one sweep works: WORKDIR/captures/SCENE, WORKDIR/results/NAME, WORKDIR/jax_cache, WORKDIR/logs."""

    workdir: Path
    results: Path = field(init=False)
    cache: Path = field(init=False)
    logs: Path = field(init=False)

    def __post_init__(self):
        self.workdir = Path(self.workdir).resolve()
        self.results, self.cache, self.logs = (self.workdir / "results", self.workdir / "jax_cache",
                                               self.workdir / "logs")

    def capture(self, scene: str) -> Path:
        return self.workdir / "captures" / scene


def _read_record(folder: Path, config: dict, needs: str | None = "metrics.json",
                 keys: tuple[str, ...] = ("cpu_s", "run_s")) -> dict | None:
    """The record of a finished run in ``folder`` with this exact config, its file ``needs`` and ``keys``
    (a record of an older sweep without them is stale), else None."""
    path = folder / RECORD
    if not path.is_file() or (needs is not None and not (folder / needs).is_file()):
        return None
    record = json.loads(path.read_text())
    if any(key not in record for key in keys):
        return None
    return record if record.get("config") == json.loads(json.dumps(config)) else None


def _write_record(folder: Path, record: dict) -> None:
    write_text_atomic(json.dumps(record, indent=2), folder / RECORD)


def prepare_scene(scene: str, preset: str, paths: SweepPaths, runner: Callable) -> dict:
    """Make the scene's capture (rule synth_capture) and its upstream run (ingest, poses, initial mesh,
    previews) once; returns the upstream record ({"name", "wall_s", ...})."""
    capture = paths.capture(scene)
    base = Variant(scene, "base")
    if not (capture / "capture.yaml").is_file():
        log.info("%s: synthesizing the capture (%s preset)", scene, preset)
        config = variant_overrides(base, preset, "", paths.cache, name=f"{scene}__capture")
        config["capture"] = ""
        wall, _ = runner(config, [f"captures/{scene}/capture.yaml"], paths.logs / f"{scene}__capture.log")
        log.info("%s: capture made in %.0f s", scene, wall)
    name = f"{scene}__upstream"
    config = variant_overrides(base, preset, capture, paths.cache, name=name)
    folder = paths.results / name
    record = _read_record(folder, config, needs="mesh/init.ply", keys=("cpu_s",))
    if record is not None:
        log.info("%s: upstream run done before (%.0f s), reused", scene, record["wall_s"])
        return record
    shutil.rmtree(folder, ignore_errors=True)
    log.info("%s: upstream run (ingest, poses, initial mesh, previews) starts", scene)
    wall, cpu = runner(config, [f"results/{name}/mesh/init.ply", f"results/{name}/previews"],
                       paths.logs / f"{name}.log")
    record = {"name": name, "wall_s": wall, "cpu_s": cpu, "config": config}
    _write_record(folder, record)
    log.info("%s: upstream run done in %.0f s (%.0f s CPU)", scene, wall, cpu)
    return record


def _figures(folder: Path) -> dict:
    """The FIGURES of a run's metrics.json (None where missing)."""
    metrics = json.loads((folder / "metrics.json").read_text())
    return {column: _dig(metrics, path) for column, (path, _, _) in FIGURES.items()}


def run_variant(variant: Variant, preset: str, paths: SweepPaths, runner: Callable, upstream: dict,
                repeat: int = 2, force: bool = False) -> dict:
    """Run one variant, again while its run compiled much (more than :data:`RECOMPILE_FRACTION` of its CPU
    time) up to ``repeat`` runs, timing the last (module docstring), unless a record with the same config
    exists. Returns its record: config, runs, run_s, run_cpu_s, cpu_s, upstream_s, upstream_cpu_s,
    new_programs, compiled, compile_s, the first run's cold_run_s, cold_cpu_s, cold_compiled (None for one
    run), and whether the runs gave the same figures (``deterministic``, None for one run)."""
    if repeat < 1:
        raise SweepError(f"repeat must be at least 1, got {repeat}")
    capture = paths.capture(variant.scene)
    config = variant_overrides(variant, preset, capture, paths.cache)
    folder = paths.results / variant.name
    record = None if force else _read_record(folder, config)
    if record is not None:
        log.info("%s: done before (%.0f s, %.0f s CPU), reused", variant.name, record["run_s"], record["cpu_s"])
        return record
    shared = not variant.upstream
    runs = []
    for attempt in range(1, repeat + 1):
        shutil.rmtree(folder, ignore_errors=True)
        if shared:
            link_upstream(paths.results / upstream["name"], folder)
        before = cache_entries(paths.cache)
        log.info("%s: run %d/%d starts (%s = %s)", variant.name, attempt, repeat, variant.key or "base",
                 value_label(variant.value))
        wall, cpu = runner(config, [], paths.logs / f"{variant.name}.{attempt}.log")
        if not (folder / "metrics.json").is_file():
            raise SweepError(f"{folder / 'metrics.json'} missing after the run of {variant.name}")
        compile_s, compiled = xla_compile_seconds(folder / "logs")
        runs.append({"run_s": wall, "run_cpu_s": cpu, "new_programs": cache_entries(paths.cache) - before,
                     "compiled": compiled, "compile_s": compile_s, "figures": _figures(folder)})
        log.info("%s: run %d/%d done in %.0f s, %.0f s CPU (%d XLA compilations, %.0f s)", variant.name, attempt,
                 repeat, wall, cpu, compiled, compile_s)
        if compile_s <= RECOMPILE_FRACTION * cpu:
            break
    last, first = runs[-1], runs[0]
    repeated = len(runs) > 1
    record = {"name": variant.name, "config": config, **{k: v for k, v in last.items() if k != "figures"},
              "upstream_s": upstream["wall_s"] if shared else 0.0,
              "upstream_cpu_s": upstream["cpu_s"] if shared else 0.0, "runs": len(runs),
              "cold_run_s": first["run_s"] if repeated else None,
              "cold_cpu_s": first["run_cpu_s"] if repeated else None,
              "cold_compiled": first["compiled"] if repeated else None,
              "deterministic": all(r["figures"] == first["figures"] for r in runs) if repeated else None}
    record["cpu_s"] = record["upstream_cpu_s"] + last["run_cpu_s"]
    if repeated and not record["deterministic"]:
        log.warning("%s: the repeated runs gave different figures: %s vs %s", variant.name, first["figures"],
                    last["figures"])
    _write_record(folder, record)
    log.info("%s: %.0f s, %.0f s CPU with the shared upstream (%.0f s, %.0f s CPU)", variant.name,
             record["upstream_s"] + last["run_s"], record["cpu_s"], record["upstream_s"], record["upstream_cpu_s"])
    return record


def run_sweep(scenes: list[str], preset: str, workdir: str | Path, runner: Callable | None = None,
              cores: int = 2, only: list[str] | None = None, repeat: int = 2, force: bool = False,
              factors: tuple[Factor, ...] = FACTORS) -> tuple[list[Variant], list[dict]]:
    """Run every planned variant (see :func:`plan_variants`; each ``repeat`` times, :func:`run_variant`) in
    ``workdir``; returns the variants and their records, in order. ``runner``: :class:`SnakemakeRunner` of
    ``workdir`` when None."""
    paths = SweepPaths(Path(workdir))
    paths.workdir.mkdir(parents=True, exist_ok=True)
    runner = runner or SnakemakeRunner(paths.workdir, cores)
    variants = plan_variants(scenes, preset, only, factors)
    log.info("sweep (%s preset): %d variants on %s", preset, len(variants), ", ".join(scenes))
    records, started = [], time.perf_counter()
    upstream = {}
    for k, variant in enumerate(variants, 1):
        if variant.scene not in upstream:
            upstream[variant.scene] = prepare_scene(variant.scene, preset, paths, runner)
        log.info("[%d/%d] %s", k, len(variants), variant.name)
        records.append(run_variant(variant, preset, paths, runner, upstream[variant.scene], repeat, force))
    log.info("sweep done in %.0f s", time.perf_counter() - started)
    return variants, records
