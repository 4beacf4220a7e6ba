"""The poses of a capture (docs/design.md §2 sfm; rule ``run_sfm``): known (poses.csv), SfM (pycolmap), or
SfM verified against poses.csv; SfM poses scaled to ``scene.distance_m``; ``cameras.csv`` and the
comparison with known poses (rotation and centre errors after a similarity alignment).
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sellip.capture.checks import check_pose_units
from sellip.capture.files import POSES_CSV
from sellip.capture.reader import read_capture
from sellip.geometry import alignment, sfm
from sellip.geometry.cameras import diffuse_view, intrinsics_matrix, pose_arrays, view_masks, write_cameras
from sellip.model.ply import write_ply

log = logging.getLogger(__name__)





def compare_to_known(result: sfm.SfmResult, known_rotations: np.ndarray, known_translations: np.ndarray,
                     distance_m: float) -> tuple[alignment.Similarity, dict, pd.DataFrame]:
    """Align SfM cameras to known poses (Sim(3)) and measure them.

    known_*: poses of the same views as ``result`` (NaN rows are skipped). Returns the similarity
    (SfM world -> known world), a summary (median/max rotation error in degrees, centre error in
    metres and as a fraction of ``distance_m``) and a per-view table.
    """
    usable = result.registered & np.isfinite(known_translations).all(axis=1)
    align = alignment.align_cameras(result.rotations[usable], result.translations[usable],
                                   known_rotations[usable], known_translations[usable])
    rotations, translations = align.apply_to_poses(result.rotations[usable], result.translations[usable])
    rotation_deg, centre_m = alignment.pose_errors(rotations, translations, known_rotations[usable],
                                                  known_translations[usable])
    table = pd.DataFrame({"view_id": np.asarray(result.view_ids)[usable], "rotation_error_deg": rotation_deg,
                          "centre_error_m": centre_m, "centre_error_fraction": centre_m / distance_m})
    summary = {
        "views_compared": int(usable.sum()),
        "rotation_error_deg": {"median": float(np.median(rotation_deg)), "mean": float(rotation_deg.mean()),
                               "max": float(rotation_deg.max())},
        "centre_error_m": {"median": float(np.median(centre_m)), "mean": float(centre_m.mean()),
                           "max": float(centre_m.max())},
        "centre_error_fraction": {"median": float(np.median(centre_m)) / distance_m,
                                  "max": float(centre_m.max()) / distance_m},
        "alignment_scale": align.scale,
    }
    return align, summary, table



def solve_poses(hdr_path: str | Path, capture_path: str | Path, cameras_path: str | Path, output: str | Path,
              options: sfm.SfmOptions = sfm.SfmOptions(), mask_options: dict | None = None) -> dict:
    """Run the stage (see the module docstring); returns the report. options: config ``sfm`` (``options.mode``: where
    the poses come from).

    Long: the three modes share their reading, scaling and writing; one function keeps their order visible."""
    from sellip.capture.hdr import read_hdr
    from sellip.jobs import atomic_directory

    started = time.perf_counter()
    mode = options.mode
    capture = read_capture(capture_path, check_files=False)  # raw frames are ingest's business
    hdr = read_hdr(hdr_path)
    view_ids = hdr.view_ids
    distance_m = float(capture.config["scene"]["distance_m"])
    known = None
    if capture.poses is not None:
        poses = capture.poses.set_index("view_id").reindex(view_ids).reset_index()
        missing = [v for v, ok in zip(view_ids, poses["qw"].notna()) if not ok]
        if missing and mode != "sfm":
            log.warning("poses.csv has no pose for %d view(s): %s; they are left out", len(missing), missing[:20])
        _, known_rotations, known_translations = pose_arrays(poses.fillna({"qw": 1.0, "qx": 0.0, "qy": 0.0,
                                                                            "qz": 0.0}))
        known_translations[poses["qw"].isna().to_numpy()] = np.nan
        known = (known_rotations, known_translations)
        if mode != "sfm":  # poses in millimetres would give a model 1000 times too large (docs/reliability.md)
            check_pose_units(known_rotations, known_translations, distance_m, str(Path(capture_path) / POSES_CSV),
                             str(Path(capture_path) / "capture.yaml"))
    if mode == "known" and known is None:
        log.info("sfm.mode is 'known' but %s has no poses.csv: running SfM", capture_path)
        mode = "sfm"
    if mode == "verify" and known is None:
        raise sfm.RegistrationError(f"sfm.mode 'verify' needs poses.csv in {capture_path}", [])
    report = {"mode": mode, "views": len(view_ids), "distance_m": distance_m}

    if mode == "known":
        has_pose = np.isfinite(known[1]).all(axis=1)
        with atomic_directory(output) as tmp:
            tmp.mkdir()
            report.update(registered=int(has_pose.sum()), unregistered=[v for v, ok in zip(view_ids, has_pose)
                                                                         if not ok],
                          total_s=time.perf_counter() - started)
            (tmp / "report.json").write_text(json.dumps(report, indent=2))
            write_cameras(cameras_path, [v for v, ok in zip(view_ids, has_pose) if ok], known[0][has_pose],
                          known[1][has_pose])
        return report

    mask_options = mask_options or {}
    masks = view_masks(hdr, mask_options)
    upscale = sfm.feature_upscale(masks, options.feature_object_px, options.max_upscale)
    images, feature_masks = [], []
    for index in range(len(view_ids)):
        diffuse, _ = diffuse_view(hdr, index)
        image, mask = sfm.feature_image(diffuse, masks[index], upscale)
        images.append(image)
        feature_masks.append(mask)
    intrinsics = sfm.scale_intrinsics(intrinsics_matrix(hdr.intrinsics), upscale)
    log.info("%d views, images magnified x%d for features (%dx%d)", len(view_ids), upscale, images[0].shape[1],
             images[0].shape[0])
    with tempfile.TemporaryDirectory(prefix="sellip-sfm-") as work:
        result = sfm.run_sfm(np.stack(images), np.stack(feature_masks), intrinsics, view_ids, work, options)
    report.update(result.stats, upscale=upscale, registered=int(result.registered.sum()),
                  unregistered=result.unregistered_ids,
                  image_names={f"{i:05d}.png": v for i, v in enumerate(view_ids)})
    sfm.check_registration(result, options.min_registered_fraction)
    normalization = sfm.metric_normalization(result, distance_m)
    result = sfm.transform_result(result, normalization)
    report["metric_scale"] = normalization.scale
    pose_table = None
    if mode == "verify":
        align, summary, pose_table = compare_to_known(result, *known, distance_m)
        result = sfm.transform_result(result, align)
        report["verify"] = summary
        log.info("verify: rotation error median %.3f deg (max %.3f), centre error median %.2f%% of %.2f m (max %.2f%%)",
                 summary["rotation_error_deg"]["median"], summary["rotation_error_deg"]["max"],
                 100 * summary["centre_error_fraction"]["median"], distance_m,
                 100 * summary["centre_error_fraction"]["max"])
    if len(result.errors):
        report["mean_reprojection_error_px"] = float(result.errors.mean() / upscale)
    report["points"] = len(result.points)
    report["total_s"] = time.perf_counter() - started

    with atomic_directory(output) as tmp:
        (tmp / "sparse").mkdir(parents=True)
        result.reconstruction.write(tmp / "sparse")
        write_ply(tmp / "points.ply", {
            "x": result.points[:, 0].astype(np.float32), "y": result.points[:, 1].astype(np.float32),
            "z": result.points[:, 2].astype(np.float32), "red": result.colors[:, 0], "green": result.colors[:, 1],
            "blue": result.colors[:, 2], "error": (result.errors / upscale).astype(np.float32),
            "track_length": np.array([len(t) for t in result.tracks], np.int32)})
        if pose_table is not None:
            pose_table.to_csv(tmp / "pose_errors.csv", index=False)
        (tmp / "report.json").write_text(json.dumps(report, indent=2))
        if mode == "verify":
            has_pose = np.isfinite(known[1]).all(axis=1)
            write_cameras(cameras_path, [v for v, ok in zip(view_ids, has_pose) if ok], known[0][has_pose],
                          known[1][has_pose])
        else:
            ok = result.registered
            write_cameras(cameras_path, [v for v, r in zip(view_ids, ok) if r], result.rotations[ok],
                          result.translations[ok])
    return report
