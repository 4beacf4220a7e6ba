"""``sellip render-outputs``: renders, Mueller images, AoLP/DoP and parameter maps of a model (rule ``render_outputs``).

    sellip render-outputs --model results/NAME/final/model.ply --cameras results/NAME/cameras.csv
                          --hdr results/NAME/hdr.zarr --capture CAPTURE --output results/NAME/final/renders
                          [--settings '{"render_views": ["v000", "v009"], "supersample": 2}']

``--settings``: :class:`sellip.report.outputs.EvaluateSettings` (config ``evaluate``) as one JSON object; this job
reads ``render_views`` and ``supersample``; a key left out takes its declared default.

Cameras: the poses of cameras.csv with the intrinsics of hdr.zarr (the HDR grid); the flash position and
polarizer from capture.yaml ``light``. ``render_views`` (none given: DEFAULT_VIEWS views evenly
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
from pathlib import Path

from sellip.capture.files import CaptureError
from sellip.fit.observe import ObserveError
from sellip.geometry.cameras import CamerasError
from sellip.model.ply import PlyError
from sellip.report.outputs import EvaluateSettings, OutputsError, render_outputs
from sellip.settings import add_renamed_argument, add_settings_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model PLY (final/model.ply)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (same world as the model)")
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr (intrinsics; measured views)")
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml light)")
    parser.add_argument("--output", required=True, type=Path, help="folder of PNGs to write")
    add_settings_argument(parser, EvaluateSettings, section="evaluate")
    add_renamed_argument(parser, "--views", '--settings \'{"render_views": [...]}\'')
    add_renamed_argument(parser, "--supersample", '--settings \'{"supersample": S}\'')


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    try:
        render_outputs(args.model, args.cameras, args.hdr, args.capture, args.output,
                       views=list(args.settings.render_views) or None, supersample=args.settings.supersample)
    except (OutputsError, CamerasError, CaptureError, PlyError, ObserveError) as exc:
        log.error("%s", exc)
        return 1
    return 0
