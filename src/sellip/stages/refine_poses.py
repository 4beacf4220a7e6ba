"""``sellip refine-poses``: every view's pose aligned to one iteration's model (rule ``refine_poses``; docs/geometry.md,
"Poses refined against the object").

    sellip refine-poses --params results/NAME/iter/1/refit.zarr --mesh results/NAME/iter/0/mesh.ply
                        --cameras results/NAME/iter/1/cameras.csv --hdr results/NAME/hdr.zarr --capture CAPTURE
                        --output results/NAME/iter/2/cameras.csv [--blur-px 1.5 0] [--rounds 2]
                        [--max-rotation-deg 2] [--max-shift-fraction 0.03] [--min-motion-px 0]

The model (the params store on its mesh, shaded with its fitted normals) is rendered through each view's camera
under the capture's flash, and the pose that best aligns the photograph with the render is the view's new pose
(:func:`sellip.fit.refine.refine_poses`, :func:`sellip.geometry.pose_refinement.refine_view`); the intrinsics are
held. Writes the cameras table (atomically) and ``<output>.json``: each view's step, the robust cost before and
after, and the views kept (too few pixels, a step too large to trust, or one too small to tell from the
alignment's noise).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", type=Path, required=True,
                        help="the iteration's params store (fitted normals, pBRDF)")
    parser.add_argument("--mesh", type=Path, required=True, help="the iteration's mesh (the store's vertices)")
    parser.add_argument("--cameras", type=Path, required=True, help="the iteration's cameras.csv")
    parser.add_argument("--hdr", type=Path, required=True, help="hdr.zarr")
    parser.add_argument("--capture", type=Path, required=True, help="capture folder (capture.yaml light)")
    parser.add_argument("--output", type=Path, required=True, help="the next iteration's cameras.csv")
    parser.add_argument("--blur-px", type=float, nargs="+", default=[1.5, 0.0],
                        help="Gaussian blurs (sigma, HDR pixels) of the photograph, coarse to fine")
    parser.add_argument("--rounds", type=int, default=2, help="renders per view")
    parser.add_argument("--max-rotation-deg", type=float, default=2.0,
                        help="a larger rotation is taken for a divergence: the view keeps its pose")
    parser.add_argument("--max-shift-fraction", type=float, default=0.03,
                        help="a larger centre shift (fraction of the camera's distance) keeps the view's pose")
    parser.add_argument("--min-motion-px", type=float, default=0.0,
                        help="a smaller move of the object (median, pixels) keeps the view's pose "
                             "(0: every view moves)")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.fit.refine import refine_poses
    from sellip.geometry.pose_refinement import PoseRefinementSettings
    from sellip.model.params import ParamsError

    try:
        settings = PoseRefinementSettings(blur_px=tuple(args.blur_px), rounds=args.rounds,
                                          max_rotation_deg=args.max_rotation_deg,
                                          max_shift_fraction=args.max_shift_fraction,
                                          min_motion_px=args.min_motion_px)
        refine_poses(args.params, args.mesh, args.cameras, args.hdr, args.capture, args.output, settings)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
