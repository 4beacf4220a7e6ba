"""The renderers of synthetic calibration frames: sellip's own analytic one (:mod:`sellip.calibrate.synthetic`)
and Mitsuba 3 (an independent renderer, :mod:`sellip.capture.mitsuba_capture`'s camera, flash and polarizer).

Public API::

    CALIBRATION_RENDERERS = ("sellip", "mitsuba")
    frame_renderer(name, seed=0) -> SellipFrames | MitsubaFrames
        .description                                                  # what rendered the frames (truth.yaml)
        .device(width, height, polarizer_deg) -> dict                 # the true device it can render
        .board(device, spec, R, t) -> analyzers (H, W, 4, 3)          # the checkerboard alone
        .spheres(device, spheres, reflect_panel) -> analyzers         # spheres before the light panel
        .board_spheres(device, spec, R, t, spheres) -> (board, spheres)   # the flash step's pair of frames
        .chart(device, R, t) -> analyzers                             # the ColorChecker under the flash
        .close()                                                      # (also a context manager)

Both draw the same scenes from the same poses (:func:`sellip.calibrate.synthetic_set.synthesize_calibration` picks
them); the frames then go through the same sensor simulator. What the Mitsuba scenes add to sellip's:

- spheres are Mitsuba ``pplastic`` (GGX, a dark diffuse base) analytic ``sphere`` shapes; the light panel is an
  ``area`` emitter (the plane z = 1 m, 2 m x 2 m, as :mod:`sellip.calibrate.panel`), so the spheres mirror it by
  Mitsuba's own Fresnel and microfacet sampling, not by sellip's panel model;
- spheres on the board stand in a dim room (a ``constant`` environment, :data:`ROOM_RADIANCE`) that they mirror
  all over, brightest at their limbs, and they shade the board from it; the board frame of the pair has the same
  room. Direct light only (``max_depth`` 2, as sellip's renderer): the spheres do not mirror the board (with
  ``max_depth`` 3 the flash's caustics through the glossy spheres sprinkle the board with fireflies at any sample
  count that renders here);
- the chart is ``pplastic`` with a varnish (:data:`CHART_VARNISH`): a glossy lobe that mirrors the polarized
  flash where the chart faces it, as a printed chart does;
- the camera is a pinhole (Mitsuba's ``perspective`` has no lens distortion) with square pixels: the device
  (:meth:`MitsubaFrames.device`) is sellip's synthetic device without distortion and with fy = fx. Board and
  chart are paper (``diffuse``, unpolarized), not sellip's pBRDF.

Radiometric units are Mitsuba's (a diffuse albedo ρ gives ρ/π); every frame is exposed relative to its own peak,
so only ratios within a scene matter. Pixel noise: stratified s x s samples per pixel (:data:`SUPERSAMPLE`).
"""

from __future__ import annotations

import numpy as np

from sellip.calibrate import synthetic

CALIBRATION_RENDERERS = ("sellip", "mitsuba")

SUPERSAMPLE = {"board": 3, "spheres": 6, "board_spheres": 6, "chart": 3}
"""Stratified samples per pixel side, per kind of frame (spheres: the mirrored panel and room are sampled; both
frames of a board pair take "board_spheres")."""

SPHERE_PPLASTIC = {"diffuse_reflectance": 0.05, "alpha": 0.08, "eta": 1.5, "specular_reflectance": 1.0}
"""A black glossy ball in Mitsuba's ``pplastic`` (GGX): a faint diffuse base under a sharp dielectric lobe."""

PANEL_RADIANCE = 0.5
"""The light panel's radiance, relative to the flash's intensity (W/sr) seen at 1 m: about 2x the spheres'
diffuse light at 0.5 m and 1/20 of their highlight's peak, as sellip's synthetic panel."""

ROOM_RADIANCE = 0.05
"""The room's radiance (a ``constant`` environment) in the board-protocol frames, relative to the flash as
:data:`PANEL_RADIANCE`: the room gives the board's paper about 5 % of the flash's light at 0.5 m, and a sphere's
limb mirrors it at up to that radiance, brighter than the board's black squares."""

CHART_VARNISH = {"alpha": 0.15, "eta": 1.5, "specular_reflectance": 1.0}
"""The chart's semi-matte varnish in ``pplastic``: a dielectric GGX lobe over the printed patches."""


def frame_renderer(name: str, seed: int = 0):
    """The calibration-frame renderer ``name`` (:data:`CALIBRATION_RENDERERS`); ``seed`` seeds Mitsuba's
    sampler (frame k of the set gets seed * 100003 + k). ValueError naming the choices for another name;
    Mitsuba missing raises ImportError saying how to install it."""
    if name == "sellip":
        return SellipFrames()
    if name == "mitsuba":
        from sellip.capture.mitsuba_capture import mitsuba_available

        if not mitsuba_available():
            raise ImportError("the Mitsuba renderer needs the mitsuba package (pyproject's test extra: "
                              "pip install -e '.[test]')")

        return MitsubaFrames(seed)
    raise ValueError(f"unknown calibration renderer {name!r}; expected one of {list(CALIBRATION_RENDERERS)}")


class SellipFrames:
    """sellip's analytic renderer (:mod:`sellip.calibrate.synthetic`): the project's pBRDF, the lens distortion
    exact, the panel mirrored by :func:`sellip.calibrate.panel.panel_reflection`."""

    description = "sellip"

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def device(self, width: int, height: int, polarizer_deg: float) -> dict:
        return synthetic.true_device(width, height, polarizer_deg)

    def board(self, device, spec, rotation, translation):
        return synthetic.render_board(device, spec, rotation, translation)

    def spheres(self, device, spheres, reflect_panel: bool):
        return synthetic.render_spheres(device, spheres, reflect_panel=reflect_panel)

    def board_spheres(self, device, spec, rotation, translation, spheres):
        board = synthetic.render_board(device, spec, rotation, translation)
        return board, synthetic.render_spheres(device, spheres, reflect_panel=False, background=board)

    def chart(self, device, rotation, translation):
        return synthetic.render_chart(device, rotation, translation)


class MitsubaFrames:
    """Mitsuba 3's calibration scenes (module docstring), rendered in a worker process (:class:`MitsubaScenes`,
    ``python -m sellip.calibrate.renderers SEED``): Dr.Jit must pick its libLLVM before anything in its process
    imports Mitsuba (else the system's aborts it: "LLVM ERROR: Cannot select ... fminimum") and start its back end
    before open3d builds a scene (:func:`sellip.capture.mitsuba_capture.choose_variant`), which a process that
    already ran other code (a test session) cannot promise. :meth:`close` (or a ``with`` block) ends the worker."""

    def __init__(self, seed: int = 0):
        import subprocess
        import sys

        self._worker = subprocess.Popen([sys.executable, "-m", "sellip.calibrate.renderers", str(int(seed))],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.description = self._call("description")

    def _call(self, method: str, *args):
        import pickle

        try:
            pickle.dump((method, args), self._worker.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._worker.stdin.flush()
            ok, value = pickle.load(self._worker.stdout)
        except (EOFError, BrokenPipeError) as exc:
            raise RuntimeError(f"the Mitsuba worker process ended (exit {self._worker.wait()}) in {method}; its "
                               "messages are above") from exc
        if not ok:
            raise RuntimeError(f"the Mitsuba worker failed in {method}:\n{value}")
        return value

    def close(self) -> None:
        if self._worker.poll() is None:
            self._worker.stdin.close()
            self._worker.wait(timeout=60)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def device(self, width: int, height: int, polarizer_deg: float) -> dict:
        """sellip's synthetic device (:func:`sellip.calibrate.synthetic.true_device`) as a pinhole with square
        pixels: Mitsuba's camera has neither distortion nor fy != fx. The principal point stays off centre."""
        device = synthetic.true_device(width, height, polarizer_deg)
        device["camera"]["fy"] = device["camera"]["fx"]
        device["camera"]["distortion"] = [0.0] * 5
        return device

    @staticmethod
    def _analyzers(stokes: np.ndarray) -> np.ndarray:
        from sellip.model.conventions import stokes_to_analyzers

        return np.asarray(stokes_to_analyzers(stokes, axis=-2), np.float32)

    def board(self, device, spec, rotation, translation, room: bool = False):
        """The checkerboard alone; ``room`` adds the board protocol's room (:data:`ROOM_RADIANCE`)."""
        return self._analyzers(self._call("board", device, spec, rotation, translation, room))

    def spheres(self, device, spheres, reflect_panel: bool = True):
        """Spheres before the light panel, which they mirror (always: it is Mitsuba's light transport;
        ``reflect_panel`` is sellip's switch and is ignored here)."""
        return self._analyzers(self._call("spheres", device, spheres))

    def board_spheres(self, device, spec, rotation, translation, spheres):
        """The pair of the board protocol, both in the room: the board alone, then with ``spheres`` on it."""
        board, with_spheres = self._call("board_spheres", device, spec, rotation, translation, spheres)
        return self._analyzers(board), self._analyzers(with_spheres)

    def chart(self, device, rotation, translation):
        """The varnished ColorChecker under the flash."""
        return self._analyzers(self._call("chart", device, rotation, translation))


def _serve(seed: int) -> None:
    """The worker process of :class:`MitsubaFrames`: reads pickled (method, args) from stdin and writes (True,
    result) or (False, traceback) to stdout until stdin ends; whatever else writes to stdout goes to stderr."""
    import os
    import pickle
    import sys
    import traceback

    requests, answers = sys.stdin.buffer, os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    scenes = MitsubaScenes(seed)
    while True:
        try:
            method, args = pickle.load(requests)
        except EOFError:
            return
        try:
            answer = (True, scenes.description if method == "description" else getattr(scenes, method)(*args))
        except Exception:  # noqa: BLE001 - reported to the parent, which raises
            answer = (False, traceback.format_exc())
        pickle.dump(answer, answers, protocol=pickle.HIGHEST_PROTOCOL)
        answers.flush()


class MitsubaScenes:
    """The Mitsuba scenes themselves (module docstring), each rendered to Stokes (H, W, 4, 3) in sellip's camera
    frame; the variant is :func:`sellip.capture.mitsuba_capture.choose_variant`'s. Run no JAX in its process."""

    def __init__(self, seed: int = 0):
        from sellip.capture.mitsuba_capture import choose_variant

        self.variant = choose_variant()  # before Mitsuba's first import: it picks Dr.Jit's libLLVM
        import mitsuba as mi

        self.description = f"mitsuba {mi.__version__} {self.variant}"
        self.seed = int(seed)
        self._frames = 0
        self._polarizer = mi.load_dict({"type": "polarizer", "theta": 0.0})

    def _render(self, device: dict, shapes, kind: str, channels: int = 1) -> np.ndarray:
        """Stokes (H, W, 4, 3) of the flash scene plus ``shapes`` (a dict, or a function of the colour channel
        giving one), one Mitsuba pass per channel (``channels`` 1: grey, copied to R, G, B)."""
        from sellip.capture.mitsuba_capture import flash_scene, render_stokes
        from sellip.model.render import Camera, flash_light

        cam, sensor = device["camera"], device["sensor"]
        k = np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])
        camera = Camera(k, np.eye(3), np.zeros(3), int(sensor["width"]), int(sensor["height"]),
                        np.asarray(cam.get("distortion", [0.0] * 5), np.float64))
        light = flash_light(camera, device["light"]["position_m"], float(device["light"]["polarizer_deg"]))
        seed = self.seed * 100003 + self._frames
        self._frames += 1
        stokes = np.zeros((camera.height, camera.width, 4, 3), np.float32)
        for channel in range(channels):
            scene = {**flash_scene(camera, light, 2.0, SUPERSAMPLE[kind], seed, self._polarizer, self.variant),
                     **(shapes(channel) if callable(shapes) else shapes)}
            stokes[..., channel] = render_stokes(scene, camera, self.variant)
        if channels == 1:
            stokes[..., 1:] = stokes[..., :1]
        return stokes

    def board(self, device, spec, rotation, translation, room: bool = False):
        """The checkerboard alone (paper: ``diffuse``, its printed squares an exact texture)."""
        shapes = {"board": _plane("board", spec.outline(), rotation, translation, _board_texture(spec))}
        if room:
            shapes["room"] = {"type": "constant", "radiance": ROOM_RADIANCE}
        # the board frame of a pair: as many samples as its sphere frame, or the room's sampling noise differs
        # between the two and reads as a change (a sphere) to the flash step
        return self._render(device, shapes, "board_spheres" if room else "board")

    def spheres(self, device, spheres):
        """Spheres before the light panel (:data:`PANEL_RADIANCE`), which they mirror."""
        panel = {"type": "rectangle", "to_world": _matrix([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]]),
                 "emitter": {"type": "area", "radiance": PANEL_RADIANCE}}
        return self._render(device, {**_spheres(spheres), "panel": panel}, "spheres")

    def board_spheres(self, device, spec, rotation, translation, spheres):
        """The board alone and with ``spheres`` on it, in the room (they mirror it and shade the board from it)."""
        board = self.board(device, spec, rotation, translation, room=True)
        shapes = {"board": _plane("board", spec.outline(), rotation, translation, _board_texture(spec)),
                  "room": {"type": "constant", "radiance": ROOM_RADIANCE}, **_spheres(spheres)}
        return board, self._render(device, shapes, "board_spheres")

    def chart(self, device, rotation, translation):
        """The ColorChecker (:func:`sellip.calibrate.synthetic.chart_texture`'s layout and reference colours),
        varnished (:data:`CHART_VARNISH`); one pass per colour channel."""
        texture = _chart_texture(synthetic.chart_reference_srgb())
        margin = 0.01
        outline = np.array([[-margin, -margin, 0], [6 * synthetic.CHART_PATCH_M + margin, -margin, 0],
                            [6 * synthetic.CHART_PATCH_M + margin, 4 * synthetic.CHART_PATCH_M + margin, 0],
                            [-margin, 4 * synthetic.CHART_PATCH_M + margin, 0]])

        def shapes(channel):
            bsdf = {"type": "pplastic", "distribution": "ggx", **CHART_VARNISH,
                    "diffuse_reflectance": _bitmap(texture[..., channel])}
            return {"chart": _plane("chart", outline, rotation, translation, bsdf=bsdf)}

        return self._render(device, shapes, "chart", channels=3)


# --------------------------------------------------------------------------- shapes


def _matrix(rows):
    import mitsuba as mi

    return mi.ScalarTransform4f(np.asarray(rows, np.float64).tolist())


def _bitmap(image: np.ndarray) -> dict:
    """A ``bitmap`` texture of a (rows, cols) float image, nearest-neighbour (texel edges are the print's edges),
    row 0 at texture v = 0."""
    import mitsuba as mi

    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, np.float32)[..., None]),
            "filter_type": "nearest", "wrap_mode": "clamp", "raw": True}


def _plane(name: str, outline: np.ndarray, rotation, translation, texture: np.ndarray | None = None,
           bsdf: dict | None = None):
    """A textured rectangle: ``outline`` (4, 3) corners in plane coordinates (the texture's (0, 0), (1, 0),
    (1, 1), (0, 1)) placed at pose (R, t) (plane -> camera), ``diffuse`` with ``texture`` unless ``bsdf``."""
    import mitsuba as mi

    from sellip.capture.mitsuba_capture import mesh_shape

    if bsdf is None:
        bsdf = {"type": "diffuse", "reflectance": _bitmap(texture)}
    vertices = outline @ np.asarray(rotation).T + np.asarray(translation)
    texcoords = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return mesh_shape(name, vertices, np.array([[0, 1, 2], [0, 2, 3]]), texcoords=texcoords,
                       bsdf=mi.load_dict({"type": "twosided", "bsdf": bsdf}))


def _spheres(spheres) -> dict:
    bsdf = {"type": "pplastic", "distribution": "ggx", **SPHERE_PPLASTIC}
    return {f"sphere_{k}": {"type": "sphere", "center": [float(v) for v in centre], "radius": float(radius),
                            "bsdf": bsdf} for k, (centre, radius) in enumerate(spheres)}


def _board_texture(spec) -> np.ndarray:
    """(rows + 3, cols + 3) albedo texels of the board's paper (:meth:`BoardSpec.outline`), one per square."""
    s = spec.square_m
    x = (np.arange(spec.cols + 3) - 1.5) * s  # texel centres in board coordinates
    y = (np.arange(spec.rows + 3) - 1.5) * s
    return spec.albedo(*np.meshgrid(x, y)).astype(np.float32)


def _chart_texture(reference: np.ndarray, texels_per_patch: int = 20) -> np.ndarray:
    """(rows, cols, 3) albedo texels of the chart card, 1 cm margin included, from
    :func:`sellip.calibrate.synthetic.chart_texture` sampled at texel centres."""
    step = synthetic.CHART_PATCH_M / texels_per_patch
    margin = 0.01
    x = -margin + (np.arange(round((6 * synthetic.CHART_PATCH_M + 2 * margin) / step)) + 0.5) * step
    y = -margin + (np.arange(round((4 * synthetic.CHART_PATCH_M + 2 * margin) / step)) + 0.5) * step
    return np.asarray(synthetic.chart_texture(reference)(*np.meshgrid(x, y)), np.float32)


if __name__ == "__main__":
    import sys

    _serve(int(sys.argv[1]))
