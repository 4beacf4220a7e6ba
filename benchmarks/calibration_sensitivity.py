"""How careful a calibration must be, the proxy (the whole-workflow table is benchmarks/calibration_reconstruction.py):
the accuracy ladder's ``sensor`` rung (the true mesh observed in the
capture's HDR images, one observe + fit pass, sellip.ladder.fit_true_mesh) with the device description
perturbed: the flash position off, the flash polarizer angle off, fx off.

    python benchmarks/calibration_sensitivity.py [--scene sphere_ior --views 24 --width 612 --height 512]
        [--workdir results/bench/calibration_sensitivity] [--cores 2]

The frames are the same in every row; only capture.yaml changes (fx re-runs ingest, whose undistortion and
output intrinsics use it). Prints a markdown table (eta per material: mean and worst error of the per-material
medians; eta per vertex median; normal error median) and writes sensitivity.json in the workdir. Resumable.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

PERTURBATIONS = {
    "true description": {},
    "flash 2 mm off (x)": {"flash_mm": (2.0, 0.0, 0.0)},
    "flash 5 mm off (x)": {"flash_mm": (5.0, 0.0, 0.0)},
    "flash 10 mm off (x)": {"flash_mm": (10.0, 0.0, 0.0)},
    "flash 5 mm off (z)": {"flash_mm": (0.0, 0.0, 5.0)},
    "polarizer 1 deg off": {"polarizer_deg": 1.0},
    "polarizer 3 deg off": {"polarizer_deg": 3.0},
    "fx 0.5 % off": {"fx_rel": 0.005},
    "fx 2 % off": {"fx_rel": 0.02},
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="sphere_ior")
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--width", type=int, default=612)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--workdir", type=Path, default=Path("results/bench/calibration_sensitivity"))
    parser.add_argument("--cores", type=int, default=2)
    args = parser.parse_args()

    from sellip.bench.calibration import perturbed_capture
    from sellip.bench.ladder import fit_true_mesh
    from sellip.capture.hdr import merge_capture
    from sellip.capture.linearize import linearize_capture
    from sellip.capture.synthetic import synthesize_capture
    from sellip.fit.observe import ObserveSettings

    work = (args.workdir / f"{args.scene}_{args.views}v_{args.width}x{args.height}").resolve()
    capture = work / "capture"
    if not (capture / "capture.yaml").is_file():
        synthesize_capture(args.scene, capture, views=args.views, width=args.width, height=args.height, progress=False)
    observe = ObserveSettings(edge_margin=0.0, threads=args.cores)  # every sample, as measured in docs
    cache = str(work / "jax_cache")
    results_path = work / "sensitivity.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    for k, (label, change) in enumerate(PERTURBATIONS.items()):
        if label in results:
            continue
        folder = perturbed_capture(capture, work / f"case{k}" / "capture", change)
        hdr_owner = folder if "fx_rel" in change else capture
        hdr = hdr_owner.parent / "hdr.zarr"
        if not hdr.exists():
            linearize_capture(hdr_owner, hdr_owner.parent / "linear.zarr", threads=args.cores)
            merge_capture(hdr_owner.parent / "linear.zarr", hdr, threads=args.cores)
        results[label] = fit_true_mesh(folder, hdr, work / f"case{k}" / "fit", observe, cache)
        results_path.write_text(json.dumps(results, indent=2))
        print(label, json.dumps(results[label]), flush=True)
    print("| description | eta per material: mean / worst error % | eta per vertex median % | normal median deg |")
    print("|---|---|---|---|")
    for label, r in results.items():
        per = r["eta_per_material"] or {}
        mean, worst = per.get("mean_error_pct", float("nan")), per.get("max_error_pct", float("nan"))
        print(f"| {label} | {mean:.2f} / {worst:.2f} | {r['eta_vertex_median_pct']:.2f} "
              f"| {r['normal_median_deg']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
