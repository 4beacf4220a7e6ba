"""``sellip fit``: the per-vertex pBRDF and normal fit of one vertex shard (rule ``fit_pbrdf``).

    sellip fit --observations results/NAME/iter/0/observations.zarr --shard 2-of-4
               --output results/NAME/iter/0/fit/2-of-4.npz
               [--prior results/NAME/iter/1/refit.zarr] [--job-settings '{"dtype": "float64"}']
               [--settings '{"lambda_d": 100, "min_views": 4}'] [--model2-sigma-ss 1.0]
               [--lobes results/NAME/iter/0/clusters] [--mem-mb 4000]

The shard's vertex range is derived at run time from the store's vertex count and chunking
(shard i of n takes an equal share of whole vertex chunks, so it reads only its own chunks).
With ``--prior`` (a parameter store: the previous iteration's) every parameter is warm-started from
the nearest previous vertex (docs/design.md §7); without it the fit starts from eta = 1.5 and the
defaults of :func:`sellip.fit.vertex_fit.default_prior`. The starting normals are the mesh normals.
``--settings`` is :class:`sellip.fit.records.FitSettings` as one JSON object (the workflow's config
``fit.settings`` of this iteration and pass; keys left out take the record's defaults); ``--job-settings`` is
:class:`sellip.fit.records.FitJobSettings` (config ``fit``: ``dtype``, ``compilation_cache``).

With ``--lobes`` (the output of ``sellip cluster-lobes``: labels.npy, models.npy, lobes.csv) this
is the augmented refit (docs/augment.md): every vertex gets the virtual specular samples of its
cluster's lobe. The prior is then the same iteration's first-pass params store (same vertices):
the fit starts from its normals as well as its parameters (and holds them with
``"fit_normal": false``). The workflow's final pass gives its first fit the previous iteration's
lobes and refit settings: its prior is then on another mesh, so it starts from the (final) mesh's
normals, and it runs the refit's compiled program (one compilation fewer, docs/speed.md).

Models (docs/design.md §7, :mod:`sellip.fit.selection`): every vertex is fitted with its own model, from
``--lobes``'s models.npy, else from the prior store's ``model`` (nearest vertex, as its
parameters), else the model of the settings (3, or 2 with ``sigma_ss_fixed``); never more
complex than the settings allow. Vertices are grouped by model, one fit per group. Model 2's
sigma_ss is the settings' ``sigma_ss_fixed`` when given, else ``--model2-sigma-ss`` (config
``model_selection.model2_sigma_ss``). The output holds
``model`` (N,) uint8, the model each vertex was fitted with.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.shard import fit_shard, parse_shard

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--observations", type=Path, required=True, help="observations.zarr of this iteration")
    parser.add_argument("--shard", type=parse_shard, default=(0, 1), help="i-of-n (default 1-of-1: all vertices)")
    parser.add_argument("--output", type=Path, required=True, help="shard result (.npz)")
    parser.add_argument("--prior", type=Path, default=None,
                        help="a parameter store to warm-start from "
                             "(the previous iteration's, or this one's first pass)")
    from sellip.fit.records import FitJobSettings, FitSettings
    from sellip.settings import add_renamed_argument, add_settings_argument

    add_settings_argument(parser, FitSettings, "--settings", "fit.settings")
    add_settings_argument(parser, FitJobSettings, "--job-settings", "fit")
    add_renamed_argument(parser, "--set", "--settings (FitSettings as one JSON object)")
    add_renamed_argument(parser, "--fixed-sigma-ss", "--model2-sigma-ss")
    parser.add_argument("--lobes", type=Path, default=None,
                        help="cluster-lobes output directory: the augmented refit (virtual specular samples)")
    parser.add_argument("--mem-mb", type=float, default=None,
                        help="memory the job may use (MB; the rule's mem_mb resource, config fit.mem_mb): a shard "
                             "needing more stops before reading, naming the shard count that fits")
    parser.add_argument("--model2-sigma-ss", type=float, default=None,
                        help="sigma_ss of the vertices of model 2 unless the settings' sigma_ss_fixed is given (config "
                             "model_selection.model2_sigma_ss; default: its declared default)")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.fit.shard_plan import ShardMemoryError

    try:
        if args.model2_sigma_ss is not None and not 0.02 <= args.model2_sigma_ss <= 1:
            raise ValueError(f"--model2-sigma-ss must be in [0.02, 1], got {args.model2_sigma_ss}")
        fit_shard(args.observations, args.shard, args.output, args.prior, args.job_settings.dtype, args.settings,
                  args.job_settings.compilation_cache, args.lobes, args.model2_sigma_ss, args.mem_mb)
    except (ObserveError, ValueError, ShardMemoryError) as error:
        log.error("%s", error)
        return 1
    return 0
