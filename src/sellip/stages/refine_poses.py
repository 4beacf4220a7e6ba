"""``sellip refine-poses``: every view's pose aligned to one iteration's model (rule ``refine_poses``; docs/geometry.md,
"Poses refined against the object").

    sellip refine-poses --params results/NAME/iter/1/refit.zarr --mesh results/NAME/iter/0/mesh.ply
                        --cameras results/NAME/iter/1/cameras.csv --hdr results/NAME/hdr.zarr --capture CAPTURE
                        --output results/NAME/iter/2/cameras.csv [--settings '{"blur_px": [1.5, 0], "rounds": 2}']

The model (the params store on its mesh, shaded with its fitted normals) is rendered through each view's camera
under the capture's flash, and the pose that best aligns the photograph with the render is the view's new pose
(:func:`sellip.fit.geometry_jobs.refine_poses`, :func:`sellip.geometry.pose_refinement.refine_view`); the intrinsics are
held. Writes the cameras table (atomically) and ``<output>.json``: each view's step, the robust cost before and
after, and the views kept (too few pixels, a step too large to trust, or one too small to tell from the
alignment's noise). ``--settings`` is :class:`sellip.geometry.pose_refinement.PoseRefinementSettings` as one JSON
object (config ``refine_poses``; keys left out take the record's defaults).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    from sellip.geometry.pose_refinement import PoseRefinementSettings
    from sellip.settings import add_settings_argument

    parser.add_argument("--params", type=Path, required=True,
                        help="the iteration's params store (fitted normals, pBRDF)")
    parser.add_argument("--mesh", type=Path, required=True, help="the iteration's mesh (the store's vertices)")
    parser.add_argument("--cameras", type=Path, required=True, help="the iteration's cameras.csv")
    parser.add_argument("--hdr", type=Path, required=True, help="hdr.zarr")
    parser.add_argument("--capture", type=Path, required=True, help="capture folder (capture.yaml light)")
    parser.add_argument("--output", type=Path, required=True, help="the next iteration's cameras.csv")
    add_settings_argument(parser, PoseRefinementSettings, "--settings", "refine_poses")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.geometry_jobs import refine_poses
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        refine_poses(args.params, args.mesh, args.cameras, args.hdr, args.capture, args.output, args.settings)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
