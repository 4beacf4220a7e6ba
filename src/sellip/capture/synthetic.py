"""Synthetic captures with known truth (docs/design.md §6; ``sellip synth``): a procedural scene rendered with
the full pBRDF under the polarized flash on a handheld orbit, through the sensor simulator (mosaic, noise,
quantization) into raw files, frames.csv, capture.yaml, poses.csv and the ground-truth model
(:func:`synthesize_capture`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from sellip.capture.files import CAPTURE_YAML, FRAMES_CSV, GROUND_TRUTH_MESH, POSES_CSV, RAW_DIR
from sellip.capture.scenes import SCENES, build_scene, handheld_orbit
from sellip.capture.sensor import SensorModel, sensor_from_device, simulate_raw
from sellip.capture.writer import CaptureWriter
from sellip.jobs import refuse_to_replace_folder
from sellip.model.ply import write_param_mesh
from sellip.model.render import Renderer, flash_light
from sellip.settings import setting

log = logging.getLogger(__name__)


FLASH_LEVELS = (1 / 4, 1 / 8, 1 / 16)
"""Relative flash power of the frames of each view (the paper's bracket)."""



FLASH_POSITION_CAM = (0.0, 0.05, 0.0)
"""The flash 5 cm from the lens, below it (OpenCV y is down): capture.yaml light.position_m."""



RENDERERS = ("sellip", "mitsuba")
"""Who renders a synthetic capture: sellip's pBRDF renderer, or Mitsuba 3's pplastic (docs/synthetic.md)."""



@dataclasses.dataclass(frozen=True)
class DemoSettings:
    """Settings of a synthetic capture of the workflow (config section ``demo``, rule ``synth_capture``; each declared
    once here, :mod:`sellip.settings`): ``sellip synth``'s options default to them. ``scene`` is also read by the
    workflow (the built-in demo is ``captures/<scene>``); the section's ``overrides`` is the workflow's own key."""

    scene: str = setting("demo", "the built-in demo capture's procedural scene (sellip.capture.scenes), made when "
                         "`capture` is empty", choices=SCENES)
    renderer: str = setting("sellip", "who renders the synthetic capture: sellip's pBRDF, or Mitsuba 3's pplastic (the "
                            "test extra; docs/synthetic.md)", choices=RENDERERS)
    views: int = setting(36, "views of the handheld orbit", minimum=3)
    width: int = setting(612, "raw mosaic width", unit="pixels", minimum=24, multiple_of=4)
    height: int = setting(512, "raw mosaic height", unit="pixels", minimum=24, multiple_of=4)
    seed: int = setting(0, "seed of the orbit's cameras and the sensor noise", minimum=0)
    noise_seed: int | None = setting(None, "seed of the sensor noise alone, the orbit kept (null: `seed`; another "
                                     "photon draw of the same capture, docs/reproducibility.md)", minimum=0)
    noise_scale: float = setting(1.0, "sensor noise standard deviations x this at the same signal, as with 1/k^2 of "
                                 "the photons at k^2 the gain (1: the real device; docs/synthetic.md)",
                                 exclusive_minimum=0)


EXPOSURE_S = 0.005
"""Nominal shutter time written to frames.csv; the flash dominates, so it does not scale the signal."""



SYNTH_ENTRIES = {CAPTURE_YAML, FRAMES_CSV, POSES_CSV, RAW_DIR, "ground_truth"}
"""What a synthetic capture folder holds."""


def is_synthetic_folder(path: Path) -> bool:
    """Whether the folder ``path`` is one ``sellip synth`` wrote (so it may replace it): its capture.yaml has a
    ``synthetic`` section, or it has no capture.yaml and nothing besides what synth writes (the workflow's
    synth_capture job, whose capture.yaml Snakemake removed before re-running it)."""
    import yaml

    entries = {entry.name for entry in path.iterdir()}
    if CAPTURE_YAML not in entries:
        return entries <= SYNTH_ENTRIES
    try:
        document = yaml.safe_load((path / CAPTURE_YAML).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(document, dict) and isinstance(document.get("synthetic"), dict)


def synthesize_capture(scene_name: str, out: str | Path, views: int = DemoSettings.views,
                       width: int = DemoSettings.width, height: int = DemoSettings.height,
                       seed: int = DemoSettings.seed, supersample: int = 2, raw_format: str = "dng", distortion=None,
                       flash_levels=FLASH_LEVELS, progress: bool = True, noise_scale: float = DemoSettings.noise_scale,
                       renderer: str = DemoSettings.renderer, mitsuba_variant: str | None = None, device=None,
                       noise_seed: int | None = DemoSettings.noise_seed, force: bool = False) -> Path:
    """Render and write a synthetic capture of ``scene_name`` to ``out``; returns the folder. ``out`` is replaced as
    a whole: a folder there that is not a synthetic capture (:func:`is_synthetic_folder`) stops it with
    :class:`sellip.jobs.WouldReplaceError` before anything is rendered, unless ``force``.

    width, height: raw mosaic size (multiples of 4); distortion: OpenCV (k1, k2, p1, p2, k3) or None;
    noise_scale: sensor noise standard deviations x this at the same signal
    (:meth:`sellip.capture.sensor.SensorModel.with_noise_scale`; 1 is the real device); renderer: "sellip"
    (:class:`sellip.model.render.Renderer`) or "mitsuba" (Mitsuba 3's pplastic,
    :class:`sellip.capture.mitsuba_capture.MitsubaRenderer` with ``mitsuba_variant``; the rest is the same).
    device: None (the default device scaled to ``width`` x ``height``: centred principal point, the sensor
    simulator's colour matrix, the flash at :data:`FLASH_POSITION_CAM` polarized at 0 deg), or a device description
    (device.yaml's ``sensor``, ``camera`` and ``light`` sections, e.g. ``sellip synth-calibration``'s truth): the
    frames are shot with that sensor (size, levels, layouts, colour matrix), lens (fx, fy, cx, cy, distortion) and
    flash, and capture.yaml describes it (``width``, ``height`` and ``distortion`` must then be left at their
    defaults or agree with it). noise_seed: the sensor noise's seed (default: ``seed``), the orbit keeps ``seed``.

    Long: the device's description, capture.yaml and the render-and-expose loop share their variables.
    """
    from tqdm import tqdm

    started = time.perf_counter()
    refuse_to_replace_folder(out, "sellip synth", is_synthetic_folder, force=force)
    if renderer not in RENDERERS:
        raise ValueError(f"renderer must be one of {list(RENDERERS)}, got {renderer!r}")
    if renderer == "mitsuba":
        # Chosen first: Dr.Jit's LLVM back end must start before open3d builds a ray-casting scene (mitsuba_capture).
        from sellip.capture.mitsuba_capture import choose_variant

        mitsuba_variant = choose_variant(mitsuba_variant)
    scene = build_scene(scene_name)
    if device is not None:
        width, height, distortion = _device_size(device, width, height, distortion)
    cameras = handheld_orbit(views, width, height, np.random.default_rng([seed, 1]),
                             distance_m=scene.distance_m, elevation_deg=scene.elevation_deg,
                             distortion=distortion)
    if device is None:
        sensor = SensorModel(width=width, height=height).with_noise_scale(noise_scale)
        k = cameras[0].intrinsics
        camera = {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
                  "distortion": [float(c) for c in (distortion if distortion is not None else [0.0] * 5)],
                  "color_matrix": [list(map(float, row)) for row in sensor.color_matrix]}
        light = {"position_m": list(FLASH_POSITION_CAM), "polarizer_deg": 0}
    else:
        sensor = sensor_from_device(device["sensor"], device["camera"]["color_matrix"]).with_noise_scale(noise_scale)
        camera = {key: float(device["camera"][key]) for key in ("fx", "fy", "cx", "cy")}
        camera["distortion"] = [float(c) for c in distortion]
        camera["color_matrix"] = [list(map(float, row)) for row in sensor.color_matrix]
        light = {"position_m": [float(v) for v in device["light"]["position_m"]],
                 "polarizer_deg": float(device["light"].get("polarizer_deg", 0.0))}
        k = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
        cameras = [dataclasses.replace(c, intrinsics=k) for c in cameras]
    noise_seed = seed if noise_seed is None else int(noise_seed)
    config = {
        "sensor": sensor.capture_sensor(),
        "camera": camera,
        "light": light,
        "scene": {"distance_m": float(np.mean(scene.distance_m))},
        "synthetic": {"scene": scene_name, "seed": int(seed), "views": int(views), "supersample": int(supersample),
                      "flash_power_dn": float(scene.flash_power), "gain_e_per_dn": sensor.gain_e_per_dn,
                      "read_noise_e": sensor.read_noise_e, "noise_scale": float(noise_scale),
                      "ground_truth": GROUND_TRUTH_MESH},
    }
    if noise_seed != seed:
        config["synthetic"]["noise_seed"] = noise_seed
    if device is not None:
        config["synthetic"]["device"] = "given"
    if renderer == "mitsuba":
        from sellip.capture.mitsuba_capture import MitsubaRenderer

        view_renderer = MitsubaRenderer(scene.mesh, variant=mitsuba_variant, seed=seed)
        config["synthetic"]["renderer"] = view_renderer.description
    else:
        view_renderer = Renderer(scene.mesh)
    saturated = []
    with CaptureWriter(out, config, raw_format=raw_format) as writer:
        for index, camera in enumerate(tqdm(cameras, desc=f"synth {scene_name}", unit="view", disable=not progress)):
            view_id = f"v{index:03d}"
            flash = flash_light(camera, config["light"]["position_m"], polarizer_deg=config["light"]["polarizer_deg"])
            analyzers = view_renderer.render(camera, flash, supersample=supersample).analyzers
            for level_index, level in enumerate(flash_levels):
                rng = np.random.default_rng([noise_seed, 2, index, level_index])
                raw = simulate_raw(analyzers, sensor, scene.flash_power * level, rng)
                saturated.append(float(np.mean(raw >= sensor.white_level)))
                writer.add_frame(f"{view_id}_f{level_index}", view_id, raw, flash_level=level, exposure_s=EXPOSURE_S)
            writer.add_pose(view_id, camera.rotation, camera.translation)
        write_param_mesh(writer.path_in_capture(GROUND_TRUTH_MESH), scene.mesh)
        path = writer.finish()
    strongest = np.asarray(saturated).reshape(views, len(flash_levels))[:, 0]
    log.info("rendered by %s", config["synthetic"].get("renderer", "sellip"))
    log.info("wrote %s: %d views x %d frames at %dx%d in %.1f s; views with saturated pixels at flash %.3g: %d",
             path, views, len(flash_levels), width, height, time.perf_counter() - started, flash_levels[0],
             int(np.sum(strongest > 0)))
    return path


def _device_size(device, width: int, height: int, distortion) -> tuple[int, int, list[float]]:
    """The raw size and distortion of a device description, checked against the ones asked for (the defaults of
    :func:`synthesize_capture` stand for "the device's")."""
    size = int(device["sensor"]["width"]), int(device["sensor"]["height"])
    if (width, height) not in (size, (612, 512)):
        raise ValueError(f"the device's sensor is {size[0]}x{size[1]}, not {width}x{height}: leave the size out")
    lens = [float(c) for c in device["camera"].get("distortion", [0.0] * 5)]
    lens += [0.0] * (5 - len(lens))
    if distortion is not None and not np.allclose(distortion, lens):
        raise ValueError(f"the device's distortion is {lens}, not {list(distortion)}: leave it out")
    return size[0], size[1], lens
