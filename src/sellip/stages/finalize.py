"""``sellip finalize``: the final model (rule ``finalize_model``, docs/design.md §4).

    sellip finalize --params results/NAME/iter/10/params.zarr --mesh results/NAME/iter/9/mesh.ply
                    --output-model results/NAME/final/model.ply --output-params results/NAME/final/params.zarr
                    [--clusters results/NAME/iter/10/clusters] [--model 3]
                    [--settings '{"eta_deviation_sigmas": 3.0, "deviation_support": 3}']

``--settings``: :class:`sellip.fit.finalize.FinalSettings` (config ``final``, its deviation keys) as one JSON
object; a key left out takes its declared default.

``--params`` is the last pass of the loop: the pBRDF refitted with the normals of the final
geometry (paper §4.4); its rows are the vertices of ``--mesh``, whose triangles the model keeps.
Written (each atomically): ``model.ply`` with the vertex properties of docs/design.md §4 (float32) plus
``confidence`` (float32) and ``model`` (uint8, :data:`sellip.model.params.MODEL_NAMES`), and
``params.zarr`` with the same arrays (plus status, loss, views_used, iterations, cluster).
``model`` is the store's own (the model each vertex was fitted with, docs/design.md §7); ``--model``
only fills it for a store without one.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.finalize import FinalSettings, finalize_model
from sellip.settings import add_settings_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", type=Path, required=True, help="the last pass's params.zarr")
    parser.add_argument("--mesh", type=Path, required=True, help="the final mesh (its triangles)")
    parser.add_argument("--output-model", type=Path, required=True, help="final model PLY")
    parser.add_argument("--output-params", type=Path, required=True, help="final params.zarr")
    parser.add_argument("--clusters", type=Path, default=None, help="cluster_lobes output of the last pass")
    add_settings_argument(parser, FinalSettings, section="final")
    parser.add_argument("--model", type=int, default=3,
                        help="model code of every vertex when the store has no model array "
                             "(sellip.model.params.MODEL_NAMES)")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        finalize_model(args.params, args.mesh, args.output_model, args.output_params, args.clusters, args.model,
                       args.settings)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
