"""The workflow on SLURM (docs/hpc.md) and the conda environments of the rule families.

- `test_family_environments`: always runs (about 20 s, no conda, no network): each envs/<family>.yaml
  is well formed, its pins lie in pyproject.toml's ranges, and importing a family's stage modules
  loads no heavy library that the family's environment does not install (scripts/check_envs.py).
- `test_tiny_scene_on_a_localhost_slurm_cluster`: only with SELLIP_SLURM_TEST=1, as root on
  Debian/Ubuntu (about 4 minutes): scripts/slurm_localhost.sh sets up a one-node SLURM cluster,
  runs the tiny scene of tests/workflow/test_workflow.py through workflow/profiles/slurm (every job through
  sbatch), runs the same target locally and compares the parameter stores array by array.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from helpers import session_jax_cache

pytestmark = pytest.mark.slow  # the whole module: `make test-fast` leaves it out

REPO = Path(__file__).resolve().parents[2]


def test_family_environments():
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "check_envs.py")], capture_output=True,
                            text=True, timeout=600, check=False)
    print(result.stdout)
    assert result.returncode == 0, f"{result.stdout}\n{result.stderr}"


@pytest.mark.skipif(os.environ.get("SELLIP_SLURM_TEST") != "1",
                    reason="needs root and apt: set SELLIP_SLURM_TEST=1 to run the localhost SLURM test")
def test_tiny_scene_on_a_localhost_slurm_cluster(tmp_path):
    if os.geteuid() != 0:
        pytest.fail("SELLIP_SLURM_TEST=1 needs root (apt-get install slurm-wlm munge, slurmctld/slurmd)")
    # a short folder: slurmd's step sockets sit in it, and a Unix socket path has at most 108 bytes (pytest's
    # tmp_path under pytest-xdist, /tmp/pytest-of-root/pytest-N/popen-gwK/test_.../slurm-test/cluster/spool/..., has
    # more: every job launch then fails and waits, requeued and held)
    workdir = Path(tempfile.mkdtemp(prefix="sellip-slurm-", dir="/tmp"))
    try:
        result = subprocess.run(["bash", str(REPO / "scripts" / "slurm_localhost.sh"), "--repo", str(REPO),
                                 "--workdir", str(workdir), "--python", sys.executable],
                                capture_output=True, text=True, timeout=1800, check=False,
                                env={**os.environ, "SELLIP_JAX_CACHE": str(session_jax_cache(tmp_path))})
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    print(result.stdout[-6000:])
    assert result.returncode == 0, f"slurm_localhost.sh failed:\n{result.stdout[-6000:]}\n{result.stderr[-6000:]}"
    assert "PASSED" in result.stdout
    assert "jobs submitted with sbatch, all COMPLETED" in result.stdout
    assert "parameter stores agree" in result.stdout
