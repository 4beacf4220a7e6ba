"""The figures of merit of a reconstruction (docs/design.md §8; rule ``evaluate_model``): normals, η per
material and per vertex, albedo, roughness, Chamfer and Hausdorff, held-out and new-light PSNR, the geometry's
convergence over the iterations -> ``metrics.json`` (:func:`evaluate_model`).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from sellip import workflow_support
from sellip.capture.files import GROUND_TRUTH_MESH
from sellip.capture.reader import read_capture
from sellip.fit.convergence import loop_convergence
from sellip.geometry.alignment import Similarity
from sellip.geometry.cameras import load_cameras
from sellip.jobs import write_text
from sellip.model.params import read_params
from sellip.model.ply import read_param_mesh
from sellip.model.render import Camera, Renderer, flash_light
from sellip.report import figures_of_merit
from sellip.report.outputs import (
    NEW_LIGHT_OFFSET_M,
    EvaluateSettings,
    OutputsError,
    convergence_figure,
    model_confidence,
    moved_flash,
    save_figure,
    timings_figure,
)

log = logging.getLogger(__name__)


def confident_vertices(model_path: Path, params_path: Path | None, count: int) -> tuple[np.ndarray, str | None]:
    """(N,) bool confident vertices (module docstring) and a note when no confidence was available."""
    if params_path is not None:
        arrays = read_params(params_path)
        if len(arrays["vertices"]) != count:
            raise OutputsError(f"{params_path}: {len(arrays['vertices'])} vertices, but {model_path} has {count}")
        confident = np.ones(count, bool)
        if "status" in arrays:
            confident &= arrays["status"] == 0
        if "confidence" in arrays:
            confident &= arrays["confidence"] > 0
        return confident, None
    confidence = model_confidence(model_path)
    if confidence is not None:
        return confidence > 0, None
    return np.ones(count, bool), f"neither --params nor a confidence property in {model_path}: all vertices count"



def sfm_mode(cameras_path: Path, report_path: Path | None) -> str | None:
    """The ``mode`` of the sfm stage's report.json (default: <cameras dir>/sfm/report.json), None if absent."""
    path = report_path or Path(cameras_path).parent / "sfm" / "report.json"
    if not path.is_file():
        return None
    return json.loads(path.read_text()).get("mode")



def _moved_camera(camera: Camera, similarity) -> Camera:
    if similarity is None:
        return camera
    rotation, translation = similarity.apply_to_poses(np.asarray(camera.rotation), np.asarray(camera.translation))
    return Camera(camera.intrinsics, rotation, translation, camera.width, camera.height, camera.distortion)



def geometry_convergence(mesh_paths: list, fit_paths: list, truth, similarity) -> list[dict]:
    """:func:`sellip.report.figures_of_merit.geometry_series` of the loop's mesh files and first-pass fit stores."""
    from sellip.fit.observe import read_mesh
    from sellip.model.render import ParamMesh

    meshes, fitted = [], []
    for index, path in enumerate(mesh_paths):
        mesh = read_mesh(path)
        meshes.append(ParamMesh(mesh.vertices, mesh.faces, mesh.normals, params=None))
        if index < len(fit_paths):
            store = read_params(fit_paths[index])
            counted = (store["status"] == 0) & (store["confidence"] > 0)
            fitted.append((store["normals"], counted))
    rows = figures_of_merit.geometry_series(meshes, fitted, truth, similarity)
    for row in rows:
        log.info("mesh %d: moved %s mm, Chamfer to the truth %s mm, mesh normals %s deg, fitted %s deg; "
                 "self-intersecting pairs %d, flipped %d, degenerate %d", row["mesh"],
                 _rounded(row["chamfer_to_previous_mm"]), _rounded(row.get("chamfer_mm")),
                 _rounded((row.get("mesh_normal_deg") or {}).get("median")),
                 _rounded((row.get("fitted_normal_deg") or {}).get("median")), row["self_intersecting_pairs"],
                 row["flipped_triangles"], row["degenerate_triangles"])
    return rows



def _rounded(value, digits: int = 3):
    return None if value is None else round(float(value), digits)



def _mean_db(per_view: dict) -> float | None:
    values = [v["psnr_db"] for v in per_view.values() if v.get("psnr_db") is not None]
    return float(np.mean(values)) if values else None



def view_psnr(renderer, camera: Camera, light, hdr, view_id: str,
              supersample: int = EvaluateSettings.metrics_supersample) -> dict:
    """:func:`sellip.report.figures_of_merit.psnr` of ``renderer``'s image at ``camera`` under ``light`` against the HDR
    store's view ``view_id``, inside :func:`sellip.report.figures_of_merit.render_mask`: how a model (or the ground
    truth) scores at a captured view."""
    result = renderer.render(camera, light, supersample=supersample)
    analyzers, valid = hdr.view(view_id)
    return figures_of_merit.psnr(analyzers, result.analyzers,
                                 figures_of_merit.render_mask(analyzers, valid, result.coverage))



def _refined_alignment(model, truth, cameras: Similarity, mode: str, geometry_samples: int) -> tuple[Similarity, dict]:
    """(the Sim(3) of an SfM world to the truth's, its record for metrics.json): ``cameras`` (the camera centres'
    Umeyama) refined by ICP of the model's vertices onto the true surface
    (:func:`sellip.geometry.alignment.refine_to_surface`). The centres alone leave millimetres of error with a narrow
    field of view (a small rotation of a camera and a shift across its axis look alike): docs/benchmarks.md, "The
    painted cow from SfM". The record keeps the centres' alignment, the refinement's size and the Chamfer distance
    and normal median (all vertices) under the centres' alignment alone."""
    from scipy.spatial.transform import Rotation

    from sellip.geometry.alignment import refine_to_surface

    refined = refine_to_surface(model.vertices, truth.vertices, truth.faces, cameras)
    step = refined.compose(cameras.inverse())
    normal_error, _ = figures_of_merit.nearest_normal_errors(model, truth, cameras)
    record = {"method": "sim3+icp", "sfm_mode": mode,
              "source": "cameras.csv centres -> poses.csv centres, refined by ICP of the model's vertices onto the "
                        "true surface",
              "scale": refined.scale, "rotation": refined.rotation.tolist(),
              "translation": refined.translation.tolist(),
              "cameras": {"scale": cameras.scale, "rotation": cameras.rotation.tolist(),
                          "translation": cameras.translation.tolist(),
                          "chamfer_mm": figures_of_merit.geometry_errors(model, truth, cameras,
                                                                 samples=geometry_samples)["chamfer_mm"],
                          "normal_median_deg": float(np.median(normal_error))},
              "refinement": {"rotation_deg": float(np.degrees(Rotation.from_matrix(step.rotation).magnitude())),
                             "translation_mm": 1000 * float(np.linalg.norm(step.translation)),
                             "scale_change": step.scale - 1.0}}
    return refined, record


def _truth_and_alignment(truth_path: Path, ground_truth_keys, capture, capture_path: Path, cameras_path, sfm_report,
                         sim3_from_sfm: bool, model, geometry_samples: int, metrics: dict, reasons: dict):
    """(truth mesh or None, Similarity from the cameras' world to the truth's or None): the ground truth when the
    capture has one, and the Sim(3) alignment when the cameras came from SfM (:func:`_refined_alignment`, recorded
    in ``metrics``; why a figure is missing in ``reasons``)."""
    similarity, truth = None, None
    if not truth_path.is_file():
        for key in ground_truth_keys:
            reasons[key] = f"the capture has no ground truth ({truth_path} does not exist)"
    else:
        truth = read_param_mesh(truth_path)
        mode = sfm_mode(Path(cameras_path), Path(sfm_report) if sfm_report else None)
        if sim3_from_sfm or mode == "sfm":
            if capture.poses is None:
                for key in ground_truth_keys:
                    reasons[key] = (f"cameras came from SfM and {capture_path} has no poses.csv to align them "
                                    "to the ground truth")
                truth = None
            else:
                from sellip.geometry.cameras import read_cameras

                own = read_cameras(cameras_path)
                ref_ids = list(capture.poses["view_id"])
                ref = [capture.pose(v) for v in ref_ids]
                try:
                    similarity = figures_of_merit.camera_alignment(*own, ref_ids, np.stack([r for r, _ in ref]),
                                                           np.stack([t for _, t in ref]))
                except ValueError as exc:
                    raise OutputsError(f"{cameras_path} vs {capture_path}/poses.csv: {exc}") from None
                similarity, metrics["alignment"] = _refined_alignment(model, truth, similarity, mode, geometry_samples)
        else:
            metrics["alignment"] = {"method": "none", "sfm_mode": mode,
                                    "source": "cameras.csv is in the ground truth's world (poses.csv)"}
    return truth, similarity


def _pose_figures(cameras: dict, initial_cameras, hdr_path, capture, truth, similarity) -> dict | None:
    """With SfM cameras (``similarity`` set) and poses.csv: :func:`sellip.report.figures_of_merit.truth_reprojection` of
    the cameras (``final``) and, when given, of ``initial_cameras`` (the poses stage's, before the refinement against
    the object: ``initial``); None otherwise."""
    if similarity is None or capture.poses is None:
        return None
    true_poses = {view: capture.pose(view) for view in capture.poses["view_id"]}
    truth_renderer = Renderer(truth)
    figures = {"final": figures_of_merit.truth_reprojection(cameras, true_poses, truth_renderer, similarity),
               "unit": "reprojection_px: HDR pixels, median over the visible true surface, then median / p90 / max "
                       "over the views; centre_mm: millimetres"}
    if initial_cameras is not None:
        initial, _ = load_cameras(initial_cameras, hdr_path)
        figures["initial"] = figures_of_merit.truth_reprojection(initial, true_poses, truth_renderer, similarity)
    if figures["final"] is None:
        return None
    for key in ("final", "initial"):
        if figures.get(key):
            log.info("poses (%s): the visible true surface lands %.3f px from where the true cameras put it (median; "
                     "max %.3f px, %s); centres %.2f mm off (median; max %.2f mm)", key,
                     figures[key]["reprojection_px"]["median"], figures[key]["reprojection_px"]["max"],
                     figures[key]["reprojection_px"]["worst_view"], figures[key]["centre_mm"]["median"],
                     figures[key]["centre_mm"]["max"])
    return figures


def _ground_truth_figures(model, truth, similarity, renderer, cameras, hdr, held_out, flash, light, metrics: dict,
                          reasons: dict, model_path: Path, params_path, supersample: int, geometry_samples: int,
                          new_light_offset_cam) -> None:
    """The figures against the ground truth, into ``metrics``: vertices, parameter errors, geometry, the new-light
    PSNR, and the held-out PSNR's ceiling (the ground truth's own)."""
    confident, note = confident_vertices(model_path, Path(params_path) if params_path else None,
                                         model.num_vertices)
    if note:
        reasons["confident_vertices"] = note
    metrics["vertices"] = {"model": model.num_vertices, "confident": int(confident.sum()),
                           "ground_truth": truth.num_vertices}
    metrics.update(figures_of_merit.parameter_errors(model, truth, confident, similarity))
    for key in ("eta_relative_error_pct", "rho_d_relative_rmse", "sigma_s_abs_error", "sigma_ss_abs_error"):
        if metrics[key] is None:
            reasons[key] = "no confident vertex with this lobe in the ground truth"
    metrics["geometry"] = figures_of_merit.geometry_errors(model, truth, similarity, samples=geometry_samples)
    log.info("normals: median %.2f deg (confident %s); chamfer %.3f mm, hausdorff %.3f mm",
             metrics["normal_error_deg"]["all"]["median"],
             (metrics["normal_error_deg"]["confident"] or {}).get("median"),
             metrics["geometry"]["chamfer_mm"], metrics["geometry"]["hausdorff_mm"])
    # New light: ground truth and model rendered under the same moved flash, ground-truth world.
    moved_model = renderer if similarity is None else Renderer(figures_of_merit.transform_mesh(model, similarity))
    truth_renderer = Renderer(truth)
    new_light = {}
    for view_id in [v for v in held_out if v in cameras] or [next(iter(cameras))]:
        camera = _moved_camera(cameras[view_id], similarity)
        lamp = moved_flash(camera, light["position_m"], new_light_offset_cam, float(light["polarizer_deg"]))
        reference = truth_renderer.render(camera, lamp, supersample=supersample)
        estimate = moved_model.render(camera, lamp, supersample=supersample)
        new_light[view_id] = figures_of_merit.psnr(reference.analyzers, estimate.analyzers,
                                           (reference.coverage > 0) | (estimate.coverage > 0))
        log.info("new light at %s: PSNR %s dB", view_id, new_light[view_id]["psnr_db"])
    metrics["psnr_new_light"] = {"views": new_light, "mean_db": _mean_db(new_light)}
    # The held-out PSNR's ceiling: the ground truth itself rendered at the held-out views against the same
    # images. Detail finer than the HDR grid (texture the demosaicing blurs) caps it below any model's.
    if metrics["psnr_held_out"] is not None:
        ceiling = {}
        for view_id in [v for v in held_out if v in cameras]:
            camera = _moved_camera(cameras[view_id], similarity)
            ceiling[view_id] = view_psnr(truth_renderer, camera, flash(camera), hdr, view_id, supersample)
            metrics["psnr_held_out"]["views"][view_id]["ground_truth_psnr_db"] = ceiling[view_id]["psnr_db"]
        metrics["psnr_held_out"]["ground_truth_mean_db"] = _mean_db(ceiling)
        log.info("held-out PSNR of the ground truth itself (the ceiling): %s dB",
                 metrics["psnr_held_out"]["ground_truth_mean_db"])


def _timings(benchmarks, timings_plot, reasons: dict) -> dict | None:
    """Per-rule wall times from the Snakemake benchmark files (:func:`sellip.report.figures_of_merit.stage_timings`) and
    their plot; None, with the reason, without the folder."""
    if benchmarks is None:
        reasons["timings"] = "no --benchmarks folder given"
        return None
    if not Path(benchmarks).is_dir():
        reasons["timings"] = f"{benchmarks} does not exist"
        return None
    timings = figures_of_merit.stage_timings(benchmarks)
    if timings_plot is not None and timings["rules"]:
        save_figure(timings_figure(timings["rules"]), timings_plot)
    return timings


def material_support(params_path, reasons: dict | None = None) -> dict | None:
    """Per material cluster of the final store ``params_path``: how often repeats of the final clustering on
    resampled vertices found it again (``support``) and what it became in the others (``alternative``: the cluster
    it was merged into most often, -1 none; :func:`sellip.fit.cluster_support.clustering_support`), and ``fragile``: the
    clusters with support below 1. None without a store or where the support was not measured (said in ``reasons``)."""
    from sellip.model.params import read_params

    store = read_params(params_path) if params_path is not None and Path(params_path).exists() else {}
    support = np.asarray(store.get("cluster_support", []), np.float64)
    if "cluster" not in store or not np.isfinite(support).any():
        if reasons is not None:
            reasons["material_support"] = "no params store, or its clustering's support was not measured"
        return None
    cluster = np.asarray(store["cluster"], np.int64)
    alternative = np.asarray(store.get("cluster_alternative", np.full(len(cluster), -1)), np.int64)
    rows = {}
    for k in np.unique(cluster):
        first = int(np.flatnonzero(cluster == k)[0])
        value = float(support[first])
        rows[str(int(k))] = {"support": value if np.isfinite(value) else None,
                             "alternative": int(alternative[first]), "vertices": int(np.sum(cluster == k))}
    return {"clusters": rows,
            "fragile": [int(k) for k, row in rows.items() if row["support"] is not None and row["support"] < 1]}


def evaluate_model(model_path: str | Path, cameras_path: str | Path, hdr_path: str | Path, capture_path: str | Path,
              output: str | Path, params_path: str | Path | None = None, benchmarks: str | Path | None = None,
              held_out: list[str] | None = None, sim3_from_sfm: bool = False, sfm_report: str | Path | None = None,
              supersample: int = EvaluateSettings.metrics_supersample,
              geometry_samples: int = EvaluateSettings.geometry_samples, timings_plot: str | Path | None = None,
              new_light_offset_cam=NEW_LIGHT_OFFSET_M, iteration_meshes: list | None = None,
              iteration_fits: list | None = None, convergence_plot: str | Path | None = None,
              logs: str | Path | None = None, initial_cameras: str | Path | None = None) -> dict:
    """Compute the figures of merit and write ``output`` (metrics.json); returns the metrics.

    ``iteration_meshes``: the loop's meshes in order (the initial one, then each iteration's), and
    ``iteration_fits``: the first-pass fit store of each (its fitted normals): ``geometry_iterations``
    in metrics.json and the ``convergence_plot``; where the loop converged (``convergence``) from the summaries beside
    the meshes.

    Long: one figure after another, each a call or a few lines; split, the figures' shared inputs would travel as
    a dozen arguments."""
    started = time.perf_counter()
    model_path, capture_path, output = Path(model_path), Path(capture_path), Path(output)
    if not model_path.is_file():
        raise OutputsError(f"{model_path}: model does not exist")
    model = read_param_mesh(model_path)
    capture = read_capture(capture_path, check_files=False)  # raw frames are ingest's business
    light = capture.config["light"]
    cameras, hdr = load_cameras(cameras_path, hdr_path)
    held_out = list(held_out or [])
    reasons: dict[str, str] = {}
    metrics: dict = {"model": str(model_path), "cameras": str(cameras_path), "capture": str(capture_path),
                     "settings": {"supersample": supersample,
                                  "psnr_peak_percentile": figures_of_merit.PSNR_PEAK_PERCENTILE,
                                  "psnr_max_db": figures_of_merit.PSNR_MAX_DB, "geometry_samples": geometry_samples,
                                  "new_light_offset_cam_m": list(map(float, new_light_offset_cam))}}
    renderer = Renderer(model)

    def flash(camera: Camera):
        return flash_light(camera, light["position_m"], polarizer_deg=float(light["polarizer_deg"]))

    # Held-out views: the model (cameras.csv world) against the measured HDR images.
    held_out_psnr = {}
    for view_id in held_out:
        if view_id not in cameras:
            held_out_psnr[view_id] = {"psnr_db": None, "reason": f"no pose in {cameras_path}"}
            continue
        camera = cameras[view_id]
        held_out_psnr[view_id] = view_psnr(renderer, camera, flash(camera), hdr, view_id, supersample)
        log.info("held-out %s: PSNR %s dB", view_id, held_out_psnr[view_id]["psnr_db"])
    metrics["psnr_held_out"] = {"views": held_out_psnr, "mean_db": _mean_db(held_out_psnr)} if held_out else None
    if not held_out:
        reasons["psnr_held_out"] = "no held-out views given (config evaluate.held_out_views)"

    # Ground truth.
    truth_path = capture_path / GROUND_TRUTH_MESH
    ground_truth_keys = ("alignment", "vertices", "normal_error_deg", "eta_relative_error_pct",
                         "rho_d_relative_rmse", "sigma_s_abs_error", "sigma_ss_abs_error",
                         "correspondence_distance_mm", "geometry", "psnr_new_light", "poses")
    metrics.update({key: None for key in ground_truth_keys})
    metrics["ground_truth"] = str(truth_path) if truth_path.is_file() else None
    truth, similarity = _truth_and_alignment(truth_path, ground_truth_keys, capture, capture_path, cameras_path,
                                              sfm_report, sim3_from_sfm, model, geometry_samples, metrics, reasons)
    if truth is not None:
        _ground_truth_figures(model, truth, similarity, renderer, cameras, hdr, held_out, flash, light, metrics,
                              reasons, model_path, params_path, supersample, geometry_samples, new_light_offset_cam)
        metrics["poses"] = _pose_figures(cameras, initial_cameras, hdr_path, capture, truth, similarity)
        if metrics["poses"] is None:
            reasons["poses"] = "the cameras are poses.csv's"

    metrics["geometry_iterations"] = None  # how the geometry converged over the loop
    if iteration_meshes:
        metrics["geometry_iterations"] = geometry_convergence(iteration_meshes, iteration_fits or [], truth,
                                                              similarity)
        if convergence_plot is not None:
            save_figure(convergence_figure(metrics["geometry_iterations"]), convergence_plot)
    else:
        reasons["geometry_iterations"] = "no --iteration-meshes given"
    # Where the loop converged and which iterations passed through (sellip.fit.convergence).
    metrics["convergence"] = loop_convergence(iteration_meshes or [])
    if metrics["convergence"] is None:
        reasons["convergence"] = "no iteration's geometry update recorded a convergence verdict"

    metrics["material_support"] = material_support(params_path, reasons)
    metrics["timings"] = _timings(benchmarks, timings_plot, reasons)
    # The run's warnings (a frame left out, views without a pose: docs/reliability.md), from the jobs' logs.
    metrics["warnings"] = [{"log": name, "message": message} for name, message in
                           (workflow_support.collect_warnings(logs) if logs is not None else [])]
    metrics.update(reasons=reasons, evaluate_s=time.perf_counter() - started)
    write_text(json.dumps(metrics, indent=2, allow_nan=False), output)
    log.info("wrote %s in %.1f s", output, metrics["evaluate_s"])
    return metrics


def headline_figures(metrics: dict) -> dict:
    """The figures a benchmark reports from a parsed ``metrics.json``: η per material (``eta_per_material``, the
    record, and its ``_mean_pct`` and ``_max_pct``), η per vertex (median and p90 %), normals (median and p90 deg)
    and the held-out PSNR (dB); None where the run has no such figure."""
    per = metrics.get("eta_per_material") or {}
    eta = metrics.get("eta_relative_error_pct") or {}
    normals = (metrics.get("normal_error_deg") or {}).get("all") or {}
    return {"eta_per_material": metrics.get("eta_per_material"),
            "eta_per_material_mean_pct": per.get("mean_error_pct"),
            "eta_per_material_max_pct": per.get("max_error_pct"),
            "eta_vertex_median_pct": eta.get("median"), "eta_vertex_p90_pct": eta.get("p90"),
            "normal_median_deg": normals.get("median"), "normal_p90_deg": normals.get("p90"),
            "held_out_psnr_db": (metrics.get("psnr_held_out") or {}).get("mean_db")}

