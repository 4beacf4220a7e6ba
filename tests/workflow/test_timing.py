"""Where a job's time goes (sellip.timing): phases add up, JAX compile time is counted apart, logs round-trip."""

from __future__ import annotations

import logging
import time

from sellip import cli, timing


def test_phases_and_jax_compiles_add_up_to_the_job():
    import jax
    import jax.numpy as jnp

    clock = timing.start()
    with timing.phase("run"):
        timing.mark("read")
        time.sleep(0.05)
        timing.mark("fit")
        x = jnp.linspace(0.0, 1.0, 1024 + 7)  # a shape no other test compiles

        @jax.jit
        def kernel(values):
            for _ in range(20):
                values = jnp.sin(values) * jnp.cos(values) + values**2
            return values.sum()

        float(kernel(x))
        time.sleep(0.05)
        with timing.phase("write"):  # nested: counts for the innermost
            time.sleep(0.03)
    report = clock.report()
    assert report["read"] >= 0.045 and report["write"] >= 0.025
    assert report["compile"] + report.get("cache_load", 0.0) > 0 and report["trace"] > 0
    # The fit phase holds its sleep but not the compile events taken out of it.
    jax_seconds = report["trace"] + report.get("lower", 0.0) + report["compile"] + report.get("cache_load", 0.0)
    assert 0.045 <= report["fit"] < 0.05 + 0.5 * jax_seconds
    parts = sum(v for k, v in report.items() if k not in ("total", "startup"))
    assert abs(parts - (report["total"] - report["startup"])) < 0.01
    assert report["startup"] >= 0


def test_cli_logs_the_phases_line_and_it_reads_back(tmp_path):
    """A real (tiny) stage run through cli.main ends its log with the phases line; read_job_phases reads it."""
    log = tmp_path / "job.log"
    handler = logging.FileHandler(log)
    logger = logging.getLogger("sellip")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.INFO)
    try:
        assert cli.main(["synth", "--scene", "tiny", "--views", "2", "--width", "64", "--height", "48",
                         "--out", str(tmp_path / "capture")]) == 0
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        handler.close()
    phases = timing.read_job_phases(log)
    assert phases is not None and phases["imports"] > 0 and phases["run"] > 0
    assert abs(sum(v for k, v in phases.items() if k not in ("total", "startup")) + phases["startup"]
               - phases["total"]) < 0.01
    assert timing.read_job_phases(tmp_path / "missing.log") is None
    (tmp_path / "empty.log").write_text("nothing here\n")
    assert timing.read_job_phases(tmp_path / "empty.log") is None


def test_phase_table_splits_overheads_from_work():
    rules = {"fit_pbrdf": {"s": 10.0, "jobs": 2, "phases_jobs": 2,
                           "phases": {"startup": 1.0, "imports": 1.5, "read": 0.5, "trace": 1.0, "lower": 0.5,
                                      "compile": 2.0, "cache_load": 0.25, "fit": 2.0, "select": 0.25, "write": 0.1,
                                      "other": 0.4, "total": 9.5}},
             "merge_hdr": {"s": 2.0, "jobs": 1, "phases_jobs": 0, "phases": {}}}
    lines = timing.phase_table(rules).splitlines()
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    assert cells[:3] == ["fit_pbrdf", "2", "10.0"]
    # startup, imports, read, trace + lower, compile, cache load, write, work (fit + select + other), snakemake
    assert cells[3:] == ["1.0", "1.5", "0.5", "1.5", "2.0", "0.2", "0.1", "2.6", "0.5"]
    assert lines[3].startswith("| merge_hdr | 1 | 2.0 | –")
    assert lines[-1].startswith("| **all** | 3 | **12.0**")
