"""Silhouettes of a run's photographs against the true ones, under the default cut and alternatives.

    python benchmarks/silhouette_iou.py RUN CAPTURE [RUN CAPTURE ...]
    python benchmarks/silhouette_iou.py --changed RUN [RUN ...]

RUN is a workflow's results folder (results/<name>, with hdr.zarr); CAPTURE its synthetic capture (poses.csv,
ground_truth/model.ply). Prints per pair and cut the IoU (median and worst over the views) and the median shares
of the true area missed and added (:mod:`sellip.bench.silhouettes`). With ``--changed``, no truth: per RUN the
views and pixels whose silhouette the default cut changes against the view's level alone. docs/geometry.md and
docs/benchmarks.md quote it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

CUTS = {"default": {}, "view's level alone (local_fraction 0)": {"local_fraction": 0.0},
        "level at 1 % (threshold 0.01, local_fraction 0)": {"threshold": 0.01, "local_fraction": 0.0}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pairs", nargs="+", type=Path, help="RUN CAPTURE pairs (RUNs with --changed)")
    parser.add_argument("--changed", action="store_true", help="only what the default cut changes, per RUN")
    args = parser.parse_args(argv)
    from sellip.bench.silhouettes import cut_difference, silhouette_agreement

    if args.changed:
        print("| run | views changed | pixels added | pixels removed | object pixels |\n|---|---|---|---|---|")
        for run in args.pairs:
            row = cut_difference(run, {}, CUTS["view's level alone (local_fraction 0)"])
            print(f"| {run.name} | {row['views_changed']} of {row['views']} | {row['added']} | {row['removed']} | "
                  f"{row['object']} |")
        return 0
    if len(args.pairs) % 2:
        parser.error("give RUN CAPTURE pairs")

    print("| run | cut | IoU median | IoU worst | missed median | extra median |\n|---|---|---|---|---|---|")
    for run, capture in zip(args.pairs[::2], args.pairs[1::2]):
        for cut, row in silhouette_agreement(run, capture, CUTS).items():
            print(f"| {run.name} | {cut} | {row['iou_median']:.3f} | {row['iou_worst']:.3f} | "
                  f"{row['missed_median']:.4f} | {row['extra_median']:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
