"""A job killed mid-write leaves nothing at its output paths (issue #38, "faults during a run"), for every rule of
the workflow, on real Snakemake jobs.

Every writer of an output builds it under a hidden temporary name and renames it when complete
(:func:`sellip.jobs.atomic_file`, :func:`sellip.jobs.atomic_directory`). The test runs a tiny capture to the end
once (``--notemp``, so every intermediate stays), then, rule by rule, forces that rule's jobs again
(``--forcerun RULE --until RULE --keep-incomplete``: Snakemake keeps whatever a failed job left) in an environment
where a ``sitecustomize`` kills the rule's ``sellip`` process with SIGKILL at its first rename onto a visible path
of the results folder: the moment a complete output would appear. Then:

- the job was killed (it reached a rename: a stage that writes its output in place and never renames fails here);
- none of the outputs Snakemake lists for the failed job exists (a stage that wrote one output in place before
  renaming another fails here);
- the next run plans the killed jobs again (``snakemake -n``; but linearize_frames, whose output is temporary and
  already merged).

About 6 minutes on 2 cores (12 views of 160x128 raw pixels, 600 vertices, one iteration).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from helpers import session_jax_cache

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
NAME = "killed"
RULES = ("linearize_frames", "merge_hdr", "plot_hdr_previews", "run_sfm", "init_mesh", "gather_observations",
         "fit_pbrdf", "gather_fit", "cluster_lobes", "refine_geometry", "finalize_model", "render_outputs",
         "evaluate_model", "export_viewer")
"""Every rule a capture's run has (``synth_capture`` makes the capture and is not part of a user's run)."""

SITECUSTOMIZE = '''
import os, signal, sys
from pathlib import Path

_stage, _root, _marks = (os.environ.get(k) for k in ("KILL_STAGE", "KILL_ROOT", "KILL_MARKS"))
_argv = [a for a in sys.argv[1:] if not a.startswith("-")]
if _stage and _argv[:1] == [_stage] and Path(sys.argv[0]).name in ("sellip", "cli.py", "__main__.py"):
    _real = {"rename": os.rename, "replace": os.replace}

    def _visible_result(destination):
        path = Path(os.path.abspath(destination))
        root = Path(_root)
        return path.is_relative_to(root) and not any(p.startswith(".") for p in path.relative_to(root).parts)

    def _wrap(name):
        def commit(source, destination, *args, **kwargs):
            if _visible_result(destination):
                Path(_marks, f"{_stage}-{os.getpid()}").write_text(str(destination))
                os.kill(os.getpid(), signal.SIGKILL)
            return _real[name](source, destination, *args, **kwargs)
        return commit

    os.rename, os.replace = _wrap("rename"), _wrap("replace")
'''


def config(workdir: Path) -> dict:
    return {
        "name": NAME, "iterations": 1,
        "demo": {"scene": "tiny", "views": 12, "width": 160, "height": 128, "seed": 5},
        "init": {"hull_resolution": 48, "max_vertices": 600},
        "observe": {"vertex_chunk": 256, "edge_margin": 0.0, "max_slope": 0.0},
        "fit": {"shards": 1, "compilation_cache": str(session_jax_cache(workdir.parent)), "settings": {"min_views": 4}},
        # The other workflow tests' value (not the 2048 this small capture would need): the lobe fits' kernels, shaped
        # by it, then come from the session's XLA cache instead of a compilation of their own (~2 CPU minutes).
        "augment": {"max_samples": 4096},
        "evaluate": {"held_out_views": ["v005"], "render_views": ["v000"], "supersample": 1},
    }


def snakemake(workdir: Path, *args: str, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    override = workdir / "killed.yaml"
    override.write_text(yaml.safe_dump(config(workdir)))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), "--cores", "2", *args]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           **(env_extra or {})}
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=1200, check=False)


def stage_of_rule() -> dict[str, str]:
    """rule name -> the ``sellip`` command its shell runs, read from workflow/rules/*.smk."""
    stages = {}
    for smk in (REPO / "workflow" / "rules").glob("*.smk"):
        for block in re.split(r"^rule ", smk.read_text(), flags=re.MULTILINE)[1:]:
            name = block.split(":", 1)[0].strip()
            # a loop job's command may follow the pass-through prefix (sellip.fit.convergence)
            match = re.search(r'sellip_shell\(\s*"(?:\{params\.pass_through\} )?([a-z-]+)', block)
            if match:
                stages[name] = match.group(1)
    return stages


def failed_outputs(text: str, rule: str) -> list[list[str]]:
    """The output lists of the failed jobs of ``rule`` in a Snakemake log ('Error in rule RULE: ... output: a, b')."""
    jobs = []
    for block in re.split(r"Error in rule ", text)[1:]:
        if block.startswith(f"{rule}:"):
            match = re.search(r"^\s*output: (.+)$", block, re.MULTILINE)
            jobs.append([p.strip() for p in match.group(1).split(",")] if match else [])
    return jobs


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("killed") / "work"
    workdir.mkdir()
    result = snakemake(workdir, "--notemp")
    assert result.returncode == 0, result.stderr[-5000:]
    assert (workdir / "results" / NAME / "metrics.json").is_file()
    return workdir


def test_every_rule_runs_a_sellip_stage():
    stages = stage_of_rule()
    assert set(RULES) <= set(stages), sorted(set(RULES) - set(stages))


@pytest.mark.parametrize("rule", RULES)
def test_a_job_killed_at_its_commit_leaves_no_output(finished, rule, tmp_path):
    stage = stage_of_rule()[rule]
    hooks, marks = tmp_path / "hooks", tmp_path / "marks"
    hooks.mkdir()
    marks.mkdir()
    (hooks / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = {"KILL_STAGE": stage, "KILL_ROOT": str(finished / "results"), "KILL_MARKS": str(marks),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(hooks), os.environ.get("PYTHONPATH")]))}
    result = snakemake(finished, "--forcerun", rule, "--until", rule, "--keep-incomplete", env_extra=env)
    text = result.stdout + result.stderr
    killed = sorted(marks.iterdir())
    assert result.returncode != 0 and killed, f"{rule} ({stage}) finished without a rename to commit:\n{text[-3000:]}"
    jobs = failed_outputs(text, rule)
    assert jobs and all(jobs), f"no failed {rule} job with outputs in Snakemake's log:\n{text[-3000:]}"
    for outputs in jobs:
        left = [p for p in outputs if (finished / p).exists()]
        assert not left, f"{rule} killed at {killed[0].read_text()} left {left} behind"
    plan = snakemake(finished, "-n")
    assert plan.returncode == 0, plan.stderr[-3000:]
    if rule != "linearize_frames":  # its linear.zarr is temporary: merge_hdr's hdr.zarr is complete, none needs it
        assert re.search(rf"^{rule}\s+\d+\s*$", plan.stdout, re.MULTILINE), plan.stdout[-3000:]


def test_a_fit_shard_over_its_memory_says_on_the_console_how_many_shards_fit(finished):
    """The workflow's fit job with a mem_mb below what the iteration's one shard needs (and above what each of two
    would): the job stops before reading, and the console names the shard count (sellip.fit.shard)."""
    import zarr

    from sellip.fit.shard import SHARD_MEMORY, largest_shard

    path = f"results/{NAME}/iter/0/observations.zarr"
    made = snakemake(finished, path)  # again, if a test above killed the job that writes it
    assert made.returncode == 0, made.stderr[-3000:]
    store = zarr.open_group(str(finished / path), mode="r")
    total, views = store["diffuse"].shape[:2]
    chunk = store["diffuse"].chunks[0]
    largest = largest_shard(total, chunk, 2)
    assert largest < total
    mem_mb = int(SHARD_MEMORY.bytes(largest, views, 8192) / 1e6) + 1
    result = snakemake(finished, "--forcerun", "fit_pbrdf", "--until", "fit_pbrdf",
                       "--set-resources", f"fit_pbrdf:mem_mb={mem_mb}")
    console = result.stdout + result.stderr
    assert result.returncode != 0
    assert "sellip: rule fit_pbrdf failed" in console and "fit shard 1 of 1 needs about" in console, console[-3000:]
    assert f"more than the job's {mem_mb:,} MB" in console and "run with fit.shards: 2" in console
