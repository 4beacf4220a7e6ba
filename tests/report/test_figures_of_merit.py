"""Figures of merit: known perturbations give known errors, Sim(3) alignment, PSNR definition, the evaluate stage."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_outputs import make_tiny_run

from sellip.capture.scenes import build_scene
from sellip.geometry.alignment import Similarity
from sellip.geometry.cameras import read_cameras, write_cameras
from sellip.model.params import write_params
from sellip.model.ply import write_param_mesh
from sellip.model.render import ParamMesh
from sellip.report import figures_of_merit
from sellip.report import metrics as report_metrics


@pytest.fixture(scope="module")
def truth():
    return build_scene("tiny").mesh


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return make_tiny_run(tmp_path_factory.mktemp("tiny_eval"), views=4)


def _with(mesh: ParamMesh, normals=None, **params) -> ParamMesh:
    return ParamMesh(mesh.vertices, mesh.faces, mesh.normals if normals is None else normals,
                     mesh.params._replace(**params), mesh.material)


def _tilted(normals: np.ndarray, degrees: float) -> np.ndarray:
    """Each normal rotated by ``degrees`` about an axis orthogonal to it."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    axis = np.cross(normals, helper)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return Rotation.from_rotvec(np.radians(degrees) * axis).apply(normals)


# --------------------------------------------------------------------------- parameters


def test_ground_truth_against_itself_has_zero_error(truth):
    errors = figures_of_merit.parameter_errors(truth, truth, np.ones(truth.num_vertices, bool))
    assert errors["normal_error_deg"]["all"]["mean"] == pytest.approx(0, abs=1e-6)
    assert errors["eta_relative_error_pct"]["mean"] == 0
    assert errors["rho_d_relative_rmse"]["relative_rmse"] == pytest.approx(0, abs=1e-12)
    assert errors["sigma_s_abs_error"]["mean"] == 0 and errors["sigma_ss_abs_error"]["mean"] == 0


def test_known_perturbations_give_known_errors(truth):
    p = truth.params
    confident = np.arange(truth.num_vertices) % 3 != 0
    normals = truth.normals.copy()
    normals[confident] = _tilted(truth.normals[confident], 5.0)
    normals[~confident] = _tilted(truth.normals[~confident], 20.0)
    model = _with(truth, normals=normals, eta=1.1 * p.eta, rho_d=3 * p.rho_d, sigma_s=p.sigma_s + 0.05,
                  sigma_ss=p.sigma_ss - 0.02)
    errors = figures_of_merit.parameter_errors(model, truth, confident)
    assert errors["normal_error_deg"]["confident"]["median"] == pytest.approx(5.0, abs=1e-6)
    assert errors["normal_error_deg"]["confident"]["mean"] == pytest.approx(5.0, abs=1e-6)
    expected_all = (5.0 * confident.sum() + 20.0 * (~confident).sum()) / truth.num_vertices
    assert errors["normal_error_deg"]["all"]["mean"] == pytest.approx(expected_all, abs=1e-6)
    assert errors["eta_relative_error_pct"]["mean"] == pytest.approx(10.0)
    assert errors["eta_relative_error_pct"]["median"] == pytest.approx(10.0)
    assert errors["rho_d_relative_rmse"]["relative_rmse"] == pytest.approx(0, abs=1e-12)
    assert errors["rho_d_relative_rmse"]["scale"] == pytest.approx(1 / 3)
    assert errors["sigma_s_abs_error"]["mean"] == pytest.approx(0.05)
    assert errors["sigma_ss_abs_error"]["mean"] == pytest.approx(0.02)
    # sigma_ss counts only where the ground truth has single scattering (the tiny scene's lower half).
    has_ss = confident & (truth.params.rho_ss.max(axis=1) > 0)
    assert errors["sigma_ss_abs_error"]["vertices"] == has_ss.sum() < confident.sum()


def test_albedo_rmse_after_the_global_scale_sees_relative_errors(truth):
    """Half the vertices 20 % brighter: the best scale cannot undo that, the RMSE is what least squares leaves."""
    rho = truth.params.rho_d.copy()
    rho[::2] *= 1.2
    errors = figures_of_merit.parameter_errors(_with(truth, rho_d=2.0 * rho), truth, np.ones(truth.num_vertices, bool))
    model, gt = 2.0 * rho, truth.params.rho_d
    k = np.sum(model * gt) / np.sum(model * model)
    expected = np.sqrt(np.mean((k * model - gt) ** 2)) / np.sqrt(np.mean(gt ** 2))
    assert errors["rho_d_relative_rmse"]["relative_rmse"] == pytest.approx(expected)
    assert 0.03 < expected < 0.2


def test_a_similarity_transformed_model_evaluates_the_same_after_alignment(truth):
    sim = Similarity(1.7, Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix(),
                     np.array([0.3, -1.2, 0.5]))
    moved = figures_of_merit.transform_mesh(truth, sim)
    aligned = figures_of_merit.parameter_errors(moved, truth, np.ones(truth.num_vertices, bool), sim.inverse())
    assert aligned["normal_error_deg"]["all"]["mean"] == pytest.approx(0, abs=1e-5)
    assert aligned["correspondence_distance_mm"]["mean"] == pytest.approx(0, abs=1e-6)
    geometry = figures_of_merit.geometry_errors(moved, truth, sim.inverse(), samples=5000)
    assert geometry["chamfer_mm"] < 1e-3 and geometry["hausdorff_mm"] < 1e-3
    unaligned = figures_of_merit.geometry_errors(moved, truth, None, samples=5000)
    assert unaligned["chamfer_mm"] > 100


def test_geometry_errors_of_a_grown_sphere_are_the_radius_difference(truth):
    grown = ParamMesh(truth.vertices * 1.05, truth.faces, truth.normals, truth.params)
    geometry = figures_of_merit.geometry_errors(grown, truth, samples=20000)
    # 4 cm sphere scaled by 1.05: 2 mm everywhere (up to the facets' sagitta, well below 0.1 mm here).
    assert geometry["hausdorff_mm"] == pytest.approx(2.0, abs=0.15)
    assert geometry["chamfer_mm"] == pytest.approx(2.0, abs=0.15)


def test_geometry_series_follows_the_meshes_of_the_loop(truth):
    """Three meshes (grown 5 %, 2.5 %, exact) with fitted normals 3 deg off: Chamfer 2, 1, 0 mm to the truth and
    1 mm between consecutive meshes; the fitted-normal error counts only the vertices asked for."""
    meshes = [ParamMesh(truth.vertices * scale, truth.faces, truth.normals, None) for scale in (1.05, 1.025, 1.0)]
    counted = np.arange(truth.num_vertices) % 2 == 0
    fitted = [(_tilted(truth.normals, 3.0), counted), None]
    rows = figures_of_merit.geometry_series(meshes, fitted, truth)
    assert [row["mesh"] for row in rows] == [0, 1, 2] and rows[0]["chamfer_to_previous_mm"] is None
    for row, expected in zip(rows, (2.0, 1.0, 0.0)):
        assert row["chamfer_mm"] == pytest.approx(expected, abs=0.15)
        assert row["mesh_normal_deg"]["median"] == pytest.approx(0.0, abs=1e-6)
    assert rows[1]["chamfer_to_previous_mm"] == pytest.approx(1.0, abs=0.15)
    assert rows[0]["fitted_normal_deg"]["median"] == pytest.approx(3.0, abs=1e-6)
    assert rows[0]["fitted_normal_deg"]["vertices"] == counted.sum() and "fitted_normal_deg" not in rows[1]
    assert "chamfer_mm" not in figures_of_merit.geometry_series(meshes, fitted, None)[2]
    assert all(row["self_intersecting_pairs"] == row["flipped_triangles"] == row["degenerate_triangles"] == 0
               for row in rows)
    # 5 % larger: the true surface lies 2 mm inside, all of it farther than 1 mm; 2.5 %: 1 mm, about half.
    assert rows[0]["truth_farther_than_1mm"] > 0.99 and rows[2]["truth_farther_than_1mm"] < 0.01


def test_geometry_series_counts_a_fold(truth):
    """A vertex pushed through the surface to the far side: its mesh has self-intersecting pairs and triangles
    flipped against the previous mesh's."""
    folded = np.array(truth.vertices, np.float64)
    folded[7] = -1.2 * folded[7]
    meshes = [ParamMesh(truth.vertices, truth.faces, truth.normals, None),
              ParamMesh(folded, truth.faces, truth.normals, None)]
    rows = figures_of_merit.geometry_series(meshes, [], None)
    assert rows[0]["self_intersecting_pairs"] == 0 and rows[0]["flipped_triangles"] == 0
    assert rows[1]["self_intersecting_pairs"] > 0 and rows[1]["flipped_triangles"] > 0


def test_camera_alignment_recovers_the_similarity(tiny_run):
    view_ids, rotations, translations = read_cameras(tiny_run["cameras"])
    sim = Similarity(0.8, Rotation.from_euler("zyx", [10, 20, 30], degrees=True).as_matrix(), np.array([1.0, 2, 3]))
    moved_r, moved_t = sim.apply_to_poses(rotations, translations)
    found = figures_of_merit.camera_alignment(view_ids, moved_r, moved_t, view_ids, rotations, translations)
    assert found.scale == pytest.approx(1 / 0.8)
    np.testing.assert_allclose(found.compose(sim).rotation, np.eye(3), atol=1e-9)
    with pytest.raises(ValueError, match="at least 3"):
        figures_of_merit.camera_alignment(view_ids[:2], moved_r[:2], moved_t[:2], view_ids, rotations, translations)


# --------------------------------------------------------------------------- PSNR and timings


def test_psnr_follows_its_definition():
    rng = np.random.default_rng(0)
    reference = np.ones((6, 8, 4, 3))
    mask = rng.random((6, 8)) > 0.2
    assert figures_of_merit.psnr(reference, 0.25 * reference, mask)["psnr_db"] == figures_of_merit.PSNR_MAX_DB
    sign = np.where(rng.random(reference.shape) > 0.5, 1.0, -1.0)
    estimate = 3.0 * (reference + 0.1 * sign)
    result = figures_of_merit.psnr(reference, estimate, mask)
    k = np.sum(reference[mask] * estimate[mask]) / np.sum(estimate[mask] ** 2)
    mse = np.mean((k * estimate[mask] - 1.0) ** 2)
    assert result["scale"] == pytest.approx(k) and result["peak"] == 1.0
    assert result["psnr_db"] == pytest.approx(10 * np.log10(1 / mse))
    assert 19 < result["psnr_db"] < 21  # about 10 % noise
    assert figures_of_merit.psnr(reference, estimate, np.zeros((6, 8), bool))["psnr_db"] is None


def _benchmark(path, seconds):
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = "\n".join(f"{s}\t0:00:01\t100\t200\t50\t60\t1\t2\t0.5\t{s}" for s in np.atleast_1d(seconds))
    path.write_text("s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n" + rows + "\n")


def _fake_benchmarks(results, vertices=1200):
    bench = results / "benchmarks"
    _benchmark(bench / "merge_hdr.tsv", 3.5)
    _benchmark(bench / "fit_pbrdf" / "0" / "fit" / "1-of-2.tsv", 2.0)
    _benchmark(bench / "fit_pbrdf" / "0" / "fit" / "2-of-2.tsv", [1.0, 3.0])  # two repeats of one job: mean 2.0
    _benchmark(bench / "gather_fit" / "0.tsv", 0.5)
    n = vertices
    write_params(results / "iter" / "0" / "fit.zarr", {
        "vertices": np.zeros((n, 3)), "normals": np.zeros((n, 3)), "eta": np.ones(n), "rho_d": np.ones((n, 3)),
        "rho_s": np.ones(n), "sigma_s": np.ones(n), "rho_ss": np.ones((n, 3)), "sigma_ss": np.ones(n)})
    return bench


def test_stage_timings_sum_per_rule_and_count_vertex_fits(tmp_path):
    from sellip.timing import format_report

    bench = _fake_benchmarks(tmp_path, vertices=1200)
    logs = tmp_path / "logs" / "fit_pbrdf" / "0" / "fit"
    logs.mkdir(parents=True)
    for shard, (read, fit) in (("1-of-2", (0.25, 1.0)), ("2-of-2", (0.5, 1.25))):  # the job logs' phases lines
        (logs / f"{shard}.log").write_text(f"warning\n2026 INFO sellip: {format_report({'read': read, 'fit': fit})}\n")
    timings = figures_of_merit.stage_timings(bench)
    assert timings["rules"]["fit_pbrdf"] == {"s": 4.0, "jobs": 2, "phases": {"read": 0.75, "fit": 2.25},
                                             "phases_jobs": 2}
    assert timings["rules"]["merge_hdr"] == {"s": 3.5, "jobs": 1, "phases": {}, "phases_jobs": 0}
    assert timings["total_s"] == pytest.approx(8.0)
    assert timings["vertex_fits"] == 1200 and timings["vertex_fits_per_s"] == pytest.approx(300.0)


# --------------------------------------------------------------------------- the stage


@pytest.mark.slow
def test_evaluate_cli_on_a_perfect_model(tiny_run, tmp_path):
    results = tiny_run["results"]
    bench = _fake_benchmarks(results)
    held_out = tiny_run["view_ids"][1:3]
    out = tmp_path / "metrics.json"
    plot = tmp_path / "timings.png"
    subprocess.run([sys.executable, "-m", "sellip.cli", "evaluate", "--model", str(tiny_run["model"]),
                    "--cameras", str(tiny_run["cameras"]), "--hdr", str(tiny_run["hdr"]),
                    "--capture", str(tiny_run["capture"]), "--benchmarks", str(bench),
                    "--settings", json.dumps({"held_out_views": held_out, "geometry_samples": 5000}),
                    "--output", str(out), "--timings-plot", str(plot)], check=True)
    metrics = json.loads(out.read_text())
    assert metrics["alignment"]["method"] == "none"
    assert metrics["normal_error_deg"]["all"]["mean"] == pytest.approx(0, abs=1e-4)
    assert metrics["eta_relative_error_pct"]["mean"] == 0
    assert metrics["geometry"]["chamfer_mm"] < 1e-3
    assert metrics["reasons"]["confident_vertices"].startswith("neither --params")
    assert metrics["material_support"] is None and "support" in metrics["reasons"]["material_support"]
    # hdr.zarr holds the ground truth rendered exactly as evaluate renders the model (7x the flash).
    for view in held_out:
        assert metrics["psnr_held_out"]["views"][view]["psnr_db"] > 60
        assert metrics["psnr_held_out"]["views"][view]["scale"] == pytest.approx(7.0, rel=1e-4)
        # The model is the ground truth: the ceiling is the model's own PSNR.
        assert metrics["psnr_held_out"]["views"][view]["ground_truth_psnr_db"] == pytest.approx(
            metrics["psnr_held_out"]["views"][view]["psnr_db"])
    assert metrics["psnr_held_out"]["ground_truth_mean_db"] == pytest.approx(metrics["psnr_held_out"]["mean_db"])
    assert metrics["psnr_new_light"]["mean_db"] == figures_of_merit.PSNR_MAX_DB
    assert metrics["timings"]["vertex_fits_per_s"] == pytest.approx(300.0)
    assert plot.stat().st_size > 1000


def test_evaluate_aligns_an_sfm_world_model_and_reports_nulls_without_ground_truth(tiny_run, tmp_path):
    """Model and cameras.csv in a Sim(3)-moved world with sfm/report.json mode 'sfm': same figures after alignment."""
    sim = Similarity(1.2, Rotation.from_euler("xyz", [20, 5, -40], degrees=True).as_matrix(), np.array([0.1, 0, 0.2]))
    run = tmp_path / "results"
    (run / "sfm").mkdir(parents=True)
    (run / "sfm" / "report.json").write_text(json.dumps({"mode": "sfm"}))
    view_ids, rotations, translations = read_cameras(tiny_run["cameras"])
    write_cameras(run / "cameras.csv", view_ids, *sim.apply_to_poses(rotations, translations))
    model = figures_of_merit.transform_mesh(tiny_run["truth"], sim)
    tilted = _with(model, normals=_tilted(model.normals, 3.0))
    write_param_mesh(run / "model.ply", tilted)
    n = model.num_vertices
    status = np.zeros(n, np.int8)
    status[: n // 2] = 2  # failed: not confident
    write_params(run / "params.zarr", {"vertices": model.vertices, "normals": tilted.normals,
                                       **tilted.params._asdict(), "confidence": np.ones(n), "status": status})
    # The poses stage's cameras before a refinement: one view turned by 0.1 degrees about its optical axis.
    turned = rotations.copy()
    turned[1] = Rotation.from_euler("z", 0.1, degrees=True).as_matrix() @ turned[1]
    write_cameras(run / "initial.csv", view_ids, *sim.apply_to_poses(turned, translations))
    metrics = report_metrics.evaluate_model(run / "model.ply", run / "cameras.csv", tiny_run["hdr"],
                                            tiny_run["capture"], run / "metrics.json", params_path=run / "params.zarr",
                                       held_out=[view_ids[0]], geometry_samples=5000, supersample=1,
                                       initial_cameras=run / "initial.csv")
    assert metrics["alignment"]["method"] == "sim3+icp"
    # Exact cameras put the true surface where the true ones do; the turned view moves it by about r * 0.1 degrees.
    final, initial = metrics["poses"]["final"], metrics["poses"]["initial"]
    assert final["reprojection_px"]["max"] < 1e-3 and final["centre_mm"]["max"] < 1e-3
    assert final["views"] == len(view_ids)
    assert initial["reprojection_px"]["worst_view"] == view_ids[1] and initial["reprojection_px"]["max"] > 0.01
    assert metrics["alignment"]["scale"] == pytest.approx(1 / 1.2)
    # Exact cameras: the refinement by ICP has nothing to add.
    assert metrics["alignment"]["cameras"]["scale"] == pytest.approx(1 / 1.2)
    assert metrics["alignment"]["refinement"]["translation_mm"] < 1e-3
    assert metrics["alignment"]["refinement"]["rotation_deg"] < 1e-3
    assert metrics["vertices"]["confident"] == n - n // 2
    assert metrics["normal_error_deg"]["confident"]["median"] == pytest.approx(3.0, abs=1e-3)
    assert metrics["geometry"]["chamfer_mm"] < 1e-3
    assert metrics["eta_relative_error_pct"]["mean"] == pytest.approx(0, abs=1e-4)
    assert json.loads((run / "metrics.json").read_text())["alignment"]["method"] == "sim3+icp"
    # Held-out PSNR is measured in the model's own (SfM) world: supersample 1 against 2 and the 3° normals cost some.
    assert metrics["psnr_held_out"]["views"][view_ids[0]]["psnr_db"] > 20

    bare = tmp_path / "capture"
    shutil.copytree(tiny_run["capture"], bare)
    shutil.rmtree(bare / "ground_truth")
    metrics = report_metrics.evaluate_model(tiny_run["model"], tiny_run["cameras"], tiny_run["hdr"], bare,
                                       tmp_path / "no_gt.json", held_out=[view_ids[0]], supersample=2,
                                       benchmarks=_fake_benchmarks(tmp_path / "bench_run"))
    written = json.loads((tmp_path / "no_gt.json").read_text())
    for key in ("normal_error_deg", "eta_relative_error_pct", "rho_d_relative_rmse", "geometry", "psnr_new_light",
                "poses"):
        assert written[key] is None and "no ground truth" in written["reasons"][key]
    assert written["psnr_held_out"]["views"][view_ids[0]]["psnr_db"] > 40
    assert written["timings"]["rules"]["merge_hdr"]["s"] == 3.5


def test_the_runs_warnings_are_in_metrics_json(tmp_path_factory):
    """`sellip evaluate --logs` (rule evaluate_model) writes the run's warnings into metrics.json (the report)."""
    from sellip.report.metrics import evaluate_model

    tiny = make_tiny_run(tmp_path_factory.mktemp("warnings"), views=3)
    logs = tiny["results"] / "logs"
    (logs / "sub").mkdir(parents=True, exist_ok=True)
    (logs / "sub" / "observe.log").write_text(
        "2026-01-01 10:00:00,000 WARNING sellip.stages.observe: poses.csv has no pose for 1 view(s): ['v002']\n")
    metrics = evaluate_model(tiny["model"], tiny["cameras"], tiny["hdr"], tiny["capture"],
                             tiny["results"] / "metrics.json", geometry_samples=500, supersample=1, logs=logs)
    assert metrics["warnings"] == [{"log": "sub/observe.log",
                                    "message": "poses.csv has no pose for 1 view(s): ['v002']"}]


def test_material_support_lists_the_fragile_materials(tmp_path):
    """metrics.json's material_support (issue #49): per cluster of the final store its support and alternative, and
    the clusters below 1 as fragile; None (with a reason) where the store has no support."""
    from sellip.model.params import write_params
    from sellip.report.metrics import material_support

    n = 6
    base = {"vertices": np.zeros((n, 3), np.float32), "normals": np.tile([0, 0, 1.0], (n, 1)),
            "eta": np.full(n, 1.5), "rho_d": np.full((n, 3), 0.3), "rho_s": np.full(n, 0.1), "sigma_s": np.full(n, 0.2),
            "rho_ss": np.zeros((n, 3)), "sigma_ss": np.full(n, 0.5), "cluster": np.array([0, 0, 0, 1, 1, 2], np.int32)}
    write_params(tmp_path / "with.zarr", {**base, "cluster_support": np.array([1, 1, 1, 0.7, 0.7, 1.0], np.float32),
                                          "cluster_alternative": np.array([-1, -1, -1, 0, 0, -1], np.int32)})
    record = material_support(tmp_path / "with.zarr")
    assert record["fragile"] == [1] and record["clusters"]["1"]["alternative"] == 0
    assert record["clusters"]["1"]["support"] == pytest.approx(0.7) and record["clusters"]["0"]["vertices"] == 3
    write_params(tmp_path / "without.zarr", base)
    reasons = {}
    assert material_support(tmp_path / "without.zarr", reasons) is None and "material_support" in reasons
