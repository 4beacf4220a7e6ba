"""``sellip bench-stability``: the stability suite (issue #9) -> stability.csv and stability.md.

    sellip bench-stability --out results/bench/stability [--cases baseline dark ...] [--cores 2]
                           [--iterations 2] [--keep] [--snakefile Snakefile] [--noise-seed S]

Each case (:data:`sellip.bench.stability.CASES`) is a real Snakemake run of the workflow on a small synthetic
capture with one failure mode built in, under ``OUT/runs/<case>/`` (its own captures/ and results/, its
Snakemake output in ``snakemake.log``); the cases share the XLA cache ``OUT/jax_cache``. A case that fails
is a row with status "failed" and the reason; the suite goes on. Written at the end (atomically):
``OUT/stability.csv`` (columns :data:`sellip.bench.stability_table.COLUMNS`, checked with pandera) and
``OUT/stability.md`` (the table of docs/benchmarks.md). Exit status 0 when the tables were written, also
when cases failed (that is a finding); 1 when the suite could not run.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.bench import stability

log = logging.getLogger(__name__)


def default_snakefile() -> Path:
    """The Snakefile in the current directory, else the one of the checkout sellip is installed from."""
    here = Path.cwd() / "Snakefile"
    return here if here.is_file() else Path(stability.__file__).resolve().parents[3] / "Snakefile"


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("results/bench/stability"),
                        help="folder for the runs and the tables (default: results/bench/stability)")
    parser.add_argument("--cases", nargs="+", choices=stability.CASE_NAMES, default=list(stability.CASE_NAMES),
                        metavar="CASE",
                        help=f"cases to run, in this order (default: all: {' '.join(stability.CASE_NAMES)})")
    parser.add_argument("--cores", type=int, default=2, help="Snakemake --cores of each run (default: 2)")
    parser.add_argument("--iterations", type=int, default=2, help="outer iterations of each run (default: 2)")
    parser.add_argument("--keep", action="store_true",
                        help="reuse the row of a case that already ran (runs/<case>/row.json)")
    parser.add_argument("--noise-seed", type=int, default=None,
                        help="draw every case's sensor noise with this seed (config demo.noise_seed; default: the "
                             "case's own): the same captures but for the photons (docs/reproducibility.md)")
    parser.add_argument("--snakefile", type=Path, default=None,
                        help="the workflow's Snakefile (default: ./Snakefile, else the installed checkout's)")


def main(args: argparse.Namespace) -> int:
    snakefile = args.snakefile or default_snakefile()
    if not snakefile.is_file():
        log.error("%s: no Snakefile there; run from the repository root or pass --snakefile", snakefile)
        return 1
    if args.cores < 1 or args.iterations < 0:
        log.error("--cores must be at least 1 and --iterations at least 0")
        return 1
    by_name = {case.name: case for case in stability.CASES}
    cases = [by_name[name] for name in dict.fromkeys(args.cases)]
    table = stability.run_suite(cases, args.out, snakefile, cores=args.cores, iterations=args.iterations,
                                keep=args.keep, noise_seed=args.noise_seed)
    failed = table.loc[table["status"] != "ok", "case"].tolist()
    if failed:
        log.warning("%d case(s) failed: %s", len(failed), ", ".join(failed))
    return 0
