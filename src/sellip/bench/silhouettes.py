"""How well the silhouettes of a run's photographs match the true ones: the ground-truth mesh ray-cast through
each pixel centre of the capture's true cameras, against :func:`sellip.geometry.silhouettes.silhouette_masks` of
the run's HDR views under several cuts (``benchmarks/silhouette_iou.py``; docs/geometry.md quotes it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sellip.geometry import silhouettes


def agreement(masks: np.ndarray, truth: np.ndarray) -> dict[str, np.ndarray]:
    """Per view of (V, H, W) bool ``masks`` against ``truth``: ``iou``, ``missed`` (true pixels left out) and
    ``extra`` (pixels added), the last two as fractions of the true area."""
    masks, truth = np.asarray(masks, bool), np.asarray(truth, bool)
    area = np.maximum(truth.sum(axis=(1, 2)), 1)
    union = np.maximum((masks | truth).sum(axis=(1, 2)), 1)
    return {"iou": (masks & truth).sum(axis=(1, 2)) / union, "missed": (truth & ~masks).sum(axis=(1, 2)) / area,
            "extra": (masks & ~truth).sum(axis=(1, 2)) / area}


def silhouette_agreement(run: str | Path, capture: str | Path, cuts: dict[str, dict]) -> dict[str, dict[str, float]]:
    """For each named cut (``SilhouetteOptions`` fields over the defaults), the median and worst over the views of
    :func:`agreement` between the silhouettes of ``run``/hdr.zarr and the truth of ``capture`` (its poses.csv and
    ground_truth/model.ply)."""
    from sellip.geometry.cameras import diffuse_view, load_cameras
    from sellip.model.ply import read_ply
    from sellip.model.render import coverage_masks

    cameras, hdr = load_cameras(Path(capture) / "poses.csv", Path(run) / "hdr.zarr")
    vertex, faces = read_ply(Path(capture) / "ground_truth" / "model.ply")
    truth = coverage_masks(np.stack([vertex[k] for k in "xyz"], axis=1), faces, list(cameras.values()))
    views = [diffuse_view(hdr, hdr.view_ids.index(view)) for view in cameras]
    table = {}
    for name, options in cuts.items():
        masks = np.stack([silhouettes.silhouette_masks(d[None], v[None], **options)[0] for d, v in views])
        figures = agreement(masks, truth)
        table[name] = {"iou_median": float(np.median(figures["iou"])), "iou_worst": float(figures["iou"].min()),
                       "missed_median": float(np.median(figures["missed"])),
                       "extra_median": float(np.median(figures["extra"]))}
    return table


def cut_difference(run: str | Path, options: dict, reference: dict) -> dict[str, int]:
    """How the silhouettes of ``run``/hdr.zarr under ``options`` differ from those under ``reference`` (both
    ``SilhouetteOptions`` fields over the defaults): views that differ, pixels added and removed, object pixels
    under the reference. No truth needed: a run whose silhouettes do not differ is the same run up to its first use
    of them."""
    from sellip.capture.hdr import read_hdr
    from sellip.geometry.cameras import diffuse_view

    hdr = read_hdr(Path(run) / "hdr.zarr")
    figures = {"views": len(hdr.view_ids), "views_changed": 0, "added": 0, "removed": 0, "object": 0}
    for index in range(len(hdr.view_ids)):
        diffuse, valid = diffuse_view(hdr, index)
        mask = silhouettes.silhouette_masks(diffuse[None], valid[None], **options)[0]
        before = silhouettes.silhouette_masks(diffuse[None], valid[None], **reference)[0]
        figures["views_changed"] += int((mask != before).any())
        figures["added"] += int((mask & ~before).sum())
        figures["removed"] += int((before & ~mask).sum())
        figures["object"] += int(before.sum())
    return figures


def model_offsets(run: str | Path, capture: str | Path, iteration: int | None = None,
                  views: int = 8) -> dict:
    """How far the photographs' silhouettes lie outside a model's, as the geometry update measures it
    (:func:`sellip.fit.geometry_jobs.measure_silhouettes`, positive outside), over ``views`` views spread evenly over
    ``run``/cameras.csv. The model: the true one of ``capture`` (its ground_truth/model.ply) when ``iteration`` is
    None, else iteration N's fitted one on the mesh it was fitted on (iter/N/refit.zarr, or fit.zarr where the
    iteration had no refit, on mesh/init.ply or iter/N-1/mesh.ply: what that iteration's geometry update saw).
    Returns ``{"views": {view: {"constraints", "offset_px_mean", "offset_px_rms"}}, "constraints", "offset_px_mean",
    "offset_px_rms"}`` (px at the HDR grid)."""
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.fit.geometry_jobs import iteration_model, measure_silhouettes
    from sellip.geometry.cameras import read_cameras
    from sellip.geometry.meshes import blend_normals, vertex_normals
    from sellip.model.ply import read_param_mesh

    run, capture = Path(run), Path(capture)
    if iteration is None:
        model = read_param_mesh(capture / GROUND_TRUTH_MESH)
        mesh, shading, params = model, model.normals, model.params
    else:
        folder = run / "iter" / str(iteration)
        store_path = folder / "refit.zarr" if (folder / "refit.zarr").exists() else folder / "fit.zarr"
        mesh_path = run / "mesh" / "init.ply" if iteration == 0 else run / "iter" / str(iteration - 1) / "mesh.ply"
        store, mesh, params, _, normal_confidence = iteration_model(store_path, mesh_path)
        shading = blend_normals(store["normals"], vertex_normals(mesh.vertices, mesh.faces), normal_confidence)
    names = list(read_cameras(run / "cameras.csv")[0])
    chosen = names[::max(1, len(names) // views)][:views]
    constraints, per_view = measure_silhouettes(mesh, vertex_normals(mesh.vertices, mesh.faces), shading, params,
                                                run / "cameras.csv", run / "hdr.zarr", capture,
                                                exclude_views=[name for name in names if name not in chosen])
    offset = constraints.offset_px
    return {"views": per_view, "constraints": int(len(offset)),
            "offset_px_mean": float(np.mean(offset)) if len(offset) else float("nan"),
            "offset_px_rms": float(np.sqrt(np.mean(offset ** 2))) if len(offset) else float("nan")}
