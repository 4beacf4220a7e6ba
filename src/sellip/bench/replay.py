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
