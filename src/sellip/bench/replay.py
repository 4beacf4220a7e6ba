"""The command line shared by the replay benchmarks (``benchmarks/replay_*.py``): a run's results folder, one of
its passes and the capture's ground truth."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path


def replay_parser(doc: str, iteration_help: str = "the pass (iter/N)") -> argparse.ArgumentParser:
    """A parser with ``run`` (results/<name>, run with ``snakemake --notemp``), ``--iteration`` and ``--truth``
    (the capture's ground_truth/model.ply); the script adds its own options."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the run's results folder (results/<name>), run with --notemp")
    parser.add_argument("--iteration", type=int, required=True, help=iteration_help)
    parser.add_argument("--truth", type=Path, required=True, help="the capture's ground_truth/model.ply")
    return parser


def ignore_snakemake_zarr_warnings() -> None:
    """Silence zarr's warning about Snakemake's timestamp files inside a run's stores."""
    warnings.filterwarnings("ignore", message=".*not recognized as a component of a Zarr hierarchy")


def clustering_overrides_and_truth(parser: argparse.ArgumentParser, pairs: list[str], truth_path: Path):
    """The ``--set FIELD=VALUE`` pairs as AugmentSettings overrides and the ground truth with its material labels,
    for a replay of a run's clustering; a bad pair or a truth without labels is ``parser.error``."""
    from sellip.fit.clusters import AugmentSettings
    from sellip.fit.shard import overrides_from_pairs
    from sellip.model.ply import read_param_mesh

    try:
        overrides = overrides_from_pairs(pairs, AugmentSettings)
    except ValueError as error:
        parser.error(str(error))
    truth = read_param_mesh(truth_path)
    if truth.material is None:
        parser.error(f"{truth_path}: the ground truth has no material labels")
    return overrides, truth
