"""``sellip evaluate``: figures of merit of the final model (docs/design.md §8) -> metrics.json
(rule ``evaluate_model``).

    sellip evaluate --model results/NAME/final/model.ply --params results/NAME/final/params.zarr
                    --cameras results/NAME/cameras.csv --hdr results/NAME/hdr.zarr --capture CAPTURE
                    --benchmarks results/NAME/benchmarks --output results/NAME/metrics.json
                    [--settings '{"held_out_views": ["v003", "v017"]}'] [--sim3-from-sfm] [--timings-plot PATH]

``--settings``: :class:`sellip.report.outputs.EvaluateSettings` (config ``evaluate``) as one JSON object; this job
reads ``held_out_views``, ``metrics_supersample`` and ``geometry_samples``; a key left out takes its declared default.

Ground truth: ``CAPTURE/ground_truth/model.ply``. Without it, metrics.json still holds the held-out PSNR
and the stage timings; the ground-truth figures are null and ``reasons`` says why.

Frames: the model and cameras.csv share a world. When the cameras came from SfM (``--sim3-from-sfm``, or
``report.json`` of the sfm stage next to cameras.csv, ``<cameras dir>/sfm/report.json``, says mode "sfm"),
the model is moved into the ground truth's world by the Sim(3) that maps the cameras.csv camera centres onto
the capture's poses.csv ones (:func:`sellip.report.figures_of_merit.camera_alignment`); otherwise (modes known, verify:
cameras.csv holds poses.csv) no alignment is applied.

Confident vertices: status 0 (fitted) and confidence > 0 in params.zarr; without --params, confidence > 0
in model.ply; without either, every vertex (said in ``reasons``).

The keys of metrics.json and the exact definitions: :mod:`sellip.report.figures_of_merit` and docs/outputs.md.
The file is written under a temporary name and renamed.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.capture.files import CaptureError
from sellip.fit.observe import ObserveError
from sellip.geometry.cameras import CamerasError
from sellip.model.params import ParamsError
from sellip.model.ply import PlyError
from sellip.report.metrics import evaluate_model
from sellip.report.outputs import EvaluateSettings, OutputsError
from sellip.settings import add_renamed_argument, add_settings_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model PLY (final/model.ply)")
    parser.add_argument("--params", type=Path, default=None, help="params.zarr of the model (status, confidence)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (same world as the model)")
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr (measured held-out views)")
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (light, ground_truth/)")
    parser.add_argument("--benchmarks", type=Path, default=None, help="Snakemake benchmark folder of the run")
    parser.add_argument("--output", required=True, type=Path, help="metrics.json to write")
    parser.add_argument("--sim3-from-sfm", action="store_true",
                        help="align cameras.csv to poses.csv by Sim(3) (automatic when sfm/report.json says sfm)")
    parser.add_argument("--sfm-report", type=Path, default=None,
                        help="report.json of the sfm stage (default: <cameras dir>/sfm/report.json)")
    parser.add_argument("--timings-plot", type=Path, default=None, help="also write a per-rule wall-time PNG")
    parser.add_argument("--iteration-meshes", type=Path, nargs="*", default=[],
                        help="the loop's meshes in order (initial, then each iteration's): geometry_iterations")
    parser.add_argument("--iteration-fits", type=Path, nargs="*", default=[],
                        help="the first-pass fit store (fit.zarr) of each of those meshes (fitted normals)")
    parser.add_argument("--convergence-plot", type=Path, default=None, help="also write the convergence PNG")
    parser.add_argument("--logs", type=Path, default=None, help="the run's log folder: its warnings into metrics.json")
    parser.add_argument("--initial-cameras", type=Path, default=None,
                        help="the poses stage's cameras.csv, measured beside --cameras when pose refinement moved them")
    add_settings_argument(parser, EvaluateSettings, section="evaluate")
    add_renamed_argument(parser, "--held-out", '--settings \'{"held_out_views": [...]}\'')
    add_renamed_argument(parser, "--supersample", '--settings \'{"metrics_supersample": S}\'')
    add_renamed_argument(parser, "--geometry-samples", '--settings \'{"geometry_samples": N}\'')


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    try:
        settings = args.settings
        evaluate_model(args.model, args.cameras, args.hdr, args.capture, args.output, params_path=args.params,
                       benchmarks=args.benchmarks, held_out=list(settings.held_out_views),
                       sim3_from_sfm=args.sim3_from_sfm, sfm_report=args.sfm_report,
                       supersample=settings.metrics_supersample, geometry_samples=settings.geometry_samples,
                       timings_plot=args.timings_plot, iteration_meshes=args.iteration_meshes,
                       iteration_fits=args.iteration_fits, convergence_plot=args.convergence_plot, logs=args.logs,
                       initial_cameras=args.initial_cameras)
    except (OutputsError, CamerasError, CaptureError, PlyError, ObserveError, ParamsError) as exc:
        log.error("%s", exc)
        return 1
    return 0
