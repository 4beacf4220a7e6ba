"""Throughput of ingest (linearize + merge) at the full IMX250MYR sensor size, 2448x2048.

    python benchmarks/bench_ingest.py [--views 4] [--threads 2] [--cores 2] [--workdir DIR]

Writes a synthetic capture of ``views`` x 3 flash levels as DNG files (a
smooth polarized scene with a highlight that saturates at flash 1/4, sensor
noise), then times, on ``--cores`` CPU cores (process affinity):

kernels   :func:`sellip.capture.ingest.process_frame` + :func:`sellip.capture.ingest.merge_hdr` in memory, one thread
stages    ``sellip linearize`` + ``sellip merge-hdr`` as the workflow runs them (DNG decoding, zarr
          I/O, ``--threads`` threads), frames per second of wall time over both stages

and prints one line per measurement, plus a JSON summary on the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sellip.capture import ingest
from sellip.capture.hdr import merge_capture
from sellip.capture.linearize import linearize_capture
from sellip.capture.reader import read_capture, read_raw_frame
from sellip.capture.sensor import SensorModel, camera_rgb_from_srgb, mosaic_sample
from sellip.capture.writer import write_capture

WIDTH, HEIGHT = 2448, 2048
LEVELS = (1 / 4, 1 / 8, 1 / 16)


def synthetic_raw(sensor: SensorModel, level: float, rng: np.random.Generator) -> np.ndarray:
    """A (H, W) uint16 mosaic: smooth polarized scene, highlight saturating at 1/4, shot + read noise.

    Built row band by row band to keep memory low (the analyzer images are float64 (H, W, 4, 3)).
    """
    raw = np.empty((sensor.height, sensor.width), np.uint16)
    band = 256
    x = np.arange(sensor.width) / sensor.width
    for top in range(0, sensor.height, band):
        y = (np.arange(top, min(top + band, sensor.height)) / sensor.height)[:, None]
        s0 = 0.2 + 0.5 * x[None, :] * (1 - y) + 2.5 * np.exp(-((x - 0.6) ** 2 + (y - 0.4) ** 2) / 0.005)
        angle = np.pi * (x + y)
        analyzers = np.stack([(s0 + 0.3 * s0 * np.cos(2 * (angle - np.radians(t)))) / 2 for t in (0, 45, 90, 135)],
                             axis=-1)[..., None] * np.array([0.8, 0.7, 0.6])
        signal = mosaic_sample(camera_rgb_from_srgb(analyzers, sensor.color_matrix), sensor.layout)
        signal = np.clip(signal, 0, None) * 3000 * level * sensor.gain_e_per_dn
        electrons = rng.poisson(np.minimum(signal, 1e5)) + rng.normal(0, sensor.read_noise_e, signal.shape)
        dn = np.rint(electrons / sensor.gain_e_per_dn + sensor.black_level)
        raw[top:top + band] = np.clip(dn, 0, sensor.white_level)
    return raw


def make_capture(path: Path, views: int) -> Path:
    sensor = SensorModel(width=WIDTH, height=HEIGHT)
    camera = {"fx": 7246.0, "fy": 7246.0, "cx": (WIDTH - 1) / 2, "cy": (HEIGHT - 1) / 2,
              "distortion": [-0.08, 0.02, 0.0, 0.0, 0.0], "color_matrix": [list(r) for r in sensor.color_matrix]}
    config = {"sensor": sensor.capture_sensor(), "camera": camera,
              "light": {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0}, "scene": {"distance_m": 0.9}}
    rng = np.random.default_rng(0)
    rows, raws = [], {}
    for v in range(views):
        for f, level in enumerate(LEVELS):
            frame_id = f"v{v:03d}_f{f}"
            raws[frame_id] = synthetic_raw(sensor, level, rng)
            rows.append({"frame_id": frame_id, "view_id": f"v{v:03d}", "file": "", "flash_level": level,
                         "exposure_s": 0.005})
    return write_capture(path, config, pd.DataFrame(rows), raws, raw_format="dng")


def bench_kernels(capture_path: Path, repeats: int) -> dict:
    """Seconds per frame of process_frame and merge_hdr (one thread, frames already decoded)."""
    capture = read_capture(capture_path)
    started = time.perf_counter()
    plan = ingest.make_ingest_plan(capture.sensor, capture.config["camera"], capture.layout)
    plan_s = time.perf_counter() - started
    view = capture.frames_of(capture.view_ids[0])
    raws = [read_raw_frame(capture, row) for _, row in view.iterrows()]
    gains = (view["flash_level"] * view["exposure_s"]).to_numpy()
    process, merge = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        frames = [ingest.process_frame(raw, plan) for raw in raws]
        process.append((time.perf_counter() - started) / len(raws))
        started = time.perf_counter()
        ingest.merge_hdr(frames, gains)
        merge.append((time.perf_counter() - started) / len(raws))
    return {"plan_s": plan_s, "process_frame_s": min(process), "merge_per_frame_s": min(merge)}


def bench_stages(capture_path: Path, workdir: Path, threads: int) -> dict:
    frames = len(read_capture(capture_path).frames)
    started = time.perf_counter()
    linear = linearize_capture(capture_path, workdir / "linear.zarr", threads=threads)
    linearize_s = time.perf_counter() - started
    started = time.perf_counter()
    merge_capture(linear, workdir / "hdr.zarr", threads=threads)
    merge_s = time.perf_counter() - started
    return {"frames": frames, "linearize_s": linearize_s, "merge_s": merge_s,
            "frames_per_s": frames / (linearize_s + merge_s)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=4, help="views of 3 frames each (default: 4)")
    parser.add_argument("--threads", type=int, default=2, help="threads of the stages (default: 2)")
    parser.add_argument("--cores", type=int, default=2, help="CPU cores the process may use (default: 2)")
    parser.add_argument("--repeats", type=int, default=3, help="repeats of the kernel timing (default: 3)")
    parser.add_argument("--workdir", type=Path, help="where to write the capture and stores (default: a temp dir)")
    args = parser.parse_args()
    available = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, available[: args.cores])
    cores = len(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory(dir=args.workdir) as tmp:
        tmp = Path(tmp)
        started = time.perf_counter()
        capture = make_capture(tmp / "capture", args.views)
        print(f"capture: {args.views * len(LEVELS)} DNG frames {WIDTH}x{HEIGHT} "
              f"in {time.perf_counter() - started:.1f} s")
        kernels = bench_kernels(capture, args.repeats)
        print(f"kernels (1 thread): plan {kernels['plan_s']:.2f} s once; process_frame "
              f"{kernels['process_frame_s']:.3f} s/frame; merge {kernels['merge_per_frame_s']:.3f} s/frame; "
              f"{1 / (kernels['process_frame_s'] + kernels['merge_per_frame_s']):.2f} frames/s")
        stages = bench_stages(capture, tmp, args.threads)
        print(f"stages ({args.threads} threads, {cores} cores): linearize {stages['linearize_s']:.1f} s + merge "
              f"{stages['merge_s']:.1f} s for {stages['frames']} frames: {stages['frames_per_s']:.2f} frames/s")
    print(json.dumps({"width": WIDTH, "height": HEIGHT, "cores": cores, "threads": args.threads, **kernels, **stages}))


if __name__ == "__main__":
    main()
