"""How each stage's cost grows with the capture (issue #20): per-job costs of measured workflow runs, a cost model
fitted to them, and the time it predicts for a capture that was not run (docs/speed.md, "Scale").

Public API::

    RULE_TERMS, ITERATED_RULES, SHARDED_RULES
    CaptureSize(views, pixels, vertices); size_terms(size) -> {term: value}
    job_costs(benchmarks_dir) -> DataFrame    # one row per job: rule, iteration, wall_s, cpu_s, max_rss_mb
    rule_costs(jobs, iterations) -> DataFrame # per rule: once_s, per_iteration_s, max_rss_mb, jobs
    fit_cost_model(runs) -> DataFrame         # per rule: term, a + b * term for once_s, per_iteration_s, max_rss_mb
    predict(model, size, iterations, cores, shards) -> DataFrame   # per rule: job time and critical-path time

A run's iterations are 0 .. I-1 and the final pass I (docs/design.md §4). Iteration 0 and the final pass compile what a
later iteration loads from the cache, and the final pass has no geometry update, so a rule's cost is split into
``once_s`` (its one-off jobs, iteration 0 and the final pass) and ``per_iteration_s`` (the mean of the iterations
1 .. I-1): a run of I iterations costs ``once_s + (I - 1) * per_iteration_s``.

The model is one term per rule, the product of capture sizes its work grows with (:data:`RULE_TERMS`: views V
fitted, raw pixels P per view, model vertices N), fitted as ``a + b * term`` by least squares over the measured
runs. The workflow's wall time is predicted as its critical path: the rules run one after another (each iteration
depends on the last), the jobs of a sharded rule side by side on ``min(shards, cores)`` cores
(:func:`predict`); on 2 cores the previews (``plot_hdr_previews``) share the cores with the chain and count in
full.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

RULE_TERMS = {
    "linearize_frames": "VP",
    "merge_hdr": "VP",
    "plot_hdr_previews": "VP",
    "run_sfm": "V",
    "init_mesh": "VP",  # the visual hull carves every view's silhouette
    "gather_observations": "VN",  # a ray per vertex and view
    "fit_pbrdf": "VN",  # a vertex's residuals have a row per view
    "gather_fit": "N",
    "cluster_lobes": "N",  # the pooled samples are capped (augment.max_samples); the clustering grows with N
    "refine_geometry": "VP",  # renders the model's silhouette in every fitted view
    "finalize_model": "N",
    "render_outputs": "P",
    "evaluate_model": "P",
}
"""The size term each rule's cost grows with: V views, P raw pixels per view, N vertices, and their products."""

ITERATED_RULES = ("gather_observations", "fit_pbrdf", "gather_fit", "cluster_lobes", "refine_geometry")
"""Rules with jobs per iteration (their benchmark paths start with the iteration: ``fit_pbrdf/3/...``)."""

SHARDED_RULES = ("fit_pbrdf",)
"""Rules whose jobs of one iteration run side by side (one per vertex shard)."""


class CaptureSize(NamedTuple):
    """views fitted (V), raw pixels per view (P = width x height of the sensor), model vertices (N)."""

    views: int
    pixels: int
    vertices: int


def size_terms(size: CaptureSize) -> dict[str, float]:
    """The cost terms of :data:`RULE_TERMS` for one capture size."""
    v, p, n = float(size.views), float(size.pixels), float(size.vertices)
    return {"V": v, "P": p, "N": n, "VP": v * p, "VN": v * n}


def job_costs(benchmarks_dir: str | Path):
    """One row per job of a workflow run from its Snakemake benchmark files (``results/NAME/benchmarks``):
    rule, iteration (int, or -1 for a rule without iterations), wall_s, cpu_s (user + system), max_rss_mb."""
    import pandas as pd

    from sellip.timing import read_benchmark

    rows = []
    benchmarks_dir = Path(benchmarks_dir)
    for path in sorted(benchmarks_dir.rglob("*.tsv")):
        relative = path.relative_to(benchmarks_dir)
        rule = relative.parts[0].removesuffix(".tsv")
        iteration = -1
        if rule in ITERATED_RULES:
            token = relative.parts[1].removesuffix(".tsv") if len(relative.parts) > 1 else ""
            if not token.isdigit():
                raise ValueError(f"{path}: a {rule} benchmark outside an iteration folder ({relative})")
            iteration = int(token)
        rows.append({"rule": rule, "iteration": iteration, **read_benchmark(path),
                     "job": str(relative.with_suffix(""))})
    if not rows:
        raise ValueError(f"no benchmark files under {benchmarks_dir}")
    return pd.DataFrame(rows)


def rule_costs(jobs, iterations: int):
    """Per rule of one run of ``iterations`` iterations (jobs from :func:`job_costs`): ``jobs``, ``total_s`` (the
    summed job wall time), ``per_iteration_s`` (the mean over iterations 1 .. I-1 of each iteration's summed job
    time; 0 for a rule without iterations), ``once_s`` = total_s - (I - 1) * per_iteration_s, ``cpu_s`` and
    ``max_rss_mb`` (the largest job's). Needs I >= 2 for an iterated rule."""
    import pandas as pd

    rows = []
    for rule, group in jobs.groupby("rule", sort=False):
        total = float(group["wall_s"].sum())
        per_iteration = 0.0
        if rule in ITERATED_RULES:
            warm = group[(group["iteration"] >= 1) & (group["iteration"] < iterations)]
            if iterations < 2 or warm.empty:
                raise ValueError(f"{rule}: no jobs of iterations 1 .. {iterations - 1} to measure an iteration by "
                                 "(run at least 2 iterations)")
            per_iteration = float(warm.groupby("iteration")["wall_s"].sum().mean())
        rows.append({"rule": rule, "jobs": len(group), "total_s": total, "per_iteration_s": per_iteration,
                     "once_s": total - (iterations - 1) * per_iteration,
                     "cpu_s": float(group["cpu_s"].sum()), "max_rss_mb": float(group["max_rss_mb"].max())})
    return pd.DataFrame(rows).set_index("rule")


def fit_cost_model(runs: list[tuple[CaptureSize, object]]):
    """Per rule (those of :data:`RULE_TERMS` in every run): its term and least-squares ``a + b * term`` of
    ``once_s``, ``per_iteration_s`` and ``max_rss_mb`` over ``runs`` [(size, :func:`rule_costs` frame)], with the
    RMS residual of each (s or MB) and the number of runs. One run gives b = value / term, a = 0 (a proportional
    model); two or more fit both."""
    import pandas as pd

    rules = set.intersection(*(set(costs.index) for _, costs in runs)) & set(RULE_TERMS)
    rows = []
    for rule in sorted(rules, key=list(RULE_TERMS).index):
        term = RULE_TERMS[rule]
        x = np.array([size_terms(size)[term] for size, _ in runs])
        row = {"rule": rule, "term": term, "runs": len(runs)}
        for column in ("once_s", "per_iteration_s", "max_rss_mb"):
            y = np.array([float(costs.loc[rule, column]) for _, costs in runs])
            a, b = _line(x, y)
            row[f"{column}_a"], row[f"{column}_b"] = a, b
            row[f"{column}_rms"] = float(np.sqrt(np.mean((a + b * x - y) ** 2)))
        rows.append(row)
    return pd.DataFrame(rows).set_index("rule")


def _line(x, y) -> tuple[float, float]:
    if len(x) == 1 or np.ptp(x) == 0:
        return 0.0, float(np.mean(y) / np.mean(x))
    b, a = np.polyfit(x, y, 1)
    return float(a), float(b)


def predict(model, size: CaptureSize, iterations: int, cores: int = 2, shards: int = 2, measured_shards: int = 2):
    """Per rule at ``size``: ``job_s``, its summed job time over ``iterations`` iterations (a sharded rule's intercept,
    what every job pays whatever its size, times shards / measured_shards); ``critical_s``, its share of the wall
    time (a sharded rule's jobs side by side on min(shards, cores) cores, every other rule's in full);
    ``max_rss_mb``, its largest job's memory (a sharded rule's at the vertices of one of ``shards`` shards, the
    model having been measured with ``measured_shards``). ``attrs["wall_s"]``: the run's predicted wall time, the
    sum of ``critical_s``."""
    import pandas as pd

    terms = size_terms(size)
    rows = []
    for rule, m in model.iterrows():
        x = terms[m["term"]]
        sharded = rule in SHARDED_RULES
        jobs = shards / measured_shards if sharded else 1.0  # the intercept is per job: start-up, imports, loading
        job = max(m["once_s_a"] * jobs + m["once_s_b"] * x, 0.0) + (iterations - 1) * max(
            m["per_iteration_s_a"] * jobs + m["per_iteration_s_b"] * x, 0.0)
        memory_x = x * measured_shards / shards if sharded else x
        rows.append({"rule": rule, "term": m["term"], "job_s": job,
                     "critical_s": job / min(shards, cores) if sharded else job,
                     "max_rss_mb": max(m["max_rss_mb_a"] + m["max_rss_mb_b"] * memory_x, 0.0)})
    frame = pd.DataFrame(rows).set_index("rule")
    frame.attrs["wall_s"] = float(frame["critical_s"].sum())
    return frame
