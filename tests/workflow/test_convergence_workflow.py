"""Convergence of the outer loop through real Snakemake (issue #54 item 1): a tiny capture whose loop is told to
converge at its second iteration (limits no update can exceed): the third iteration's jobs pass their inputs
through (stores linked, mesh copied, markers), the final pass runs on the converged model, metrics.json says where
the loop converged, and a second `snakemake` finds nothing to do (the static DAG's outputs stay up to date)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from helpers import session_jax_cache

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def _snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    override = workdir / "converge.yaml"
    override.write_text(yaml.safe_dump({
        "name": "conv", "iterations": 3,
        "converge": {"min_iterations": 2, "max_offset_edges": 100.0, "max_eta_change": 100.0},
        "demo": {"scene": "tiny", "views": 24, "width": 320, "height": 256, "seed": 3},
        "init": {"hull_resolution": 48, "max_vertices": 1200},
        "observe": {"vertex_chunk": 256, "edge_margin": 0.0, "max_slope": 0.0},
        "fit": {"shards": 1, "compilation_cache": str(session_jax_cache(workdir)), "settings": {"min_views": 6}},
        "augment": {"enabled": False},
        "evaluate": {"held_out_views": ["v005", "v017"], "render_views": ["v000"], "supersample": 1},
    }))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), "--cores", "2", *args]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=1500, check=False)
    assert result.returncode == 0, f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


def test_a_converged_loop_passes_its_later_iteration_through(tmp_path):
    _snakemake(tmp_path)
    run = tmp_path / "results" / "conv"
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["convergence"]["converged_at"] == 1 and metrics["convergence"]["passed_through"] == [2]
    assert not metrics["convergence"]["verdicts"]["0"]["converged"]  # iteration 0: no previous fit to compare
    summary = json.loads((run / "iter" / "2" / "mesh.ply.json").read_text())
    assert summary["passed_through"] and summary["convergence"]["iteration"] == 1
    assert (run / "iter" / "2" / "mesh.ply").read_bytes() == (run / "iter" / "1" / "mesh.ply").read_bytes()
    store = run / "iter" / "2" / "fit.zarr"  # linked file by file: no copy of a store (augmentation off: no clusters)
    linked = [path for path in store.rglob("*") if path.is_file() and path.name != ".snakemake_timestamp"]
    assert linked and all(os.path.samefile(path, run / "iter" / "1" / "fit.zarr" / path.relative_to(store))
                          for path in linked)
    for log in ("gather_observations/2.log", "fit_pbrdf/2/fit/1-of-1.log", "refine_geometry/2.log"):
        assert "passed through: the loop converged at iteration 1" in (run / "logs" / log).read_text()
    assert "passed through" not in (run / "logs" / "fit_pbrdf" / "3" / "fit" / "1-of-1.log").read_text()
    assert np.isfinite(metrics["normal_error_deg"]["all"]["median"]) and (run / "final" / "model.ply").is_file()
    rerun = _snakemake(tmp_path, "-n")
    assert "Nothing to be done" in rerun.stdout + rerun.stderr, (rerun.stdout + rerun.stderr)[-3000:]
