"""``sellip synth``: generate a synthetic capture folder (docs/design.md §3) with ground truth.

    sellip synth --scene demo --out captures/demo [--views N --width W --height H --seed S] [--noise-scale K]
                 [--renderer sellip|mitsuba] [--mitsuba-variant V] [--device device.yaml] [--noise-seed S]

For each view of a handheld orbit (:func:`sellip.capture.scenes.handheld_orbit`) the
scene is rendered once with the full pBRDF (:mod:`sellip.model.render`) under the
rig's polarized flash, then exposed at each flash level through the sensor
model (:mod:`sellip.capture.sensor`) with independent noise. Written: capture.yaml,
frames.csv, poses.csv, raw/ frames, ground_truth/model.ply. The same seed
gives byte-identical files; the folder appears only when complete. An existing --out that is not a synthetic capture
(its capture.yaml has no ``synthetic`` section) is never replaced without --force. ``--renderer mitsuba`` renders the
views with Mitsuba 3's pplastic instead (:mod:`sellip.capture.mitsuba_capture`; the ``test`` extra), the rest
unchanged: an independent renderer for the validation set (docs/synthetic.md). ``--device`` shoots the frames
with a described device (device.yaml, or ``sellip synth-calibration``'s truth.yaml): its sensor, lens, colour
matrix and flash, as the calibration set of that device was (docs/calibration.md, "The synthetic example").
The defaults of ``--scene``, ``--renderer``, ``--views``, ``--width``, ``--height``, ``--seed``, ``--noise-scale`` and
``--noise-seed`` are the declarations of :class:`sellip.capture.synthetic.DemoSettings` (config ``demo``; rule
``synth_capture`` passes the keys the config sets).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.capture.scenes import SCENES
from sellip.capture.synthetic import RENDERERS, DemoSettings, synthesize_capture
from sellip.capture.writer import RAW_FORMATS

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", choices=SCENES, default=DemoSettings.scene,
                        help="procedural scene (default: %(default)s)")
    parser.add_argument("--out", required=True, type=Path, help="capture folder to write")
    parser.add_argument("--views", type=int, default=DemoSettings.views, help="number of views (default: %(default)s)")
    parser.add_argument("--width", type=int, default=DemoSettings.width,
                        help="raw mosaic width, a multiple of 4 (default: %(default)s)")
    parser.add_argument("--height", type=int, default=DemoSettings.height,
                        help="raw mosaic height, a multiple of 4 (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=DemoSettings.seed,
                        help="seed for cameras and noise (default: %(default)s)")
    parser.add_argument("--supersample", type=int, default=2, help="s: s x s samples per pixel (default: 2)")
    parser.add_argument("--raw-format", choices=sorted(RAW_FORMATS), default="dng",
                        help="raw frame files (default: dng)")
    parser.add_argument("--distortion", type=float, nargs=5, metavar=("K1", "K2", "P1", "P2", "K3"),
                        help="OpenCV lens distortion to simulate (default: none)")
    parser.add_argument("--noise-scale", type=float, default=DemoSettings.noise_scale,
                        help="sensor noise standard deviations x this at the same signal, as with 1/k^2 of the "
                             "photons at k^2 the gain (default: %(default)s, the real device)")
    parser.add_argument("--renderer", choices=RENDERERS, default=DemoSettings.renderer,
                        help="who renders the views: sellip's pBRDF or Mitsuba 3's pplastic (default: %(default)s)")
    parser.add_argument("--mitsuba-variant", default=None,
                        help="Mitsuba variant (default: llvm_ad_mono_polarized when a new enough libLLVM is found, "
                             "else scalar_spectral_polarized)")
    parser.add_argument("--device", type=Path, default=None,
                        help="device.yaml (or synth-calibration's truth.yaml) whose sensor, lens and flash shoot the "
                             "frames; its sensor size is the capture's (default: the built-in device at --width "
                             "x --height)")
    parser.add_argument("--noise-seed", type=int, default=DemoSettings.noise_seed,
                        help="seed of the sensor noise alone (default: --seed, which also sets the orbit)")
    parser.add_argument("--force", action="store_true",
                        help="replace --out even when it is not a synthetic capture (it is replaced as a whole)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    from sellip.capture.synthetic import is_synthetic_folder
    from sellip.jobs import WouldReplaceError, refuse_to_replace_folder

    try:  # before anything is rendered
        refuse_to_replace_folder(args.out, "sellip synth", is_synthetic_folder, force=args.force)
    except WouldReplaceError as exc:
        raise SystemExit(f"sellip synth: {exc}") from None
    if args.width % 4 or args.height % 4 or args.width < 24 or args.height < 24:
        raise SystemExit(f"--width and --height must be multiples of 4 and at least 24, "
                         f"got {args.width}x{args.height}")
    if args.views < 1 or args.supersample < 1:
        raise SystemExit("--views and --supersample must be at least 1")
    if args.renderer == "mitsuba":
        from sellip.capture.mitsuba_capture import mitsuba_available

        if not mitsuba_available():
            raise SystemExit("--renderer mitsuba needs the mitsuba package (pip install 'sellip[test]')")
    if not args.noise_scale > 0:
        raise SystemExit(f"--noise-scale must be positive, got {args.noise_scale}")
    device = None
    if args.device is not None:
        from sellip.yaml_files import DuplicateKeyError, load_yaml_file

        try:
            document = load_yaml_file(args.device) or {}
        except DuplicateKeyError as exc:
            raise SystemExit(f"{args.device}: {exc}") from None
        device = document.get("device", document)  # truth.yaml keeps the device under "device"
        missing = [key for key in ("sensor", "camera", "light") if not isinstance(device.get(key), dict)]
        if missing:
            raise SystemExit(f"{args.device}: no {', '.join(missing)} section(s); run sellip calibrate first")
        args.width, args.height = int(device["sensor"]["width"]), int(device["sensor"]["height"])
    synthesize_capture(args.scene, args.out, views=args.views, width=args.width, height=args.height, seed=args.seed,
                       supersample=args.supersample, raw_format=args.raw_format, distortion=args.distortion,
                       progress=not args.no_progress, noise_scale=args.noise_scale, renderer=args.renderer,
                       mitsuba_variant=args.mitsuba_variant, device=device, noise_seed=args.noise_seed,
                       force=args.force)
    return 0
