"""How careful a calibration must be, on whole reconstructions (issue #39 item 7): ``sphere_ior`` shot by the
synthetic device of ``sellip synth-calibration``, one Snakemake run of the workflow per description of the device
(the truth with two noise seeds; the flash, the polarizer, fx and the colour matrix off; the description
``sellip calibrate`` measured on a synthetic calibration set). ``sellip.bench.calibration`` does the work.

    nice -n 10 python benchmarks/calibration_reconstruction.py [--workdir results/bench/calibration_reconstruction]
        [--views 36 --width 612 --height 512 --max-vertices 10000 --iterations 2] [--cores 2] [--rows 0 1 2]

Resumable (a finished row is read back). Prints and writes the markdown table (``WORKDIR/table.md``) and every
row's figures (``WORKDIR/rows.json``). About 4-5 min per row on 2 idle cores at the default size, 13 rows.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


def main() -> int:
    from sellip.bench import calibration

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path("results/bench/calibration_reconstruction"))
    parser.add_argument("--scene", default="sphere_ior")
    parser.add_argument("--views", type=int, default=36)
    parser.add_argument("--width", type=int, default=612)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--max-vertices", type=int, default=10000)
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--rows", type=int, nargs="*", help="run only these rows (indices of PERTURBATIONS)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    rows = calibration.PERTURBATIONS if not args.rows else tuple(calibration.PERTURBATIONS[k] for k in args.rows)
    done = calibration.run_sensitivity(args.workdir, args.scene, args.views, args.width, args.height, args.max_vertices,
                           args.iterations, args.cores, rows)
    print(calibration.sensitivity_markdown(done))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
