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
