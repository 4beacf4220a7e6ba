"""The scale benchmark's cost model (sellip.bench.scale): benchmark files in, per-rule costs, a fitted model,
predictions."""

import numpy as np
import pytest

from sellip.bench import scale

HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def _benchmark(path, seconds, rss=100.0):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEADER + f"{seconds}\t0:00:01\t{rss}\t1\t1\t1\t0\t0\t50\t{seconds * 0.9}\n")


def _run(folder, iterations, once, per_iteration, final, shard_rss=500.0):
    """Benchmark files of a run: ingest once, and per iteration (0 cold, then warm; the final pass I) an observe
    job and two fit shards of each pass."""
    _benchmark(folder / "merge_hdr.tsv", once)
    for it in range(iterations + 1):
        cost = once if it == 0 else final if it == iterations else per_iteration
        _benchmark(folder / "gather_observations" / f"{it}.tsv", cost)
        for part in ("fit", "refit"):
            for shard in (1, 2):
                _benchmark(folder / "fit_pbrdf" / str(it) / part / f"{shard}-of-2.tsv", cost / 4, shard_rss)


def test_a_runs_cost_splits_into_one_off_jobs_and_an_iteration(tmp_path):
    _run(tmp_path, iterations=4, once=10.0, per_iteration=2.0, final=5.0)
    jobs = scale.job_costs(tmp_path)
    assert len(jobs) == 1 + 5 + 5 * 4
    assert set(jobs.loc[jobs["rule"] == "fit_pbrdf", "iteration"]) == {0, 1, 2, 3, 4}
    assert (jobs.loc[jobs["rule"] == "merge_hdr", "iteration"] == -1).all()
    costs = scale.rule_costs(jobs, iterations=4)
    observe = costs.loc["gather_observations"]
    assert observe["per_iteration_s"] == pytest.approx(2.0)
    assert observe["once_s"] == pytest.approx(10.0 + 5.0)  # iteration 0 and the final pass
    assert observe["total_s"] == pytest.approx(observe["once_s"] + 3 * observe["per_iteration_s"])
    assert costs.loc["fit_pbrdf", "per_iteration_s"] == pytest.approx(2.0)  # four jobs of 0.5 s
    assert costs.loc["fit_pbrdf", "max_rss_mb"] == 500.0 and costs.loc["merge_hdr", "per_iteration_s"] == 0.0
    with pytest.raises(ValueError, match="at least 2 iterations"):
        scale.rule_costs(jobs[jobs["iteration"] <= 0], iterations=1)


def test_a_benchmark_outside_an_iteration_folder_is_named(tmp_path):
    _benchmark(tmp_path / "fit_pbrdf" / "shard.tsv", 1.0)
    with pytest.raises(ValueError, match="shard.tsv.*outside an iteration"):
        scale.job_costs(tmp_path)
    with pytest.raises(ValueError, match="no benchmark files"):
        scale.job_costs(tmp_path / "empty")


def test_the_model_recovers_linear_costs_and_predicts_the_critical_path(tmp_path):
    """Three runs whose costs are exactly a + b * term (observe: V N; merge: V P) give back a and b; the prediction
    of a run of 10 iterations is once + 9 per iteration per rule, the fit shards side by side on min(shards, cores)."""
    sizes = [scale.CaptureSize(20, 300_000, 10_000), scale.CaptureSize(68, 1_250_000, 30_000),
             scale.CaptureSize(96, 1_250_000, 100_000)]
    runs = []
    for i, size in enumerate(sizes):
        t = scale.size_terms(size)
        folder = tmp_path / str(i)
        per_iteration = 1.0 + 2e-6 * t["VN"]
        _run(folder, iterations=3, once=3.0 + 4e-8 * t["VP"], per_iteration=per_iteration,
             final=per_iteration, shard_rss=200 + 1e-4 * t["VN"])
        runs.append((size, scale.rule_costs(scale.job_costs(folder), 3)))
    model = scale.fit_cost_model(runs)
    assert list(model.index) == ["merge_hdr", "gather_observations", "fit_pbrdf"]
    assert model.loc["merge_hdr", "term"] == "VP" and model.loc["fit_pbrdf", "term"] == "VN"
    np.testing.assert_allclose(model.loc["merge_hdr", ["once_s_a", "once_s_b"]].astype(float), [3.0, 4e-8], rtol=1e-6)
    np.testing.assert_allclose(model.loc["gather_observations", ["per_iteration_s_a", "per_iteration_s_b"]]
                               .astype(float), [1.0, 2e-6], rtol=1e-6)
    assert model.loc["gather_observations", "per_iteration_s_rms"] < 1e-9
    paper = scale.CaptureSize(196, 2448 * 2048, 500_000)
    t = scale.size_terms(paper)
    two = scale.predict(model, paper, 10, cores=2, shards=2)
    per = 1.0 + 2e-6 * t["VN"]
    once_observe = model.loc["gather_observations", "once_s_a"] + model.loc["gather_observations", "once_s_b"] * t["VN"]
    assert two.loc["gather_observations", "job_s"] == pytest.approx(once_observe + 9 * per, rel=1e-6)
    assert two.loc["fit_pbrdf", "critical_s"] == pytest.approx(two.loc["fit_pbrdf", "job_s"] / 2)
    node = scale.predict(model, paper, 10, cores=32, shards=32)
    assert node.loc["fit_pbrdf", "critical_s"] == pytest.approx(node.loc["fit_pbrdf", "job_s"] / 32)
    fit = model.loc["fit_pbrdf"]  # every one of 32 jobs pays the intercept that each of the measured 2 paid
    once, per = (fit[f"{c}_a"] * 16 + fit[f"{c}_b"] * t["VN"] for c in ("once_s", "per_iteration_s"))
    assert node.loc["fit_pbrdf", "job_s"] == pytest.approx(once + 9 * per, rel=1e-6)
    assert node.attrs["wall_s"] == pytest.approx(node["critical_s"].sum())
    assert node.attrs["wall_s"] < two.attrs["wall_s"]
    # a shard's memory follows its vertices: 32 shards hold 1/16 of what 2 shards each held
    a, b = model.loc["fit_pbrdf", ["max_rss_mb_a", "max_rss_mb_b"]].astype(float)
    assert node.loc["fit_pbrdf", "max_rss_mb"] == pytest.approx(a + b * t["VN"] * 2 / 32)
