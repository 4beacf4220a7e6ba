"""The demo run whole over sensor-noise seeds and core counts (issue #49's first target; docs/reproducibility.md).

Each run is the built-in demo (``make demo``: config/config.yaml with its ``demo.overrides``) on a capture that
differs only in the sensor noise's seed (:func:`sellip.capture.synthetic.synthesize_capture` ``noise_seed``; the
orbit, the scene and every setting stay the demo's), with the workflow given one core (Snakemake ``--cores 1``,
the whole process tree pinned to one CPU, so XLA's intra-op pool has one thread) or two (``--cores 2``, unpinned).
Noise seed 0 with two cores is ``make demo`` itself: its figures must equal the README's demo row.

Public API::

    TARGETS                                       # issue #49: materials, eta within 2 %, normals within 1 deg
    demo_overrides(config_yaml) -> dict           # config/config.yaml's demo.overrides
    seed_run_config(capture, name, overrides, compilation_cache) -> dict
    seed_captures(out, noise_seeds, workers=2) -> {seed: capture folder}
    run_seed(out, capture, noise_seed, cores, snakefile, cpu=None, ...) -> dict   # one run's row (resumable)
    seed_row(results) -> dict                     # the figures and decisions of a finished run
    with_figures(row, results) -> dict            # a recorded row (seed, wall time, error) with seed_row's figures
    seed_summary(rows) -> dict                    # each target over the runs, and what missed it
    decision_agreement(rows) -> dict              # one scene's decisions over noise seeds (the suite's scenes)

The stability suite's scenes take their noise seed from ``sellip bench-stability --noise-seed`` (config
``demo.noise_seed``); ``benchmarks/suite_seeds.py`` runs them and :func:`decision_agreement` counts how often each
decision came out the same.
"""

from __future__ import annotations

import copy
import json
import shutil
import time
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

TARGETS = {"materials": 3, "eta_max_error_pct": 2.0, "normal_median_deg": 1.0}
"""Issue #49 on the demo: three materials at every iteration, every material's eta within 2 % and the normals'
median within 1 deg, in every run."""


def demo_overrides(config_yaml: str | Path) -> dict:
    """``demo.overrides`` of the workflow's config file (the settings the built-in demo runs with)."""
    import yaml

    config = yaml.safe_load(Path(config_yaml).read_text()) or {}
    return dict((config.get("demo") or {}).get("overrides") or {})


def seed_run_config(capture: str | Path, name: str, overrides: Mapping, compilation_cache: str | Path) -> dict:
    """The config override of one run: the demo's ``overrides`` given as settings (a capture that is not the built-in
    demo gets the defaults otherwise), the ``capture`` folder, the results ``name`` and the XLA compilation cache."""
    config = copy.deepcopy(dict(overrides))
    config.update(capture=str(Path(capture).resolve()), name=str(name))
    config.setdefault("fit", {})["compilation_cache"] = str(Path(compilation_cache).resolve())
    return config


def _synthesize(args: tuple[str, int]) -> str:
    from sellip.capture.synthetic import synthesize_capture

    folder, noise_seed = args
    if not (Path(folder) / "capture.yaml").is_file():
        synthesize_capture("demo", folder, noise_seed=noise_seed, progress=False)
    return folder


def seed_captures(out: str | Path, noise_seeds: Iterable[int], workers: int = 2) -> dict[int, Path]:
    """The demo capture with each of ``noise_seeds`` under ``out/captures/noise<seed>`` (made where missing, on
    ``workers`` processes; a finished capture is kept). Returns {seed: folder}."""
    seeds = sorted({int(s) for s in noise_seeds})
    folders = {s: Path(out) / "captures" / f"noise{s}" for s in seeds}
    with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
        list(pool.map(_synthesize, [(str(folders[s]), s) for s in seeds]))
    return folders


def run_name(noise_seed: int, cores: int) -> str:
    return f"noise{int(noise_seed)}_cores{int(cores)}"


def run_seed(out: str | Path, capture: str | Path, noise_seed: int, cores: int, snakefile: str | Path,
             cpu: int | None = None, timeout_s: float = 3600.0, config_yaml: str | Path | None = None) -> dict:
    """One run of the demo on ``capture`` with ``cores`` (``cpu``: pin the process tree to that CPU) in
    ``out/<run_name>`` and its row (:func:`seed_row`, plus ``noise_seed``, ``cores``, ``wall_s``). A run whose
    ``row.json`` exists is not run again (the benchmark resumes); a failed run's row has ``error``."""
    import yaml

    from sellip.bench.stability import run_failure, run_snakemake, snakemake_command, write_row

    name = run_name(noise_seed, cores)
    workdir = Path(out) / name
    row_path = workdir / "row.json"
    if row_path.is_file():
        return with_figures(json.loads(row_path.read_text()), workdir / "results" / name)
    if workdir.exists():
        shutil.rmtree(workdir)
    workdir.mkdir(parents=True)
    snakefile = Path(snakefile).resolve()
    overrides = demo_overrides(config_yaml or snakefile.parent / "config" / "config.yaml")
    override = workdir / "override.yaml"
    cache = Path(out) / f"jax_cache_cores{int(cores)}"
    override.write_text(yaml.safe_dump(seed_run_config(capture, name, overrides, cache), sort_keys=False))
    command = snakemake_command(snakefile, workdir, override, "--cores", str(int(cores)))
    started = time.perf_counter()
    error = run_failure(lambda: run_snakemake(command, workdir, workdir / "snakemake.log", timeout_s,
                                              cpus=None if cpu is None else {int(cpu)}), timeout_s)
    wall_s = time.perf_counter() - started
    row = {"noise_seed": int(noise_seed), "cores": int(cores), "wall_s": round(wall_s, 1)}
    if error is not None:
        row["error"] = error
    write_row(workdir, row)
    return with_figures(row, workdir / "results" / name)


def with_figures(row: dict, results: Path) -> dict:
    """``row`` (what the run recorded: seed, cores, wall time, error) with the figures read from its results now."""
    return row if "error" in row else {**row, **seed_row(results)}


def seed_row(results: str | Path) -> dict:
    """The figures of the finished run ``results`` (``results/<name>``): ``k`` (materials at each iteration,
    ``iter/<it>/clusters/clusters.json``) and ``merges`` (each iteration's merge rules in order,
    :func:`sellip.bench.reproducibility.merge_rule`), ``materials`` (rows of final/materials.csv), per true material
    its eta error (``eta_error_pct`` {label: %}, metrics.json), the normals' median (deg), held-out PSNR (dB),
    Chamfer (mm), the materials flagged fragile (``fragile``: cluster ids whose support is below 1), and per
    material cluster of materials.csv (keyed by its majority true material, ``gt_material``) the lobe ``model``,
    whether the 95 % eta interval holds the true eta (``covered``, per true material of metrics.json: False for one
    that has no cluster of its own) and the interval's width relative to eta (``ci_width_pct``)."""
    import pandas as pd

    from sellip.bench.reproducibility import merge_rule
    from sellip.fit.lobe_store import pass_clusters

    results = Path(results)
    metrics = json.loads((results / "metrics.json").read_text())
    support = metrics.get("material_support") or {}
    clusters = [record for _, record in pass_clusters(results)]
    table = pd.read_csv(results / "final" / "materials.csv")
    covered = (table["eta_ci_low"] <= table["gt_eta"]) & (table["gt_eta"] <= table["eta_ci_high"])
    width = 100 * (table["eta_ci_high"] - table["eta_ci_low"]) / table["eta"]
    per = (metrics.get("eta_per_material") or {}).get("materials") or {}
    # Each true material's cluster: the largest whose majority it is; a material that has none (merged into
    # another's cluster) has no model of its own and its interval is not its own: not covered.
    by_truth = {str(int(table["gt_material"].iloc[i])): i for i in np.argsort(table["vertices"].to_numpy())}
    by_truth = dict(sorted(by_truth.items(), key=lambda item: int(item[0])))
    return {"k": [int(c["k"]) for c in clusters],
            "merges": [[merge_rule(m["reason"]) for m in c.get("merges") or []] for c in clusters],
            "materials": len(table),
            "model": {m: int(table["model"].iloc[i]) for m, i in by_truth.items()},
            "covered": {m: m in by_truth and bool(covered.iloc[by_truth[m]]) for m in per},
            "ci_width_pct": {m: float(width.iloc[i]) for m, i in by_truth.items()},
            "eta_error_pct": {label: float(row["error_pct"]) for label, row in per.items()},
            "normal_median_deg": float(metrics["normal_error_deg"]["all"]["median"]),
            "psnr_held_out_db": float(metrics["psnr_held_out"]["mean_db"]),
            "chamfer_mm": float(metrics["geometry"]["chamfer_mm"]),
            "fragile": list(support.get("fragile") or [])}


def seed_summary(rows: Sequence[Mapping]) -> dict:
    """Each target of :data:`TARGETS` over the finished ``rows`` (:func:`run_seed`): how many runs meet it, the runs
    that miss it, and the spread (min, max) of every figure; failed runs are counted and named."""
    done = [r for r in rows if "error" not in r]
    failed = [f"noise{r['noise_seed']} cores{r['cores']}: {r['error']}" for r in rows if "error" in r]

    def label(r):
        return f"noise{r['noise_seed']} cores{r['cores']}"

    def spread(values):
        values = np.asarray(list(values), np.float64)
        return [float(values.min()), float(values.max())] if values.size else None

    want = TARGETS["materials"]
    three = [r for r in done if r["k"] and all(k == want for k in r["k"]) and r["materials"] == want]
    labels = sorted({m for r in done for m in r["eta_error_pct"]}, key=int)
    eta = {m: spread(r["eta_error_pct"][m] for r in done if m in r["eta_error_pct"]) for m in labels}
    eta_ok = [r for r in done if r["eta_error_pct"]
              and max(r["eta_error_pct"].values()) <= TARGETS["eta_max_error_pct"]]
    normals_ok = [r for r in done if r["normal_median_deg"] <= TARGETS["normal_median_deg"]]
    return {"runs": len(rows), "finished": len(done), "failed": failed,
            "materials_at_every_iteration": {"met": len(three), "missed": [label(r) for r in done if r not in three]},
            "eta_within": {"met": len(eta_ok), "missed": [label(r) for r in done if r not in eta_ok],
                           "error_pct_range": eta},
            "normals_within": {"met": len(normals_ok), "missed": [label(r) for r in done if r not in normals_ok],
                               "median_deg_range": spread(r["normal_median_deg"] for r in done)},
            "psnr_held_out_db_range": spread(r["psnr_held_out_db"] for r in done),
            "chamfer_mm_range": spread(r["chamfer_mm"] for r in done),
            "fragile_runs": [label(r) for r in done if r["fragile"]],
            "models": {m: dict(sorted(Counter(r["model"][m] for r in done if m in r["model"]).items()))
                       for m in labels},
            "merges": dict(sorted(Counter(" | ".join(" ".join(it) or "-" for it in r["merges"])
                                          for r in done).items())),
            "covered": {"materials": sum(len(r["covered"]) for r in done),
                        "covered": sum(sum(r["covered"].values()) for r in done),
                        "median_width_pct": float(np.median([w for r in done for w in r["ci_width_pct"].values()]))
                        if done else None},
            "wall_s_by_cores": {int(c): spread(r["wall_s"] for r in done if r["cores"] == c)
                                for c in sorted({r["cores"] for r in done})}}



def decision_agreement(rows: Sequence[Mapping]) -> dict:
    """How often one scene's discrete decisions came out the same over finished ``rows`` (:func:`seed_row` each, with
    ``noise_seed``): the decision is the number of materials and the lobe model of each true material's cluster
    (``model``; a material merged into another's cluster has none). Returns {runs, decision: the most common one,
    agree: in how many runs, others: {decision: [seeds]}, k_at_every_iteration: {K sequence: count},
    fragile: {seed: cluster ids flagged}, eta_error_pct: {material: [min, max]}, covered: [covered, materials]}."""
    done = [r for r in rows if "error" not in r]

    def key(r):
        return f"{r['materials']} materials; models " + " ".join(f"{m}:{r['model'].get(m, '-')}"
                                                                 for m in sorted(r["eta_error_pct"], key=int))

    counts = Counter(key(r) for r in done)
    decision, agree = counts.most_common(1)[0] if counts else (None, 0)
    others: dict[str, list[int]] = {}
    for r in done:
        if key(r) != decision:
            others.setdefault(key(r), []).append(int(r["noise_seed"]))
    labels = sorted({m for r in done for m in r["eta_error_pct"]}, key=int)
    errors = {m: [r["eta_error_pct"][m] for r in done if m in r["eta_error_pct"]] for m in labels}
    return {"runs": len(rows), "finished": len(done), "decision": decision, "agree": agree, "others": others,
            "k_at_every_iteration": {" ".join(map(str, k)): n for k, n in
                                     sorted(Counter(tuple(r["k"]) for r in done).items())},
            "fragile": {int(r["noise_seed"]): r["fragile"] for r in done if r["fragile"]},
            "eta_error_pct": {m: [float(min(v)), float(max(v))] for m, v in errors.items() if v},
            "covered": [sum(sum(r["covered"].values()) for r in done), sum(len(r["covered"]) for r in done)]}
