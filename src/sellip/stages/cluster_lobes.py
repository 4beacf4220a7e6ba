"""``sellip cluster-lobes``: material clusters and per-cluster specular lobes (rule ``cluster_lobes``).

    sellip cluster-lobes --params results/NAME/iter/0/fit.zarr
                         --observations results/NAME/iter/0/observations.zarr
                         --output results/NAME/iter/0/clusters --seed 0
                         [--augment-settings '{"k_max": 8, "min_coherence": 0.5}'] [--stability-resamples 10]
                         [--settings '{"lambda_psi": 100}'] [--model-selection '{"folds": 4}']
                         [--job-settings '{"compilation_cache": DIR}'] [--inherit-models]
                         [--previous-clusters results/NAME/iter/N-1/clusters]

Writes the directory ``--output`` (built under a temporary name, then renamed) with

- ``labels.npy``: (N,) int32, the cluster of every vertex of the params store;
- ``models.npy``: (N,) uint8, the model of every vertex (its cluster's; :data:`sellip.model.params.MODEL_NAMES`);
- ``lobes.csv``: one row per cluster (:func:`lobes_schema`): cluster, vertices, eta, sigma_s,
  sigma_ss, rho_s, rho_ss_r, rho_ss_g, rho_ss_b, samples, loss, model;
- ``lobes.png``: each cluster's lobe against its samples as a function of theta_h (paper Fig. 7b);
- ``clusters.json``: K, the BIC per K, the merges, the regions added (:func:`sellip.fit.clusters.cluster_materials`),
  ``support`` (with ``--stability-resamples``; :func:`sellip.fit.cluster_support.clustering_support`): per cluster the
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
With ``--previous-clusters`` (every pass after the first, in the workflow) a region of another albedo that was a
material of its own at the previous pass is split off on ``keep_coherence_margin`` less coherence: hysteresis, so
that a material found is not lost on weaker evidence than found it (docs/reproducibility.md).
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
import dataclasses
import logging
from pathlib import Path

from sellip.fit.augment_pass import cluster_and_fit_lobes

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.records import FitJobSettings, FitSettings
    from sellip.fit.selection import SelectionSettings
    from sellip.settings import add_renamed_argument, add_settings_argument

    parser.add_argument("--params", type=Path, required=True, help="this iteration's first-pass params store")
    parser.add_argument("--observations", type=Path, required=True, help="this iteration's observations.zarr")
    parser.add_argument("--output", type=Path, required=True, help="output directory (clusters)")
    parser.add_argument("--seed", type=int, default=0)
    add_settings_argument(parser, AugmentSettings, "--augment-settings", "augment")
    parser.add_argument("--stability-resamples", type=int, default=AugmentSettings.stability_resamples,
                        help="repeat the clustering on this many seeded 90 %% subsamples and record each cluster's "
                             "support (clusters.json 'support'; 0: not measured; the workflow: config "
                             "augment.stability_resamples at the final pass)")
    add_settings_argument(parser, FitSettings, "--settings", "fit.settings")
    add_settings_argument(parser, FitJobSettings, "--job-settings", "fit")
    add_settings_argument(parser, SelectionSettings, "--model-selection", "model_selection")
    add_renamed_argument(parser, "--set", "--settings (FitSettings as one JSON object)")
    add_renamed_argument(parser, "--fixed-sigma-ss", "--model-selection '{\"model2_sigma_ss\": ...}'")
    parser.add_argument("--inherit-models", action="store_true",
                        help="no candidate fits: each cluster takes its vertices' most common model in --params")
    parser.add_argument("--previous-clusters", type=Path, default=None,
                        help="the previous pass's clusters directory: a material found there is kept on less "
                             "coherence (augment keep_coherence_margin; docs/reproducibility.md)")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        settings = dataclasses.replace(args.augment_settings, stability_resamples=args.stability_resamples)
        cluster_and_fit_lobes(args.params, args.observations, args.output, args.seed, settings, args.settings,
                              args.job_settings.compilation_cache, args.model_selection, args.inherit_models,
                              args.previous_clusters)
    except (ObserveError, ParamsError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
