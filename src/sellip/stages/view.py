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
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

log = logging.getLogger(__name__)


def find_capture(results: Path) -> Path | None:
    """The capture folder recorded in ``results/metrics.json`` (None when there is none)."""
    metrics = results / "metrics.json"
    if metrics.is_file():
        capture = json.loads(metrics.read_text()).get("capture")
        if capture and Path(capture).is_dir():
            return Path(capture)
    return None


def ground_truth_for(results: Path, capture: Path | None):
    """The capture's ground-truth ParamMesh when its world is the model's (known or verified poses), else None."""
    from sellip.io import GROUND_TRUTH_MESH, read_param_mesh

    if capture is None or not (capture / GROUND_TRUTH_MESH).is_file():
        return None
    report = results / "sfm" / "report.json"
    if report.is_file() and json.loads(report.read_text()).get("mode") == "sfm":
        log.info("poses from SfM: the materials table has no ground-truth columns (the worlds differ by a Sim(3))")
        return None
    return read_param_mesh(capture / GROUND_TRUTH_MESH)


def run_stage(results: Path, capture: Path | None = None) -> dict:
    """Write materials.csv, model.glb, the map PLYs and the viewer of ``results``; returns what was written."""
    from sellip.report.export import write_glb, write_map_plys
    from sellip.report.materials import material_table, write_materials
    from sellip.report.viewer import load_inputs, maps_of, write_viewer

    results = Path(results)
    capture = Path(capture) if capture is not None else find_capture(results)
    inputs = load_inputs(results, capture)  # ViewerError when there is no finished model
    final = results / "final"
    written = {}
    if inputs.store:
        table = material_table(inputs.store, inputs.faces, ground_truth_for(results, capture))
        written["materials"] = write_materials(final / "materials.csv", table)
        inputs.materials = table
        log.info("materials:\n%s", table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    else:
        log.warning("%s: no params.zarr: no materials table", final)
    vertex = dict(inputs.vertex)
    if "cluster" not in vertex and "cluster" in inputs.store:
        vertex["cluster"] = inputs.store["cluster"]
    up = None
    if inputs.cameras:
        import numpy as np

        up = np.mean([-r[1] for _, r, _ in inputs.cameras], axis=0)
    written["glb"] = write_glb(final / "model.glb", vertex, inputs.faces, up=up, name=results.name)
    maps = maps_of(inputs)
    tmp = final / "maps.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    write_map_plys(tmp, vertex, inputs.faces, maps)
    shutil.rmtree(final / "maps", ignore_errors=True)
    tmp.rename(final / "maps")
    written["maps"] = final / "maps"
    written["viewer"] = write_viewer(results / "viewer", inputs)
    for note in inputs.notes:
        log.info("viewer: %s", note)
    log.info("wrote %s", ", ".join(str(p) for p in written.values()))
    print(f"sellip viewer: open {written['viewer'].resolve()} (or: sellip view {results} --serve)", flush=True)
    return written


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("results", type=Path, help="a run's results folder (results/NAME)")
    parser.add_argument("--capture", type=Path, default=None,
                        help="capture folder (the flash, the ground truth); default: the one metrics.json names")
    parser.add_argument("--serve", action="store_true", help="then serve the page on localhost until interrupted")
    parser.add_argument("--port", type=int, default=8000, help="port for --serve (default 8000)")


def main(args: argparse.Namespace) -> int:
    from sellip.report.materials import MaterialsError
    from sellip.report.viewer import ViewerError, serve

    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
    try:
        written = run_stage(args.results, args.capture)
    except (ViewerError, MaterialsError) as exc:
        log.error("%s", exc)
        return 1
    if args.serve:
        try:
            serve(written["viewer"].parent, args.port)
        except KeyboardInterrupt:
            pass
    return 0
