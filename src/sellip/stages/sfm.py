"""``sellip sfm``: camera poses for every view (rule ``run_sfm``, docs/design.md §2 sfm).

    sellip sfm --hdr results/NAME/hdr.zarr --capture CAPTURE --cameras results/NAME/cameras.csv
               --output results/NAME/sfm [--settings '{"mode": "verify", "max_features": 8192}'] [--threads 2]

``--settings``: :class:`sellip.geometry.sfm.SfmOptions` (config ``sfm``) as one JSON object; a key left out takes
its declared default.

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
    ``scene.distance_m`` (:func:`sellip.geometry.sfm.metric_normalization`).

Images: I_d = 2 I90 of hdr.zarr, silhouette-masked (:func:`sellip.geometry.silhouettes.silhouette_masks`),
magnified when the object is small (:func:`sellip.geometry.sfm.feature_upscale`), tone-mapped to 8 bit.

Written (all or nothing): ``cameras.csv`` (view_id, qw, qx, qy, qz, tx, ty, tz: cam_from_world,
metres) and the folder ``--output`` with ``report.json`` (mode, registered/unregistered views,
scale, timings, verify errors), and after SfM ``sparse/`` (COLMAP binary model: cameras, images,
points3D with tracks, in the cameras.csv world; image i is view i of hdr.zarr, named
``{i:05d}.png``, see report.json ``image_names``), ``points.ply`` (x y z red green blue error
track_length) and, in verify mode, ``pose_errors.csv``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from sellip.capture.files import CaptureError
from sellip.geometry import sfm
from sellip.geometry.poses import solve_poses
from sellip.settings import add_settings_argument
from sellip.stages._arguments import add_image_arguments

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- cameras.csv


# --------------------------------------------------------------------------- images


# --------------------------------------------------------------------------- stage


def configure_parser(parser: argparse.ArgumentParser) -> None:
    add_image_arguments(parser)
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml, poses.csv)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv to write")
    parser.add_argument("--output", required=True, type=Path, help="folder for the sparse model and report")
    add_settings_argument(parser, sfm.SfmOptions, section="sfm")
    parser.add_argument("--seed", type=int, default=0, help="SfM's random seed (config seed)")


def main(args: argparse.Namespace) -> int:
    options = dataclasses.replace(args.settings, threads=args.threads, seed=args.seed)
    try:
        solve_poses(args.hdr, args.capture, args.cameras, args.output, options=options,
                    mask_options={"threshold": args.silhouette_settings.threshold})
    except (sfm.RegistrationError, CaptureError) as exc:
        log.error("%s", exc)
        return 1
    return 0
