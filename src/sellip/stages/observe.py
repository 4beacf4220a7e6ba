"""``sellip observe``: per-vertex, per-view observations of one iteration's mesh (rule ``gather_observations``).

    sellip observe --mesh results/NAME/mesh/init.ply --cameras results/NAME/cameras.csv
                   --hdr results/NAME/hdr.zarr --capture CAPTURE
                   --output results/NAME/iter/0/observations.zarr
                   [--vertex-chunk 4096] [--view-chunk 8] [--occlusion-tolerance 1e-3]
                   [--shadow-offset 0.5] [--min-cos 0] [--missing-poses skip|error] [--threads 2]
                   [--exclude-views v003 v017] [--max-views 12]

Views: those of hdr.zarr that have a pose in cameras.csv, in hdr.zarr's order. SfM leaves
unregistered views out of cameras.csv; ``--missing-poses skip`` (default) leaves them out here
too with a warning, ``error`` stops. A cameras.csv view that hdr.zarr lacks is always an error.
Held-out views (``--exclude-views``) are left out; then ``--max-views N`` keeps N of the remaining
views spread evenly over their order (:func:`spread_subset`; for an orbit, evenly around it), to
measure what fewer views cost (config ``observe.max_views``; the initial mesh still uses every view).
The flash position (``light.position_m``, camera coordinates) comes from capture.yaml.

Views are processed ``view_chunk`` at a time (:class:`sellip.fit.observe.Observer`), and each
group is written to the store (layout: :mod:`sellip.fit.observe`) before the next starts, so memory
holds one HDR view and N x view_chunk observations. The store is written under a temporary
name and renamed when complete.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.capture.files import CaptureError
from sellip.fit.observe import ObserveError, ObserveSettings
from sellip.fit.observe_mesh import MISSING_POSES, observe_mesh
from sellip.geometry.cameras import CamerasError
from sellip.stages._arguments import add_silhouette_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    defaults = ObserveSettings()
    parser.add_argument("--mesh", required=True, type=Path, help="mesh PLY with vertex normals (this iteration's)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (cam_from_world poses)")
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr store (sellip merge-hdr)")
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml: flash position)")
    parser.add_argument("--output", required=True, type=Path, help="observations.zarr store to write")
    parser.add_argument("--vertex-chunk", type=int, default=defaults.vertex_chunk, help="vertices per chunk")
    parser.add_argument("--view-chunk", type=int, default=defaults.view_chunk,
                        help="views per chunk and per processing group (memory grows with vertices x this)")
    parser.add_argument("--occlusion-tolerance", type=float, default=defaults.occlusion_tolerance,
                        help="hidden when the mesh is hit before (1 - this) of the camera-vertex distance")
    parser.add_argument("--shadow-offset", type=float, default=defaults.shadow_offset,
                        help="shadow rays start this many median edge lengths above the vertex")
    parser.add_argument("--min-cos", type=float, default=defaults.min_cos,
                        help="front-facing / lit when the cosine to the camera / flash exceeds this")
    parser.add_argument("--edge-margin", type=float, default=defaults.edge_margin,
                        help="a sample must lie this many HDR pixels inside the object's silhouette (0: off)")
    add_silhouette_argument(parser)  # the silhouette of --edge-margin
    parser.add_argument("--max-slope", type=float, default=defaults.max_slope,
                        help="leave out samples whose footprint has an intensity slope above this "
                             "(|grad S0| / S0 per HDR pixel; 0: off)")
    parser.add_argument("--missing-poses", choices=MISSING_POSES, default="skip",
                        help="HDR views without a pose in cameras.csv: leave them out, or stop")
    parser.add_argument("--threads", type=int, default=0, help="ray-casting threads (0: all cores)")
    parser.add_argument("--exclude-views", nargs="*", default=[], metavar="VIEW",
                        help="views held out for evaluation: left out of the store")
    parser.add_argument("--max-views", type=int, default=None, metavar="N",
                        help="observe only N of the remaining views, spread evenly over their order (default: all)")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    try:
        settings = ObserveSettings(vertex_chunk=args.vertex_chunk, view_chunk=args.view_chunk,
                                   occlusion_tolerance=args.occlusion_tolerance, shadow_offset=args.shadow_offset,
                                   min_cos=args.min_cos, edge_margin=args.edge_margin,
                                   mask_threshold=args.silhouette_settings.threshold, max_slope=args.max_slope,
                                   threads=args.threads)
    except ValueError as exc:
        log.error("bad settings: %s", exc)
        return 1
    if args.max_views is not None and args.max_views < 1:
        log.error("bad settings: --max-views must be at least 1, got %d", args.max_views)
        return 1
    try:
        observe_mesh(args.mesh, args.cameras, args.hdr, args.capture, args.output, settings,
                  missing_poses=args.missing_poses, exclude_views=tuple(args.exclude_views),
                  max_views=args.max_views)
    except (ObserveError, CamerasError, CaptureError) as exc:
        log.error("%s", exc)
        return 1
    return 0
