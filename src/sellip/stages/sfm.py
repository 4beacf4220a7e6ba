"""``sellip sfm``: camera poses for every view (rule ``run_sfm``, DESIGN §2 sfm).

    sellip sfm --hdr results/NAME/hdr.zarr --capture CAPTURE --cameras results/NAME/cameras.csv
               --output results/NAME/sfm [--mode known|verify|sfm] [--threads 2] [options]

Modes (config ``sfm.mode``):

``known`` (default)
    poses.csv of the capture is used as it is; no SfM runs. Without poses.csv the stage
    falls back to ``sfm``.
``verify``
    SfM runs anyway; its cameras are aligned to poses.csv (Sim(3), Umeyama on the camera
    centres, robust to a few bad poses) and the rotation and centre errors are reported.
    cameras.csv holds poses.csv; the sparse model is moved into the poses.csv world.
``sfm``
    poses.csv is ignored. cameras.csv holds the registered views' SfM poses in metric
    scale: origin at the object centre, median camera-to-object distance = capture.yaml
    ``scene.distance_m`` (:func:`sellip.sfm.metric_normalization`).

Images: I_d = 2 I90 of hdr.zarr, silhouette-masked (:func:`sellip.geometry.silhouette_masks`),
magnified when the object is small (:func:`sellip.sfm.feature_upscale`), tone-mapped to 8 bit.

Written (all or nothing): ``cameras.csv`` (view_id, qw, qx, qy, qz, tx, ty, tz: cam_from_world,
metres) and the folder ``--output`` with ``report.json`` (mode, registered/unregistered views,
scale, timings, verify errors), and after SfM ``sparse/`` (COLMAP binary model: cameras, images,
points3D with tracks, in the cameras.csv world; image i is view i of hdr.zarr, named
``{i:05d}.png``, see report.json ``image_names``), ``points.ply`` (x y z red green blue error
track_length) and, in verify mode, ``pose_errors.csv``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sellip import geometry, sfm
from sellip.conventions import quaternion_to_rotation, rotation_to_quaternion
from sellip.capture import checks
from sellip.io import POSE_COLUMNS, POSES_CSV, CaptureError, read_capture, validate_poses, write_ply

log = logging.getLogger(__name__)

MODES = ("known", "verify", "sfm")


# --------------------------------------------------------------------------- cameras.csv


def write_cameras(path: str | Path, view_ids: list[str], rotations: np.ndarray, translations: np.ndarray) -> None:
    """Write a poses table (POSE_COLUMNS) atomically (temporary file + rename)."""
    path = Path(path)
    quaternions = rotation_to_quaternion(np.asarray(rotations, np.float64))
    table = pd.DataFrame({"view_id": list(view_ids)})
    for k, name in enumerate(POSE_COLUMNS[1:5]):
        table[name] = quaternions[:, k]
    for k, name in enumerate(POSE_COLUMNS[5:]):
        table[name] = np.asarray(translations, np.float64)[:, k]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    table.to_csv(tmp, index=False, float_format="%.17g")
    tmp.rename(path)


def read_cameras(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(view_ids, rotations (N, 3, 3), translations (N, 3)) of a cameras.csv / poses.csv file."""
    table = validate_poses(pd.read_csv(path, dtype={"view_id": str}, keep_default_na=False), str(path))
    return _pose_arrays(table)


def _pose_arrays(table: pd.DataFrame) -> tuple[list[str], np.ndarray, np.ndarray]:
    rotations = quaternion_to_rotation(table[list(POSE_COLUMNS[1:5])].to_numpy(np.float64))
    return list(table["view_id"]), rotations, table[list(POSE_COLUMNS[5:])].to_numpy(np.float64)


# --------------------------------------------------------------------------- images


def diffuse_view(hdr, index: int) -> tuple[np.ndarray, np.ndarray]:
    """I_d = 2 I90 (H, W, C) float32 and valid (H, W) of view ``index`` of an hdr.zarr store (one chunk read)."""
    i90 = np.asarray(hdr.analyzers[index, :, :, 2, :], np.float32)
    return 2 * i90, np.asarray(hdr.valid[index], bool)


def view_masks(hdr, mask_options: dict) -> np.ndarray:
    """(V, H, W) silhouettes of every view of an hdr store (read one view at a time)."""
    masks = []
    for index in range(len(hdr.view_ids)):
        diffuse, valid = diffuse_view(hdr, index)
        masks.append(geometry.silhouette_masks(diffuse[None], valid[None], **mask_options)[0])
    return np.stack(masks)


def intrinsics_matrix(intrinsics: dict) -> np.ndarray:
    """(3, 3) K from hdr.zarr's ``intrinsics`` attrs (fx, fy, cx, cy)."""
    return np.array([[intrinsics["fx"], 0.0, intrinsics["cx"]], [0.0, intrinsics["fy"], intrinsics["cy"]],
                     [0.0, 0.0, 1.0]], np.float64)


# --------------------------------------------------------------------------- stage


def compare_to_known(result: sfm.SfmResult, known_rotations: np.ndarray, known_translations: np.ndarray,
                     distance_m: float) -> tuple[geometry.Similarity, dict, pd.DataFrame]:
    """Align SfM cameras to known poses (Sim(3)) and measure them.

    known_*: poses of the same views as ``result`` (NaN rows are skipped). Returns the similarity
    (SfM world -> known world), a summary (median/max rotation error in degrees, centre error in
    metres and as a fraction of ``distance_m``) and a per-view table.
    """
    usable = result.registered & np.isfinite(known_translations).all(axis=1)
    align = geometry.align_cameras(result.rotations[usable], result.translations[usable],
                                   known_rotations[usable], known_translations[usable])
    rotations, translations = align.apply_to_poses(result.rotations[usable], result.translations[usable])
    rotation_deg, centre_m = geometry.pose_errors(rotations, translations, known_rotations[usable],
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


def run_stage(hdr_path: str | Path, capture_path: str | Path, cameras_path: str | Path, output: str | Path,
              mode: str = "known", options: sfm.SfmOptions = sfm.SfmOptions(), min_registered_fraction: float = 0.9,
              feature_object_px: float = 400.0, max_upscale: int = 3, mask_options: dict | None = None) -> dict:
    """Run the stage (see the module docstring); returns the report."""
    from sellip.stages.linearize import atomic_directory
    from sellip.stages.merge_hdr import read_hdr

    started = time.perf_counter()
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
        _, known_rotations, known_translations = _pose_arrays(poses.fillna({"qw": 1.0, "qx": 0.0, "qy": 0.0,
                                                                            "qz": 0.0}))
        known_translations[poses["qw"].isna().to_numpy()] = np.nan
        known = (known_rotations, known_translations)
        if mode != "sfm":  # poses in millimetres would give a model 1000 times too large (docs/reliability.md)
            checks.check_pose_units(known_rotations, known_translations, distance_m, str(Path(capture_path) /
                                    POSES_CSV), str(Path(capture_path) / "capture.yaml"))
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
    upscale = sfm.feature_upscale(masks, feature_object_px, max_upscale)
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
    sfm.check_registration(result, min_registered_fraction)
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


def add_image_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments shared by the stages that read hdr.zarr and cut silhouettes (sfm, init-mesh)."""
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr store (sellip merge-hdr)")
    parser.add_argument("--mask-threshold", type=float, default=0.03,
                        help="silhouette: fraction of the view's robust maximum")
    parser.add_argument("--threads", type=int, default=-1, help="threads (-1: all cores)")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    defaults = sfm.SfmOptions()
    add_image_arguments(parser)
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml, poses.csv)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv to write")
    parser.add_argument("--output", required=True, type=Path, help="folder for the sparse model and report")
    parser.add_argument("--mode", choices=MODES, default="known", help="known poses, verify them, or SfM only")
    parser.add_argument("--matching", choices=("auto", "exhaustive", "retrieval"), default=defaults.matching)
    parser.add_argument("--exhaustive-max-views", type=int, default=defaults.exhaustive_max_views,
                        help="auto matching: exhaustive up to this many views, retrieval above")
    parser.add_argument("--retrieval-neighbors", type=int, default=defaults.retrieval_neighbors)
    parser.add_argument("--max-features", type=int, default=defaults.max_features)
    parser.add_argument("--feature-object-px", type=float, default=400.0,
                        help="magnify images so that the object spans about this many pixels")
    parser.add_argument("--max-upscale", type=int, default=3, help="largest magnification (1: never)")
    parser.add_argument("--refine-intrinsics", action="store_true", help="let bundle adjustment refine K")
    parser.add_argument("--min-registered-fraction", type=float, default=0.9,
                        help="fail when fewer views register")
    parser.add_argument("--seed", type=int, default=0)


def main(args: argparse.Namespace) -> int:
    options = sfm.SfmOptions(matching=args.matching, exhaustive_max_views=args.exhaustive_max_views,
                             retrieval_neighbors=args.retrieval_neighbors, max_features=args.max_features,
                             refine_intrinsics=args.refine_intrinsics, threads=args.threads, seed=args.seed)
    try:
        run_stage(args.hdr, args.capture, args.cameras, args.output, mode=args.mode, options=options,
                  min_registered_fraction=args.min_registered_fraction, feature_object_px=args.feature_object_px,
                  max_upscale=args.max_upscale, mask_options={"threshold": args.mask_threshold})
    except (sfm.RegistrationError, CaptureError) as exc:
        log.error("%s", exc)
        return 1
    return 0
