"""``sellip gather-fit``: assemble the fit shards of one iteration into its params.zarr (rule ``gather_fit``).

    sellip gather-fit --observations results/NAME/iter/0/observations.zarr
                      --shards results/NAME/iter/0/fit/1-of-2.npz results/NAME/iter/0/fit/2-of-2.npz
                      --output results/NAME/iter/0/fit.zarr [--job-settings '{"min_fitted_share": 0.25}']

The shards must cover the store's vertices exactly once. When the fitted vertices are less than
``min_fitted_share`` of the vertices some view sees (config ``fit.min_fitted_share``,
:class:`sellip.fit.records.FitJobSettings`), the stage stops with what is missing and writes nothing
(:mod:`sellip.fit.evidence`). Vertices that could not be fitted (too few views, failed) get parameters interpolated
from their fitted neighbours and confidence 0 (docs/design.md §7); they keep their starting normal (the mesh's: a
neighbour's normal belongs to another part of the surface; interpolating them left the demo's unlit underside 17
deg median off its own mesh) and their ``model`` (their cluster's, not fitted). The store layout is
:mod:`sellip.model.params`; ``model`` (the model each vertex was fitted with) is written when every shard has it.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.evidence import EvidenceError
from sellip.fit.records import FitJobSettings
from sellip.fit.shard import gather_shards
from sellip.settings import add_settings_argument

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--observations", type=Path, required=True)
    parser.add_argument("--shards", type=Path, nargs="+", required=True)
    parser.add_argument("--output", type=Path, required=True)
    add_settings_argument(parser, FitJobSettings, "--job-settings", "fit")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        gather_shards(args.observations, args.shards, args.output, args.job_settings.min_fitted_share)
    except (ObserveError, ParamsError, EvidenceError) as error:
        log.error("%s", error)
        return 1
    return 0
