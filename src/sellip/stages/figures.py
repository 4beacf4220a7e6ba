"""``sellip figures``: the documented figures regenerated and compared with the documents (issue #49 item 6).

    sellip figures check [--only RUN ...] [--size small|all] [--results results] [--record FILE]
    sellip figures run   [--only RUN ...] [--size small|all] [--record FILE]

``check`` reads the finished runs under ``--results`` and prints, per registered figure
(:data:`sellip.bench.figures.FIGURES`), the value its document's table shows, the measured one, the tolerance, the
difference and PASS / FAIL / MISSING (no finished run: the line says which command makes it). ``run`` first runs
each selected run's recorded command from the repository root (they write under ``results/``), then checks. The
runs: ``demo`` (small: ``make demo``, minutes on 2 cores); ``sphere_ior_scale``, ``sphere_ior_mitsuba``,
``cow_painted_sellip`` and ``cow_painted_mitsuba`` (large: 19-58 min each). ``--record`` writes the comparison as
JSON with the commit, package versions, machine and seeds.
Exit status 0 when every figure passed, 1 otherwise (a figure outside its tolerance, a missing run, a document row
that no longer parses, a command of ``run`` that failed).
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import subprocess
import sys
from pathlib import Path

from sellip.bench import figures
from sellip.jobs import write_text

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=["check", "run"],
                        help="check: compare finished runs with the documents; run: run the commands, then check")
    parser.add_argument("--only", nargs="+", metavar="RUN", default=None,
                        help=f"these runs only (of: {' '.join(r.name for r in figures.RUNS)})")
    parser.add_argument("--size", choices=["small", "all"], default="all",
                        help="small: the runs a 2-core machine does in minutes (the demo); all (default)")
    parser.add_argument("--results", type=Path, default=Path("results"),
                        help="the results root the runs wrote under (default: results; `run` always uses results)")
    parser.add_argument("--root", type=Path, default=Path("."),
                        help="the repository root: its README.md and docs (default: the current directory)")
    parser.add_argument("--record", type=Path, default=None,
                        help="also write the comparison, commit, versions, machine and seeds to this JSON file")


def _run_command(run: figures.Run, root: Path) -> int:
    argv = shlex.split(run.command)
    if argv[0] == "python":
        argv[0] = sys.executable
    log.info("%s: running `%s` (about %d min on 2 cores)", run.name, run.command, run.minutes)
    return subprocess.run(argv, cwd=root).returncode


def main(args: argparse.Namespace) -> int:
    root = args.root.resolve()
    try:
        runs = figures.select(args.only, args.size)
    except figures.FiguresError as error:
        log.error("%s", error)
        return 1
    if not runs:
        log.error("no registered run is selected by --only %s --size %s", args.only, args.size)
        return 1
    results, failed_commands = args.results, []
    if args.action == "run":
        results = root / "results"
        for run in runs:
            status = _run_command(run, root)
            if status != 0:
                failed_commands.append(run.command)
                log.error("%s: `%s` failed with exit status %d; what it left is checked, and the check fails",
                          run.name, run.command, status)
    problems = figures.document_problems(root)
    for problem in problems:
        log.error("%s", problem)
    if problems:
        return 1
    comparisons = figures.check(root, results, runs)
    print("\n".join(figures.report_lines(comparisons)))
    if args.record is not None:
        write_text(json.dumps(figures.record(comparisons, root, runs), indent=2), args.record)
    failed = [c for c in comparisons if c.status != "PASS"]
    if failed_commands:
        log.error("these commands failed: %s", "; ".join(failed_commands))
        return 1
    if failed:
        log.error("%d of %d documented figures were not reproduced within their tolerance: %s", len(failed),
                  len(comparisons), ", ".join(c.figure.name for c in failed))
        return 1
    log.info("all %d documented figures of %s reproduced within their tolerance", len(comparisons),
             ", ".join(run.name for run in runs))
    return 0
