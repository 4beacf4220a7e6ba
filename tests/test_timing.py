"""Where a job's time goes (sellip.timing): phases add up, JAX compile time is counted apart, logs round-trip."""

from __future__ import annotations

import logging
import time

import numpy as np

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
