"""The Snakemake workflow end to end: a real `snakemake --cores 2` run on a tiny synthetic capture
(synth -> ingest -> known poses -> initial mesh -> observations -> sharded fit -> gather), with
the fitted parameters checked against the ground truth."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]


def tiny_config(workdir: Path) -> dict:
    """Overrides of config/config.yaml for a run of a few minutes on 2 cores."""
    return {
        "name": "tiny",
        "demo": {"scene": "tiny", "views": 24, "width": 320, "height": 256, "seed": 3},
        "init": {"hull_resolution": 64, "max_vertices": 2500},
        "fit": {"shards": 2, "compilation_cache": str(workdir / "jax_cache"), "settings": {"min_views": 6}},
    }


def _snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    """Run snakemake on the repository's workflow in ``workdir`` with the tiny-scene config on top."""
    override = workdir / "tiny.yaml"
    override.write_text(yaml.safe_dump(tiny_config(workdir)))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), *args]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=1500)
    if result.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}")
    return result


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("workflow")
    _snakemake(workdir, "--cores", "2")
    return workdir


def test_dry_run_has_one_fit_job_per_shard(tmp_path):
    for shards in (2, 3):
        out = _snakemake(tmp_path, "-n", "--set-scatter", f"fit={shards}").stdout
        counts = dict(line.split()[:2] for line in out.splitlines()
                      if line.strip() and line.split()[0] in ("fit_pbrdf", "gather_fit"))
        assert counts == {"fit_pbrdf": str(shards), "gather_fit": "1"}, out[-2000:]


def test_tiny_capture_fits_close_to_the_ground_truth(tiny_run):
    from sellip.fit import STATUS_FITTED
    from sellip.io import read_param_mesh
    from sellip.observe import read_mesh
    from sellip.params import read_params

    params = read_params(tiny_run / "results" / "tiny" / "iter" / "0" / "params.zarr")
    truth = read_param_mesh(tiny_run / "captures" / "tiny" / "ground_truth" / "model.ply")
    for name in ("normals", "eta", "rho_d", "sigma_s", "confidence"):
        assert np.all(np.isfinite(params[name])), name
    fitted = params["status"] == STATUS_FITTED
    assert fitted.mean() > 0.85
    nearest = cKDTree(truth.vertices).query(params["vertices"])[1]
    angle = np.degrees(np.arccos(np.clip(np.sum(params["normals"] * truth.normals[nearest], -1), -1, 1)))
    eta_error = np.abs(params["eta"] / np.asarray(truth.params.eta)[nearest] - 1)
    mesh = read_mesh(tiny_run / "results" / "tiny" / "mesh" / "init.ply")
    before = np.degrees(np.arccos(np.clip(np.sum(mesh.normals * truth.normals[nearest], -1), -1, 1)))
    print(f"tiny capture, iteration 0: normal error median {np.median(angle[fitted]):.2f} deg "
          f"(initial mesh {np.median(before[fitted]):.2f} deg), eta error median {100 * np.median(eta_error[fitted]):.2f} %")
    # Measured 2026-11-21: 3.2 deg (initial mesh 3.6 deg), eta 8.8 % (24 views of 160x128 demosaiced
    # pixels, a 4 cm sphere, the visual-hull mesh 1.6 mm off): bounds catch regressions, not targets.
    assert np.median(angle[fitted]) < min(4.0, np.median(before[fitted]))
    assert np.median(eta_error[fitted]) < 0.12
    assert np.all(params["confidence"][~fitted] == 0)
