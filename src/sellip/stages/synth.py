"""``sellip synth``: generate a synthetic capture folder (DESIGN §3) with ground truth.

    sellip synth --scene demo --out captures/demo [--views N --width W --height H --seed S] [--noise-scale K]

For each view of a handheld orbit (:func:`sellip.capture.scenes.handheld_orbit`) the
scene is rendered once with the full pBRDF (:mod:`sellip.model.render`) under the
rig's polarized flash, then exposed at each flash level through the sensor
model (:mod:`sellip.capture.sensor`) with independent noise. Written: capture.yaml,
frames.csv, poses.csv, raw/ frames, ground_truth/model.ply. The same seed
gives byte-identical files; the folder appears only when complete.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from sellip.capture.files import GROUND_TRUTH_MESH
from sellip.capture.scenes import SCENES, build_scene, handheld_orbit
from sellip.capture.sensor import SensorModel, simulate_raw
from sellip.capture.writer import RAW_FORMATS, CaptureWriter
from sellip.model.ply import write_param_mesh
from sellip.model.render import Renderer, flash_light

log = logging.getLogger(__name__)

FLASH_LEVELS = (1 / 4, 1 / 8, 1 / 16)
"""Relative flash power of the frames of each view (the paper's bracket)."""

FLASH_POSITION_CAM = (0.0, 0.05, 0.0)
"""The flash 5 cm from the lens, below it (OpenCV y is down): capture.yaml light.position_m."""

EXPOSURE_S = 0.005
"""Nominal shutter time written to frames.csv; the flash dominates, so it does not scale the signal."""


def synthesize_capture(scene_name: str, out: str | Path, views: int = 36, width: int = 612, height: int = 512,
                       seed: int = 0, supersample: int = 2, raw_format: str = "dng", distortion=None,
                       flash_levels=FLASH_LEVELS, progress: bool = True, noise_scale: float = 1.0) -> Path:
    """Render and write a synthetic capture of ``scene_name`` to ``out``; returns the folder.

    width, height: raw mosaic size (multiples of 4); distortion: OpenCV (k1, k2, p1, p2, k3) or None;
    noise_scale: sensor noise standard deviations x this at the same signal
    (:meth:`sellip.capture.sensor.SensorModel.with_noise_scale`; 1 is the real device).
    """
    from tqdm import tqdm

    started = time.perf_counter()
    scene = build_scene(scene_name)
    cameras = handheld_orbit(views, width, height, np.random.default_rng([seed, 1]),
                             distance_m=scene.distance_m, elevation_deg=scene.elevation_deg,
                             distortion=distortion)
    sensor = SensorModel(width=width, height=height).with_noise_scale(noise_scale)
    k = cameras[0].intrinsics
    config = {
        "sensor": sensor.capture_sensor(),
        "camera": {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
                   "distortion": [float(c) for c in (distortion if distortion is not None else [0.0] * 5)],
                   "color_matrix": [list(map(float, row)) for row in sensor.color_matrix]},
        "light": {"position_m": list(FLASH_POSITION_CAM), "polarizer_deg": 0},
        "scene": {"distance_m": float(np.mean(scene.distance_m))},
        "synthetic": {"scene": scene_name, "seed": int(seed), "views": int(views), "supersample": int(supersample),
                      "flash_power_dn": float(scene.flash_power), "gain_e_per_dn": sensor.gain_e_per_dn,
                      "read_noise_e": sensor.read_noise_e, "noise_scale": float(noise_scale),
                      "ground_truth": GROUND_TRUTH_MESH},
    }
    renderer = Renderer(scene.mesh)
    saturated = []
    with CaptureWriter(out, config, raw_format=raw_format) as writer:
        for index, camera in enumerate(tqdm(cameras, desc=f"synth {scene_name}", unit="view", disable=not progress)):
            view_id = f"v{index:03d}"
            light = flash_light(camera, FLASH_POSITION_CAM, polarizer_deg=0.0)
            analyzers = renderer.render(camera, light, supersample=supersample).analyzers
            for level_index, level in enumerate(flash_levels):
                rng = np.random.default_rng([seed, 2, index, level_index])
                raw = simulate_raw(analyzers, sensor, scene.flash_power * level, rng)
                saturated.append(float(np.mean(raw >= sensor.white_level)))
                writer.add_frame(f"{view_id}_f{level_index}", view_id, raw, flash_level=level, exposure_s=EXPOSURE_S)
            writer.add_pose(view_id, camera.rotation, camera.translation)
        write_param_mesh(writer.path_in_capture(GROUND_TRUTH_MESH), scene.mesh)
        path = writer.finish()
    strongest = np.asarray(saturated).reshape(views, len(flash_levels))[:, 0]
    log.info("wrote %s: %d views x %d frames at %dx%d in %.1f s; views with saturated pixels at flash %.3g: %d",
             path, views, len(flash_levels), width, height, time.perf_counter() - started, flash_levels[0],
             int(np.sum(strongest > 0)))
    return path


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", choices=SCENES, default="demo", help="procedural scene (default: demo)")
    parser.add_argument("--out", required=True, type=Path, help="capture folder to write")
    parser.add_argument("--views", type=int, default=36, help="number of views (default: 36)")
    parser.add_argument("--width", type=int, default=612, help="raw mosaic width, a multiple of 4 (default: 612)")
    parser.add_argument("--height", type=int, default=512, help="raw mosaic height, a multiple of 4 (default: 512)")
    parser.add_argument("--seed", type=int, default=0, help="seed for cameras and noise (default: 0)")
    parser.add_argument("--supersample", type=int, default=2, help="s: s x s samples per pixel (default: 2)")
    parser.add_argument("--raw-format", choices=sorted(RAW_FORMATS), default="dng",
                        help="raw frame files (default: dng)")
    parser.add_argument("--distortion", type=float, nargs=5, metavar=("K1", "K2", "P1", "P2", "K3"),
                        help="OpenCV lens distortion to simulate (default: none)")
    parser.add_argument("--noise-scale", type=float, default=1.0,
                        help="sensor noise standard deviations x this at the same signal, as with 1/k^2 of the "
                             "photons at k^2 the gain (default: 1, the real device)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    if args.width % 4 or args.height % 4 or args.width < 24 or args.height < 24:
        raise SystemExit(f"--width and --height must be multiples of 4 and at least 24, "
                         f"got {args.width}x{args.height}")
    if args.views < 1 or args.supersample < 1:
        raise SystemExit("--views and --supersample must be at least 1")
    if not args.noise_scale > 0:
        raise SystemExit(f"--noise-scale must be positive, got {args.noise_scale}")
    synthesize_capture(args.scene, args.out, views=args.views, width=args.width, height=args.height, seed=args.seed,
                       supersample=args.supersample, raw_format=args.raw_format, distortion=args.distortion,
                       progress=not args.no_progress, noise_scale=args.noise_scale)
    return 0
