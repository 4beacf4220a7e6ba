"""A synthetic calibration folder with known truth (``sellip synth-calibration``), its frames drawn by sellip's
own renderer (:mod:`sellip.calibrate.synthetic`) or by Mitsuba 3 (:mod:`sellip.calibrate.renderers`).

Public API::

    synthesize_calibration(out, width=2448, height=2048, seed=0, ..., renderer="sellip") -> Path   # the folder

A calibration folder (``sellip synth-calibration --out DIR [--renderer mitsuba]``)::

    sensor.yaml                the sensor section only: what a user knows from the datasheet
    truth.yaml                 the renderer, the true device (sensor, camera, light), board poses, sphere centres,
                               chart corners
    board/board_NN.dng         checkerboard frames (board_NN_bK.dng: frame K of a burst of pose NN)
    spheres/spheres_NN.dng     frames of glossy spheres of known radius (likewise), exposed for the highlights
    spheres/spheres_NN_long.dng   the same layout exposed for the spheres' diffuse light (the polarization
                               check's bracket, :data:`sellip.calibrate.flash.LONG_SUFFIX`): the spheres' median at
                               :data:`LONG_LEVEL` of full scale, highlights and panel clipped; both record their
                               ExposureTime
    board_spheres/spheres_NN_board.dng, spheres_NN.dng   the board alone, then spheres resting on it at square
                               centres, from one camera position (the flash step's board protocol)
    chart/chart_00.dng         a ColorChecker under the flash

Both renderers draw the same poses, layouts and sensor noise from the same seed; only the images differ (and
Mitsuba's device is a pinhole with square pixels, :meth:`sellip.calibrate.renderers.MitsubaFrames.device`).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from sellip.calibrate.board_spheres import BOARD_SUFFIX, sphere_centre
from sellip.calibrate.flash import LONG_SUFFIX
from sellip.calibrate.renderers import frame_renderer
from sellip.calibrate.synthetic import (
    CHART_PATCH_M,
    SPHERE_RADIUS_M,
    BoardSpec,
    board_poses,
    board_sphere_layouts,
    chart_corners_board,
    expose,
    look_at,
    project,
    sphere_layouts,
)
from sellip.capture.writer import write_raw_file
from sellip.jobs import refuse_to_replace_folder

_LAP = [0.0]

SPHERE_EXPOSURE_S = 0.01
"""ExposureTime recorded in the sphere frames exposed for their highlights; the long frames record it times the
brightness ratio."""

LONG_LEVEL = 0.2
"""The long sphere frame's exposure: the median over the spheres' discs (their diffuse light, the highlight a small
part) reads this share of full scale (docs/calibration.md, section 4)."""


def _disc_median(analyzers: np.ndarray, device: dict, spheres: list[tuple[np.ndarray, float]]) -> float:
    """The median of ``analyzers`` (H, W, 4, C) over the discs of ``spheres`` (centre (3,), radius): what the
    spheres' diffuse light reads."""
    height, width = analyzers.shape[:2]
    yy, xx = np.mgrid[0:height, 0:width]
    inside = np.zeros((height, width), bool)
    for centre, radius in spheres:
        u, v = project(device, np.asarray(centre))
        r_px = device["camera"]["fx"] * radius / np.sqrt(centre @ centre - radius ** 2)
        inside |= np.hypot(xx - u, yy - v) < 0.95 * r_px
    return float(np.median(analyzers[inside]))


def _lap() -> float:
    """Seconds since the last call (the progress lines' time per frame, rendering and exposure)."""
    now = time.perf_counter()
    lap, _LAP[0] = now - (_LAP[0] or now), now
    return lap


def _burst_seed(base: list[int], frame: int) -> list[int]:
    """The noise seed of a burst's frame: the first frame keeps the seed it has without bursts."""
    return base if frame == 0 else [*base, frame]


def _burst_name(kind: str, pose: int, frame: int, burst: int, suffix: str) -> str:
    return f"{kind}_{pose:02d}{suffix}" if burst == 1 else f"{kind}_{pose:02d}_b{frame}{suffix}"


def _write_board_spheres(folder: Path, device: dict, spec: BoardSpec, count: int, radius: float, peak_dn: float,
                         seed: int, suffix: str, record: dict, progress: bool, frames) -> None:
    """``count`` pairs into ``folder``: the board alone (NAME_board) and spheres resting on it (NAME), exposed
    alike (the sphere frame's peak at ``peak_dn``); their marks, centres and poses into ``record``."""
    rng = np.random.default_rng([seed, 40])
    record["radius_m"] = radius
    for k, (rotation, translation, marks) in enumerate(board_sphere_layouts(spec, device, count, rng, radius)):
        centres = [sphere_centre(rotation, translation, m, radius) for m in marks]
        board, analyzers = frames.board_spheres(device, spec, rotation, translation, [(c, radius) for c in centres])
        peak = float(np.max(analyzers))
        name = f"spheres_{k:02d}"
        for image, stem in ((board, f"{name}{BOARD_SUFFIX}"), (analyzers, name)):
            raw = expose(image, device, peak_dn, np.random.default_rng([seed, 41, k, len(stem)]),
                         reference=peak)
            write_raw_file(folder / f"{stem}{suffix}", raw, device["sensor"])
        record["marks_m"][name + suffix] = marks.tolist()
        record["centres_m"][name + suffix] = [c.tolist() for c in centres]
        record["poses"][name + suffix] = {"rotation": rotation.tolist(), "translation_m": translation.tolist()}
        if progress:
            print(f"spheres on the board {k + 1}/{count} ({_lap():.1f} s)", flush=True)


def synthesize_calibration(out: str | Path, width: int = 2448, height: int = 2048, seed: int = 0,
                           board_frames: int = 24, sphere_frames: int = 6, spheres_per_frame: int = 3,
                           spec: BoardSpec | None = None, raw_format: str = "dng", polarizer_deg: float = 0.0,
                           progress: bool = False, burst: int = 1, reflect_panel: bool = True,
                           board_sphere_frames: int = 6, force: bool = False, renderer: str = "sellip") -> Path:
    """Write a calibration folder (module docstring) for the synthetic device; returns it. Atomic: written to a
    temporary sibling and renamed. The same seed gives the same files. An existing ``out`` without truth.yaml (not
    one this function wrote) stops it with :class:`sellip.jobs.WouldReplaceError`, unless ``force``.

    ``burst``: frames per pose (board and sphere layouts alike), each with its own sensor noise (a camera's burst):
    ``board_07_b2.dng`` is pose 7's third frame (``board_07.dng`` at ``burst`` 1, as a burst's first).
    ``reflect_panel``: the spheres mirror the light panel (as real glossy spheres do). ``board_sphere_frames``:
    layouts of 3 spheres resting on the board (:func:`board_sphere_layouts`), each a pair of frames from one tripod
    position, ``board_spheres/spheres_NN_board`` (the board alone) and ``board_spheres/spheres_NN`` (the spheres on
    it), exposed alike (docs/calibration.md, the board protocol). ``renderer``: "sellip" or "mitsuba"
    (:func:`sellip.calibrate.renderers.frame_renderer`; with Mitsuba the spheres always mirror what surrounds them,
    ``reflect_panel`` is sellip's). Long: one loop per kind of frame, kept together
    so that each kind's seeds stay visible side by side."""
    out = Path(out)
    spec = spec or BoardSpec()
    refuse_to_replace_folder(out, "sellip synth-calibration", lambda path: (path / "truth.yaml").is_file(), force)
    frames = frame_renderer(renderer, seed)
    device = frames.device(width, height, polarizer_deg)
    suffix = {"dng": ".dng", "tiff": ".tiff", "png": ".png"}[raw_format]
    scale = width / 2448
    white = device["sensor"]["white_level"] - float(np.max(device["sensor"]["black_level"]))
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    _lap()  # the progress lines time each frame from here
    if tmp.exists():
        shutil.rmtree(tmp)
    truth = {"renderer": frames.description, "device": device,
             "board": {"cols": spec.cols, "rows": spec.rows, "square_m": spec.square_m, "poses": {}},
             "spheres": {"radius_m": SPHERE_RADIUS_M, "centres_m": {}, "reflect_panel": bool(reflect_panel)},
             "board_spheres": {"radius_m": SPHERE_RADIUS_M, "marks_m": {}, "centres_m": {}, "poses": {}},
             "chart": {}}
    try:
        for sub in ("board", "spheres", "board_spheres", "chart"):
            (tmp / sub).mkdir(parents=True)
        rng = np.random.default_rng([seed, 10])
        for k, (rotation, translation) in enumerate(board_poses(spec, device, board_frames, rng)):
            analyzers = frames.board(device, spec, rotation, translation)
            for b in range(burst):
                raw = expose(analyzers, device, 0.7 * white, np.random.default_rng(_burst_seed([seed, 11, k], b)))
                name = _burst_name("board", k, b, burst, suffix)
                write_raw_file(tmp / "board" / name, raw, device["sensor"])
                truth["board"]["poses"][name] = {"rotation": rotation.tolist(),
                                                 "translation_m": translation.tolist()}
            if progress:
                print(f"board {k + 1}/{board_frames} ({_lap():.1f} s)", flush=True)
        rng = np.random.default_rng([seed, 20])
        radius = SPHERE_RADIUS_M if scale >= 0.5 else SPHERE_RADIUS_M * 0.6
        truth["spheres"]["radius_m"] = radius
        for k, centres in enumerate(sphere_layouts(device, sphere_frames, rng, radius=radius,
                                                   per_frame=spheres_per_frame)):
            analyzers = frames.spheres(device, [(c, radius) for c in centres], reflect_panel)
            peak = float(np.max(analyzers))
            diffuse = _disc_median(analyzers, device, [(c, radius) for c in centres])
            # the bracket: exposed for the highlight (peak at 75 % of full scale), and for the diffuse light
            long_exposure = SPHERE_EXPOSURE_S * (LONG_LEVEL / diffuse) / (0.75 / peak)
            for b in range(burst):
                raw = expose(analyzers, device, 0.75 * white, np.random.default_rng(_burst_seed([seed, 21, k], b)),
                             reference=peak)
                name = _burst_name("spheres", k, b, burst, suffix)
                write_raw_file(tmp / "spheres" / name, raw, device["sensor"], exposure_s=SPHERE_EXPOSURE_S)
                truth["spheres"]["centres_m"][name] = [c.tolist() for c in centres]
                raw = expose(analyzers, device, LONG_LEVEL * white,
                             np.random.default_rng(_burst_seed([seed, 22, k], b)), reference=diffuse)
                name = _burst_name("spheres", k, b, burst, LONG_SUFFIX + suffix)
                write_raw_file(tmp / "spheres" / name, raw, device["sensor"], exposure_s=long_exposure)
                truth["spheres"]["centres_m"][name] = [c.tolist() for c in centres]
            if progress:
                print(f"spheres {k + 1}/{sphere_frames} ({_lap():.1f} s)", flush=True)
        _write_board_spheres(tmp / "board_spheres", device, spec, board_sphere_frames, radius, 0.75 * white, seed,
                             suffix, truth["board_spheres"], progress, frames)
        rng = np.random.default_rng([seed, 30])
        rotation = look_at(np.zeros(3), 10.0, rng)
        distance = 1.1 * 6 * CHART_PATCH_M * device["camera"]["fx"] / (0.8 * width)
        translation = np.array([0.0, 0.0, distance]) - rotation @ chart_corners_board().mean(axis=0)
        analyzers = frames.chart(device, rotation, translation)
        raw = expose(analyzers, device, 0.6 * white, np.random.default_rng([seed, 31]))
        write_raw_file(tmp / "chart" / f"chart_00{suffix}", raw, device["sensor"])
        corners = project(device, chart_corners_board() @ rotation.T + translation)
        truth["chart"] = {"file": f"chart_00{suffix}", "corners_px": corners.tolist(),
                          "rotation": rotation.tolist(), "translation_m": translation.tolist()}
        with open(tmp / "sensor.yaml", "w") as f:
            yaml.safe_dump({"sensor": device["sensor"]}, f, sort_keys=False, default_flow_style=None)
        with open(tmp / "truth.yaml", "w") as f:
            yaml.safe_dump(truth, f, sort_keys=False, default_flow_style=None)
        if out.exists():
            shutil.rmtree(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(out)
    finally:
        frames.close()
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out
