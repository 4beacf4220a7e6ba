"""``sellip init-mesh``: the initial mesh (rule ``init_mesh``, docs/design.md §2 mesh_init).

    sellip init-mesh --hdr results/NAME/hdr.zarr --cameras results/NAME/cameras.csv --sfm results/NAME/sfm
                     --output results/NAME/mesh/init.ply [--mode hull|mvs|mesh] [--mesh-path scan.ply]
                     [--max-vertices 30000] [options]

``hull`` (default, CPU): silhouettes of the flash-lit object (:func:`sellip.geometry.silhouettes.silhouette_masks`),
a visual hull robust to a few bad masks, fused with the SfM points when ``sfm/sparse`` exists, screened
Poisson at depth 7, cleaned, remeshed to the density of depth 9 (at most ``--max-vertices``), see
:func:`sellip.geometry.hull.hull_mesh`. ``mvs`` (needs pycolmap built with CUDA and an SfM model): COLMAP
PatchMatch stereo and fusion give the oriented points instead of the hull surface. ``mesh``: the mesh in
``--mesh-path`` (a scan in the cameras.csv world, metres; PLY or OBJ) is resampled to ``--max-vertices`` and
checked against the silhouettes (:func:`sellip.geometry.scan.user_initial_mesh`); a mesh that does not fit them stops
the stage with an error naming the file and what is off (units, place, frame).

Written (atomically): the mesh PLY (x y z nx ny nz float32, triangles) in the cameras.csv world, and
beside it ``<stem>.json``: vertex and face counts, hull and fusion statistics, per-view silhouette
disagreement, timings (mode mesh: the source file, its counts and ``check``, the figures of the silhouette
check). A warning names the views whose silhouette disagrees with the hull (or with the supplied mesh).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.geometry import hull as geometry_hull
from sellip.geometry.initial import INIT_MODES, OUTLIER_VIEW_Z, InitMeshError, make_initial_mesh
from sellip.stages._arguments import add_image_arguments

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    defaults = geometry_hull.InitMeshOptions()
    add_image_arguments(parser)
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (sellip sfm)")
    parser.add_argument("--sfm", required=True, type=Path, help="the sfm folder (sparse model, report)")
    parser.add_argument("--output", required=True, type=Path, help="mesh PLY to write (+ .json beside it)")
    parser.add_argument("--mode", choices=INIT_MODES, default="hull")
    parser.add_argument("--mesh-path", type=Path, default=None,
                        help="mode mesh: the mesh to start from (PLY/OBJ, in the cameras.csv world, metres)")
    parser.add_argument("--hull-resolution", type=int, default=defaults.hull_resolution)
    parser.add_argument("--min-inside-fraction", type=float, default=defaults.min_inside_fraction)
    parser.add_argument("--poisson-depth", type=int, default=defaults.poisson_depth)
    parser.add_argument("--target-depth", type=int, default=defaults.target_depth)
    parser.add_argument("--max-vertices", type=int, default=defaults.max_vertices)
    parser.add_argument("--outlier-view-z", type=float, default=OUTLIER_VIEW_Z,
                        help="warn about a view whose silhouette disagreement is this many robust standard "
                             f"deviations above the views' median (default {OUTLIER_VIEW_Z})")


def main(args: argparse.Namespace) -> int:
    options = geometry_hull.InitMeshOptions(hull_resolution=args.hull_resolution,
                                       min_inside_fraction=args.min_inside_fraction,
                                       poisson_depth=args.poisson_depth, target_depth=args.target_depth,
                                       max_vertices=args.max_vertices, threads=args.threads)
    try:
        make_initial_mesh(args.hdr, args.cameras, args.sfm, args.output, mode=args.mode, options=options,
                  mask_options={"threshold": args.silhouette_settings.threshold}, mesh_path=args.mesh_path,
                  outlier_view_z=args.outlier_view_z)
    except (InitMeshError, ValueError) as exc:
        log.error("%s", exc)
        return 1
    return 0
