"""``sellip bench-sweep``: the speed-accuracy sweep of the whole workflow (issue #9, docs/benchmarks.md).

    sellip bench-sweep --scenes demo sphere_ior --preset quick --out results/bench/sweep
                       [--cores 2] [--only FACTOR ...] [--repeat 2] [--force] [--report-only]

Runs the workflow once per variant (:mod:`sellip.bench.sweep`: the preset's base per scene, then one factor
changed at a time) in OUT/work/PRESET (a Snakemake working directory: captures/, results/NAME/,
jax_cache/, logs/, configs/), then writes into OUT:

- ``sweep.csv``: one row per variant (:data:`sellip.bench.sweep_tables.SWEEP_COLUMNS`, pandera-checked): times and
  figures;
- ``sweep.png``: accuracy (normal median error, eta median error, held-out PSNR) against total time per scene,
  each variant labelled, the Pareto front marked;
- ``ior.csv``: fitted eta per material of the paper's Table 1, for every sphere_ior variant (column ``name``);
- ``tables.md``: the sweep, the IOR table (sphere_ior base), augmentation on/off and sigma_ss fixed/free,
  each next to the paper's numbers, and model selection on/off with the final vertices per model.

A variant whose results folder holds a record of the same config is not run again: an interrupted sweep
resumes, and ``--report-only`` redraws the outputs from finished runs without running anything.
Every output is written under a temporary name and renamed.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from sellip.bench import sweep, sweep_plan
from sellip.bench.sweep_report import write_outputs

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenes", nargs="+", default=["demo", "sphere_ior"],
                        help="built-in scenes to sweep (sellip.capture.scenes.SCENES; default: demo sphere_ior)")
    parser.add_argument("--preset", choices=sorted(sweep_plan.PRESETS), default="quick",
                        help="base configuration and factor values (default: quick)")
    parser.add_argument("--out", type=Path, default=Path("results/bench/sweep"),
                        help="output folder; the runs go to OUT/work/PRESET (default: results/bench/sweep)")
    parser.add_argument("--cores", type=int, default=2, help="snakemake --cores of every run (default: 2)")
    parser.add_argument("--only", nargs="+", default=None, metavar="FACTOR",
                        help=f"sweep only these factors (the base always runs): {[f.name for f in sweep_plan.FACTORS]}")
    parser.add_argument("--repeat", type=int, default=2,
                        help="at most this many runs per variant, the last timed: a run that spent over 10 %% of "
                             "its CPU time compiling XLA kernels runs again (default 2; 1 times compilation too)")
    parser.add_argument("--force", action="store_true", help="run every variant again, even if finished before")
    parser.add_argument("--report-only", action="store_true",
                        help="run nothing: redraw the outputs from the variants finished before")


def main(args: argparse.Namespace) -> int:
    from sellip.capture.scenes import SCENES

    unknown = [s for s in args.scenes if s not in SCENES]
    if unknown:
        log.error("unknown scene(s) %s; expected some of %s", unknown, list(SCENES))
        return 1
    if args.cores < 1 or args.repeat < 1:
        log.error("--cores and --repeat must be at least 1")
        return 1
    workdir = args.out / "work" / args.preset
    started = time.perf_counter()
    try:
        if args.report_only:
            variants = sweep_plan.plan_variants(args.scenes, args.preset, args.only)
            records = []
            for variant in variants:
                path = workdir / "results" / variant.name / sweep.RECORD
                if not path.is_file():
                    raise sweep_plan.SweepError(f"{path} missing: {variant.name} has not run (drop --report-only)")
                records.append(json.loads(path.read_text()))
        else:
            variants, records = sweep.run_sweep(args.scenes, args.preset, workdir, cores=args.cores,
                                                only=args.only, repeat=args.repeat, force=args.force)
        written = write_outputs(variants, records, args.preset, args.out, workdir)
    except (sweep_plan.SweepError, ValueError) as exc:
        log.error("%s", exc)
        return 1
    log.info("wrote %s in %.0f s", ", ".join(str(p) for p in written.values()), time.perf_counter() - started)
    return 0
