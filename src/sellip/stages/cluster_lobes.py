"""``sellip cluster-lobes``: material clusters and per-cluster specular lobes (rule ``cluster_lobes``).

    sellip cluster-lobes --params results/NAME/iter/0/fit.zarr
                         --observations results/NAME/iter/0/observations.zarr
                         --output results/NAME/iter/0/clusters --seed 0
                         [--k-max 8] [--max-samples 20000] [--min-cluster-vertices 50] [--min-coherence 0.5]
                         [--settings '{"lambda_psi": 100}'] [--model-selection '{"folds": 4}']
                         [--job-settings '{"compilation_cache": DIR}'] [--inherit-models]

Writes the directory ``--output`` (built under a temporary name, then renamed) with

- ``labels.npy``: (N,) int32, the cluster of every vertex of the params store;
- ``models.npy``: (N,) uint8, the model of every vertex (its cluster's; :data:`sellip.model.params.MODEL_NAMES`);
- ``lobes.csv``: one row per cluster (:func:`lobes_schema`): cluster, vertices, eta, sigma_s,
  sigma_ss, rho_s, rho_ss_r, rho_ss_g, rho_ss_b, samples, loss, model;
- ``lobes.png``: each cluster's lobe against its samples as a function of theta_h (paper Fig. 7b);
- ``clusters.json``: K, the BIC per K, the merges, the regions added (:func:`sellip.fit.clusters.cluster_materials`),
  ``support`` (with ``--stability-resamples``; :func:`sellip.fit.clusters.clustering_support`): per cluster the
  share of repeats on resampled vertices that found it again, and what it became otherwise;
  ``degenerate``: what could not be computed on these data and what was done instead (a cluster without a
  confident vertex or a usable sample, albedos without spread; the run goes on, lower in confidence),
  the settings (``settings``: the clustering's; ``fit_settings``: the lobe fit's) and the seed, and under
  ``model_selection`` per cluster the chosen model, the held-out loss of every candidate and why.

Model selection (docs/design.md §7, :mod:`sellip.fit.selection`; ``--model-selection`` is
:class:`sellip.fit.selection.SelectionSettings` as one JSON object, config ``model_selection``; on unless its
``enabled`` is false): per cluster,
the simplest model whose held-out loss is within the tolerance of the best; the cluster's lobe is
then fitted with that model. Without it every cluster gets the model of the fit settings (3, or 2
with the settings' ``sigma_ss_fixed``). The fit settings (``--settings``) are also the most complex model allowed.
With ``--inherit-models`` (iterations between selections, config ``model_selection.every``) no candidate
is fitted: each cluster takes the model most of its vertices have in ``--params`` (their ``model``, from
the previous iteration), capped by what the settings allow; a store without models selects as usual.

The numerics are :mod:`sellip.fit` and :mod:`sellip.fit.selection`; ``sellip fit --lobes DIR`` turns
the result into virtual samples and fits every vertex with its model. ``--settings`` is
:class:`sellip.fit.records.FitSettings` as one JSON object (view selection, lambda_psi, lambda_s, lobes,
sigma_ss_fixed; config ``fit.settings``).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.fit.augment_pass import cluster_and_fit_lobes

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.records import FitJobSettings, FitSettings
    from sellip.fit.selection import SelectionSettings
    from sellip.settings import add_renamed_argument, add_settings_argument

    defaults = AugmentSettings()
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
    parser.add_argument("--stability-resamples", type=int, default=defaults.stability_resamples,
                        help="repeat the clustering on this many seeded 90 %% subsamples and record each cluster's "
                             "support (clusters.json 'support'; 0: not measured)")
    add_settings_argument(parser, FitSettings, "--settings", "fit.settings")
    add_settings_argument(parser, FitJobSettings, "--job-settings", "fit")
    add_settings_argument(parser, SelectionSettings, "--model-selection", "model_selection")
    add_renamed_argument(parser, "--set", "--settings (FitSettings as one JSON object)")
    add_renamed_argument(parser, "--fixed-sigma-ss", "--model-selection '{\"model2_sigma_ss\": ...}'")
    parser.add_argument("--inherit-models", action="store_true",
                        help="no candidate fits: each cluster takes its vertices' most common model in --params")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        if args.k_max < 1 or args.max_samples < 1 or args.min_cluster_vertices < 1:
            raise ValueError("--k-max, --max-samples and --min-cluster-vertices must be >= 1")
        settings = AugmentSettings(k_max=args.k_max, max_samples=args.max_samples,
                                   min_cluster_vertices=args.min_cluster_vertices, min_coherence=args.min_coherence,
                                   pool_min_coherence=args.pool_min_coherence,
                                   stability_resamples=args.stability_resamples)
        cluster_and_fit_lobes(args.params, args.observations, args.output, args.seed, settings, args.settings,
                              args.job_settings.compilation_cache, args.model_selection, args.inherit_models)
    except (ObserveError, ParamsError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
