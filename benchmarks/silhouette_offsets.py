"""How far a run's photographs' silhouettes lie outside its model's, as the geometry update measures them.

    python benchmarks/silhouette_offsets.py RUN CAPTURE [--iterations N ...] [--views 8]

RUN is a workflow's results folder (results/<name>, with cameras.csv, hdr.zarr and iter/); CAPTURE its synthetic
capture (ground_truth/model.ply). Prints one row for the true model and one per fitted iteration given: the mean and
RMS offset (px, positive where the photograph's silhouette lies outside the model's) over the constraints of
``--views`` views spread evenly (:func:`sellip.bench.silhouettes.model_offsets`). The true model's offset is the
operator's own bias; a fitted iteration's is what pushes the surface. docs/geometry.md quotes it ("Dark patches").
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("capture", type=Path)
    parser.add_argument("--iterations", type=int, nargs="*", default=[], help="fitted iterations to measure too")
    parser.add_argument("--views", type=int, default=8)
    args = parser.parse_args(argv)
    from sellip.bench.silhouettes import model_offsets

    print("| model | views | constraints | offset mean (px) | offset RMS (px) |\n|---|---|---|---|---|")
    for iteration in [None, *args.iterations]:
        row = model_offsets(args.run, args.capture, iteration, args.views)
        name = "truth" if iteration is None else f"iteration {iteration}, fitted"
        print(f"| {name} | {len(row['views'])} | {row['constraints']} | {row['offset_px_mean']:+.3f} | "
              f"{row['offset_px_rms']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
