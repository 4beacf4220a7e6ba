"""The demo run whole over sensor-noise seeds and 1 or 2 cores (issue #49; docs/reproducibility.md).

    python benchmarks/demo_seeds.py --out results/bench/demo_seeds [--seeds 0 1 ... 9] [--cores 1 2] \
        [--json summary.json]

Per noise seed the demo capture is made once (``OUT/captures/noise<seed>``: the demo's scene, orbit and settings,
only the sensor noise's seed changed), then the demo's workflow runs on it once per core count
(``OUT/noise<seed>_cores<c>``): one core pinned to one CPU (two such runs side by side, one per CPU), two cores
alone. A run with a ``row.json`` is kept (the command resumes). Prints one line per run (materials at each
iteration, eta error per true material, normals, PSNR, Chamfer, fragile materials, wall time) and each target of
issue #49 (:data:`sellip.bench.noise_seeds.TARGETS`) over the runs; ``--json`` writes the rows and the summary.
About 6 min a run with two cores on an idle 2-core machine, 8-10 min a pinned one-core run.
"""

from __future__ import annotations

import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from queue import Queue

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="work folder (captures and one folder per run)")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)), help="sensor-noise seeds")
    parser.add_argument("--cores", type=int, nargs="+", default=[1, 2], choices=[1, 2], help="core counts")
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    parser.add_argument("--json", type=Path, default=None, help="write the rows and the summary here")
    args = parser.parse_args(argv)

    from sellip.bench.noise_seeds import run_name, run_seed, seed_captures, seed_summary

    captures = seed_captures(args.out, args.seeds)
    snakefile = ROOT / "Snakefile"
    rows = []

    def report(row):
        rows.append(row)
        if "error" in row:
            print(f"{run_name(row['noise_seed'], row['cores'])}: FAILED {row['error']}", flush=True)
            return
        eta = " / ".join(f"{row['eta_error_pct'][m]:.3f}" for m in sorted(row["eta_error_pct"], key=int))
        print(f"{run_name(row['noise_seed'], row['cores'])}: K {row['k']}, {row['materials']} materials, "
              f"eta {eta} %, normals {row['normal_median_deg']:.4f} deg, {row['psnr_held_out_db']:.2f} dB, "
              f"Chamfer {row['chamfer_mm']:.4f} mm, fragile {row['fragile'] or '-'}, {row['wall_s']:.0f} s",
              flush=True)

    # One-core runs two at a time, each pinned to its own CPU; then the two-core runs one at a time.
    if 1 in args.cores:
        cpus: Queue = Queue()
        for cpu in (0, 1):
            cpus.put(cpu)

        def one_core(seed):
            cpu = cpus.get()
            try:
                return run_seed(args.out, captures[seed], seed, 1, snakefile, cpu=cpu, timeout_s=args.timeout)
            finally:
                cpus.put(cpu)

        with ThreadPoolExecutor(max_workers=2) as pool:
            for row in pool.map(one_core, args.seeds):
                report(row)
    if 2 in args.cores:
        for seed in args.seeds:
            report(run_seed(args.out, captures[seed], seed, 2, snakefile, timeout_s=args.timeout))
    summary = seed_summary(rows)
    print(json.dumps(summary, indent=1))
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))
    return 0 if not summary["failed"] else 1


if __name__ == "__main__":
    sys.exit(main())
