"""The speed-accuracy sweep (sellip.bench.sweep, sellip bench-sweep): Pareto front, plan, tables, the paper's
comparisons, the upstream reuse (checked with a real snakemake dry run), and the orchestration with a
fake runner. The real sweep is docs/benchmarks.md's command, not a test."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from sellip.bench import sweep, sweep_plan, sweep_report, sweep_tables
from sellip.capture.scenes import SPHERE_IOR_ETAS
from sellip.fit.observe_mesh import spread_subset
from sellip.model.pbrdf import PBRDFParams
from sellip.model.render import ParamMesh
from sellip.report.outputs import save_figure

REPO = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- Pareto front


def test_pareto_front_keeps_exactly_the_non_dominated_points():
    cost = [10, 20, 30, 15, 40, 25]
    loss = [5.0, 3.0, 1.0, 6.0, 1.0, 3.0]
    # 15/6 is dominated by 10/5; 40/1 by 30/1; 25/3 by 20/3.
    assert sweep_tables.pareto_front(cost, loss).tolist() == [True, True, True, False, False, False]


def test_pareto_front_ties_nans_and_shapes():
    # Equal points do not dominate each other; a NaN is never on the front and dominates nothing.
    assert sweep_tables.pareto_front([1, 1, 2], [2, 2, 1]).tolist() == [True, True, True]
    assert sweep_tables.pareto_front([1, np.nan, 3], [5, 0, 4]).tolist() == [True, False, True]
    assert sweep_tables.pareto_front([0.5, 3], [np.nan, 1]).tolist() == [False, True]
    assert sweep_tables.pareto_front([], []).tolist() == []
    with pytest.raises(ValueError, match="one length"):
        sweep_tables.pareto_front([1, 2], [1])


def test_pareto_front_matches_brute_force_on_random_points():
    rng = np.random.default_rng(4)
    cost, loss = rng.integers(0, 6, 40).astype(float), rng.integers(0, 6, 40).astype(float)
    expected = [not any(cost[j] <= cost[i] and loss[j] <= loss[i] and (cost[j] < cost[i] or loss[j] < loss[i])
                        for j in range(40)) for i in range(40)]
    assert sweep_tables.pareto_front(cost, loss).tolist() == expected


# --------------------------------------------------------------------------- plan and configs


def _defaults():
    return yaml.safe_load((REPO / "config" / "config.yaml").read_text())


def test_plan_has_the_base_first_then_one_factor_at_a_time():
    variants = sweep_plan.plan_variants(["demo", "tiny"], "quick")
    per_scene = len(variants) // 2
    assert [v.factor for v in variants[:1]] == ["base"] and variants[per_scene].factor == "base"
    assert [v.scene for v in variants] == ["demo"] * per_scene + ["tiny"] * per_scene
    expected = sum(len(f.values_for("quick")) for f in sweep_plan.FACTORS)
    assert per_scene == 1 + expected
    # Both presets narrow sphere_ior to its base and model selection off (SCENE_FACTORS).
    for preset in ("quick", "full"):
        ior = [v.name for v in sweep_plan.plan_variants(["sphere_ior"], preset)]
        assert ior == ["sphere_ior__base", "sphere_ior__model_selection-off"]
    variants = sweep_plan.plan_variants(["demo"], "quick")
    names = [v.name for v in variants]
    assert len(set(names)) == len(names)
    assert all(re.fullmatch(r"[A-Za-z0-9_.-]+", n) for n in names)  # the Snakefile's {name} constraint
    labels = {v.name: v.label for v in variants}
    assert labels["demo__sigma_ss-0.9"] == "σss 0.9" and labels["demo__augment-off"] == "aug off"
    assert labels["demo__iterations-3"] == "3 it" and labels["demo__model_selection-off"] == "selection off"
    assert labels["demo__dtype-float64"] == "float64" and labels["demo__sigma_ss-1"] == "σss 1"
    full = {v.name: v.label for v in sweep_plan.plan_variants(["demo"], "full")}
    assert list(full) == ["demo__base", "demo__iterations-2", "demo__iterations-4", "demo__views-24",
                          "demo__augment-off", "demo__sigma_ss-0.9", "demo__model_selection-off", "demo__lm_cap-10"]


def test_the_full_preset_is_the_demos_own_settings():
    """The full preset's base is what `make demo` runs (config demo and demo.overrides), but for the rendered
    views: a sweep run takes the capture as a folder, so the demo's overrides would not apply by themselves."""
    defaults = _defaults()
    demo = sweep_plan.merge(defaults, defaults["demo"]["overrides"])

    def leaves(node, prefix=""):
        for key, value in node.items():
            if isinstance(value, dict):
                yield from leaves(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}", value

    full = dict(leaves(sweep_plan.PRESETS["full"]))
    assert {key: value for key, value in leaves(defaults["demo"]["overrides"])
            if key != "evaluate.render_views"}.items() <= full.items()

    def value_of(key):
        try:
            return sweep_plan.get_key(demo, key)
        except KeyError:  # config.yaml leaves it to its settings record's declaration
            return sweep_plan.declared_default(key)

    for key, value in full.items():
        if key != "evaluate.render_views":
            assert value_of(key) == value, key


def test_plan_skips_the_base_value_and_checks_names():
    extra = sweep_plan.FACTORS + (sweep_plan.Factor("lm_again", "fit.settings.max_iterations", (30, 7), "LM {}"),)
    variants = sweep_plan.plan_variants(["tiny"], "quick", only=["lm_again"], factors=extra)
    # 30 is the base's own value (config.yaml): only 7 runs; --only keeps the base.
    assert [(v.factor, v.value) for v in variants] == [("base", None), ("lm_again", 7)]
    with pytest.raises(sweep_plan.SweepError, match="unknown factor"):
        sweep_plan.plan_variants(["tiny"], "quick", only=["nope"])
    with pytest.raises(sweep_plan.SweepError, match="unknown preset"):
        sweep_plan.plan_variants(["tiny"], "huge")


def test_variant_config_sets_one_key_over_the_base_and_validates(tmp_path):
    variant = next(v for v in sweep_plan.plan_variants(["tiny"], "full") if v.factor == "sigma_ss" and v.value == 0.9)
    before = json.dumps(sweep_plan.PRESETS)
    config = sweep_plan.variant_overrides(variant, "quick", tmp_path / "cap", tmp_path / "cache")  # quick base
    assert json.dumps(sweep_plan.PRESETS) == before  # the presets are not mutated
    assert config["fit"]["settings"] == {"min_views": 6, "sigma_ss_fixed": 0.9}
    assert config["name"] == "tiny__sigma_ss-0.9" and config["demo"]["scene"] == "tiny"
    assert Path(config["capture"]).is_absolute() and config["fit"]["compilation_cache"] == str(tmp_path / "cache")
    assert config["iterations"] == 2 and config["demo"]["views"] == 24
    # The merged config passes the workflow's schema.
    from snakemake.utils import validate

    merged = sweep_plan.merge(_defaults(), config)
    validate(merged, str(REPO / "config" / "config.schema.yaml"))
    for preset in ("quick", "full"):
        views = next(v for v in sweep_plan.plan_variants(["demo"], preset) if v.factor == "views")
        validate(sweep_plan.merge(_defaults(), sweep_plan.variant_overrides(views, preset, tmp_path, tmp_path)),
                 str(REPO / "config" / "config.schema.yaml"))


def test_set_key_and_merge():
    config = {"a": {"b": 1, "c": {"d": 2}}, "e": 3}
    out = sweep_plan.set_key(config, "a.c.d", 5)
    assert out["a"]["c"]["d"] == 5 and config["a"]["c"]["d"] == 2
    assert sweep_plan.set_key({}, "x.y", None) == {"x": {"y": None}}
    with pytest.raises(ValueError, match="not a mapping"):
        sweep_plan.set_key({"e": 3}, "e.f", 1)
    assert sweep_plan.merge(config, {"a": {"c": {"z": 1}}, "e": 4}) == {"a": {"b": 1, "c": {"d": 2, "z": 1}}, "e": 4}
    assert sweep_plan.get_key(config, "a.c.d") == 2
    with pytest.raises(KeyError):
        sweep_plan.get_key(config, "a.q")


def test_spread_subset_is_even_distinct_and_starts_at_the_first_view():
    assert spread_subset(22, 12).tolist() == [0, 1, 3, 5, 7, 9, 11, 12, 14, 16, 18, 20]
    assert spread_subset(32, 8).tolist() == [0, 4, 8, 12, 16, 20, 24, 28]
    assert spread_subset(5, None).tolist() == [0, 1, 2, 3, 4] and spread_subset(5, 9).tolist() == [0, 1, 2, 3, 4]
    picked = spread_subset(97, 13)
    assert len(set(picked)) == 13 and np.all(np.diff(picked) >= 7) and np.all(np.diff(picked) <= 8)
    with pytest.raises(ValueError):
        spread_subset(5, 0)


# --------------------------------------------------------------------------- rows, tables, chart


def _metrics(normal=10.0, eta=15.0, psnr=20.0, fit=30.0):
    return {"normal_error_deg": {"all": {"mean": normal + 1, "median": normal}},
            "eta_relative_error_pct": {"mean": eta + 2, "median": eta},
            "eta_per_material": {"mean_error_pct": eta, "max_error_pct": 2 * eta},
            "rho_d_relative_rmse": {"relative_rmse": 0.2}, "sigma_s_abs_error": {"median": 0.1},
            "geometry": {"chamfer_mm": 0.9}, "psnr_held_out": {"mean_db": psnr}, "psnr_new_light": None,
            "vertices": {"model": 3000, "confident": 2500},
            "timings": {"total_s": 100.0, "rules": {"fit_pbrdf": {"s": fit, "jobs": 12},
                                                    "cluster_lobes": {"s": 9.0, "jobs": 3}}}}


def _table(specs):
    """sweep table from (scene, factor, value, run_s, normal, eta, psnr, fit)."""
    rows = []
    for scene, factor, value, run_s, normal, eta, psnr, fit in specs:
        variant = sweep_plan.Variant(scene, factor, value, factor if factor == "base" else f"{factor} {value}",
                                None if factor == "base" else "k")
        rows.append(sweep_tables.sweep_row(variant, _metrics(normal, eta, psnr, fit),
                                    {"run_s": run_s, "upstream_s": 10.0, "new_programs": 0, "cpu_s": run_s}, "quick",
                                    {"fit_pbrdf": fit, "merge_hdr": 1.0, "other": run_s - fit - 1.0}))
    return sweep_tables.sweep_table(rows)


def test_sweep_row_flattens_metrics_and_adds_the_shared_upstream_time():
    variant = sweep_plan.Variant("demo", "sigma_ss", 1.0, "σss 1", "fit.settings.sigma_ss_fixed")
    record = {"run_s": 50.0, "upstream_s": 12.5, "cold_run_s": 80.0, "new_programs": 2, "cpu_s": 44.0,
              "compile_s": 3.5, "compiled": 9}
    row = sweep_tables.sweep_row(variant, _metrics(), record, "quick", {"fit_pbrdf": 20.0, "init_mesh": 4.5})
    assert list(row) == list(sweep_tables.SWEEP_COLUMNS)
    assert row["cpu_s"] == 44.0 and row["fit_cpu_s"] == 20.0 and row["compiled"] == 9 and row["compile_s"] == 3.5
    assert np.isnan(sweep_tables.sweep_row(variant, _metrics(), {"run_s": 1.0}, "quick")["cpu_s"])
    assert row["total_s"] == 62.5 and row["fit_s"] == 30.0 and row["cluster_s"] == 9.0 and row["jobs_s"] == 100.0
    assert row["normal_median_deg"] == 10.0 and row["eta_mean_pct"] == 17.0 and row["psnr_held_out_db"] == 20.0
    assert np.isnan(row["psnr_new_light_db"]) and np.isnan(row["refine_s"])
    assert row["value"] == "1" and row["name"] == "demo__sigma_ss-1"
    table = sweep_tables.sweep_table([row])
    assert len(table) == 1
    with pytest.raises(ValueError, match="name"):
        sweep_tables.sweep_table([row, row])  # duplicate variant
    with pytest.raises(ValueError, match="run_s"):
        sweep_tables.sweep_table([{**row, "run_s": -1.0}])


def test_job_cpu_seconds_sums_the_benchmark_files_per_rule(tmp_path):
    header = "s\th:m:s\tmax_rss\tcpu_time\n"
    _touch(tmp_path / "fit_pbrdf" / "0" / "fit" / "1-of-2.tsv", header + "10.0\t0:00:10\t5\t7.5\n")
    _touch(tmp_path / "fit_pbrdf" / "1" / "refit" / "2-of-2.tsv", header + "9.0\t0:00:09\t5\t2.0\n4\t0\t5\t4.0\n")
    _touch(tmp_path / "merge_hdr.tsv", header + "1.0\t0:00:01\t5\t0.5\n")
    _touch(tmp_path / "run_sfm.tsv", "s\th:m:s\n1.0\t0:00:01\n")  # no cpu_time column: 0
    assert sweep_tables.job_cpu_seconds(tmp_path) == {"fit_pbrdf": 10.5, "merge_hdr": 0.5, "run_sfm": 0.0}


def test_augmentation_and_sigma_ss_tables_pair_the_right_rows():
    table = _table([("demo", "base", None, 100.0, 10.0, 15.0, 20.0, 40.0),
                    ("demo", "augment", False, 60.0, 10.5, 15.0, 14.0, 40.0),
                    ("demo", "sigma_ss", 0.9, 80.0, 10.1, 16.0, 20.5, 30.0),
                    ("demo", "sigma_ss", 1.0, 81.0, 10.2, 16.5, 19.5, 10.0),
                    ("tiny", "sigma_ss", 0.9, 80.0, 10.1, 16.0, 20.5, 30.0)])  # no tiny base: left out
    aug = sweep_tables.augmentation_table(table)
    assert aug[["augmentation", "psnr_held_out_db", "paper_psnr_db"]].values.tolist() == [["on", 20.0, 34.0],
                                                                                          ["off", 14.0, 30.8]]
    sigma = sweep_tables.sigma_ss_table(table)
    assert sigma["sigma_ss"].tolist() == ["free", "0.9", "1"]
    np.testing.assert_allclose(sigma["fit_saving_pct"], [0.0, 25.0, 75.0])
    np.testing.assert_allclose(sigma["cpu_saving_pct"], [0.0, 20.0, 19.0])
    np.testing.assert_allclose(sigma["paper_psnr_db"], [34.0, 34.2, 33.9])
    text = sweep_tables.markdown_table(sigma, {"sigma_ss": ("σss", ""), "fit_saving_pct": ("saved %", ".0f"),
                                        "eta_median_pct": ("η", ".1f")})
    assert text.splitlines()[:3] == ["| σss | saved % | η |", "|---|---|---|", "| free | 0 | 15.0 |"]
    assert "| – |" in sweep_tables.markdown_table(pd.DataFrame({"x": [np.nan]}), {"x": ("x", ".1f")})


def test_model_selection_table_pairs_on_and_off_and_shows_the_models():
    table = _table([("sphere_ior", "base", None, 80.0, 10.0, 15.0, 20.0, 30.0),
                    ("sphere_ior", "model_selection", False, 100.0, 10.0, 15.5, 19.9, 40.0),
                    ("demo", "base", None, 80.0, 10.0, 15.0, 20.0, 30.0)])  # no demo "off" run: left out
    models = {"sphere_ior__base": {1: 750, 3: 250}, "sphere_ior__model_selection-off": {3: 1000}}
    frame = sweep_tables.model_selection_table(table, models)
    assert frame["selection"].tolist() == ["on", "off"] and frame["scene"].tolist() == ["sphere_ior"] * 2
    assert frame["models"].tolist() == ["1: 75 %, 3: 25 %", "3: 100 %"]
    np.testing.assert_allclose(frame["cpu_saving_pct"], [20.0, 0.0])
    np.testing.assert_allclose(frame["psnr_held_out_db"], [20.0, 19.9])
    assert sweep_tables.model_selection_table(table.iloc[:1], models).empty


def test_front_marks_and_chart(tmp_path):
    table = _table([("demo", "base", None, 100.0, 10.0, 15.0, 20.0, 40.0),
                    ("demo", "iterations", 1, 50.0, 12.0, 14.0, 18.0, 20.0),
                    ("demo", "iterations", 4, 200.0, 11.0, 16.0, 19.0, 80.0),  # dominated by the base in all
                    ("sphere_ior", "base", None, 90.0, 5.0, 5.0, 25.0, 40.0)])
    assert sweep_tables.front_marks(table) == ["1 3", "1 2 3", "", "1 2 3"]
    path = save_figure(sweep_tables.sweep_figure(table), tmp_path / "img" / "sweep.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not list(path.parent.glob(".*tmp*"))
    csv = sweep_report.write_csv(table, tmp_path / "sweep.csv")
    back = sweep_tables.sweep_table(pd.read_csv(csv, dtype={"value": str}).to_dict("records"))
    assert back["name"].tolist() == table["name"].tolist() and back["total_s"].tolist() == table["total_s"].tolist()


def test_tables_markdown_has_every_section():
    from sellip.bench.sweep_report import tables_markdown

    table = _table([("sphere_ior", "base", None, 100.0, 10.0, 15.0, 20.0, 40.0),
                    ("sphere_ior", "augment", False, 60.0, 10.5, 15.0, 14.0, 40.0),
                    ("sphere_ior", "sigma_ss", 1.0, 81.0, 10.2, 16.5, 19.5, 10.0),
                    ("sphere_ior", "model_selection", False, 90.0, 10.0, 15.0, 20.0, 45.0)])
    ior = pd.DataFrame([{"material": n, "eta_true": m, "vertices": 5, "eta_ours": m, "error_pct": 1.0,
                         "vertex_error_pct": 2.0, "eta_paper": p, "paper_error_pct": e}
                        for n, m, p, e in sweep_tables.PAPER_TABLE1])
    text = tables_markdown(table, ior, "quick",
                           {"sphere_ior__base": {1: 10}, "sphere_ior__model_selection-off": {3: 10}})
    for heading in ("## sphere_ior", "## Refractive index", "## Augmentation on/off", "## σss free vs fixed",
                    "## Model selection on/off"):
        assert heading in text
    assert "| average |" in text and "| 1.49 |" in text


# --------------------------------------------------------------------------- IOR table


def _sphere(eta, material):
    n = len(eta)
    direction = np.random.default_rng(1).normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    params = PBRDFParams(eta=np.asarray(eta, float), rho_d=np.full((n, 3), 0.2), rho_s=np.ones(n),
                         sigma_s=np.full(n, 0.2), rho_ss=np.zeros((n, 3)), sigma_ss=np.full(n, 0.5))
    return ParamMesh(vertices=0.06 * direction, faces=np.zeros((0, 3), np.int64), normals=direction, params=params,
                     material=None if material is None else np.asarray(material))


def test_ior_table_takes_the_median_of_the_confident_vertices_of_each_material():
    assert tuple(m for _, m, _, _ in sweep_tables.PAPER_TABLE1) == SPHERE_IOR_ETAS  # the scene's wedges, in order
    material = np.arange(700) % 7
    truth = _sphere(np.asarray(SPHERE_IOR_ETAS)[material], material)
    eta = truth.params.eta * (1 + 0.01 * (material == 2))  # material 2 fitted 1 % high
    eta[material == 4] = np.where(np.arange(100) % 2, 2.295 * 1.05, 9.0)  # half wild, half 5 % high
    confident = ~((material == 4) & (np.arange(700) // 7 % 2 == 0))  # ... and the wild half not confident
    model = ParamMesh(truth.vertices + 1e-6, truth.faces, truth.normals, truth.params._replace(eta=eta))
    table = sweep_tables.ior_table(model, truth, confident)
    assert table["material"].tolist() == [m for m, _, _, _ in sweep_tables.PAPER_TABLE1]
    np.testing.assert_allclose(table["error_pct"], [0, 0, 1, 0, 5, 0, 0], atol=1e-9)
    np.testing.assert_allclose(table["eta_ours"][2], 1.503 * 1.01)
    assert table["vertices"].tolist() == [100, 100, 100, 100, 50, 100, 100]
    assert table["paper_error_pct"].tolist() == [0.10, 0.61, 1.80, 0.34, 2.22, 2.61, 2.77]
    with pytest.raises(ValueError, match="no per-vertex material"):
        sweep_tables.ior_table(model, _sphere(truth.params.eta, None), confident)


# --------------------------------------------------------------------------- upstream reuse


def _touch(path: Path, text: str = "x", mtime: float = 1.7e9) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    os.utime(path, (mtime, mtime))


def _fake_upstream(results: Path, mtime: float = 1.7e9) -> None:
    for k, name in enumerate(["hdr.zarr/zarr.json", "hdr.zarr/.snakemake_timestamp", "cameras.csv",
                              "sfm/report.json", "sfm/.snakemake_timestamp", "mesh/init.ply", "mesh/init.json",
                              "previews/.snakemake_timestamp", "previews/v000_s0.png"]):
        _touch(results / name, mtime=mtime + 10 * k)
    for rule in sweep.UPSTREAM_RULES:  # written when a job ends: newer than the outputs (else they look stale)
        _touch(results / "benchmarks" / f"{rule}.tsv", "s\th:m:s\n1.5\t0:00:01\n", mtime + 200)
    for folder in ("hdr.zarr", "sfm", "mesh", "previews"):  # as written: each folder as new as its newest file
        newest = max(p.stat().st_mtime for p in (results / folder).iterdir())
        os.utime(results / folder, (newest, newest))


def test_link_upstream_keeps_every_mtime_and_shares_the_files(tmp_path):
    source, target = tmp_path / "a", tmp_path / "b"
    _fake_upstream(source)
    sweep.link_upstream(source, target)
    files = [p for p in source.rglob("*") if p.is_file()]
    assert len(files) == 9 + len(sweep.UPSTREAM_RULES)
    for path in files + [source / name for name in sweep.UPSTREAM_OUTPUTS]:  # every file, every output folder
        twin = target / path.relative_to(source)
        assert twin.exists(), twin
        assert twin.stat().st_mtime == path.stat().st_mtime, twin
        if path.is_file():
            assert os.path.samefile(path, twin)
    (source / "cameras.csv").unlink()
    with pytest.raises(sweep_plan.SweepError, match="cameras.csv is missing"):
        sweep.link_upstream(source, tmp_path / "c")


def _dry_run(workdir: Path, config: dict, targets=()) -> dict[str, int]:
    """Job counts of the sweep's own snakemake command with -n."""
    log_path = workdir / "logs" / "dry.log"
    sweep.SnakemakeRunner(workdir, cores=2, extra=("-n",))(config, list(targets), log_path)
    return {line.split()[0]: int(line.split()[1]) for line in log_path.read_text().splitlines()
            if len(line.split()) == 2 and line.split()[1].isdigit()}


@pytest.mark.slow
def test_linked_upstream_is_up_to_date_for_snakemake(tmp_path):
    """With the upstream outputs linked in, the real Snakefile plans only the loop and the evaluation."""
    capture = tmp_path / "captures" / "tiny"
    for name in ("capture.yaml", "frames.csv", "poses.csv"):
        _touch(capture / name, mtime=1.6e9)
    variant = sweep_plan.Variant("tiny", "augment", False, "aug off", "augment.enabled", False)
    config = sweep_plan.variant_overrides(variant, "quick", capture, tmp_path / "cache")
    results = tmp_path / "results"
    # Controls: with nothing linked, the upstream rules would run; the upstream targets stop at the mesh.
    assert _dry_run(tmp_path, config)["init_mesh"] == 1
    upstream = _dry_run(tmp_path, config, [f"results/{variant.name}/mesh/init.ply"])
    assert upstream["init_mesh"] == 1 and "fit_pbrdf" not in upstream
    _fake_upstream(results / "tiny__upstream")
    sweep.link_upstream(results / "tiny__upstream", results / variant.name)
    counts = _dry_run(tmp_path, config)
    assert not set(counts) & set(sweep.UPSTREAM_RULES), counts
    assert counts["gather_observations"] == 3 and counts["evaluate_model"] == 1 and "cluster_lobes" not in counts


# --------------------------------------------------------------------------- orchestration


class FakeRunner:
    """Stands in for snakemake: makes the files a run would, adds one XLA cache entry per new fit setting."""

    def __init__(self, workdir: Path):
        self.workdir, self.calls, self.compiled = workdir, [], set()

    def __call__(self, config, targets, log_path):
        self.calls.append((config["name"], list(targets), config.get("iterations")))
        results = self.workdir / "results" / config["name"]
        if targets and targets[0].startswith("captures/"):
            _touch(self.workdir / targets[0])
        elif targets and targets[0].endswith("init.ply"):
            _fake_upstream(results)
        else:
            assert not targets and (results / "mesh" / "init.ply").is_file()  # the upstream was linked in
            key = json.dumps([config["fit"], config["observe"]], sort_keys=True)
            line = "Finished XLA compilation of jit(f) in 0.5 sec"  # over 10 % of 3 s CPU: a repeat
            if key not in self.compiled:
                self.compiled.add(key)
                _touch(self.workdir / "jax_cache" / f"entry{len(self.compiled)}")
            else:
                line = "Persistent compilation cache hit for 'jit_f'\n" + line
            _touch(results / "logs" / "fit_pbrdf" / "0" / "fit" / "1-of-2.log", line + "\n")
            (results / "metrics.json").write_text(json.dumps(_metrics()))
        return 7.0, 3.0


# Two factors with one value each, independent of the presets' values.
TWO_FACTORS = (sweep_plan.Factor("augment", "augment.enabled", (False,), "aug {}"),
               sweep_plan.Factor("sigma_ss", "fit.settings.sigma_ss_fixed", (0.9,), "σss {}"))


def test_run_sweep_repeats_reuses_the_upstream_and_resumes(tmp_path):
    runner = FakeRunner(tmp_path)
    variants, records = sweep.run_sweep(["tiny"], "quick", tmp_path, runner, factors=TWO_FACTORS)
    assert [v.name for v in variants] == ["tiny__base", "tiny__augment-off", "tiny__sigma_ss-0.9"]
    names = [name for name, _, _ in runner.calls]
    # A new fit setting compiles (a new cache entry): run again, time the second run; augment-off reuses the
    # base's kernels and runs once.
    assert names == ["tiny__capture", "tiny__upstream", "tiny__base", "tiny__base", "tiny__augment-off",
                     "tiny__sigma_ss-0.9", "tiny__sigma_ss-0.9"]
    assert [(r["runs"], r["cold_compiled"], r["compiled"], r["new_programs"]) for r in records] == [
        (2, 1, 0, 0), (1, None, 0, 0), (2, 1, 0, 0)]
    assert [r["deterministic"] for r in records] == [True, None, True]
    assert (tmp_path / "jax_cache" / "entry2").is_file() and not (tmp_path / "jax_cache" / "entry3").exists()
    assert all(r["upstream_s"] == 7.0 and r["run_s"] == 7.0 and r["cpu_s"] == 6.0 for r in records)
    assert records[0]["cold_cpu_s"] == 3.0 and records[1]["cold_cpu_s"] is None
    # A second sweep runs nothing; --force runs the variants again (not the capture or the upstream).
    runner.calls.clear()
    again = sweep.run_sweep(["tiny"], "quick", tmp_path, runner, factors=TWO_FACTORS)[1]
    assert runner.calls == [] and [r["run_s"] for r in again] == [7.0] * 3
    runner.compiled.clear()  # a cold cache: with repeat=1 the base runs once all the same
    once = sweep.run_sweep(["tiny"], "quick", tmp_path, runner, only=["augment"], repeat=1, force=True,
                           factors=TWO_FACTORS)[1]
    assert [name for name, _, _ in runner.calls] == ["tiny__base", "tiny__augment-off"]
    assert once[0]["compiled"] == 1 and once[0]["cold_cpu_s"] is None and once[0]["deterministic"] is None
    row = sweep_tables.sweep_row(variants[0], _metrics(), once[0], "quick")
    assert np.isnan(row["cold_cpu_s"]) and row["cpu_s"] == 6.0


def test_a_failed_run_names_its_log(tmp_path, monkeypatch):
    script = tmp_path / "fail.py"
    script.write_text("import sys; print('boom: bad config'); sys.exit(3)\n")
    runner = sweep.SnakemakeRunner(tmp_path, cores=1)
    run = subprocess.run
    # snakemake replaced by a script that fails: the runner reports the exit code and the log's tail.
    monkeypatch.setattr(sweep.subprocess, "run", lambda command, **kw: run([sys.executable, str(script)], **kw))
    with pytest.raises(sweep_plan.SweepError, match=r"(?s)failed \(exit 3\).*x\.log.*boom: bad config"):
        runner({"name": "x"}, [], tmp_path / "logs" / "x.log")
    assert (tmp_path / "configs" / "x.yaml").is_file()


def test_runner_measures_the_cpu_of_the_whole_process_tree(tmp_path, monkeypatch):
    script = tmp_path / "spin.py"
    # A child that burns ~0.4 s of CPU in a grandchild, and reports whether JAX will log its compilations.
    script.write_text("import os, subprocess, sys\n"
                      "print('JAX_LOG_COMPILES', os.environ.get('JAX_LOG_COMPILES'))\n"
                      "subprocess.run([sys.executable, '-c', 'import time\\nt = time.process_time()\\n"
                      "while time.process_time() - t < 0.4: pass'], check=True)\n")
    run = subprocess.run
    monkeypatch.setattr(sweep.subprocess, "run", lambda command, **kw: run([sys.executable, str(script)], **kw))
    wall, cpu = sweep.SnakemakeRunner(tmp_path, cores=1)({"name": "spin"}, [], tmp_path / "spin.log")
    assert 0.4 <= cpu <= wall + 0.5 and "JAX_LOG_COMPILES 1" in (tmp_path / "spin.log").read_text()


def test_xla_compile_seconds_counts_compilations_not_cache_loads(tmp_path):
    log = ("2026 WARNING jax._src.dispatch: Finished tracing + transforming f for pjit in 0.01 sec\n"
           "2026 WARNING jax._src.dispatch: Finished XLA compilation of jit(f) in 1.5 sec\n"
           "2026 WARNING jax._src.compiler: Persistent compilation cache hit for 'jit_g' with key 'abc'\n"
           "2026 WARNING jax._src.dispatch: Finished XLA compilation of jit(g) in 0.02 sec\n"
           "2026 INFO sellip.stages.fit: fitted\n"
           "2026 WARNING jax._src.dispatch: Finished XLA compilation of jit(h) in 2.25 sec\n")
    _touch(tmp_path / "fit_pbrdf" / "0" / "fit" / "1-of-2.log", log)
    _touch(tmp_path / "cluster_lobes" / "0.log", "Finished XLA compilation of jit(k) in 1e-1 sec\n")
    seconds, count = sweep.xla_compile_seconds(tmp_path)
    assert count == 3 and seconds == pytest.approx(3.85)


def test_cli_rejects_an_unknown_scene(tmp_path, caplog):
    from sellip.cli import main

    assert main(["bench-sweep", "--scenes", "nowhere", "--out", str(tmp_path)]) == 1
    assert "unknown scene" in caplog.text
    assert main(["bench-sweep", "--scenes", "tiny", "--out", str(tmp_path), "--report-only"]) == 1
    assert "has not run" in caplog.text
