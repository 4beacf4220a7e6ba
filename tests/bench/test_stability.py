"""The stability suite (sellip.bench.stability, `sellip bench-stability`): its scenes, the synthetic noise option,
bad frames through ingest, the perturbation and miscalibration steps, the confidence-flagging figures, the
finiteness check and the tables. The suite's Snakemake runs themselves take half an hour (docs/stability.md);
here every piece is checked on its own, with a fake runner for the suite."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from sellip.bench import stability, stability_table
from sellip.bench.sweep_plan import merge
from sellip.capture import files, reader
from sellip.capture import synthetic as capture_synthetic
from sellip.capture.scenes import build_scene, icosphere
from sellip.capture.sensor import SensorModel, simulate_raw
from sellip.geometry.meshes import vertex_normals
from sellip.model import ply as model_ply

REPO = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- scenes and the noise option


@pytest.mark.parametrize("name, rho_d, sigma_s", [("tiny_dark", (0.02, 0.05), (0.15, 0.3)),
                                                  ("tiny_white", (0.6, 0.85), (0.55, 0.6)),
                                                  ("tiny_mirror", (0.03, 0.08), (0.03, 0.05))])
def test_failure_case_scenes_have_the_materials_they_promise(name, rho_d, sigma_s):
    scene = build_scene(name)
    mesh, p = scene.mesh, scene.mesh.params
    assert scene.name == name and mesh.vertices.shape == (2562, 3) and len(scene.materials) == 2
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices, axis=1), 0.04)
    np.testing.assert_allclose(np.sum(mesh.normals * mesh.vertices / 0.04, axis=1), 1.0, atol=1e-12)
    assert rho_d[0] - 1e-9 <= p.rho_d.min() and p.rho_d.max() <= rho_d[1] + 1e-9
    assert p.rho_d.max() / p.rho_d.min() > 1.2  # a texture, not a flat colour
    assert set(np.unique(p.sigma_s)) == set(sigma_s)
    assert set(np.unique(mesh.material)) == {0, 1} and abs(np.mean(mesh.material) - 0.5) < 0.1
    if name == "tiny_white":  # single scattering as wide as the specular lobe on the bottom half
        bottom = mesh.material == 1
        assert np.all(p.rho_ss[bottom] > 0) and np.all(p.rho_ss[~bottom] == 0)
        assert np.all(np.abs(p.sigma_ss[bottom] - p.sigma_s[bottom]) <= 0.05)
    assert scene.flash_power == build_scene("tiny").flash_power


def test_bumpy_scene_has_bumps_and_dents_with_the_normals_of_its_surface():
    from sellip.capture.scenes import TINY_BUMPS

    scene = build_scene("tiny_bumpy")
    mesh = scene.mesh
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert mesh.vertices.shape == (10242, 3) and len(TINY_BUMPS) == 6
    assert radius.max() == pytest.approx(0.044, abs=2e-4) and radius.min() == pytest.approx(0.036, abs=2e-4)
    np.testing.assert_allclose(mesh.normals, vertex_normals(mesh.vertices, mesh.faces, area_weighted=True))
    tilt = np.degrees(np.arccos(np.clip(np.sum(mesh.normals * mesh.vertices / radius[:, None], axis=1), -1, 1)))
    assert 15 < tilt.max() < 25 and np.mean(tilt > 5) > 0.1  # detail a smooth sphere does not have
    np.testing.assert_array_equal(np.unique(mesh.params.eta), [1.4, 1.6])  # the tiny scene's materials


def test_noise_scale_multiplies_the_noise_and_keeps_the_signal():
    analyzers = np.full((128, 128, 4, 3), 1.0)
    residuals = {}
    for scale in (1.0, 4.0):
        sensor = SensorModel(width=128, height=128, color_layout="mono").with_noise_scale(scale)
        raw = simulate_raw(analyzers, sensor, 300.0, np.random.default_rng(5)).astype(np.float64) - 64
        assert raw.mean() == pytest.approx(300, abs=1.0)
        residuals[scale] = raw.std()
    assert residuals[4.0] / residuals[1.0] == pytest.approx(4.0, rel=0.05)
    with pytest.raises(ValueError, match="positive"):
        SensorModel(width=8, height=8).with_noise_scale(0)


@pytest.mark.slow
def test_synth_records_the_noise_scale_and_the_workflow_passes_it(tmp_path):
    path = capture_synthetic.synthesize_capture("tiny_dark", tmp_path / "capture", views=1, width=64, height=48,
                                                supersample=1, progress=False, noise_scale=3.0)
    extra = reader.read_capture(path).config["synthetic"]
    assert extra["noise_scale"] == 3.0 and extra["gain_e_per_dn"] == pytest.approx(2.58 / 9)
    assert extra["read_noise_e"] == pytest.approx(0.8)
    # The demo: section reaches `sellip synth` (dry run, commands printed).
    override = tmp_path / "override.yaml"
    override.write_text(yaml.safe_dump(stability.case_config(stability.CASES[stability.CASE_NAMES.index("noise_x4")],
                                                             tmp_path)))
    out = subprocess.run(stability.snakemake_command(REPO / "Snakefile", tmp_path / "work", override, "-n", "-p"),
                         capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    # ingest: nothing set, so linearize takes the declared defaults (bad_frames "error")
    linearize = [line for line in out.stdout.splitlines() if " linearize --capture " in line]
    assert "--noise-scale 4.0" in out.stdout and linearize and "--settings '{}'" in linearize[0]


# --------------------------------------------------------------------------- bad frames through ingest


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    """Three views of the tiny sphere at 64x48 (9 DNG frames)."""
    return capture_synthetic.synthesize_capture("tiny", tmp_path_factory.mktemp("capture") / "tiny", views=3, width=64,
                                                height=48, supersample=1, progress=False)


def _copy(capture, to):
    import shutil

    shutil.copytree(capture, to)
    return to


@pytest.mark.slow
def test_bad_frames_skip_merges_from_the_other_frames_and_drops_empty_views(small_capture, tmp_path, caplog):
    from sellip.capture.hdr import merge_capture, read_hdr
    from sellip.capture.ingest import IngestSettings
    from sellip.capture.linearize import linearize_capture
    from sellip.geometry import poses as geometry_poses

    clean = read_hdr(merge_capture(linearize_capture(small_capture, tmp_path / "clean" / "linear.zarr"),
                                   tmp_path / "clean" / "hdr.zarr"))
    capture = _copy(small_capture, tmp_path / "broken")
    touched = stability.damage_frames(capture, missing=("v000_f0", "v002_f0", "v002_f1"), corrupt=("v001_f1",),
                                      truncated=("v002_f2",), seed=1)
    assert touched == ["raw/v000_f0.dng", "raw/v002_f0.dng", "raw/v002_f1.dng", "raw/v001_f1.dng",
                       "raw/v002_f2.dng"]
    # The default stops at the first bad frame, naming its file and frames.csv row; nothing is written.
    with pytest.raises(files.CaptureError, match=r"row 0 \(line 2\).*v000_f0\.dng"):
        linearize_capture(capture, tmp_path / "error" / "linear.zarr")
    only_corrupt = _copy(small_capture, tmp_path / "corrupt")
    stability.damage_frames(only_corrupt, corrupt=("v001_f1",), seed=1)
    with pytest.raises(files.CaptureError, match=r"v001_f1\.dng.*row 4 \(line 6\).*bad_frames: skip"):
        linearize_capture(only_corrupt, tmp_path / "error" / "linear.zarr", threads=2)
    assert not (tmp_path / "error").exists() or not any((tmp_path / "error").iterdir())
    # skip: the frames are left out with a warning naming the file and row; v002 has no frame left.
    with caplog.at_level("WARNING"):
        linear = linearize_capture(capture, tmp_path / "skip" / "linear.zarr", threads=2,
                                   settings=IngestSettings(bad_frames="skip"))
    assert "v001_f1.dng: cannot be read" in caplog.text and "row 4 (line 6)" in caplog.text
    assert "v000_f0.dng: raw frame does not exist" in caplog.text
    import zarr

    skipped = zarr.open_group(str(linear), mode="r").attrs["skipped"]
    assert [s is not None for s in skipped] == [True, False, False, False, True, False, True, True, True]
    hdr = read_hdr(merge_capture(linear, tmp_path / "skip" / "hdr.zarr"))
    assert hdr.view_ids == ["v000", "v001"] and hdr.attrs["frames_per_view"] == [2, 2]
    assert hdr.attrs["dropped_views"] == ["v002"]
    for view in ("v000", "v001"):  # the same HDR image from two frames as from three, within the noise
        (a, valid), (b, clean_valid) = hdr.view(view), clean.view(view)
        both = valid & clean_valid
        assert both.mean() > 0.9 * clean_valid.mean()
        bright = both[..., None, None] & (b > 0.2 * b.max())
        assert np.median(np.abs(a[bright] / b[bright] - 1)) < 0.05
    # Stages that never read raw frames go on; known poses only for the views that remain, and a held-out
    # view that was dropped is simply not there to hold out.
    from sellip.fit import observe_mesh
    from sellip.stages import observe

    cameras = tmp_path / "skip" / "cameras.csv"
    geometry_poses.solve_poses(tmp_path / "skip" / "hdr.zarr", capture, cameras, tmp_path / "skip" / "sfm")
    assert list(pd.read_csv(cameras)["view_id"]) == ["v000", "v001"]
    observe_mesh.observe_mesh(capture / files.GROUND_TRUTH_MESH, cameras, tmp_path / "skip" / "hdr.zarr", capture,
                      tmp_path / "skip" / "observations.zarr", exclude_views=("v002",))
    assert zarr.open_group(str(tmp_path / "skip" / "observations.zarr"), mode="r").attrs["view_ids"] == ["v000", "v001"]
    with pytest.raises(observe.ObserveError, match="v009"):  # a held-out view that never existed is an error
        observe_mesh.observe_mesh(capture / files.GROUND_TRUTH_MESH, cameras, tmp_path / "skip" / "hdr.zarr", capture,
                          tmp_path / "skip" / "other.zarr", exclude_views=("v009",))
    with pytest.raises(files.MissingFileError):
        reader.read_capture(capture)  # the default still insists on every file


# --------------------------------------------------------------------------- breaking the capture and the mesh


def test_perturbation_moves_along_the_normals_by_sigma_and_is_seeded():
    d, faces = icosphere(3)
    normals = vertex_normals(d, faces, area_weighted=True)
    moved = stability.perturb_along_normals(d, 2 * normals, 0.01, seed=7)
    offset = moved - d
    np.testing.assert_allclose(np.linalg.norm(np.cross(offset, normals), axis=1), 0, atol=1e-12)
    signed = np.sum(offset * normals, axis=1)
    assert np.sqrt(np.mean(signed ** 2)) == pytest.approx(0.01, rel=0.1) and abs(signed.mean()) < 0.002
    np.testing.assert_array_equal(moved, stability.perturb_along_normals(d, 2 * normals, 0.01, seed=7))
    assert not np.array_equal(moved, stability.perturb_along_normals(d, normals, 0.01, seed=8))
    with pytest.raises(ValueError, match="non-zero"):
        stability.perturb_along_normals(d, normals * 0, 0.01, seed=7)
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        stability.perturb_along_normals(d, normals[:-1], 0.01, seed=7)


def test_perturbed_mesh_file_keeps_faces_and_gets_the_new_surfaces_normals(tmp_path):
    d, faces = icosphere(3)
    vertex = {k: v.astype(np.float32) for k, v in zip(("x", "y", "z", "nx", "ny", "nz"), np.hstack([d, d]).T)}
    path = tmp_path / "init.ply"
    model_ply.write_ply(path, vertex, faces)
    stability.perturb_mesh_file(path, 0.02, seed=3)
    out, out_faces = model_ply.read_ply(path)
    np.testing.assert_array_equal(out_faces, faces)
    xyz = np.stack([out[k] for k in "xyz"], axis=1)
    radius = np.linalg.norm(xyz, axis=1)
    assert 0.015 < np.std(radius) < 0.025 and out["x"].dtype == np.float32
    normals = np.stack([out[k] for k in ("nx", "ny", "nz")], axis=1)
    np.testing.assert_allclose(normals, vertex_normals(xyz.astype(np.float64), faces, area_weighted=True), atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["init.ply"]  # no temporary left behind


def test_miscalibrated_flash_changes_only_the_declared_position(small_capture, tmp_path):
    capture = _copy(small_capture, tmp_path / "capture")
    before = yaml.safe_load((capture / "capture.yaml").read_text())
    true, declared = stability.miscalibrate_flash(capture, (0.01, 0.0, -0.005))
    assert true == [0.0, 0.05, 0.0] and declared == pytest.approx([0.01, 0.05, -0.005])
    after = reader.read_capture(capture).config
    assert after["light"]["position_m"] == pytest.approx(declared)
    assert after["sensor"] == before["sensor"] and after["camera"] == before["camera"]
    assert after["synthetic"]["true_flash_position_m"] == true
    with pytest.raises(stability.StabilityError, match="v999_f0"):
        stability.damage_frames(capture, missing=("v999_f0",))


# --------------------------------------------------------------------------- figures


def test_rank_auc_matches_counting_pairs():
    rng = np.random.default_rng(0)
    score = rng.integers(0, 6, 200).astype(float)  # many ties
    positive = rng.random(200) < 0.3
    pos, neg = score[positive], score[~positive]
    pairs = (pos[:, None] > neg[None, :]).mean() + 0.5 * (pos[:, None] == neg[None, :]).mean()
    assert stability_table.rank_auc(score, positive) == pytest.approx(pairs)
    assert stability_table.rank_auc(score, np.zeros(200, bool)) is None


def test_confidence_flagging_counts_recall_precision_and_ranking():
    error = np.array([1.0, 2.0, 3.0, 20.0, 30.0, 40.0])
    confidence = np.array([0.9, 0.8, 0.3, 0.1, 0.0, 0.7])  # one good vertex flagged, one bad one missed
    out = stability_table.confidence_flagging(error, confidence, bad_above=10)
    assert out["bad_share"] == 0.5 and out["flagged_share"] == 0.5
    assert out["bad_flagged"] == pytest.approx(2 / 3) and out["flagged_bad"] == pytest.approx(2 / 3)
    assert out["auc"] == pytest.approx(8 / 9)  # a bad vertex below a good one in 8 of the 9 pairs
    perfect = stability_table.confidence_flagging(error, 1 - error / 30, bad_above=10)
    assert perfect["auc"] == 1.0 and perfect["bad_flagged"] == 1.0
    blind = stability_table.confidence_flagging(error, np.full(6, 0.8), bad_above=10)
    assert blind["auc"] == 0.5 and blind["bad_flagged"] == 0.0 and blind["flagged_bad"] is None
    # The worst tenth is the 40 deg vertex: its 0.7 is below two of the five others' confidences.
    assert out["worst_auc"] == pytest.approx(2 / 5) and blind["worst_auc"] == 0.5
    nan = stability_table.confidence_flagging(error, np.array([0.9, 0.8, 0.7, np.nan, 0.6, 0.9]), bad_above=10)
    assert nan["bad_flagged"] == pytest.approx(1 / 3)  # NaN confidence counts as flagged
    with pytest.raises(ValueError, match="one length"):
        stability_table.confidence_flagging(error, confidence[:-1], bad_above=10)


def _fake_run(workdir: Path, case: stability_table.Case, nan: bool = False, folds: tuple[int, ...] = (0, 0)) -> None:
    """A finished run of ``case`` in ``workdir``: ground truth, a model whose normals are 30 deg off on a cap
    (and flagged there with confidence 0.1 except for a band), params.zarr, a renders npz and metrics.json."""
    from sellip.model.params import write_params
    from sellip.model.ply import write_param_mesh
    from sellip.model.render import ParamMesh

    truth = build_scene("tiny").mesh
    results = workdir / "results" / case.name
    for folder in (workdir / "captures" / "tiny" / "ground_truth", results / "final" / "renders"):
        folder.mkdir(parents=True, exist_ok=True)
    write_param_mesh(workdir / "captures" / "tiny" / files.GROUND_TRUTH_MESH, truth)
    z = truth.vertices[:, 2] / 0.04
    cap = z > 0.5
    tilt = np.radians(30)
    normals = truth.normals.copy()
    normals[cap] = normals[cap] * np.cos(tilt) + np.cross(normals[cap], [1.0, 0, 0]) * np.sin(tilt)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    confidence = np.where(cap & (z > 0.6), 0.1, 0.9).astype(np.float32)
    eta = np.asarray(truth.params.eta, np.float64).copy()
    if nan:
        eta[3] = np.nan
    params = truth.params._replace(eta=eta)
    model = ParamMesh(vertices=truth.vertices, faces=truth.faces, normals=normals, params=params)
    write_param_mesh(results / "final" / "model.ply", model, extra={"confidence": confidence})
    write_params(results / "final" / "params.zarr", {"vertices": truth.vertices, "normals": normals, "eta": eta,
                 **{k: getattr(truth.params, k) for k in ("rho_d", "rho_s", "sigma_s", "rho_ss", "sigma_ss")},
                 "confidence": confidence})
    np.savez(results / "final" / "renders" / "mueller.npz", mueller=np.ones((2, 2, 3, 3, 3), np.float32))
    metrics = {"vertices": {"model": 2562, "confident": 2000}, "normal_error_deg": {"all": {"mean": 5.0,
               "median": 1.0, "p90": 30.0}}, "eta_relative_error_pct": {"median": 3.0},
               "eta_per_material": {"mean_error_pct": 0.5, "max_error_pct": 0.8},
               "rho_d_relative_rmse": {"relative_rmse": 0.1}, "sigma_s_abs_error": None,
               "geometry": {"chamfer_mm": 0.5, "hausdorff_mm": 2.0, "truth_farther_than_1mm": 0.02},
               "psnr_held_out": {"mean_db": 25.0}, "psnr_new_light": None,
               "geometry_iterations": [{"mesh": it, "self_intersecting_pairs": folds, "flipped_triangles": 0,
                                        "degenerate_triangles": 0} for it, folds in enumerate(folds)]}
    # Two passes of the clustering (as sellip.fit.augment_pass writes clusters.json): three clusters, then three with
    # one region kept as found before; the final clusters' support with one fragile.
    metrics["eta_per_material"]["materials"] = {"0": {"error_pct": 0.3}, "1": {"error_pct": 0.8}}
    metrics["material_support"] = {"clusters": {"0": {"support": 1.0}, "1": {"support": 1.0}, "2": {"support": 0.7}},
                                   "fragile": [2]}
    for it, regions in ((0, []), (1, [{"inside": 0, "vertices": 60, "coherence": 0.45, "found_before": 2}])):
        (results / "iter" / str(it) / "clusters").mkdir(parents=True)
        (results / "iter" / str(it) / "clusters" / "clusters.json").write_text(
            json.dumps({"k": 3, "merges": [], "regions": regions}))
    (results / "metrics.json").write_text(json.dumps(metrics))


def test_case_row_reads_the_figures_the_flagging_and_finiteness(tmp_path):
    case = stability.CASES[0]
    _fake_run(tmp_path, case)
    row = stability_table.case_row(case, tmp_path, wall_s=12.0)
    cap = build_scene("tiny").mesh.vertices[:, 2] / 0.04
    assert row["status"] == "ok" and row["outputs_finite"] and row["nonfinite"] == ""
    assert row["normal_median_deg"] == 1.0 and row["confident_share"] == pytest.approx(2000 / 2562)
    assert row["eta_material_mean_pct"] == 0.5 and row["eta_material_max_pct"] == 0.8
    assert row["sigma_s_median_err"] is None and row["psnr_new_light_db"] is None
    assert row["bad_share"] == pytest.approx(np.mean(cap > 0.5))
    assert row["bad_flagged"] == pytest.approx(np.sum(cap > 0.6) / np.sum(cap > 0.5))
    assert row["flagged_bad"] == 1.0 and row["auc"] > 0.9 and row["worst_auc"] > 0.8
    assert row["eta_bad_share"] == 0.0 and row["eta_auc"] is None and row["eta_worst_auc"] is None  # all tied
    assert row["truth_far_share"] == 0.02 and row["folds_max"] == 0 and row["fold_first_mesh"] is None
    assert row["true_materials"] == 2 and row["clusters_per_pass"] == "3 3" and row["found_before"] == 1
    assert row["fragile"] == "2 (0.7)"
    assert "| baseline | 2 | 3 3 | 1 | 2 (0.7) |" in stability_table.stability_markdown(
        stability_table.validate_table([row]))

    # A fold at any mesh of the loop fails the case, naming the mesh.
    _fake_run(tmp_path / "folded", case, folds=(0, 3, 0))
    row = stability_table.case_row(case, tmp_path / "folded", wall_s=12.0)
    assert row["status"] == "failed" and row["folds_max"] == 3 and row["fold_first_mesh"] == 1
    assert row["error"] == "the surface folds: mesh 1: 3 self-intersecting pairs, 0 flipped"
    assert "3 (from mesh 1)" in stability_table.stability_markdown(stability_table.validate_table([row]))

    broken = stability_table.Case("broken", "capture", "x")
    _fake_run(tmp_path / "nan", broken, nan=True)
    (tmp_path / "nan" / "results" / "broken" / "metrics.json").write_text('{"psnr": NaN}')
    row = stability_table.case_row(broken, tmp_path / "nan", wall_s=1.0, error="Error in rule fit_pbrdf: boom")
    assert row["status"] == "failed" and not row["outputs_finite"]
    assert row["nonfinite"] == "model.ply:eta 1; params.zarr:eta 1; metrics.json 1"


def test_infinite_uncertainty_is_by_design_only_where_it_is_unknown(tmp_path):
    """+inf std: not fitted (status != 0) or singular covariance (confidence 0). Anywhere else, and NaN
    anywhere, it is a defect."""
    from sellip.model.params import write_params

    def bad(status, confidence, eta_std):
        folder = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
        write_params(folder / "final" / "params.zarr", {
            "vertices": np.zeros((3, 3)), "normals": np.tile([0.0, 0.0, 1.0], (3, 1)), "eta": np.full(3, 1.5),
            "rho_d": np.full((3, 3), 0.5), "rho_s": np.zeros(3), "sigma_s": np.full(3, 0.3),
            "rho_ss": np.zeros((3, 3)), "sigma_ss": np.full(3, 0.6), "status": np.asarray(status, np.int8),
            "confidence": np.asarray(confidence, np.float32), "eta_std": np.asarray(eta_std, np.float32),
            "normal_std_deg": np.ones(3, np.float32)})
        return stability_table.nonfinite_outputs(folder).get("params.zarr:eta_std", 0)

    assert bad([0, 1, 0], [0.5, 0.0, 0.0], [0.1, np.inf, np.inf]) == 0
    assert bad([0, 1, 0], [0.5, 0.0, 0.2], [np.inf, np.inf, 0.1]) == 1
    assert bad([0, 1, 0], [0.5, 0.0, 0.0], [0.1, np.nan, np.nan]) == 2


def test_finiteness_check_reports_missing_outputs(tmp_path):
    assert stability_table.nonfinite_outputs(tmp_path) == {"model.ply": -1, "params.zarr": -1, "renders": -1,
                                                     "metrics.json": -1}


def test_failure_reason_names_the_rule_and_its_log_line(tmp_path):
    (tmp_path / "results" / "c" / "logs").mkdir(parents=True)
    (tmp_path / "results" / "c" / "logs" / "merge_hdr.log").write_text(
        "INFO starting\nERROR sellip.stages.merge_hdr: hdr.zarr: no view has a frame left to merge\n")
    output = ("rule merge_hdr:\n    input: x\n\nError in rule merge_hdr:\n    message: None\n    jobid: 3\n"
              "    log: results/c/logs/merge_hdr.log (check log file(s) for error details)\n")
    reason = stability.failure_reason(output, tmp_path)
    assert reason.startswith("Error in rule merge_hdr: ") and reason.endswith("no view has a frame left to merge")



def test_run_failure_turns_a_failed_or_slow_command_into_its_reason(tmp_path):
    import sys

    log_path = tmp_path / "snakemake.log"
    fails = [sys.executable, "-c", "import sys; print('Error in rule fit_pbrdf:'); sys.exit(1)"]
    reason = stability.run_failure(lambda: stability.run_snakemake(fails, tmp_path, log_path, 60.0), 60.0)
    assert reason is not None and "fit_pbrdf" in reason
    slow = [sys.executable, "-c", "import time; time.sleep(30)"]
    assert stability.run_failure(lambda: stability.run_snakemake(slow, tmp_path, log_path, 1.0), 1.0) == \
        "timed out after 1 s"
    assert stability.run_failure(lambda: stability.run_snakemake([sys.executable, "-c", "pass"], tmp_path, log_path,
                                                                  60.0), 60.0) is None
    stability.write_row(tmp_path, {"case": "x", "error": reason})
    assert json.loads((tmp_path / "row.json").read_text()) == {"case": "x", "error": reason}
    assert log_path.read_text().count("$ ") == 3  # each command logged before its output

# --------------------------------------------------------------------------- configuration and the suite


def test_every_case_config_is_valid_for_the_workflow(tmp_path):
    import jsonschema

    defaults = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    schema = yaml.safe_load((REPO / "config" / "config.schema.yaml").read_text())
    names = set()
    for case in stability.CASES:
        config = stability.case_config(case, tmp_path)
        jsonschema.validate(merge(defaults, config), schema)
        views = case.views or stability.BASE_VIEWS
        assert config["name"] == case.name and config["demo"]["views"] == views
        assert all(int(v[1:]) < views for v in config["evaluate"]["held_out_views"])
        damaged = {f.split("_")[0] for f in case.missing + case.corrupt + case.truncated}
        assert not damaged & set(config["evaluate"]["held_out_views"] + config["evaluate"]["render_views"])
        names.add(case.name)
        assert "noise_seed" not in config["demo"]
        seeded = stability.case_config(case, tmp_path, noise_seed=3)
        jsonschema.validate(merge(defaults, seeded), schema)
        assert seeded["demo"] == {**config["demo"], "noise_seed": 3}
    assert len(names) == len(stability.CASES)


def test_suite_writes_validated_tables_and_keeps_going_after_a_failure(tmp_path):
    calls = []

    def fake_runner(case, workdir, snakefile, cores, iterations, jax_cache, noise_seed=None):
        calls.append(case.name)
        workdir.mkdir(parents=True, exist_ok=True)
        if case.name == "dark":
            return stability_table.case_row(case, workdir, 3.0, error="Error in rule fit_pbrdf: exploded")
        _fake_run(workdir, case)
        row = stability_table.case_row(case, workdir, 5.0)
        (workdir / "row.json").write_text(json.dumps(row))
        return row

    cases = stability.CASES[:3]
    table = stability.run_suite(cases, tmp_path, REPO / "Snakefile", runner=fake_runner)
    assert list(table["case"]) == ["baseline", "dark", "white_rough"]
    assert list(table["status"]) == ["ok", "failed", "ok"]
    csv = pd.read_csv(tmp_path / "stability.csv")
    assert list(csv.columns) == list(stability_table.COLUMNS) and len(csv) == 3
    markdown = (tmp_path / "stability.md").read_text()
    assert "**failed**: Error in rule fit_pbrdf: exploded" in markdown
    tables = [[line for line in block.splitlines() if line.startswith("|")] for block in markdown.split("\n\n")]
    tables = [t for t in tables if t]
    assert [len(t) for t in tables] == [5, 5, 5]  # header, rule, three cases
    for t in tables:
        assert all(line.count(" | ") == t[0].count(" | ") for line in t[2:])
        assert t[1].count("---") == len(t[0].split(" | "))
    # --keep reuses finished cases (baseline, white_rough) and reruns the one without a row.json; a kept run's
    # figures are read again from its folder (a column added since it ran gets filled), its times kept.
    calls.clear()
    metrics_path = tmp_path / "runs" / "baseline" / "results" / "baseline" / "metrics.json"
    metrics = json.loads(metrics_path.read_text())
    del metrics["eta_per_material"]
    metrics_path.write_text(json.dumps(metrics))
    baseline = tmp_path / "runs" / "baseline"
    (baseline / "row.json").write_text(json.dumps(stability_table.case_row(cases[0], baseline, 7.0)))
    metrics["eta_per_material"] = {"mean_error_pct": 0.25, "max_error_pct": 0.5}
    metrics_path.write_text(json.dumps(metrics))
    kept = stability.run_suite(cases, tmp_path, REPO / "Snakefile", keep=True, runner=fake_runner)
    assert calls == ["dark"]
    assert list(kept["eta_material_max_pct"])[0] == 0.5 and list(kept["wall_s"])[0] == 7.0
    assert json.loads((baseline / "row.json").read_text())["eta_material_mean_pct"] == 0.25
    with pytest.raises(Exception, match="auc"):  # pandera names the column
        stability_table.validate_table([{**table.iloc[0].to_dict(), "auc": 1.5}])


@pytest.mark.slow
def test_cli_lists_the_cases():
    out = subprocess.run([sys.executable, "-m", "sellip.cli", "bench-stability", "--help"], capture_output=True,
                         text=True, check=True).stdout
    assert "init_perturbed" in out and "--cores" in out


def test_suite_skips_a_case_whose_package_is_missing(tmp_path, caplog):
    from sellip.bench.stability_table import Case

    calls = []

    def fake_runner(case, workdir, snakefile, cores, iterations, jax_cache, noise_seed=None):
        calls.append(case.name)
        workdir.mkdir(parents=True, exist_ok=True)
        _fake_run(workdir, case)
        return stability_table.case_row(case, workdir, 5.0)

    needy = Case("needs_nothing_installed", "renderer", "a case that needs a package that is not there",
                 needs=("sellip_no_such_package_36",))
    assert stability.missing_packages(needy) == ["sellip_no_such_package_36"]
    assert all(stability.missing_packages(c) == [] for c in stability.CASES if "mitsuba" not in c.needs)
    with caplog.at_level("WARNING"):
        table = stability.run_suite([stability.CASES[0], needy], tmp_path, REPO / "Snakefile", runner=fake_runner)
    assert calls == ["baseline"] and list(table["case"]) == ["baseline"]
    assert "needs_nothing_installed: skipped, it needs sellip_no_such_package_36" in caplog.text
