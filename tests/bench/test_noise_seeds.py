"""The demo over sensor-noise seeds and core counts (sellip.bench.noise_seeds, issue #49): its runs' config and how
the targets are counted over finished runs."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import yaml

from sellip.bench import noise_seeds

ROOT = Path(__file__).resolve().parents[2]


def test_a_seed_run_is_the_demo_on_another_capture(tmp_path):
    overrides = noise_seeds.demo_overrides(ROOT / "config" / "config.yaml")
    before = json.dumps(overrides, sort_keys=True)
    config = noise_seeds.seed_run_config(tmp_path / "captures" / "noise3", "noise3_cores1", overrides,
                                        tmp_path / "cache")
    assert json.dumps(overrides, sort_keys=True) == before  # not changed in place
    # Every setting the demo runs with is in the override, as a setting (a capture that is not the built-in demo
    # gets the defaults otherwise), and the rest is the capture, the name and the shared compilation cache.
    for key, value in overrides.items():
        if key != "fit":
            assert config[key] == value
    assert config["iterations"] == overrides["iterations"] and config["init"]["max_vertices"] == 6000
    assert Path(config["capture"]).is_absolute() and config["capture"].endswith("noise3")
    assert config["name"] == "noise3_cores1" and Path(config["fit"]["compilation_cache"]).is_absolute()
    # The workflow's config with the override merged validates against the schema.
    base = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    for key, value in config.items():
        base[key] = {**base[key], **value} if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    jsonschema.validate(base, yaml.safe_load((ROOT / "config" / "config.schema.yaml").read_text()))


TRUE_ETA = (1.48, 1.36, 1.62)


def _finished_run(folder: Path, k, eta_errors, normals=0.74, fragile=()):
    """A results folder as the workflow leaves it, with the files seed_row reads: with K = 2 at the end the eyes
    (material 2) are merged into the plumage's cluster."""
    for it, value in enumerate(k):
        (folder / "iter" / str(it) / "clusters").mkdir(parents=True)
        merges = [{"reason": "spatially incoherent: 0.44 of its vertices' neighbours in it < min_coherence 0.5"}]
        (folder / "iter" / str(it) / "clusters" / "clusters.json").write_text(
            json.dumps({"k": value, "merges": merges if value < 3 else []}))
    (folder / "final").mkdir(parents=True)
    lines = ["cluster,vertices,eta,eta_ci_low,eta_ci_high,model,gt_material,gt_eta"]
    for i in range(k[-1]):
        eta = TRUE_ETA[i] * (1 + eta_errors[i] / 100)
        lines.append(f"{i},{1000 // (i + 1)},{eta},{eta - 0.01},{eta + 0.01},{1 + (i == 1)},{i},{TRUE_ETA[i]}")
    (folder / "final" / "materials.csv").write_text("\n".join(lines) + "\n")
    (folder / "metrics.json").write_text(json.dumps({
        "eta_per_material": {"materials": {str(i): {"error_pct": e} for i, e in enumerate(eta_errors)}},
        "normal_error_deg": {"all": {"median": normals}}, "psnr_held_out": {"mean_db": 31.6},
        "geometry": {"chamfer_mm": 0.065}, "material_support": {"fragile": list(fragile)}}))
    return folder


def test_the_targets_are_counted_over_runs_and_every_miss_is_named(tmp_path):
    rows = []
    cases = [(0, 1, [3, 3, 3], [0.1, 0.2, 1.5], 0.74, ()),
             (0, 2, [3, 2, 3], [0.1, 0.2, 8.5], 0.75, (2,)),    # the eyes merged at pass 1: two targets missed
             (1, 1, [3, 3, 3], [0.1, 2.4, 1.0], 1.02, ())]      # the disc 2.4 % off, normals 1.02 deg
    for seed, cores, k, errors, normals, fragile in cases:
        row = {"noise_seed": seed, "cores": cores, "wall_s": 300.0}
        row.update(noise_seeds.seed_row(_finished_run(tmp_path / f"{seed}_{cores}", k, errors, normals, fragile)))
        rows.append(row)
    rows.append({"noise_seed": 1, "cores": 2, "wall_s": 12.0, "error": "fit_shard: out of memory"})
    assert rows[1]["k"] == [3, 2, 3] and rows[1]["eta_error_pct"]["2"] == 8.5 and rows[1]["fragile"] == [2]
    assert rows[1]["merges"] == [[], ["coherence"], []]
    # An interval 0.01 either side holds the truth where the error is below 0.01 / eta.
    assert rows[0]["covered"] == {"0": True, "1": True, "2": False}
    assert rows[0]["model"] == {"0": 1, "1": 2, "2": 1}
    assert abs(rows[0]["ci_width_pct"]["0"] - 100 * 0.02 / (1.48 * 1.001)) < 1e-9
    summary = noise_seeds.seed_summary(rows)
    assert summary["runs"] == 4 and summary["finished"] == 3
    assert summary["failed"] == ["noise1 cores2: fit_shard: out of memory"]
    assert summary["materials_at_every_iteration"] == {"met": 2, "missed": ["noise0 cores2"]}
    assert summary["eta_within"]["met"] == 1
    assert summary["eta_within"]["missed"] == ["noise0 cores2", "noise1 cores1"]
    assert summary["eta_within"]["error_pct_range"]["2"] == [1.0, 8.5]
    assert summary["normals_within"] == {"met": 2, "missed": ["noise1 cores1"], "median_deg_range": [0.74, 1.02]}
    assert summary["fragile_runs"] == ["noise0 cores2"]
    assert summary["merges"] == {"- | - | -": 2, "- | coherence | -": 1}
    assert summary["models"]["1"] == {2: 3}
    assert summary["covered"]["materials"] == 9 and summary["covered"]["covered"] == 5


def test_a_scenes_decisions_are_counted_over_seeds_with_the_runs_that_differ(tmp_path):
    rows = []
    for seed in range(10):
        merged = seed == 7  # the eyes merged into the plumage's cluster at the end in one seed
        k, errors = ([3, 3, 2], [0.1, 0.2, 8.5]) if merged else ([3, 3, 3], [0.1, 0.2, 0.3])
        row = {"noise_seed": seed, **noise_seeds.seed_row(_finished_run(tmp_path / str(seed), k, errors,
                                                                       fragile=(0,) if merged else ()))}
        rows.append(row)
    rows.append({"noise_seed": 10, "error": "timed out after 3600 s"})
    agreement = noise_seeds.decision_agreement(rows)
    assert agreement["runs"] == 11 and agreement["finished"] == 10
    assert agreement["decision"] == "3 materials; models 0:1 1:2 2:1" and agreement["agree"] == 9
    assert agreement["others"] == {"2 materials; models 0:1 1:2 2:-": [7]}
    assert agreement["k_at_every_iteration"] == {"3 3 2": 1, "3 3 3": 9}
    assert agreement["fragile"] == {7: [0]}
    assert agreement["eta_error_pct"]["2"] == [0.3, 8.5]
    # Every material's interval (0.01 either side) holds its truth but the eyes' in the merged run.
    assert agreement["covered"] == [29, 30]
