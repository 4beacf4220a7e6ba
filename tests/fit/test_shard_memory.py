"""The memory a fit shard needs (issue #38, "an out-of-memory fit shard is reported as such, with the shard count
that would fit"): the model's arithmetic, what the job may use (/proc/meminfo, cgroups), the stage stopping before
it reads with the count that fits (and that count then passing), an allocation failure reported the same way, and
the console's words for a job killed from outside."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from sellip import cli, workflow_support
from sellip.fit import shard as fit_shard_module
from sellip.fit.shard import available_memory, memory_budget
from sellip.fit.shard_plan import (
    SHARD_MEMORY,
    ShardMemory,
    ShardMemoryError,
    fit_shard_plan,
    largest_shard,
    planned_shards,
)

MODEL = ShardMemory(base=500e6, loaded=400.0, working=4000.0)


@pytest.mark.parametrize("total", [1, 7, 1000, 123_457])
@pytest.mark.parametrize("budget", [0.4e9, 0.6e9, 1.5e9, 9e9])
def test_shards_for_is_the_fewest_shards_that_fit(total, budget):
    views, chunk = 72, 8192
    shards = MODEL.shards_for(total, views, chunk, budget)
    fits = [k for k in range(1, min(total, 400) + 1) if MODEL.bytes(-(-total // k), views, chunk) <= budget]
    if shards is None:
        assert not fits and MODEL.bytes(1, views, chunk) > budget
    else:
        assert shards == fits[0]


def test_the_bytes_grow_with_vertices_and_views_and_the_chunk_caps_the_working_part():
    assert MODEL.bytes(2000, 36, 8192) < MODEL.bytes(4000, 36, 8192) < MODEL.bytes(4000, 72, 8192)
    beyond = MODEL.bytes(20000, 36, 8192) - MODEL.bytes(10000, 36, 8192)
    assert beyond == pytest.approx(36 * 400.0 * 10000)  # past one chunk only the loaded part grows


def _fake_system(root, available_kb=None, cgroup=None):
    (root / "proc").mkdir(parents=True, exist_ok=True)
    if available_kb is not None:
        (root / "proc" / "meminfo").write_text(f"MemTotal: 99999999 kB\nMemAvailable: {available_kb} kB\n")
    if cgroup is not None:
        (root / "sys" / "fs" / "cgroup").mkdir(parents=True, exist_ok=True)
        (root / "sys" / "fs" / "cgroup" / "memory.max").write_text(f"{cgroup[0]}\n")
        (root / "sys" / "fs" / "cgroup" / "memory.current").write_text(f"{cgroup[1]}\n")
    return root


def test_available_memory_is_the_smaller_of_the_system_and_the_cgroup(tmp_path):
    assert available_memory(_fake_system(tmp_path / "a", 8_000_000)) == 8_000_000 * 1024
    assert available_memory(_fake_system(tmp_path / "b", 8_000_000, (2_000_000_000, 500_000_000))) == 1_500_000_000
    assert available_memory(_fake_system(tmp_path / "c", 1_000, ("max", 5))) == 1_024_000
    assert available_memory(_fake_system(tmp_path / "d")) is None


def test_memory_budget_takes_the_smaller_and_says_which(tmp_path):
    root = _fake_system(tmp_path, 8_000_000)
    assert memory_budget(4000, root) == (4e9, "the job's 4,000 MB (its mem_mb resource: config fit.mem_mb)")
    budget, source = memory_budget(16000, root)
    assert budget == 8_000_000 * 1024 and "available" in source
    assert memory_budget(None, tmp_path / "nothing") == (None, "no limit known")


def _store(folder, vertices=256, views=12):
    """A real observation store of simulated observations, vertex chunks of 64."""
    from sellip.fit.observe import ObservationWriter, ObserveMesh, ObserveSettings
    from sellip.fit.simulate import vertex_observations
    from sellip.model.pbrdf import PBRDFParams

    rng = np.random.default_rng(0)
    normals = np.tile([0.0, 0.0, 1.0], (vertices, 1))
    truth = PBRDFParams(eta=np.full(vertices, 1.5), rho_d=np.full((vertices, 3), 0.5), rho_s=np.full(vertices, 0.5),
                        sigma_s=np.full(vertices, 0.2), rho_ss=np.zeros((vertices, 3)),
                        sigma_ss=np.full(vertices, 0.6))
    obs = vertex_observations(rng, truth, normals, n_views=views, flash_offset_m=0.055, dtype=np.float32)
    mesh = ObserveMesh(rng.normal(size=(vertices, 3)).astype(np.float32), normals.astype(np.float32),
                       np.zeros((0, 3), np.int64))
    writer = ObservationWriter(folder / "observations.zarr", mesh, [f"v{k}" for k in range(views)],
                               {"camera_up": np.asarray(obs.camera_up)[0], "light_axis": np.asarray(obs.light_axis)[0]},
                               ObserveSettings(vertex_chunk=64, view_chunk=views))
    for name in ("diffuse", "diffuse_pol", "specular", "to_light", "to_camera", "light_distance", "usable"):
        writer.arrays[name][...] = np.asarray(getattr(obs, name))
    return folder / "observations.zarr"


@pytest.mark.slow
def test_a_shard_over_its_memory_stops_before_reading_and_the_count_it_names_fits(tmp_path, caplog):
    store = _store(tmp_path)
    chunk = 8192
    # Between what half the vertices and all of them need: one shard is too big, two fit.
    mem_mb = (SHARD_MEMORY.bytes(256, 12, chunk) + SHARD_MEMORY.bytes(128, 12, chunk)) / 2 / 1e6
    common = ["fit", "--observations", str(store), "--mem-mb", f"{mem_mb:.6f}", "--settings", '{"max_iterations": 2}',
              "--job-settings", '{"compilation_cache": null}']  # no persistent cache (the workflow's is the default)
    with caplog.at_level(logging.INFO):
        assert cli.main([*common, "--shard", "1-of-1", "--output", str(tmp_path / "all.npz")]) == 1
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert errors and "fit shard 1 of 1 needs about" in errors[-1] and "fit.shards: 2" in errors[-1], errors
    assert not (tmp_path / "all.npz").exists()
    for k in (1, 2):
        assert cli.main([*common, "--shard", f"{k}-of-2", "--output", str(tmp_path / f"{k}.npz")]) == 0
        assert (tmp_path / f"{k}.npz").is_file()


def test_no_shard_count_fits_below_the_fixed_part(tmp_path, caplog):
    store = _store(tmp_path, vertices=64)
    assert cli.main(["fit", "--observations", str(store), "--mem-mb", "10", "--output", str(tmp_path / "x.npz"),
                     "--job-settings", '{"compilation_cache": null}']) == 1
    assert "no shard count fits" in caplog.text and "raise fit.mem_mb" in caplog.text


def test_an_allocation_that_fails_is_reported_with_the_count_that_fits(tmp_path, monkeypatch):
    store = _store(tmp_path)

    def exhausted(*args, **kwargs):
        raise MemoryError("Unable to allocate 3.1 GiB for an array")

    monkeypatch.setattr(fit_shard_module, "fit_rows", exhausted)
    with pytest.raises(ShardMemoryError) as raised:
        fit_shard_module.fit_shard(store, (0, 1), tmp_path / "x.npz", mem_mb=100_000)
    text = str(raised.value)
    assert text.startswith("out of memory (MemoryError): fit shard 1 of 1 needs about") and "fit.shards: 2" in text


@pytest.mark.slow
def test_a_job_killed_from_outside_says_so_on_the_console_with_its_memory_line(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "fit.log").write_text(
        "2026-11-26 10:00:00,000 INFO sellip.fit.shard: shard 1 of 2: vertices [0, 40000) of 80000\n"
        "2026-11-26 10:00:00,100 INFO sellip.fit.shard: memory: about 3.10 GB for 40000 vertices of 72 views; may "
        "use the job's 4,000 MB (its mem_mb resource: config fit.mem_mb) (fit.shards: 4 would halve the part that "
        "grows with the vertices)\n"
        "2026-11-26 10:00:09,000 INFO sellip.fit.shard: fitted 8192 / 40000 vertices (9 s)\n")
    (logs / "bad.log").write_text("2026-11-26 10:00:00,000 ERROR sellip.stages.fit: frames.csv row 3: bad\n")
    snakemake_log = tmp_path / "snakemake.log"
    snakemake_log.write_text("Error in rule fit_pbrdf:\n    jobid: 3\n    log: logs/fit.log (check log file(s) for "
                             "error details)\nError in rule merge_hdr:\n    log: logs/bad.log\n")
    text = workflow_support.format_failures([snakemake_log], tmp_path)
    fit_part, merge_part = text.split("sellip: rule merge_hdr failed")
    assert "killed from outside" in fit_part and "its memory: about 3.10 GB" in fit_part and "fit.shards: 4" in fit_part
    assert "killed from outside" not in merge_part and "frames.csv row 3: bad" in merge_part


def test_shards_are_whole_store_chunks():
    # 600 vertices in chunks of 256: two shards are 256 + 344 (shard_rows), so the largest is 344, not 300.
    views, chunk = 12, 8192
    budget = MODEL.bytes(320, views, chunk)
    assert MODEL.shards_for(600, views, chunk, budget) == 2  # by vertices alone, 300 would fit
    assert MODEL.shards_for(600, views, chunk, budget, vertex_chunk=256) == 3
    assert largest_shard(600, 256, 2) == 344
    # 591 vertices: the last chunk holds 79, so two shards are 256 + 335.
    assert largest_shard(591, 256, 2) == 335
    assert MODEL.shards_for(591, views, chunk, MODEL.bytes(335, views, chunk), vertex_chunk=256) == 2


def test_a_log_that_is_not_sellips_is_not_called_killed(tmp_path):
    (tmp_path / "shell.log").write_text("bash: line 1: sellip: command not found\n")
    (tmp_path / "empty.log").write_text("")
    assert workflow_support.killed_from_outside(tmp_path / "shell.log") == []
    assert workflow_support.killed_from_outside(tmp_path / "empty.log") == []


# --------------------------------------------------------------------------- the shard count planned before a run

def test_planned_shards_keeps_the_requested_count_where_it_fits_and_raises_it_to_the_fewest_that_fit():
    views, chunk, vertex_chunk = 40, 8192, 1024
    assert planned_shards(2, 6000, views, chunk, 9000, vertex_chunk, MODEL) == (2, None)
    budget_mb = MODEL.bytes(largest_shard(200_000, vertex_chunk, 5), views, chunk) / 1e6 + 1
    count, why = planned_shards(2, 200_000, views, chunk, budget_mb, vertex_chunk, MODEL)
    assert count == 5 and "fit.shards 2 raised to 5" in why and "init.max_vertices" in why
    assert MODEL.bytes(largest_shard(200_000, vertex_chunk, count), views, chunk) <= budget_mb * 1e6
    assert MODEL.bytes(largest_shard(200_000, vertex_chunk, count - 1), views, chunk) > budget_mb * 1e6
    assert planned_shards(8, 200_000, views, chunk, budget_mb, vertex_chunk, MODEL) == (8, None)  # more is kept


def test_planned_shards_refuses_a_memory_no_shard_count_holds():
    with pytest.raises(ShardMemoryError, match=r"config fit.mem_mb 300 MB is less than one fit job needs at any "
                                               r"shard count: about 0.52 GB for the smallest shard, 128 vertices"):
        planned_shards(2, 10_000, 40, 8192, 300, 128, MODEL)


def test_the_workflows_plan_reads_the_capture_views_and_the_declared_settings():
    schema = workflow_support.load_yaml(Path(__file__).resolve().parents[2] / "config" / "config.schema.yaml")
    config = {"fit": {"shards": 1, "mem_mb": 1200, "settings": {}}, "evaluate": {"held_out_views": ["v001"]},
              "init": {"max_vertices": 50_000}, "observe": {}}
    views = [f"v{k:03d}" for k in range(37)]
    count, why = fit_shard_plan(config, schema, views)  # 36 views, chunk 8192, vertex chunk 4096
    assert count == SHARD_MEMORY.shards_for(50_000, 36, 8192, 1200e6, 4096) and count > 1 and "36 views" in why
    capped = {**config, "observe": {"max_views": 12}}
    assert fit_shard_plan(capped, schema, views)[0] == SHARD_MEMORY.shards_for(
        50_000, 12, 8192, 1200e6, 4096)
    smaller = {**config, "augment": {"settings": {"chunk_size": 16384}}}  # the refit's chunk, larger, counts
    assert fit_shard_plan(smaller, schema, views)[0] == SHARD_MEMORY.shards_for(
        50_000, 36, 16384, 1200e6, 4096)
    assert fit_shard_plan(config, schema, None) == (1, None)  # the capture not readable yet
    assert workflow_support.declared_setting(config, schema, "init.max_vertices") == 50_000
    assert workflow_support.declared_setting({}, schema, "init.max_vertices") == 30_000
    assert workflow_support.declared_setting({"observe": {"max_views": None}}, schema, "observe.max_views") is None
