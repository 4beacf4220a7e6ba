"""``sellip init-mesh``: the initial mesh (rule ``init_mesh``, docs/design.md §2 mesh_init).

    sellip init-mesh --hdr results/NAME/hdr.zarr --cameras results/NAME/cameras.csv --sfm results/NAME/sfm
                     --output results/NAME/mesh/init.ply [--mesh-path scan.ply]
                     [--settings '{"mode": "hull", "max_vertices": 30000}'] [--silhouette-settings JSON]

``--settings``: :class:`sellip.geometry.hull.InitMeshOptions` (config ``init``) as one JSON object; a key left out
takes its declared default.

``hull`` (default, CPU): silhouettes of the flash-lit object (:func:`sellip.geometry.silhouettes.silhouette_masks`),
a visual hull robust to a few bad masks, fused with the SfM points when ``sfm/sparse`` exists, screened
Poisson at ``poisson_depth``, cleaned, remeshed to the density of ``target_depth`` (at most ``max_vertices``), see
:func:`sellip.geometry.hull.hull_mesh`. ``mvs`` (needs pycolmap built with CUDA and an SfM model): COLMAP
PatchMatch stereo and fusion give the oriented points instead of the hull surface. ``mesh``: the mesh in
``--mesh-path`` (a scan in the cameras.csv world, metres; PLY or OBJ) is resampled to ``max_vertices`` and
checked against the silhouettes (:func:`sellip.geometry.scan.user_initial_mesh`); a mesh that does not fit them stops
the stage with an error naming the file and what is off (units, place, frame).

Written (atomically): the mesh PLY (x y z nx ny nz float32, triangles) in the cameras.csv world, and
beside it ``<stem>.json``: vertex and face counts, hull and fusion statistics, per-view silhouette
disagreement, timings (mode mesh: the source file, its counts and ``check``, the figures of the silhouette
check). A warning names the views whose silhouette disagrees with the hull (or with the supplied mesh).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from sellip.geometry.hull import InitMeshOptions
from sellip.geometry.initial import InitMeshError, make_initial_mesh
from sellip.settings import add_settings_argument
from sellip.stages._arguments import add_image_arguments

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    add_image_arguments(parser)
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (sellip sfm)")
    parser.add_argument("--sfm", required=True, type=Path, help="the sfm folder (sparse model, report)")
    parser.add_argument("--output", required=True, type=Path, help="mesh PLY to write (+ .json beside it)")
    add_settings_argument(parser, InitMeshOptions, section="init")
    parser.add_argument("--mesh-path", type=Path, default=None,
                        help="mode mesh: the mesh to start from (PLY/OBJ, in the cameras.csv world, metres)")


def main(args: argparse.Namespace) -> int:
    options = dataclasses.replace(args.settings, threads=args.threads)
    try:
        make_initial_mesh(args.hdr, args.cameras, args.sfm, args.output, options=options,
                          mask_options={"threshold": args.silhouette_settings.threshold}, mesh_path=args.mesh_path)
    except (InitMeshError, ValueError) as exc:
        log.error("%s", exc)
        return 1
    return 0
