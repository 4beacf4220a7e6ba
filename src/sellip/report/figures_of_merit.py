"""Figures of merit of a reconstructed model (docs/design.md §8): parameters, geometry, re-render PSNR, stage timings.

Public API::

    transform_mesh(mesh, similarity) -> ParamMesh                     # vertices s R x + t, normals R n
    camera_alignment(view_ids, rotations, translations, ref_view_ids, ref_rotations, ref_translations)
        -> Similarity                                                # cameras.csv world -> reference world
    parameter_errors(model, truth, confident, similarity=None) -> dict
    geometry_errors(model, truth, similarity=None, samples=50000) -> dict (mm)
    psnr(reference, estimate, mask) -> dict                          # definition below
    render_mask(measured_analyzers, valid, coverage) -> (H, W) bool
    stage_timings(benchmarks_dir, results_dir=None) -> dict
    vertex_errors(model, truth, similarity=None) -> dict of (N,) arrays   # per-vertex normal and η errors

Definitions (all exact; docs/outputs.md repeats them):

* Correspondence: each model vertex (after the optional Sim(3) into the ground-truth world) is compared
  with its nearest ground-truth vertex (cKDTree on positions).
* Normal angular error: arccos of the dot product of the (rotated) model normal and the ground-truth
  normal, degrees; mean, median and 90th percentile over all model vertices and over confident ones.
* η relative error: |η - η_gt| / η_gt in percent; mean, median over confident vertices.
* Diffuse albedo relative RMSE: k = Σ ρ_d·ρ_d,gt / Σ ρ_d·ρ_d (one global scale, least squares over the
  confident vertices and the three channels), then sqrt(mean (k ρ_d - ρ_d,gt)^2) / sqrt(mean ρ_d,gt^2).
* Roughness error: mean and median |σ - σ_gt|, for σ_s over confident vertices whose ground truth has a
  specular lobe (ρ_s > 0), for σ_ss over those whose ground truth has single scattering (max ρ_ss > 0).
* Geometry: Chamfer distance (mean of the two directed mean surface-to-surface distances) and Hausdorff
  distance (largest of them), millimetres, by :func:`sellip.geometry.meshes.mesh_distances`.
* PSNR: the four analyzer RGB images (H, W, 4, 3). One global scale k (least squares, :func:`fit_scale`)
  brings the estimate to the reference (the flash power is unknown); both are divided by the 99th
  percentile of the reference's values inside the mask; PSNR = 10 log10(1 / MSE) with MSE the mean of
  the squared differences over the mask's pixels x 4 analyzers x 3 channels, floored at
  10^(-PSNR_MAX_DB / 10) (so identical images give PSNR_MAX_DB, never infinity).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sellip.geometry.alignment import Similarity, align_cameras
from sellip.geometry.meshes import angular_error_deg, mesh_distances, surface_defects
from sellip.geometry.silhouettes import silhouette_masks
from sellip.model.render import ParamMesh
from sellip.report.outputs import fit_scale

log = logging.getLogger(__name__)

PSNR_PEAK_PERCENTILE = 99.0
"""Percentile of the reference's analyzer values (inside the mask) that normalizes both images to peak 1."""

PSNR_MAX_DB = 100.0
"""Largest reported PSNR: the MSE is floored at 10^(-PSNR_MAX_DB / 10)."""

FIT_RULE = "fit_pbrdf"
"""The Snakemake rule whose jobs are the per-vertex fits (benchmarks/fit_pbrdf/{it}/{shard}.tsv)."""


# --------------------------------------------------------------------------- frames


def transform_mesh(mesh: ParamMesh, similarity: Similarity | None) -> ParamMesh:
    """The mesh moved by a similarity: vertices s R x + t, normals R n (parameters unchanged)."""
    if similarity is None:
        return mesh
    return ParamMesh(vertices=similarity.apply(np.asarray(mesh.vertices, np.float64)), faces=mesh.faces,
                     normals=np.asarray(mesh.normals, np.float64) @ np.asarray(similarity.rotation).T,
                     params=mesh.params, material=mesh.material)


def camera_alignment(view_ids: list[str], rotations: np.ndarray, translations: np.ndarray, ref_view_ids: list[str],
                     ref_rotations: np.ndarray, ref_translations: np.ndarray) -> Similarity:
    """Sim(3) from the cameras' world to the reference world (robust Umeyama on the centres of common views).

    Raises ValueError when fewer than 3 views are in both.
    """
    ref_row = {v: i for i, v in enumerate(ref_view_ids)}
    common = [(i, ref_row[v]) for i, v in enumerate(view_ids) if v in ref_row]
    if len(common) < 3:
        raise ValueError(f"Sim(3) alignment needs at least 3 views with both poses, found {len(common)}")
    own, ref = (np.array(c) for c in zip(*common))
    return align_cameras(rotations[own], translations[own], ref_rotations[ref], ref_translations[ref])


def truth_reprojection(cameras: dict, true_poses: dict, truth_renderer, similarity: Similarity | None,
                       max_points: int = 5000) -> dict | None:
    """How far each camera puts the visible true surface from where its true camera puts it, and how far its centre is.

    cameras: {view: Camera} in the model's world; true_poses: {view: (R (3, 3), t (3,))} in the truth's world;
    truth_renderer: a :class:`sellip.model.render.Renderer` of the true mesh; similarity: model world -> truth world
    (None: the same world). Per view that both have: the true surface points behind the true camera's fully covered
    pixels (at most ``max_points``, evenly spread), moved into the model's world by the inverse of ``similarity`` and
    projected through the model's camera, against their projection through the true camera (pixels, median over
    the points); and the distance of the model's camera centre, moved into the truth's world, from the true one
    (millimetres). The hidden side is left out: a step of a narrow-field camera along its weak directions (a shift
    across the axis with a turn, or along it) moves the far side far more than the side the camera photographs.
    Returns {"reprojection_px": {"median", "p90", "max", "worst_view"}, "centre_mm": {"median", "p90", "max",
    "worst_view"}, "views"} or None when no view has both."""
    from sellip.model.conventions import camera_center
    from sellip.model.render import Camera

    reprojection, centre = {}, {}
    vertices = np.asarray(truth_renderer.mesh.vertices, np.float64)
    for view, camera in cameras.items():
        if view not in true_poses or not np.all(np.isfinite(camera.translation)):
            continue
        rotation, translation = true_poses[view]
        true_camera = Camera(camera.intrinsics, rotation, translation, camera.width, camera.height, camera.distortion)
        surface, coverage = truth_renderer.interpolate(true_camera, vertices)
        points = surface[coverage >= 1].astype(np.float64)
        if not len(points):
            continue
        points = points[np.linspace(0, len(points) - 1, min(len(points), max_points)).astype(int)]
        own_points = points if similarity is None else similarity.inverse().apply(points)
        reprojection[view] = float(np.median(np.linalg.norm(camera.project(own_points) - true_camera.project(points),
                                                            axis=-1)))
        own_centre = camera.center if similarity is None else similarity.apply(camera.center)
        centre[view] = 1e3 * float(np.linalg.norm(own_centre - camera_center(np.asarray(rotation, np.float64),
                                                                             np.asarray(translation, np.float64))))
    if not reprojection:
        return None

    def spread(per_view: dict) -> dict:
        values = np.array(list(per_view.values()))
        return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
                "max": float(values.max()), "worst_view": max(per_view, key=per_view.get)}

    return {"reprojection_px": spread(reprojection), "centre_mm": spread(centre), "views": len(reprojection)}


# --------------------------------------------------------------------------- parameters and geometry


def _summary(values: np.ndarray, percentile_90: bool = False) -> dict | None:
    if values.size == 0:
        return None
    out = {"mean": float(np.mean(values)), "median": float(np.median(values)), "vertices": int(values.size)}
    if percentile_90:
        out["p90"] = float(np.percentile(values, 90))
    return out




def eta_per_material(eta: np.ndarray, eta_gt: np.ndarray, material: np.ndarray | None) -> dict | None:
    """η per ground-truth material (paper Table 1): the median of its vertices' η against the true one.

    eta, eta_gt (N,) of the confident vertices, material (N,) their true material label (None: no labels,
    returns None). Returns {"materials": {label: {eta_true, eta, error_pct, vertices}}, "mean_error_pct",
    "max_error_pct"}.
    """
    if material is None or len(eta) == 0:
        return None
    rows = {}
    for label in np.unique(material):
        members = material == label
        true, ours = float(np.median(eta_gt[members])), float(np.median(eta[members]))
        rows[str(int(label))] = {"eta_true": true, "eta": ours, "error_pct": 100 * abs(ours - true) / true,
                                 "vertices": int(members.sum())}
    errors = [row["error_pct"] for row in rows.values()]
    return {"materials": rows, "mean_error_pct": float(np.mean(errors)), "max_error_pct": float(np.max(errors))}


def parameter_errors(model: ParamMesh, truth: ParamMesh, confident: np.ndarray,
                     similarity: Similarity | None = None) -> dict:
    """Normal, η, diffuse-albedo and roughness errors at each model vertex's nearest ground-truth vertex.

    confident: (N,) bool, the model vertices that were fitted with confidence > 0. ``similarity``: model world
    -> ground-truth world (None: same world). Definitions: module docstring. Figures over an empty set are None.
    """
    model = transform_mesh(model, similarity)
    confident = np.asarray(confident, bool)
    distance, nearest = cKDTree(np.asarray(truth.vertices, np.float64)).query(np.asarray(model.vertices), k=1)
    angle = angular_error_deg(np.asarray(model.normals, np.float64), np.asarray(truth.normals, np.float64)[nearest])
    p, t = model.params, truth.params

    def at(values, rows):
        return np.asarray(values, np.float64)[rows]

    eta_gt = at(t.eta, nearest)[confident]
    eta_error = 100 * np.abs(at(p.eta, confident) - eta_gt) / eta_gt
    rho, rho_gt = at(p.rho_d, confident), at(t.rho_d, nearest)[confident]
    albedo = None
    if rho.size and np.sum(rho * rho) > 0 and np.sum(rho_gt * rho_gt) > 0:
        scale = float(np.sum(rho * rho_gt) / np.sum(rho * rho))
        rmse = np.sqrt(np.mean((scale * rho - rho_gt) ** 2)) / np.sqrt(np.mean(rho_gt ** 2))
        albedo = {"relative_rmse": float(rmse), "scale": scale, "vertices": len(rho)}
    has_specular = confident & (at(t.rho_s, nearest) > 0)
    has_single = confident & (at(t.rho_ss, nearest).max(axis=-1) > 0)
    sigma_s_error = np.abs(at(p.sigma_s, has_specular) - at(t.sigma_s, nearest)[has_specular])
    sigma_ss_error = np.abs(at(p.sigma_ss, has_single) - at(t.sigma_ss, nearest)[has_single])
    return {
        "normal_error_deg": {"all": _summary(angle, True), "confident": _summary(angle[confident], True)},
        "eta_relative_error_pct": _summary(eta_error, True),
        "eta_per_material": eta_per_material(
            at(p.eta, confident), eta_gt, None if truth.material is None else at(truth.material, nearest)[confident]),
        "rho_d_relative_rmse": albedo,
        "sigma_s_abs_error": _summary(sigma_s_error),
        "sigma_ss_abs_error": _summary(sigma_ss_error),
        "correspondence_distance_mm": _summary(1000 * distance),
    }


def geometry_errors(model: ParamMesh, truth: ParamMesh, similarity: Similarity | None = None,
                    samples: int = 50000, seed: int = 0) -> dict:
    """Chamfer and Hausdorff distance (mm) between the model (moved by ``similarity``) and the true surface, and
    ``truth_farther_than_1mm``: the share of the true surface farther than 1 mm from the model."""
    model = transform_mesh(model, similarity)
    d = mesh_distances(np.asarray(model.vertices), np.asarray(model.faces), np.asarray(truth.vertices),
                       np.asarray(truth.faces), count=samples, seed=seed)
    return {"chamfer_mm": 1000 * d.chamfer, "hausdorff_mm": 1000 * d.hausdorff,
            "model_to_truth_mm": 1000 * d.a_to_b, "truth_to_model_mm": 1000 * d.b_to_a,
            "truth_farther_than_1mm": d.b_far_share, "samples": samples}


def nearest_normal_errors(mesh: ParamMesh, truth: ParamMesh,
                          similarity: Similarity | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(errors (N,) deg, true normals (N, 3)): the angle between each vertex normal of ``mesh`` (moved by
    ``similarity``) and the normal of its nearest ground-truth vertex, and that normal."""
    moved = transform_mesh(mesh, similarity)
    _, nearest = cKDTree(np.asarray(truth.vertices, np.float64)).query(np.asarray(moved.vertices), k=1)
    true_normals = np.asarray(truth.normals, np.float64)[nearest]
    return angular_error_deg(np.asarray(moved.normals, np.float64), true_normals), true_normals


def geometry_series(meshes: list[ParamMesh], fitted: list[tuple[np.ndarray, np.ndarray] | None],
                    truth: ParamMesh | None, similarity: Similarity | None = None, samples: int = 20000,
                    seed: int = 0) -> list[dict]:
    """How the geometry converged: one row per mesh of the loop (the initial mesh, then each iteration's).

    ``fitted``: per mesh, the normals (N, 3) fitted at its vertices and the (N,) bool vertices to count
    (confident), or None. Each row: ``chamfer_to_previous_mm``; the mesh's folds
    (:func:`sellip.geometry.meshes.surface_defects`: ``self_intersecting_pairs``, ``flipped_triangles`` against
    the previous mesh where it has the same faces, ``degenerate_triangles``); against ``truth`` (None: left out)
    ``chamfer_mm``, ``hausdorff_mm``, ``truth_farther_than_1mm`` (the share of the true surface farther than 1 mm
    from the mesh), the mesh's normal error and the fitted normals' error at the
    nearest ground-truth vertex (``mesh_normal_deg`` / ``fitted_normal_deg``: median and p90).
    """
    rows = []
    for index, mesh in enumerate(meshes):
        row: dict = {"mesh": index, "vertices": mesh.num_vertices, "chamfer_to_previous_mm": None}
        previous = meshes[index - 1] if index else None
        same_faces = previous is not None and np.array_equal(np.asarray(previous.faces), np.asarray(mesh.faces))
        row.update(surface_defects(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                   np.asarray(previous.vertices) if same_faces else None).as_dict())
        if index:
            moved = mesh_distances(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(previous.vertices),
                                   np.asarray(previous.faces), count=samples, seed=seed)
            row["chamfer_to_previous_mm"] = 1000 * moved.chamfer
        if truth is not None:
            geometry = geometry_errors(mesh, truth, similarity, samples=samples, seed=seed)
            row.update(chamfer_mm=geometry["chamfer_mm"], hausdorff_mm=geometry["hausdorff_mm"],
                       truth_farther_than_1mm=geometry["truth_farther_than_1mm"])
            mesh_error, true_normals = nearest_normal_errors(mesh, truth, similarity)
            row["mesh_normal_deg"] = _summary(mesh_error, True)
            if index < len(fitted) and fitted[index] is not None:
                normals, counted = fitted[index]
                if similarity is not None:
                    normals = np.asarray(normals, np.float64) @ np.asarray(similarity.rotation).T
                counted = np.asarray(counted, bool)
                row["fitted_normal_deg"] = _summary(angular_error_deg(np.asarray(normals, np.float64)[counted],
                                                                      true_normals[counted]), True)
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- images


def psnr(reference: np.ndarray, estimate: np.ndarray, mask: np.ndarray) -> dict:
    """PSNR (dB) of ``estimate`` against ``reference``, (H, W, 4, C) analyzer images, inside ``mask`` (H, W).

    Definition: module docstring. Returns {"psnr_db", "scale" (k applied to the estimate), "peak"
    (the normalizing value, reference units), "pixels"}; psnr_db is None when the mask is empty or the
    reference is black there.
    """
    mask = np.asarray(mask, bool)
    reference = np.asarray(reference, np.float64)
    estimate = np.asarray(estimate, np.float64)
    if not mask.any():
        return {"psnr_db": None, "scale": None, "peak": None, "pixels": 0}
    scale = fit_scale(reference, estimate, mask)
    peak = float(np.percentile(reference[mask], PSNR_PEAK_PERCENTILE))
    if peak <= 0:
        return {"psnr_db": None, "scale": scale, "peak": peak, "pixels": int(mask.sum())}
    mse = float(np.mean(((scale * estimate[mask] - reference[mask]) / peak) ** 2))
    value = 10 * np.log10(1 / max(mse, 10 ** (-PSNR_MAX_DB / 10)))
    return {"psnr_db": float(value), "scale": scale, "peak": peak, "pixels": int(mask.sum())}


def render_mask(measured_analyzers: np.ndarray, valid: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """Pixels compared for a held-out view: valid and (the measured object's silhouette or the model's footprint).

    The silhouette is :func:`sellip.geometry.silhouettes.silhouette_masks` of I_d = 2 I90 (as SfM and the initial mesh
    cut it); taking the union penalizes a model that is too small as well as one that is too large.
    """
    diffuse = 2 * np.asarray(measured_analyzers, np.float32)[..., 2, :]
    silhouette = silhouette_masks(diffuse[None], np.asarray(valid, bool)[None])[0]
    return np.asarray(valid, bool) & (silhouette | (np.asarray(coverage) > 0))


# --------------------------------------------------------------------------- timings


def stage_timings(benchmarks_dir: str | Path, results_dir: str | Path | None = None) -> dict:
    """Wall time per rule from Snakemake ``benchmark:`` files, and vertex fits per second.

    Every ``*.tsv`` under ``benchmarks_dir`` is one job; its rule is the first path component
    (``fit_pbrdf/0/3.tsv`` -> fit_pbrdf, ``merge_hdr.tsv`` -> merge_hdr). Per rule: the summed wall time
    ``s`` and the job count. Vertex fits per second: the vertices of ``results_dir/iter/{it}/{pass}.zarr``
    summed over the passes that have fit_pbrdf benchmarks (``fit_pbrdf/{it}/{pass}/{shard}.tsv``), divided
    by those jobs' summed wall time (per core-second of a single-threaded shard job)
    (``results_dir`` defaults to the parent of ``benchmarks_dir``); None with a reason when not available.
    Per rule also ``phases``: the seconds of each part of its jobs (:mod:`sellip.timing`: start-up, imports,
    read, trace, compile, fit, write ...) summed from the phases line of each job's log, the log at the same
    path under ``results_dir/logs`` (``phases_jobs``: how many logs had one).
    """
    from sellip.timing import read_benchmark, read_job_phases

    benchmarks_dir = Path(benchmarks_dir)
    results_dir = Path(results_dir) if results_dir is not None else benchmarks_dir.parent
    rules: dict[str, dict] = {}
    fit_seconds: dict[str, float] = {}
    for path in sorted(benchmarks_dir.rglob("*.tsv")):
        relative = path.relative_to(benchmarks_dir)
        rule = relative.parts[0].removesuffix(".tsv")
        seconds = read_benchmark(path)["wall_s"]
        entry = rules.setdefault(rule, {"s": 0.0, "jobs": 0, "phases": {}, "phases_jobs": 0})
        entry["s"] += seconds
        entry["jobs"] += 1
        phases = read_job_phases(results_dir / "logs" / relative.with_suffix(".log"))
        if phases:
            entry["phases_jobs"] += 1
            for name, value in phases.items():
                entry["phases"][name] = entry["phases"].get(name, 0.0) + float(value)
        if rule == FIT_RULE and len(relative.parts) >= 4:
            key = relative.parts[1:3]  # (iteration, pass)
            fit_seconds[key] = fit_seconds.get(key, 0.0) + seconds
    out = {"rules": rules, "total_s": float(sum(r["s"] for r in rules.values())), "vertex_fits": None,
           "vertex_fits_per_s": None, "vertex_fits_reason": None}
    if not fit_seconds:
        out["vertex_fits_reason"] = f"no {FIT_RULE} benchmarks under {benchmarks_dir}"
        return out
    vertices, seconds, missing = 0, 0.0, []
    for (iteration, fit_pass), s in sorted(fit_seconds.items()):
        store = results_dir / "iter" / iteration / f"{fit_pass}.zarr"
        count = _store_vertices(store)
        if count is None:
            missing.append(str(store))
            continue
        vertices += count
        seconds += s
    if seconds > 0:
        out.update(vertex_fits=vertices, vertex_fits_per_s=vertices / seconds)
    if missing:
        out["vertex_fits_reason"] = f"no vertex count for {len(missing)} iteration(s): {missing[:3]} missing"
    return out


def _store_vertices(path: Path) -> int | None:
    """Vertex count of a params.zarr store (attrs num_vertices, else the rows of ``vertices``), None if absent."""
    import zarr

    if not (path / "zarr.json").is_file():
        return None
    group = zarr.open_group(str(path), mode="r")
    if "num_vertices" in group.attrs:
        return int(group.attrs["num_vertices"])
    return int(group["vertices"].shape[0]) if "vertices" in group else None


# --------------------------------------------------------------------------- per vertex


def vertex_errors(model: ParamMesh, truth: ParamMesh, similarity: Similarity | None = None) -> dict[str, np.ndarray]:
    """Per model vertex, against its nearest ground-truth vertex (the correspondence of :func:`parameter_errors`).

    Returns (N,) arrays: ``normal_error_deg``, ``eta_relative_error_pct`` (|η - η_gt| / η_gt in percent),
    ``distance_mm`` (to the nearest ground-truth vertex) and ``nearest`` (its index). ``similarity``: model
    world -> ground-truth world (None: same world).
    """
    model = transform_mesh(model, similarity)
    distance, nearest = cKDTree(np.asarray(truth.vertices, np.float64)).query(np.asarray(model.vertices), k=1)
    angle = angular_error_deg(np.asarray(model.normals, np.float64), np.asarray(truth.normals, np.float64)[nearest])
    eta_gt = np.asarray(truth.params.eta, np.float64)[nearest]
    eta_error = 100 * np.abs(np.asarray(model.params.eta, np.float64) - eta_gt) / eta_gt
    return {"normal_error_deg": angle, "eta_relative_error_pct": eta_error, "distance_mm": 1000 * distance,
            "nearest": nearest}
