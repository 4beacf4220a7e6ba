"""``sellip fit``: the per-vertex pBRDF and normal fit of one vertex shard (rule ``fit_pbrdf``).

    sellip fit --observations results/NAME/iter/0/observations.zarr --shard 2-of-4
               --output results/NAME/iter/0/fit/2-of-4.npz
               [--prior results/NAME/iter/1/refit.zarr] [--dtype float32]
               [--set lambda_d=100 --set sigma_ss_fixed=0.9 ...] [--compilation-cache DIR]
               [--lobes results/NAME/iter/0/clusters] [--mem-mb 4000]

The shard's vertex range is derived at run time from the store's vertex count and chunking
(shard i of n takes an equal share of whole vertex chunks, so it reads only its own chunks).
With ``--prior`` (a parameter store: the previous iteration's) every parameter is warm-started from
the nearest previous vertex (DESIGN §7); without it the fit starts from eta = 1.5 and the
defaults of :func:`sellip.fit.vertex_fit.default_prior`. The starting normals are the mesh normals.
``--set`` overrides a field of :class:`sellip.fit.records.FitSettings`.

With ``--lobes`` (the output of ``sellip cluster-lobes``: labels.npy, models.npy, lobes.csv) this
is the augmented refit (docs/augment.md): every vertex gets the virtual specular samples of its
cluster's lobe. The prior is then the same iteration's first-pass params store (same vertices):
the fit starts from its normals as well as its parameters (and holds them with
``--set fit_normal=false``). The workflow's final pass gives its first fit the previous iteration's
lobes and refit settings: its prior is then on another mesh, so it starts from the (final) mesh's
normals, and it runs the refit's compiled program (one compilation fewer, docs/speed.md).

Models (DESIGN §7, :mod:`sellip.fit.selection`): every vertex is fitted with its own model, from
``--lobes``'s models.npy, else from the prior store's ``model`` (nearest vertex, as its
parameters), else the model of the settings (3, or 2 with ``sigma_ss_fixed``); never more
complex than the settings allow. Vertices are grouped by model, one fit per group. Model 2's
sigma_ss is ``--set sigma_ss_fixed`` when given, else ``--fixed-sigma-ss``. The output holds
``model`` (N,) uint8, the model each vertex was fitted with.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.shard import fit_shard, parse_shard, settings_from_pairs

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--observations", type=Path, required=True, help="observations.zarr of this iteration")
    parser.add_argument("--shard", type=parse_shard, default=(0, 1), help="i-of-n (default 1-of-1: all vertices)")
    parser.add_argument("--output", type=Path, required=True, help="shard result (.npz)")
    parser.add_argument("--prior", type=Path, default=None,
                        help="a parameter store to warm-start from "
                             "(the previous iteration's, or this one's first pass)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a FitSettings field (repeatable)")
    parser.add_argument("--compilation-cache", default=None, help="directory for XLA's persistent compilation cache")
    parser.add_argument("--lobes", type=Path, default=None,
                        help="cluster-lobes output directory: the augmented refit (virtual specular samples)")
    parser.add_argument("--mem-mb", type=float, default=None,
                        help="memory the job may use (MB; the rule's mem_mb resource, config fit.mem_mb): a shard "
                             "needing more stops before reading, naming the shard count that fits")
    from sellip.fit.selection import SelectionSettings

    parser.add_argument("--fixed-sigma-ss", type=float, default=SelectionSettings().sigma_ss_fixed,
                        help="sigma_ss of the vertices of model 2 when --set sigma_ss_fixed is not given")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.fit.shard import ShardMemoryError

    try:
        settings = settings_from_pairs(args.overrides)
        if not 0.02 <= args.fixed_sigma_ss <= 1:
            raise ValueError(f"--fixed-sigma-ss must be in [0.02, 1], got {args.fixed_sigma_ss}")
        fit_shard(args.observations, args.shard, args.output, args.prior, args.dtype, settings,
                  args.compilation_cache, args.lobes, args.fixed_sigma_ss, args.mem_mb)
    except (ObserveError, ValueError, ShardMemoryError) as error:
        log.error("%s", error)
        return 1
    return 0
