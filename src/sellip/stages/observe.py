"""``sellip observe``: per-vertex, per-view observations of one iteration's mesh (rule ``gather_observations``).

    sellip observe --mesh results/NAME/mesh/init.ply --cameras results/NAME/cameras.csv
                   --hdr results/NAME/hdr.zarr --capture CAPTURE
                   --output results/NAME/iter/0/observations.zarr
                   [--settings '{"view_chunk": 8, "missing_poses": "error", "max_views": 12}']
                   [--silhouette-settings '{"threshold": 0.03}'] [--threads 2] [--exclude-views v003 v017]

``--settings``: :class:`sellip.fit.observe.ObserveSettings` (config ``observe``) as one JSON object; a key left
out takes its declared default.

Views: those of hdr.zarr that have a pose in cameras.csv, in hdr.zarr's order. SfM leaves
unregistered views out of cameras.csv; ``missing_poses: skip`` (default) leaves them out here
too with a warning, ``error`` stops. A cameras.csv view that hdr.zarr lacks is always an error.
Held-out views (``--exclude-views``) are left out; then ``max_views: N`` keeps N of the remaining
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
import dataclasses
import logging
from pathlib import Path

from sellip.capture.files import CaptureError
from sellip.fit.observe import ObserveError, ObserveSettings
from sellip.fit.observe_mesh import observe_mesh
from sellip.geometry.cameras import CamerasError
from sellip.settings import add_settings_argument
from sellip.stages._arguments import add_silhouette_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", required=True, type=Path, help="mesh PLY with vertex normals (this iteration's)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (cam_from_world poses)")
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr store (sellip merge-hdr)")
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml: flash position)")
    parser.add_argument("--output", required=True, type=Path, help="observations.zarr store to write")
    add_settings_argument(parser, ObserveSettings, section="observe")
    add_silhouette_argument(parser)  # the silhouette of the settings' edge_margin
    parser.add_argument("--threads", type=int, default=0, help="ray-casting threads (0: all cores)")
    parser.add_argument("--exclude-views", nargs="*", default=[], metavar="VIEW",
                        help="views held out for evaluation: left out of the store")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    try:
        settings = dataclasses.replace(args.settings, mask_threshold=args.silhouette_settings.threshold,
                                       threads=args.threads)
    except ValueError as exc:
        log.error("bad settings: %s", exc)
        return 1
    try:
        observe_mesh(args.mesh, args.cameras, args.hdr, args.capture, args.output, settings,
                     exclude_views=tuple(args.exclude_views))
    except (ObserveError, CamerasError, CaptureError) as exc:
        log.error("%s", exc)
        return 1
    return 0
