"""The Snakemake workflow end to end: real `snakemake --cores 2` runs on a tiny synthetic capture
(synth -> ingest -> known poses -> initial mesh -> one iteration of observe / sharded fit /
clusters / refit / geometry update -> final refit -> model, renders, metrics), checked against
the ground truth; resumability after SIGKILL (in the last iteration of a copy of that run); one
fit job per shard, pass and iteration."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from helpers import session_jax_cache

pytestmark = pytest.mark.slow  # the whole module: `make test-fast` leaves it out

REPO = Path(__file__).resolve().parents[2]
ITERATIONS = 1
SHARDS = 2


def tiny_config(workdir: Path) -> dict:
    """Overrides of config/config.yaml for a run of a few minutes on 2 cores."""
    return {
        "name": "tiny",
        "iterations": ITERATIONS,
        "demo": {"scene": "tiny", "views": 24, "width": 320, "height": 256, "seed": 3},
        "init": {"hull_resolution": 64, "max_vertices": 2500},
        # Fit shards are whole observation chunks: 256-vertex chunks split ~2.4k vertices over both shards.
        # The 2-px silhouette margin drops 38 % of the samples of a 160x128-pixel capture: normal median
        # 4.73 deg instead of < 4 (docs/accuracy.md). Off here; the bounds below are about everything else.
        # The demo's slope test (demo.overrides) is for its 612x512 capture; at this size it leaves too few samples
        # (docs/observe.md). Set here, it stays off: a user's setting wins over the demo's even at the default.
        "observe": {"vertex_chunk": 256, "edge_margin": 0.0, "max_slope": 0.0},
        "fit": {"shards": SHARDS, "compilation_cache": str(session_jax_cache(workdir)), "settings": {"min_views": 6}},
        "augment": {"max_samples": 4096},
        "evaluate": {"held_out_views": ["v005", "v017"], "render_views": ["v000"], "supersample": 1},
    }


def _command(workdir: Path, *args: str) -> tuple[list[str], dict]:
    override = workdir / "tiny.yaml"
    override.write_text(yaml.safe_dump(tiny_config(workdir)))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), *args]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    return command, env


def _snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    """Run snakemake on the repository's workflow in ``workdir`` with the tiny-scene config on top."""
    command, env = _command(workdir, *args)
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=1500, check=False)
    if result.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}")
    return result


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("workflow")
    _snakemake(workdir, "--cores", "2")
    return workdir


def test_dry_run_has_one_fit_job_per_shard_pass_and_iteration(tmp_path):
    passes = 2 * (ITERATIONS + 1)  # fit and refit, iterations 0..ITERATIONS (the last is the final pass)
    for shards in (2, 3):
        out = _snakemake(tmp_path, "-n", "--set-scatter", f"fit={shards}").stdout
        counts = {line.split()[0]: int(line.split()[1]) for line in out.splitlines()
                  if len(line.split()) == 2 and line.split()[1].isdigit()}
        assert counts["fit_pbrdf"] == shards * passes, out[-2000:]
        assert counts["gather_fit"] == passes and counts["cluster_lobes"] == ITERATIONS + 1
        assert counts["refine_geometry"] == ITERATIONS and counts["gather_observations"] == ITERATIONS + 1


def test_the_demo_overrides_apply_where_the_user_set_nothing(tmp_path):
    """The built-in demo runs demo.overrides (six iterations) where the user set nothing, and the user's own value
    where they set one, also a value equal to the default (iterations 10, by --config)."""
    def dry_run(*args: str) -> tuple[int, str]:
        command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory",
                   str(tmp_path), "--configfile", str(REPO / "config" / "config.yaml"), "-n", "-p", *args]
        out = subprocess.run(command, capture_output=True, text=True, timeout=600, check=True).stdout
        return next(int(line.split()[1]) for line in out.splitlines() if line.startswith("cluster_lobes ")), out

    jobs, out = dry_run()  # iterations 0..6 (the last the final pass), the slope test
    # augment sets nothing: min_coherence takes its declared default (0.5)
    assert jobs == 6 + 1 and '"max_slope": 0.4' in out and "--augment-settings '{}'" in out
    jobs, out = dry_run("--config", "iterations=10")
    assert jobs == 10 + 1 and '"max_slope": 0.4' in out


def test_tiny_capture_reconstructs_close_to_the_ground_truth(tiny_run):
    from sellip.model.params import read_params
    from sellip.model.ply import read_param_mesh, read_ply

    results = tiny_run / "results" / "tiny"
    metrics = json.loads((results / "metrics.json").read_text())
    print("tiny capture metrics:", json.dumps(metrics, indent=1)[:3000])
    model = read_param_mesh(results / "final" / "model.ply")
    vertex, _ = read_ply(results / "final" / "model.ply")
    store = read_params(results / "final" / "params.zarr")
    assert model.num_vertices == len(store["vertices"]) and {"confidence", "model"} <= set(vertex)
    for name in ("normals", "eta", "rho_d", "rho_s", "sigma_s", "rho_ss", "sigma_ss", "confidence"):
        assert np.all(np.isfinite(store[name])), name
    assert (results / "final" / "renders").is_dir() and any((results / "final" / "renders").glob("*.png"))
    # The last rule (issue #40): the viewer, the materials table (with the truth beside it) and the exports.
    assert (results / "viewer" / "index.html").is_file() and (results / "final" / "model.glb").is_file()
    assert "gt_eta" in (results / "final" / "materials.csv").read_text().splitlines()[0]
    assert (results / "final" / "maps" / "map_eta.ply").is_file()
    # Measured 2026-11-24 on this scene (24 views of 160x128 demosaiced pixels, a 4 cm sphere): one
    # iteration, normal median 3.2 deg, eta median 10.7 %, Chamfer 0.97 mm, held-out PSNR 23.8 dB (two
    # iterations: 2.9 deg, 10.3 %, 0.95 mm, 23.2 dB; one keeps the suite inside CI's time).
    # Bounds that catch regressions, not targets (see docs/reconstruction.md).
    assert metrics["normal_error_deg"]["all"]["median"] < 4.0
    assert metrics["eta_relative_error_pct"]["median"] < 14.0
    assert metrics["geometry"]["chamfer_mm"] < 1.2
    assert metrics["psnr_held_out"]["mean_db"] > 20.0
    assert metrics["timings"]["rules"]["fit_pbrdf"]["jobs"] == SHARDS * 2 * (ITERATIONS + 1)
    # The geometry over the loop: the initial mesh, then each iteration's; the update moved the surface.
    series = metrics["geometry_iterations"]
    assert [row["mesh"] for row in series] == list(range(ITERATIONS + 1)) and series[0]["fitted_normal_deg"]
    assert series[1]["chamfer_to_previous_mm"] > 0 and (results / "final" / "geometry_convergence.png").is_file()


def test_the_clustering_replay_reproduces_the_runs_clusters(tiny_run, capsys):
    """benchmarks/replay_clustering.py (the replays of docs/augment.md) re-runs the workflow's clustering: on the
    run's own settings it gives the run's labels; with the coherence test off, the clustering without it."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("replay_clustering", REPO / "benchmarks" / "replay_clustering.py")
    replay = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(replay)
    run = tiny_run / "results" / "tiny"
    clustering, settings, _ = replay.replay(run, 0)
    assert settings["min_coherence"] == 0.5  # the default
    np.testing.assert_array_equal(clustering.labels, np.load(run / "iter" / "0" / "clusters" / "labels.npy"))
    # The final pass was given pass 0's clusters (the hysteresis), and its replay with them gives its labels.
    assert "the previous pass's clusters: results/tiny/iter/0/clusters" in (
        run / "logs" / "cluster_lobes" / "1.log").read_text()
    final, _, _ = replay.replay(run, 1)
    np.testing.assert_array_equal(final.labels, np.load(run / "iter" / "1" / "clusters" / "labels.npy"))
    truth = tiny_run / "captures" / "tiny" / "ground_truth" / "model.ply"
    assert replay.main([str(run), "--iteration", "0", "--truth", str(truth), "--set", "min_coherence=0"]) == 0
    out = capsys.readouterr().out
    assert "'min_coherence': 0" in out and "eta per material (cluster medians)" in out
    with pytest.raises(ValueError, match="not AugmentSettings fields"):
        replay.replay(run, 0, {"min_coherenc": 0.5})
    # clusters.json also records the lobe fit's settings, which benchmarks/replay_lobes.py fits with.
    from sellip.fit.records import FitSettings

    info = json.loads((run / "iter" / "0" / "clusters" / "clusters.json").read_text())
    assert FitSettings(**info["fit_settings"]).min_views == 6  # the run's fit.settings (tiny_run)


def _kill_when(command, env, ready: Path, timeout: float = 900) -> None:
    """Start ``command``; SIGKILL its whole process group as soon as ``ready`` exists."""
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    began = time.monotonic()
    try:
        while not ready.exists():
            if process.poll() is not None:
                raise AssertionError(f"snakemake ended (exit {process.returncode}) before {ready} appeared")
            if time.monotonic() - began > timeout:
                raise AssertionError(f"{ready} did not appear within {timeout} s")
            time.sleep(0.5)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()


def test_killed_run_resumes_without_redoing_finished_jobs(tiny_run, tmp_path_factory):
    """A copy of the finished run with its last iteration and outputs removed (Snakemake's metadata kept), so
    the killed run redoes one iteration, not the whole pipeline: SIGKILL once the last iteration's fit is
    gathered, then resume. The copy sits beside the first run so that both configs name the same XLA cache."""
    from sellip.model.params import read_params

    workdir = tmp_path_factory.mktemp("resumed")
    shutil.copytree(tiny_run, workdir, symlinks=True, dirs_exist_ok=True)
    results = workdir / "results" / "tiny"
    for stale in (results / "iter" / str(ITERATIONS), results / "final"):
        shutil.rmtree(stale)
    (results / "metrics.json").unlink()
    # Outputs of the jobs before the last iteration: neither the killed run nor the resumed one may redo them.
    finished = {path: path.stat().st_mtime_ns for path in
                [results / "mesh" / "init.ply", results / "hdr.zarr" / "zarr.json",
                 results / "iter" / "0" / "refit.zarr" / "zarr.json",
                 results / "iter" / str(ITERATIONS - 1) / "mesh.ply"]}
    command, env = _command(workdir, "--cores", "2")
    _kill_when(command, env, results / "iter" / str(ITERATIONS) / "fit.zarr")
    # (The job that wrote the last fit.zarr may have been killed before Snakemake recorded it as complete:
    # re-running it is then correct.)
    assert not (results / "final" / "model.ply").exists()
    _snakemake(workdir, "--unlock")
    resumed_run = _snakemake(workdir, "--cores", "2", "--rerun-incomplete")
    log = resumed_run.stdout + resumed_run.stderr  # Snakemake logs "rule NAME:" per job on stderr
    for path, mtime in finished.items():
        assert path.stat().st_mtime_ns == mtime, f"{path} was made again"
    assert "rule init_mesh:" not in log and "rule merge_hdr:" not in log and "rule refine_geometry:" not in log
    assert "rule finalize_model:" in log and "rule evaluate_model:" in log
    resumed = read_params(results / "final" / "params.zarr")
    uninterrupted = read_params(tiny_run / "results" / "tiny" / "final" / "params.zarr")
    for name in ("vertices", "normals", "eta", "rho_d", "sigma_s", "confidence"):
        np.testing.assert_allclose(resumed[name], uninterrupted[name], rtol=1e-5, atol=1e-6, err_msg=name)


def test_pose_refinement_joins_the_loop_and_keeps_true_poses(tiny_run, tmp_path_factory):
    """`refine_poses.enabled: true` (auto: only for SfM poses) puts a refine_poses job before every iteration after
    the first, whose cameras the rest of the loop, the renders and the figures then read; run on a copy of the
    finished run (known, exact poses), it aligns every view to iteration 0's model and keeps the poses within a
    fraction of a pixel of the truth."""
    from sellip.geometry.cameras import load_cameras
    from sellip.report.figures_of_merit import truth_reprojection

    workdir = tmp_path_factory.mktemp("refined")
    shutil.copytree(tiny_run, workdir, symlinks=True, dirs_exist_ok=True)
    results = workdir / "results" / "tiny"
    plan = _snakemake(workdir, "-n", "-p", "--config", "refine_poses={enabled: true}").stdout
    counts = {line.split()[0]: int(line.split()[1]) for line in plan.splitlines()
              if len(line.split()) == 2 and line.split()[1].isdigit()}
    assert counts["refine_poses"] == ITERATIONS and counts["gather_observations"] == 1, plan[-3000:]
    assert f"--cameras results/tiny/iter/{ITERATIONS}/cameras.csv" in plan  # the later jobs read the new poses
    assert "refine_poses" not in _snakemake(workdir, "-n").stdout  # auto, with poses.csv: off
    assert "refine_poses" in _snakemake(workdir, "-n", "--config", "sfm={mode: sfm}").stdout  # auto, SfM poses: on
    _snakemake(workdir, "--cores", "2", "--config", "refine_poses={enabled: true}", "--allowed-rules", "refine_poses",
               "--", f"results/tiny/iter/{ITERATIONS}/cameras.csv")
    report = json.loads((results / "iter" / str(ITERATIONS) / "cameras.csv.json").read_text())
    # Every view was aligned (none short of pixels), and every aligned pose, taken or not, puts the visible surface
    # within a fraction of a pixel of where the true pose puts it (motion_px: the start is the truth). A view keeps
    # its pose only by the divergence guard (2 deg, a shift of 3 % of 0.9 m): from exact poses the centres drift
    # along the narrow field's weak direction, which the photographs do not pin (15 mm median, docs/geometry.md), and
    # how many cross the guard follows the model's noise, so the count is not the claim: at most 4 of 24 from an
    # initial mesh of 2,393 vertices, 6 from ones of 2,395 and 2,400 (2026-11-28; turns of 1.8-2.4 deg and shifts of
    # 28-38 mm that move the visible surface 0.10-0.43 px). Most views take their pose: the bounds below test them.
    per_view = report["per_view"]
    assert report["views"] == 24 == len(per_view) and report["refined"] > 12, report["kept"]
    assert all("taken for a divergence" in why for why in report["kept"].values()), report["kept"]
    assert all(view["motion_px"] < 0.6 for view in per_view.values()), \
        {name: view.get("motion_px") for name, view in per_view.items()}
    hdr = results / "hdr.zarr"
    known, _ = load_cameras(results / "cameras.csv", hdr)
    refined, _ = load_cameras(results / "iter" / str(ITERATIONS) / "cameras.csv", hdr)
    from sellip.model.ply import read_param_mesh
    from sellip.model.render import Renderer

    truth = Renderer(read_param_mesh(workdir / "captures" / "tiny" / "ground_truth" / "model.ply"))
    moved = truth_reprojection(refined, {v: (c.rotation, c.translation) for v, c in known.items()}, truth, None)
    # Aligned to the hull's first fit on a 160x128-pixel capture the visible surface moved 0.12 px in the median view
    # (0.35 the worst) when this was written: the model's own error. (The centres moved 15 mm in the median: the
    # weak direction of a narrow field of view, which the photographs do not pin; docs/geometry.md.)
    assert moved["reprojection_px"]["median"] < 0.25 and moved["reprojection_px"]["max"] < 0.6, moved


# --------------------------------------------------------------------------- a failed or interrupted run is visible

def test_a_failed_rerun_says_the_model_is_stale(tiny_run, tmp_path_factory):
    """An input changed so that a job fails (capture.yaml's camera.fx in millimetres): the console says that the
    model on disk is an earlier run's and which rule failed, and `sellip view` says so too (before: the previous
    run's model, metrics and viewer in place, unmarked)."""
    workdir = tmp_path_factory.mktemp("stale")
    shutil.copytree(tiny_run, workdir, symlinks=True, dirs_exist_ok=True)
    capture_yaml = workdir / "captures" / "tiny" / "capture.yaml"
    config = yaml.safe_load(capture_yaml.read_text())
    config["camera"]["fx"] = 2.0
    capture_yaml.write_text(yaml.safe_dump(config))
    command, env = _command(workdir, "--cores", "2")
    failed = subprocess.run(command, capture_output=True, text=True, env=env, timeout=900, check=False)
    text = failed.stdout + failed.stderr
    assert failed.returncode != 0, text[-3000:]
    assert "sellip: rule linearize_frames failed" in text
    stale = [line for line in text.splitlines() if line.startswith("sellip: results/tiny/final/model.ply (made ")]
    assert stale and ") is out of date: the last run (started " in stale[0], text[-3000:]
    assert "failed at rule linearize_frames (log: results/tiny/logs/linearize_frames.log)" in stale[0]
    assert "1 capture file(s) changed after it (captures/tiny/capture.yaml)" in stale[0]
    record = json.loads((workdir / "results" / "tiny" / "last_run.json").read_text())
    assert record["status"] == "failed" and record["failed"][0]["rule"] == "linearize_frames"
    view = subprocess.run([sys.executable, "-m", "sellip.cli", "view", "results/tiny"], cwd=workdir, env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    warned = [line for line in view.stderr.splitlines() if "WARNING" in line and "is out of date" in line]
    assert warned and "rule linearize_frames" in warned[0] and "capture file(s) changed after it" in warned[0], \
        view.stderr[-3000:]
