"""The stability suite's multi-material scenes over sensor-noise seeds (issue #49; docs/reproducibility.md).

    python benchmarks/suite_seeds.py --out results/bench/suite_seeds [--cases pplastic_set mitsuba_set] \
        [--seeds 0 1 ... 9] [--cores 2] [--json OUT.json]

Per seed, ``sellip bench-stability --noise-seed SEED`` on the cases (``OUT/noise<seed>/runs/<case>``: the case's
capture with only its sensor noise drawn again; a case already run there is kept). Then, per case, how often the
decision (the number of materials and the lobe model per true material) came out the same, K at every iteration,
the materials flagged fragile, the eta error per true material over the seeds and how many eta intervals held the
truth (:func:`sellip.bench.noise_seeds.decision_agreement`). Issue #49's target: the same decision in at least 9 of
10 seeds, or the material flagged fragile in materials.csv. Each run costs what its case costs in the suite
(200-550 CPU-s on 2 cores).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    import argparse

    from sellip.bench import stability
    from sellip.bench.noise_seeds import decision_agreement, with_figures

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="work folder (one suite folder per seed)")
    parser.add_argument("--cases", nargs="+", default=["pplastic_set", "mitsuba_set"], choices=stability.CASE_NAMES,
                        metavar="CASE", help="suite cases (default: the two four-material scenes)")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)), help="sensor-noise seeds")
    parser.add_argument("--cores", type=int, default=2, help="Snakemake --cores of each run")
    parser.add_argument("--json", type=Path, default=None, help="write every run's row and the agreement here")
    args = parser.parse_args(argv)

    by_name = {case.name: case for case in stability.CASES}
    cases = [by_name[name] for name in dict.fromkeys(args.cases)]
    for seed in args.seeds:
        stability.run_suite(cases, args.out / f"noise{seed}", ROOT / "Snakefile", cores=args.cores, keep=True,
                            noise_seed=seed)
    report = {}
    for case in cases:
        rows = []
        for seed in args.seeds:
            workdir = args.out / f"noise{seed}" / "runs" / case.name
            recorded = json.loads((workdir / "row.json").read_text())
            row = {"noise_seed": seed, "wall_s": recorded.get("wall_s")}
            if recorded.get("error"):
                row["error"] = recorded["error"]
            rows.append(with_figures(row, workdir / "results" / case.name))
        report[case.name] = {"rows": rows, "agreement": decision_agreement(rows)}
        print(f"{case.name}: {json.dumps(report[case.name]['agreement'], indent=1)}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
