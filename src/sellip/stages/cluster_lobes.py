"""``sellip cluster-lobes``: material clusters and per-cluster specular lobes (rule ``cluster_lobes``).

    sellip cluster-lobes --params results/NAME/iter/0/fit.zarr
                         --observations results/NAME/iter/0/observations.zarr
                         --output results/NAME/iter/0/clusters --seed 0
                         [--k-max 8] [--max-samples 20000] [--min-cluster-vertices 50] [--min-coherence 0.5]
                         [--set lambda_psi=100 ...]
                         [--no-model-selection] [--candidates 0 1 2 3] [--held-out-fraction 0.25]
                         [--selection-tolerance 0.01] [--selection-standard-errors 1]
                         [--fixed-sigma-ss 0.9] [--selection-max-samples 4096] [--inherit-models]

Writes the directory ``--output`` (built under a temporary name, then renamed) with

- ``labels.npy``: (N,) int32, the cluster of every vertex of the params store;
- ``models.npy``: (N,) uint8, the model of every vertex (its cluster's; :data:`sellip.model.params.MODEL_NAMES`);
- ``lobes.csv``: one row per cluster (:func:`lobes_schema`): cluster, vertices, eta, sigma_s,
  sigma_ss, rho_s, rho_ss_r, rho_ss_g, rho_ss_b, samples, loss, model;
- ``lobes.png``: each cluster's lobe against its samples as a function of theta_h (paper Fig. 7b);
- ``clusters.json``: K, the BIC per K, the merges, the regions added (:func:`sellip.fit.clusters.cluster_materials`),
  ``degenerate``: what could not be computed on these data and what was done instead (a cluster without a
  confident vertex or a usable sample, albedos without spread; the run goes on, lower in confidence),
  the settings (``settings``: the clustering's; ``fit_settings``: the lobe fit's) and the seed, and under
  ``model_selection`` per cluster the chosen model, the held-out loss of every candidate and why.

Model selection (DESIGN §7, :mod:`sellip.fit.selection`, on unless ``--no-model-selection``): per cluster,
the simplest model whose held-out loss is within the tolerance of the best; the cluster's lobe is
then fitted with that model. Without it every cluster gets the model of the fit settings (3, or 2
with ``--set sigma_ss_fixed=...``). The fit settings (``--set``) are also the most complex model allowed.
With ``--inherit-models`` (iterations between selections, config ``model_selection.every``) no candidate
is fitted: each cluster takes the model most of its vertices have in ``--params`` (their ``model``, from
the previous iteration), capped by what the settings allow; a store without models selects as usual.

The numerics are :mod:`sellip.fit` and :mod:`sellip.fit.selection`; ``sellip fit --lobes DIR`` turns
the result into virtual samples and fits every vertex with its model. ``--set`` overrides
:class:`sellip.fit.records.FitSettings` (view selection, lambda_psi, lambda_s, lobes, sigma_ss_fixed).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.augment_pass import cluster_and_fit_lobes

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.selection import SelectionSettings

    defaults = AugmentSettings()
    selection = SelectionSettings()
    parser.add_argument("--params", type=Path, required=True, help="this iteration's first-pass params store")
    parser.add_argument("--observations", type=Path, required=True, help="this iteration's observations.zarr")
    parser.add_argument("--output", type=Path, required=True, help="output directory (clusters)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--k-max", type=int, default=defaults.k_max)
    parser.add_argument("--max-samples", type=int, default=defaults.max_samples)
    parser.add_argument("--min-cluster-vertices", type=int, default=defaults.min_cluster_vertices)
    parser.add_argument("--min-coherence", type=float, default=defaults.min_coherence,
                        help="merge a cluster whose vertices' nearest neighbours lie in it less often than this "
                             "(a cut through one material's noise, not a material; 0: no test)")
    parser.add_argument("--pool-min-coherence", type=float, default=defaults.pool_min_coherence,
                        help="pool only a cluster's vertices whose nearest neighbours lie in it at least this often "
                             "in its lobe fit and model selection, where half of them do (0: every vertex)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a FitSettings field (repeatable)")
    parser.add_argument("--compilation-cache", default=None, help="directory for XLA's persistent compilation cache")
    parser.add_argument("--model-selection", action=argparse.BooleanOptionalAction, default=selection.enabled,
                        help="choose each cluster's model on held-out vertices (default on)")
    parser.add_argument("--inherit-models", action="store_true",
                        help="no candidate fits: each cluster takes its vertices' most common model in --params")
    parser.add_argument("--candidates", type=int, nargs="+", default=list(selection.candidates),
                        help="model codes tried (sellip.model.params.MODEL_NAMES)")
    parser.add_argument("--held-out-fraction", type=float, default=selection.held_out_fraction,
                        help="share of a cluster's vertices held out, with --selection-folds 1")
    parser.add_argument("--selection-folds", type=int, default=selection.folds,
                        help="k >= 2: k-fold cross-validation (every vertex held out once); 1: one held-out part")
    parser.add_argument("--selection-tolerance", type=float, default=selection.tolerance,
                        help="relative held-out loss a simpler model may lose")
    parser.add_argument("--selection-standard-errors", type=float, default=selection.standard_errors,
                        help="plus this many standard errors of the difference")
    parser.add_argument("--fixed-sigma-ss", type=float, default=selection.sigma_ss_fixed,
                        help="sigma_ss of model 2 when --set sigma_ss_fixed is not given")
    parser.add_argument("--selection-max-samples", type=int, default=selection.max_samples,
                        help="training samples per candidate fit")
    parser.add_argument("--selection-max-theta-error-deg", type=float, default=selection.max_theta_error_deg,
                        help="|Delta theta_h| bound of the candidate fits and their held-out scores among models 1-3 "
                             "(0: none; model 0 against a lobe keeps the lobe fit's)")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.observe import ObserveError
    from sellip.fit.selection import SelectionSettings
    from sellip.fit.shard import settings_from_pairs
    from sellip.model.params import ParamsError

    try:
        if args.k_max < 1 or args.max_samples < 1 or args.min_cluster_vertices < 1 or args.selection_max_samples < 1:
            raise ValueError("--k-max, --max-samples, --min-cluster-vertices and --selection-max-samples must be >= 1")
        settings = AugmentSettings(k_max=args.k_max, max_samples=args.max_samples,
                                   min_cluster_vertices=args.min_cluster_vertices, min_coherence=args.min_coherence,
                                   pool_min_coherence=args.pool_min_coherence)
        selection = SelectionSettings(enabled=args.model_selection, candidates=tuple(args.candidates),
                                      held_out_fraction=args.held_out_fraction, folds=args.selection_folds,
                                      tolerance=args.selection_tolerance,
                                      standard_errors=args.selection_standard_errors,
                                      sigma_ss_fixed=args.fixed_sigma_ss, max_samples=args.selection_max_samples,
                                      max_theta_error_deg=args.selection_max_theta_error_deg)
        cluster_and_fit_lobes(args.params, args.observations, args.output, args.seed, settings,
                  settings_from_pairs(args.overrides), args.compilation_cache, selection, args.inherit_models)
    except (ObserveError, ParamsError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
