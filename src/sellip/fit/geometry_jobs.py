"""The updates between iterations. The geometry (rule ``refine_geometry``; docs/geometry_update.md): the fitted
normals blended by confidence, the photographs' silhouettes measured against the model's predicted
photograph, and the mesh moved by normal integration (:func:`refine_geometry`). The poses (rule
``refine_poses``; docs/geometry.md, "Poses refined against the object"): every view aligned to the iteration's
model (:func:`refine_poses`).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sellip.jobs import atomic_file, write_text
from sellip.settings import setting

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeometryUpdateSettings:
    """Settings of the geometry update (config section ``refine_geometry``, docs/geometry_update.md; each declared
    once here, :mod:`sellip.settings`): :func:`refine_geometry`. The mesh's vertices move along its normals until
    the surface agrees with the fitted normals, as far as their confidence allows; the faces stay."""

    smoothness: float = setting(0.01, "weight of smooth offsets: where the fit is unsure the surface bends smoothly",
                                unit="no units", minimum=0, per_iteration=True)
    smoothness_unconfident: float = setting(1.0, "added where the fitted normals are unsure, times 1 - their "
                                            "confidence: there the surface moves with its neighbours, so the "
                                            "silhouettes cannot pull single vertices out of an unseen part",
                                            unit="no units", minimum=0, per_iteration=True)
    anchor: float = setting(1e-3, "weight that holds each vertex where it is: the mean offset and the shape far from "
                            "any confident normal, which normals cannot tell (larger keeps more of the previous "
                            "surface)", unit="no units", exclusive_minimum=0, per_iteration=True)
    rounds: int = setting(3, "linearisations around the moved surface per update", minimum=1)
    silhouette: float = setting(0.01, "weight of the photographs' silhouettes: each contour vertex moves the model's "
                                "silhouette (a render of the current model, developed like a photograph) onto the "
                                "photograph's; fixes the mean offset and size that normals cannot tell; held-out views "
                                "are not used; 0: none", unit="no units", minimum=0, per_iteration=True)
    keep_surface: bool = setting(True, "shorten each vertex's step where the full step would make triangles cross, "
                                 "flip or degenerate (docs/geometry_update.md, \"Folds\"); false: every step in full")


def raw_camera(capture, camera):
    """The raw sensor's camera (capture.yaml ``camera``: intrinsics at the mosaic's resolution, its lens
    distortion) at the pose of ``camera`` (a :class:`sellip.model.render.Camera` at the HDR resolution)."""
    from sellip.geometry.cameras import hdr_camera

    lens = {**capture.config["camera"], "width": capture.sensor["width"], "height": capture.sensor["height"]}
    return hdr_camera(lens, camera.rotation, camera.translation, capture.root / "capture.yaml")



def predicted_diffuse(renderer, camera, capture, plan) -> np.ndarray:
    """I_d = 2 I90 (H, W, C) of the current model as the photograph of ``camera`` (HDR resolution) would show it:
    rendered at the raw sensor's resolution and lens (:func:`raw_camera`) under the capture's flash, sampled by
    its polarization and colour mosaic and developed like a photograph (``plan``:
    :func:`sellip.capture.ingest.make_ingest_plan`; :func:`sellip.capture.ingest.develop`), so that the demosaicing
    blurs its silhouette as it blurs the photograph's. The background is a tiny positive value: the silhouette
    operator then ranks the same pixels as in a photograph, whose background is noise, not zero
    (:func:`sellip.geometry.silhouettes.silhouette_level` takes its level from a percentile of the positive pixels).

    Only what I90 needs is computed: the raw pixels behind the 90-degree analyzer (one in four: the render is a
    camera on their lattice, one sample at each pixel's centre), inside the model's box (whole mosaic periods,
    with a margin of two for the demosaicing's reach), and that analyzer's demosaicing."""
    from sellip.capture.ingest import CELL, analyzer_plan, develop
    from sellip.capture.sensor import sensor_colors
    from sellip.model.conventions import ANALYZER_ANGLES_DEG
    from sellip.model.render import Camera, flash_light

    light = capture.config["light"]
    raw = raw_camera(capture, camera)
    flash = flash_light(raw, light["position_m"], polarizer_deg=float(light["polarizer_deg"]))
    analyzer = ANALYZER_ANGLES_DEG.index(90)
    one = analyzer_plan(plan, analyzer)
    dy, dx = (int(x) for x in one.demosaic.phases[0])
    period = capture.layout.period
    mosaic = np.zeros((raw.height, raw.width), np.float32)
    pixels = raw.project(np.asarray(renderer.mesh.vertices, np.float64))
    pixels = pixels[np.all(np.isfinite(pixels), axis=1)]
    if len(pixels):
        lo = np.clip(np.floor((pixels.min(axis=0) - 2 * period) / period) * period, 0, [raw.width, raw.height])
        hi = np.clip(np.ceil((pixels.max(axis=0) + 2 * period) / period) * period, 0, [raw.width, raw.height])
        (x0, y0), (x1, y1) = lo.astype(int), hi.astype(int)
        if x1 > x0 and y1 > y0:
            # Lattice pixel (i, j) is raw pixel (x0 + dx + CELL j, y0 + dy + CELL i).
            intrinsics = np.array(raw.intrinsics, np.float64)
            intrinsics[:2] /= CELL
            intrinsics[0, 2] = (raw.intrinsics[0, 2] - x0 - dx) / CELL
            intrinsics[1, 2] = (raw.intrinsics[1, 2] - y0 - dy) / CELL
            lattice = Camera(intrinsics, raw.rotation, raw.translation, (x1 - x0) // CELL, (y1 - y0) // CELL,
                             raw.distortion)
            rgb = np.nan_to_num(renderer.render(lattice, flash, supersample=1).analyzers[..., analyzer, :])
            rows, columns = slice(y0 + dy, y1, CELL), slice(x0 + dx, x1, CELL)
            colors = capture.layout.color_map(raw.height, raw.width)[rows, columns]
            seen = sensor_colors(capture.layout, capture.config["camera"].get("color_matrix"))[colors]
            mosaic[rows, columns] = np.einsum("hwc,hwc->hw", seen, rgb)
    diffuse = 2 * develop(mosaic, one)[..., 0, :]
    return np.where(np.isfinite(diffuse) & (diffuse > 0), diffuse, 1e-12).astype(np.float32)



def measure_silhouettes(mesh, mesh_normals: np.ndarray, shading_normals: np.ndarray, params, cameras_path: Path,
                        hdr_path: Path, capture_path: Path, exclude_views=(), mask_options: dict | None = None):
    """The silhouette constraints of every view of cameras.csv but ``exclude_views`` (the held-out ones):
    the observed silhouette of each photograph against the same operator's silhouette of the current model
    (``mesh`` with its geometric ``mesh_normals`` (V, 3), shaded with ``shading_normals`` (V, 3) and ``params``)
    as the camera would photograph it (:func:`predicted_diffuse`), both placed to a fraction of a pixel
    (:class:`sellip.geometry.silhouettes.Silhouette`, :func:`sellip.geometry.update.silhouette_constraints`). Returns
    the constraints and a per-view summary (constraints; the mean and RMS offset in pixels, positive where the
    photograph's silhouette lies outside)."""
    from sellip.capture.ingest import make_ingest_plan
    from sellip.capture.reader import read_capture
    from sellip.geometry.cameras import diffuse_view, load_cameras
    from sellip.geometry.silhouettes import Silhouette
    from sellip.geometry.update import SilhouetteConstraints, silhouette_constraints
    from sellip.model.render import ParamMesh, Renderer

    capture = read_capture(capture_path, check_files=False)
    plan = make_ingest_plan(capture.sensor, capture.config["camera"], capture.layout)
    cameras, hdr = load_cameras(cameras_path, hdr_path)
    renderer = Renderer(ParamMesh(mesh.vertices, mesh.faces, shading_normals, params))
    options = mask_options or {}
    parts, per_view = [], {}
    excluded = set(exclude_views)
    for view in (v for v in cameras if v not in excluded):
        camera = cameras[view]
        diffuse, valid = diffuse_view(hdr, hdr.view_ids.index(view))
        observed = Silhouette.of(diffuse, valid, **options)
        predicted = Silhouette.of(predicted_diffuse(renderer, camera, capture, plan), **options)
        part = silhouette_constraints(mesh.vertices, mesh_normals, camera.intrinsics, camera.rotation,
                                      camera.translation, observed, predicted)
        parts.append(part)
        per_view[view] = {"constraints": len(part),
                          "offset_px_mean": float(np.mean(part.offset_px)) if len(part) else None,
                          "offset_px_rms": float(np.sqrt(np.mean(part.offset_px ** 2))) if len(part) else None}
    return SilhouetteConstraints.concatenate(parts), per_view



def iteration_model(params_path: Path, mesh_path: Path):
    """One iteration's model: (the params store, its mesh (:func:`sellip.fit.observe.read_mesh`), the pBRDF
    parameters (float64), each vertex's confidence (V,) (1 where the store has none), its normal confidence (V,)
    from the fit's normal uncertainty, or the confidence where the store has none). Raises ParamsError when the store's
    vertices are not the mesh's."""
    from sellip.fit.observe import read_mesh
    from sellip.fit.vertex_fit import confidence_from_uncertainty
    from sellip.model.params import PARAM_FIELDS, ParamsError, params_from, read_params, same_vertices

    store = read_params(params_path)
    vertices = store["vertices"]
    confidence = store.get("confidence")
    if confidence is None:
        confidence = np.ones(len(vertices), np.float32)
    # The normals move the surface as far as they are certain (eta's uncertainty does not matter here).
    normal_confidence = np.asarray(confidence_from_uncertainty(store["normal_std_deg"], 0.0)
                                   if "normal_std_deg" in store else confidence, np.float64)
    mesh = read_mesh(mesh_path)
    if not same_vertices(mesh.vertices, vertices):
        raise ParamsError(f"{params_path}: its {len(vertices)} vertices are not those of {mesh_path} "
                          f"({mesh.num_vertices})")
    params = params_from({name: store[name] for name in PARAM_FIELDS}, np.float64)
    return store, mesh, params, confidence, normal_confidence


def refine_geometry(params_path: Path, mesh_path: Path, output: Path,
                    settings: GeometryUpdateSettings = GeometryUpdateSettings(), min_confidence: float = 0.5,
                    reference_mesh: Path | None = None, cameras_path: Path | None = None, hdr_path: Path | None = None,
                    capture_path: Path | None = None, exclude_views=(), mask_options: dict | None = None,
                    iteration: int | None = None, previous_params: Path | None = None,
                    poses_summary: Path | None = None, convergence=None) -> dict:
    """Write the next iteration's mesh ``output`` and ``<output>.json``; returns the summary written there.
    ``settings``: config ``refine_geometry`` of this iteration (:class:`GeometryUpdateSettings`).
    ``min_confidence``: the vertices whose normal agreement is reported. ``settings.silhouette`` > 0: the weight of the
    silhouette constraints of the photographs (``cameras_path``, ``hdr_path``, ``capture_path`` needed; the
    ``exclude_views`` not used; ``mask_options`` of :func:`sellip.geometry.silhouettes.silhouette_masks`);
    ``settings.keep_surface``: steps that would fold the mesh are shortened
    (:func:`sellip.geometry.update.step_without_folds`). With ``iteration`` given, the summary's ``convergence`` is
    the loop's verdict (:func:`sellip.fit.convergence.judge`, ``convergence`` a ConvergenceSettings) from the step,
    ``previous_params`` (iteration - 1's parameters: η's change) and ``poses_summary`` (this iteration's pose
    refinement, where the poses are refined).

    Long: one job's steps in order (read, blend, silhouettes, integrate, carry parameters, write), each a call."""
    from sellip.fit.observe import read_mesh
    from sellip.geometry.meshes import angular_error_deg, blend_normals, mesh_distances, surface_defects, vertex_normals
    from sellip.geometry.update import refine_from_normals
    from sellip.model.params import ParamsError
    from sellip.model.ply import write_param_mesh
    from sellip.model.render import ParamMesh

    started = time.perf_counter()
    smoothness, smoothness_unconfident, anchor = settings.smoothness, settings.smoothness_unconfident, settings.anchor
    rounds, silhouette, keep_surface = settings.rounds, settings.silhouette, settings.keep_surface
    store, mesh, params, confidence, normal_confidence = iteration_model(params_path, mesh_path)
    vertices, fitted = store["vertices"], store["normals"]
    reference = None
    if reference_mesh is not None:
        reference = read_mesh(reference_mesh)
        if reference.num_vertices != mesh.num_vertices or not np.array_equal(reference.faces, mesh.faces):
            raise ParamsError(f"{reference_mesh}: not the same mesh as {mesh_path} (vertices {reference.num_vertices} "
                              f"vs {mesh.num_vertices}, or other faces); the loop keeps the initial mesh's faces")
        reference = reference.vertices
    confident = normal_confidence >= min_confidence
    log.info("%s: %d vertices, %d with normal confidence >= %.2f (median %.2f); smoothness %g (unconfident %g), "
             "anchor %g, %d rounds", params_path, len(vertices), int(confident.sum()), min_confidence,
             float(np.median(normal_confidence)), smoothness, smoothness_unconfident, anchor, rounds)
    mesh_normals = vertex_normals(mesh.vertices, mesh.faces)
    silhouettes, per_view = None, {}
    if silhouette > 0:
        if None in (cameras_path, hdr_path, capture_path):
            raise ValueError("the silhouette constraints (silhouette > 0) need cameras.csv, hdr.zarr and the capture")
        shading = blend_normals(fitted, mesh_normals, normal_confidence)
        silhouettes, per_view = measure_silhouettes(mesh, mesh_normals, shading, params, cameras_path, hdr_path,
                                                    capture_path, exclude_views, mask_options)
        log.info("silhouettes of %d views: %d constraints; the photographs' outside the model's by %.3f px on "
                 "average (RMS %.3f px)", len(per_view), len(silhouettes),
                 *((float(np.mean(silhouettes.offset_px)), float(np.sqrt(np.mean(silhouettes.offset_px ** 2))))
                   if len(silhouettes) else (np.nan, np.nan)))
    new_vertices = refine_from_normals(mesh.vertices, mesh.faces, fitted, normal_confidence, smoothness=smoothness,
                                       smoothness_unconfident=smoothness_unconfident, anchor=anchor, rounds=rounds,
                                       reference=reference, silhouettes=silhouettes, silhouette_weight=silhouette,
                                       keep_surface=keep_surface)
    new_normals = vertex_normals(new_vertices, mesh.faces)
    output = Path(output)
    moved = mesh_distances(new_vertices, mesh.faces, mesh.vertices, mesh.faces, count=20000)
    offsets = np.linalg.norm(new_vertices - mesh.vertices, axis=1)

    def agreement(normals):
        return float(np.median(angular_error_deg(fitted[confident], normals[confident]))) if confident.any() else None

    summary = {"vertices": len(new_vertices), "confident_vertices": int(confident.sum()),
               "moved_chamfer_mm": 1e3 * moved.chamfer, "moved_hausdorff_mm": 1e3 * moved.hausdorff,
               "offset_median_mm": 1e3 * float(np.median(offsets)), "offset_max_mm": 1e3 * float(offsets.max()),
               "fitted_vs_mesh_before_deg": agreement(mesh_normals),
               "fitted_vs_mesh_after_deg": agreement(new_normals),
               "surface_defects": surface_defects(new_vertices, mesh.faces, mesh.vertices).as_dict(),
               "keep_surface": keep_surface,
               "silhouette_weight": silhouette,
               "silhouette_constraints": 0 if silhouettes is None else len(silhouettes),
               "silhouette_offset_px": per_view}
    if iteration is not None:
        summary["convergence"] = _verdict(iteration, offsets, mesh, store, confident, previous_params, poses_summary,
                                          convergence)
    summary["seconds"] = time.perf_counter() - started
    write_text(json.dumps(summary, indent=1), f"{output}.json")
    with atomic_file(output) as tmp:
        write_param_mesh(tmp, ParamMesh(new_vertices, mesh.faces, new_normals, params),
                         extra={"confidence": np.asarray(confidence, np.float32)})
    log.info("wrote %s in %.1f s: the surface moved %.3f mm (Chamfer; Hausdorff %.3f mm, vertex offsets median "
             "%.3f mm); fitted vs mesh normals (median, confident vertices) %.2f -> %.2f deg", output,
             summary["seconds"], summary["moved_chamfer_mm"], summary["moved_hausdorff_mm"],
             summary["offset_median_mm"], *(np.nan if summary[key] is None else summary[key]
                                          for key in ("fitted_vs_mesh_before_deg", "fitted_vs_mesh_after_deg")))
    return summary



def _verdict(iteration, offsets, mesh, store, confident, previous_params, poses_summary, convergence) -> dict:
    """The loop's convergence verdict of this geometry update (:func:`sellip.fit.convergence.judge`)."""
    from sellip.fit.convergence import ConvergenceSettings, judge
    from sellip.model.params import read_params

    edges = mesh.vertices[mesh.faces[:, [1, 2, 0]]] - mesh.vertices[mesh.faces]
    mean_edge = float(np.linalg.norm(edges, axis=-1).mean())
    eta_before = (None if previous_params is None
                  else np.asarray(read_params(previous_params, fields=["eta"])["eta"], np.float64))
    eta = np.asarray(store["eta"], np.float64)
    if eta_before is not None and eta_before.shape != eta.shape:
        eta_before = None  # another mesh (a user's restart): nothing to compare
    poses = None if poses_summary is None else json.loads(Path(poses_summary).read_text(encoding="utf-8"))
    verdict = judge(iteration, offsets, mean_edge, eta.ravel(), None if eta_before is None else eta_before.ravel(),
                    confident, poses, convergence or ConvergenceSettings())
    log.info("iteration %d: %s", iteration, verdict["reason"])
    return verdict


def refine_poses(params_path: Path, mesh_path: Path, cameras_path: Path, hdr_path: Path, capture_path: Path,
                 output: Path, settings=None, views=None) -> dict:
    """Write the next iteration's cameras table ``output`` (cameras.csv columns) and ``<output>.json``: every view
    of ``cameras_path`` with its pose aligned to this iteration's model (``params_path`` on ``mesh_path``, shaded
    with its fitted normals blended by confidence as the geometry update does) by
    :func:`sellip.geometry.pose_refinement.refine_view` under the capture's flash; ``views`` (default: all) limits
    which are aligned, the others are copied. ``settings``: a :class:`PoseRefinementSettings`. Returns the
    summary written beside it (per view: the step and the cost; over the views: medians and maxima)."""
    from sellip.capture.reader import read_capture
    from sellip.geometry.cameras import load_cameras, read_cameras, write_cameras
    from sellip.geometry.meshes import blend_normals, vertex_normals
    from sellip.geometry.pose_refinement import PoseRefinementSettings, refine_view
    from sellip.model.render import ParamMesh, Renderer, flash_light

    started = time.perf_counter()
    settings = settings or PoseRefinementSettings()
    store, mesh, params, confidence, normal_confidence = iteration_model(params_path, mesh_path)
    shading = blend_normals(store["normals"], vertex_normals(mesh.vertices, mesh.faces), normal_confidence)
    renderer = Renderer(ParamMesh(mesh.vertices, mesh.faces, shading, params))
    light = read_capture(capture_path, check_files=False).config["light"]

    def flash(camera):
        return flash_light(camera, light["position_m"], polarizer_deg=float(light["polarizer_deg"]))

    cameras, hdr = load_cameras(cameras_path, hdr_path)
    view_ids, rotations, translations = read_cameras(cameras_path)
    chosen = set(cameras if views is None else views)
    per_view = {}
    for index, view in enumerate(view_ids):
        if view not in cameras or view not in chosen or not np.all(np.isfinite(translations[index])):
            continue
        analyzers, valid = hdr.view(view)
        camera, per_view[view] = refine_view(renderer, cameras[view], flash, analyzers, valid, settings,
                                             vertex_confidence=confidence)
        rotations[index], translations[index] = camera.rotation, camera.translation
        log.info("%s: %s", view, _step_text(per_view[view]))
    refined = [r for r in per_view.values() if r["refined"]]
    summary = {"views": len(per_view), "refined": len(refined),
               "kept": {view: r["reason"] for view, r in per_view.items() if not r["refined"]},
               "rotation_deg": _spread([r["rotation_deg"] for r in refined]),
               "shift_mm": _spread([r["shift_mm"] for r in refined]),
               "motion_px": _spread([r["motion_px"] for r in refined]),
               "settings": {name: getattr(settings, name) for name in settings.__dataclass_fields__},
               "per_view": per_view, "seconds": time.perf_counter() - started}
    write_text(json.dumps(summary, indent=1), f"{output}.json")
    write_cameras(output, view_ids, rotations, translations)  # atomic
    log.info("wrote %s in %.1f s: %d of %d views refined (rotation median %s deg, centre shift median %s mm), %d kept",
             output, summary["seconds"], len(refined), len(per_view), (summary["rotation_deg"] or {}).get("median"),
             (summary["shift_mm"] or {}).get("median"), len(summary["kept"]))
    return summary


def _step_text(report: dict) -> str:
    if not report["refined"]:
        return "kept: " + report["reason"]
    return (f"rotated {report['rotation_deg']:.4f} deg, centre moved {report['shift_mm']:.3f} mm, the object "
            f"{report['motion_px']:.3f} px, robust cost {report['cost_start']:.4g} -> {report['cost_end']:.4g} "
            f"({report['pixels']:d} pixels)")


def _spread(values) -> dict | None:
    return {"median": float(np.median(values)), "max": float(np.max(values))} if len(values) else None
