"""``sellip refine-geometry``: the geometry update of one iteration (rule ``refine_geometry``, paper §4.4).

    sellip refine-geometry --params results/NAME/iter/3/refit.zarr --mesh results/NAME/iter/2/mesh.ply
                           --output results/NAME/iter/3/mesh.ply [--reference-mesh results/NAME/mesh/init.ply]
                           [--settings '{"smoothness": 0.01, "silhouette": 0.01, "keep_surface": true}']
                           [--cameras results/NAME/cameras.csv --hdr results/NAME/hdr.zarr
                            --capture CAPTURE --exclude-views v004 ...
                            --silhouette-settings '{"threshold": 0.02}']

``--settings``: :class:`sellip.fit.geometry_jobs.GeometryUpdateSettings` (config ``refine_geometry``, this
iteration's values) as one JSON object; a key left out takes its declared default.

The mesh's vertices move along its normals until its surface agrees with the iteration's fitted normals, as far
as the fit's normal confidence allows (:func:`sellip.geometry.update.refine_from_normals`, docs/geometry_update.md);
what normals cannot tell (the mean offset, the shape far from any confident normal) is held at ``--reference-
mesh`` (the loop's initial mesh, so that small biases of the normals do not add up over the iterations; default:
``--mesh``). With ``silhouette`` > 0 the photographs' silhouettes hold the mean offset and size instead: the
current model is rendered in every view but the held-out ones as the camera would photograph it (raw pixels,
mosaic, the ingest's demosaicing: :func:`predicted_diffuse`), the same silhouette operator is applied to the
render and to the photograph, both boundaries are placed to a fraction of a pixel, and each contour vertex moves
the model's silhouette onto the photograph's (:func:`measure_silhouettes`,
:func:`sellip.geometry.update.silhouette_constraints`). The faces stay, so every vertex
keeps its parameters (the next fit's warm start) and the vertex count does not drift. Written atomically as a
model PLY (:func:`sellip.model.ply.write_param_mesh`) with the normals of the new surface and the ``confidence``: the
mesh of the next iteration. Beside it, ``<output>.json`` says how far the surface moved and how far the fitted
normals were from the mesh's before and after (a convergence figure that needs no ground truth), and with
``--iteration`` whether the loop has converged (:func:`sellip.fit.convergence.judge`; later iterations then pass
through, ``sellip pass-through``).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.convergence import ConvergenceSettings
from sellip.fit.geometry_jobs import GeometryUpdateSettings, refine_geometry
from sellip.settings import add_settings_argument
from sellip.stages._arguments import add_silhouette_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", type=Path, required=True, help="this iteration's params.zarr (fitted normals)")
    parser.add_argument("--mesh", type=Path, required=True, help="this iteration's mesh (its vertices and normals)")
    parser.add_argument("--output", type=Path, required=True, help="the next iteration's mesh (.ply)")
    add_settings_argument(parser, GeometryUpdateSettings, section="refine_geometry")
    parser.add_argument("--reference-mesh", type=Path, default=None,
                        help="the mesh (same faces) whose surface the anchor holds (default: --mesh)")
    parser.add_argument("--cameras", type=Path, default=None, help="cameras.csv (for the silhouettes)")
    parser.add_argument("--hdr", type=Path, default=None, help="hdr.zarr (for the silhouettes)")
    parser.add_argument("--capture", type=Path, default=None, help="capture folder (capture.yaml light)")
    parser.add_argument("--exclude-views", nargs="*", default=[], help="views whose silhouettes are not used "
                        "(the held-out views)")
    add_silhouette_argument(parser)
    parser.add_argument("--iteration", type=int, default=None,
                        help="the loop's iteration: judge whether the loop has converged (the summary's convergence)")
    parser.add_argument("--previous-params", type=Path, default=None,
                        help="iteration - 1's parameters (eta's change for the convergence verdict)")
    parser.add_argument("--poses-summary", type=Path, default=None,
                        help="this iteration's pose refinement summary (cameras.csv.json), where poses are refined")
    add_settings_argument(parser, ConvergenceSettings, flag="--convergence", section="converge")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        refine_geometry(args.params, args.mesh, args.output, args.settings, reference_mesh=args.reference_mesh,
                        cameras_path=args.cameras, hdr_path=args.hdr, capture_path=args.capture,
                        exclude_views=args.exclude_views,
                        mask_options={"threshold": args.silhouette_settings.threshold}, iteration=args.iteration,
                        previous_params=args.previous_params, poses_summary=args.poses_summary,
                        convergence=args.convergence)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
