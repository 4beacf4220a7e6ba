"""``sellip render-outputs``: renders, Mueller images, AoLP/DoP and parameter maps of a model (rule ``render_outputs``).

    sellip render-outputs --model results/NAME/final/model.ply --cameras results/NAME/cameras.csv
                          --hdr results/NAME/hdr.zarr --capture CAPTURE --output results/NAME/final/renders
                          [--views v000 v009 ...] [--supersample 2]

Cameras: the poses of cameras.csv with the intrinsics of hdr.zarr (the HDR grid); the flash position and
polarizer from capture.yaml ``light``. ``--views`` (default, or none given: DEFAULT_VIEWS views evenly
spread over cameras.csv; views without a pose, e.g. not registered by SfM, are skipped with a warning)
are re-rendered; the first is the reference view of everything else.

Written into the folder ``--output`` (appears only when complete; :mod:`sellip.report.outputs` makes the images):

``view_<id>.png``             re-rendered captured view (s0, sRGB, its 99.5th percentile white)
``view_<id>_measured.png``    the measured HDR view after one global scale, same exposure as the render
``novel_view.png``            a camera between the reference view and its nearest neighbour, raised 20 deg
``new_light.png``             the reference view with the polarized flash 20 cm to the right of the camera
``mueller.png``, ``mueller.npz``  3x3 linear Mueller block of the reference view (figure; float data)
``aolp.png``, ``dop.png``     AoLP and DoP of the re-rendered reference view, with colour bars
``map_<name>.png``            eta, rho_d, rho_s, sigma_s, rho_ss, sigma_ss, normal (and confidence when
                              model.ply has it), each with a colour bar; ``maps.png``: all in one grid
``index.json``                the list of files with what each shows
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from sellip.capture.files import CaptureError
from sellip.capture.reader import read_capture
from sellip.fit.observe import ObserveError
from sellip.model.ply import PlyError, read_param_mesh, read_ply
from sellip.report.outputs import write_renders

log = logging.getLogger(__name__)

DEFAULT_VIEWS = 3
"""Views re-rendered when --views is not given (evenly spread over cameras.csv)."""


class OutputsError(ValueError):
    """An input of render-outputs or evaluate that is missing or inconsistent (the message names the file)."""


def load_cameras(cameras_path: str | Path, hdr_path: str | Path) -> tuple[dict, object]:
    """({view_id: Camera} for every view of cameras.csv that hdr.zarr has, the opened hdr store).

    Cameras are at the HDR resolution (hdr.zarr ``intrinsics``) with cameras.csv poses.
    """
    from sellip.stages.merge_hdr import read_hdr
    from sellip.stages.observe import hdr_camera
    from sellip.stages.sfm import read_cameras

    if not Path(cameras_path).is_file():
        raise OutputsError(f"{cameras_path}: cameras table does not exist")
    if not (Path(hdr_path) / "zarr.json").is_file():
        raise OutputsError(f"{hdr_path}: not an HDR store (no zarr.json); run `sellip merge-hdr` first")
    view_ids, rotations, translations = read_cameras(cameras_path)
    hdr = read_hdr(hdr_path)
    known = set(hdr.view_ids)
    strangers = [v for v in view_ids if v not in known]
    if strangers:
        raise OutputsError(f"{cameras_path}: view(s) {strangers[:10]} are not in {hdr_path}")
    cameras = {v: hdr_camera(hdr.intrinsics, rotations[i], translations[i], hdr_path) for i, v in enumerate(view_ids)}
    if not cameras:
        raise OutputsError(f"{cameras_path}: no camera")
    return cameras, hdr


def default_views(view_ids: list[str], count: int = DEFAULT_VIEWS) -> list[str]:
    """``count`` view ids evenly spread over ``view_ids`` (all of them when there are fewer)."""
    picks = np.unique(np.linspace(0, len(view_ids) - 1, min(count, len(view_ids))).round().astype(int))
    return [view_ids[i] for i in picks]


def model_confidence(model_path: str | Path) -> np.ndarray | None:
    """The ``confidence`` vertex property of a model PLY (V,) float64, None when it has none."""
    vertex, _ = read_ply(model_path)
    return vertex["confidence"].astype(np.float64) if "confidence" in vertex else None


def run_stage(model_path: str | Path, cameras_path: str | Path, hdr_path: str | Path, capture_path: str | Path,
              output: str | Path, views: list[str] | None = None, supersample: int = 2) -> dict:
    """Write the renders folder (module docstring); returns its index."""
    from sellip.stages.linearize import atomic_directory

    started = time.perf_counter()
    if not Path(model_path).is_file():
        raise OutputsError(f"{model_path}: model does not exist")
    mesh = read_param_mesh(model_path)
    light = read_capture(capture_path, check_files=False).config["light"]  # no raw frame is read here
    cameras, hdr = load_cameras(cameras_path, hdr_path)
    unknown = [v for v in views or [] if v not in cameras]
    if unknown:  # e.g. views SfM could not register: render the others
        log.warning("%s has no pose for requested view(s) %s; they are skipped", cameras_path, unknown)
    views = [v for v in views or [] if v in cameras] or default_views(list(cameras))
    confidence = model_confidence(model_path)
    extra = {"confidence": confidence} if confidence is not None else None
    log.info("%s: %d vertices; rendering views %s at %dx%d (supersample %d)", model_path, mesh.num_vertices, views,
             cameras[views[0]].width, cameras[views[0]].height, supersample)
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        index = write_renders(mesh, cameras, light["position_m"], float(light["polarizer_deg"]), views, tmp,
                              supersample=supersample, measured=hdr.view, extra_maps=extra)
    log.info("wrote %s (%d files) in %.1f s", output, len(index["files"]) + 1, time.perf_counter() - started)
    return index


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model PLY (final/model.ply)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (same world as the model)")
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr (intrinsics; measured views)")
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml light)")
    parser.add_argument("--output", required=True, type=Path, help="folder of PNGs to write")
    parser.add_argument("--views", nargs="*", default=None,
                        help=f"views to re-render; the first is the reference (default or none given: "
                             f"{DEFAULT_VIEWS} spread evenly; views without a pose are skipped with a warning)")
    parser.add_argument("--supersample", type=int, default=2, help="s x s samples per pixel (default: 2)")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    if args.supersample < 1:
        raise SystemExit("--supersample must be at least 1")
    try:
        run_stage(args.model, args.cameras, args.hdr, args.capture, args.output, views=args.views,
                  supersample=args.supersample)
    except (OutputsError, CaptureError, PlyError, ObserveError) as exc:
        log.error("%s", exc)
        return 1
    return 0
