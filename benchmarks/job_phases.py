"""Where the jobs of a workflow run spent their time (docs/speed.md): one row per rule.

    python benchmarks/job_phases.py results/demo [--json out.json]

Reads the Snakemake benchmark files (wall time per job) and the phases line that ``sellip`` writes at
the end of every job's log (:mod:`sellip.timing`), and prints :func:`sellip.timing.phase_table`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results/NAME of a workflow run")
    parser.add_argument("--json", type=Path, default=None, help="also write the per-rule sums here")
    args = parser.parse_args(argv)
    from sellip.report.figures_of_merit import stage_timings
    from sellip.timing import phase_table

    if not (args.results / "benchmarks").is_dir():
        parser.error(f"{args.results / 'benchmarks'} does not exist (not a workflow run's results folder)")
    timings = stage_timings(args.results / "benchmarks", args.results)
    print(phase_table(timings["rules"]))
    if args.json:
        args.json.write_text(json.dumps(timings, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
