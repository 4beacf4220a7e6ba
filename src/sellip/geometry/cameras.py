"""The cameras table ``cameras.csv`` (poses.csv's columns: COLMAP cam_from_world) and cameras built
from it: its reader and writer, the intrinsics matrix of capture.yaml's camera, a view's camera at the HDR
images' resolution (half the raw mosaic), the diffuse image and silhouette masks a view gives SfM and the hull.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from sellip.capture.files import POSE_COLUMNS
from sellip.capture.tables import validate_poses
from sellip.geometry import silhouettes as geometry_silhouettes
from sellip.model.conventions import quaternion_to_rotation, rotation_to_quaternion
from sellip.model.render import Camera


class CamerasError(ValueError):
    """A cameras table that does not fit its HDR store (missing, empty, views the store does not have)."""


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
    return pose_arrays(table)



def pose_arrays(table: pd.DataFrame) -> tuple[list[str], np.ndarray, np.ndarray]:
    rotations = quaternion_to_rotation(table[list(POSE_COLUMNS[1:5])].to_numpy(np.float64))
    return list(table["view_id"]), rotations, table[list(POSE_COLUMNS[5:])].to_numpy(np.float64)



def diffuse_view(hdr, index: int) -> tuple[np.ndarray, np.ndarray]:
    """I_d = 2 I90 (H, W, C) float32 and valid (H, W) of view ``index`` of an hdr.zarr store (one chunk read)."""
    i90 = np.asarray(hdr.analyzers[index, :, :, 2, :], np.float32)
    return 2 * i90, np.asarray(hdr.valid[index], bool)



def view_masks(hdr, mask_options: dict) -> np.ndarray:
    """(V, H, W) silhouettes of every view of an hdr store (read one view at a time)."""
    masks = []
    for index in range(len(hdr.view_ids)):
        diffuse, valid = diffuse_view(hdr, index)
        masks.append(geometry_silhouettes.silhouette_masks(diffuse[None], valid[None], **mask_options)[0])
    return np.stack(masks)



def intrinsics_matrix(intrinsics: dict) -> np.ndarray:
    """(3, 3) K from hdr.zarr's ``intrinsics`` attrs (fx, fy, cx, cy)."""
    return np.array([[intrinsics["fx"], 0.0, intrinsics["cx"]], [0.0, intrinsics["fy"], intrinsics["cy"]],
                     [0.0, 0.0, 1.0]], np.float64)


def hdr_camera(intrinsics: dict, rotation: np.ndarray, translation: np.ndarray, hdr_path) -> Camera:
    """The camera of one view from ``intrinsics`` (fx, fy, cx, cy, width, height[, distortion]: hdr.zarr's attrs, or
    capture.yaml's ``camera`` at the sensor's size) and a cameras.csv pose; ``hdr_path`` names the source in errors."""
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in intrinsics]
    if missing:
        raise CamerasError(f"{hdr_path}: attrs 'intrinsics' lacks {missing}")
    distortion = np.asarray(intrinsics.get("distortion") or [0.0] * 5, np.float64)
    return Camera(intrinsics=intrinsics_matrix(intrinsics), rotation=rotation, translation=translation,
                  width=int(intrinsics["width"]), height=int(intrinsics["height"]),
                  distortion=distortion if np.any(distortion) else None)


def load_cameras(cameras_path: str | Path, hdr_path: str | Path) -> tuple[dict, object]:
    """({view_id: Camera} for every view of cameras.csv that hdr.zarr has, the opened hdr store).

    Cameras are at the HDR resolution (hdr.zarr ``intrinsics``) with cameras.csv poses.
    """
    from sellip.capture.hdr import read_hdr
    from sellip.geometry.cameras import hdr_camera, read_cameras

    if not Path(cameras_path).is_file():
        raise CamerasError(f"{cameras_path}: cameras table does not exist")
    if not (Path(hdr_path) / "zarr.json").is_file():
        raise CamerasError(f"{hdr_path}: not an HDR store (no zarr.json); run `sellip merge-hdr` first")
    view_ids, rotations, translations = read_cameras(cameras_path)
    hdr = read_hdr(hdr_path)
    known = set(hdr.view_ids)
    strangers = [v for v in view_ids if v not in known]
    if strangers:
        raise CamerasError(f"{cameras_path}: view(s) {strangers[:10]} are not in {hdr_path}")
    cameras = {v: hdr_camera(hdr.intrinsics, rotations[i], translations[i], hdr_path) for i, v in enumerate(view_ids)}
    if not cameras:
        raise CamerasError(f"{cameras_path}: no camera")
    return cameras, hdr
