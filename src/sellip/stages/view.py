"""``sellip view``: the per-material table, the exports and the interactive viewer of a final model
(rule ``export_viewer``; issue #40, docs/viewer.md).

    sellip view results/NAME [--capture CAPTURE] [--serve [--port 8000]]

Reads ``results/NAME/final/model.ply`` (required) with ``final/params.zarr``, ``cameras.csv``, ``hdr.zarr`` and the
capture's ``capture.yaml`` (the flash; ``ground_truth/model.ply`` for the table's truth columns when the poses are
the capture's own, not SfM's); ``--capture`` defaults to the one metrics.json names. Writes, each atomically:

- ``final/materials.csv``: one row per material cluster (:mod:`sellip.report.materials`);
- ``final/model.glb``: glTF 2.0 binary with the parameters as ``_ETA``-style vertex attributes
  (:mod:`sellip.report.export`);
- ``final/maps/map_<name>.ply``: the mesh coloured by each map (MeshLab, Blender);
- ``viewer/``: the static page (``viewer/index.html``, :mod:`sellip.report.viewer`), then, with ``--serve``,
  serves it on http://127.0.0.1:PORT/ until interrupted.

A model older than a failed run (``last_run.json``) or than the capture's files is named in a WARNING first
(:func:`sellip.workflow_support.stale_model`).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("results", type=Path, help="a run's results folder (results/NAME)")
    parser.add_argument("--capture", type=Path, default=None,
                        help="capture folder (the flash, the ground truth); default: the one metrics.json names")
    parser.add_argument("--serve", action="store_true", help="then serve the page on localhost until interrupted")
    parser.add_argument("--port", type=int, default=8000, help="port for --serve (default 8000)")


def main(args: argparse.Namespace) -> int:
    from sellip.report.materials import MaterialsError
    from sellip.report.viewer import ViewerError, export_results, find_capture, serve
    from sellip.workflow_support import stale_model

    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
    try:
        for line in stale_model(args.results, args.capture or find_capture(args.results)):
            log.warning("%s", line)  # a failed or pending re-run: the page shows an earlier run's model
        written = export_results(args.results, args.capture)
    except (ViewerError, MaterialsError) as exc:
        log.error("%s", exc)
        return 1
    if args.serve:
        try:
            serve(written["viewer"].parent, args.port)
        except KeyboardInterrupt:
            pass
    return 0
