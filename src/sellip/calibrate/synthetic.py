"""Synthetic calibration frames with known truth: a checkerboard, glossy spheres in front of a light panel,
and a ColorChecker, all under the rig's polarized flash, through the project's sensor simulator (the folder of
them: :mod:`sellip.calibrate.synthetic_set`).

Public API::

    DEVICE_DISTORTION                                  # the lens distortion the synthetic device has
    true_device(width=2448, height=2048) -> dict       # device.yaml of the synthetic device (the truth)
    BoardSpec(cols=14, rows=10, square_m=0.010)        # inner corners, square side
    board_poses(spec, device, count, rng) -> list[(R (3, 3), t (3,))]   # board -> camera, board fully in view
    render_board(device, spec, rotation, translation, supersample=3, blur_px=0) -> analyzers (H, W, 4, 3)
    render_spheres(device, spheres, supersample=2, panel=0.5, reflect_panel=True) -> analyzers (H, W, 4, 3)
    panel.panel_reflection(points, normals, eta, panel) -> analyzers (N, 4)   # the panel mirrored, Fresnel-polarized
    render_chart(device, rotation, translation, supersample=2, shadow=1.0) -> analyzers (H, W, 4, 3)
    expose(analyzers, device, peak_fraction, rng) -> raw (H, W) uint16    # sellip.sensor.simulate_raw

Everything is rendered analytically in camera coordinates (OpenCV axes, metres): every sub-pixel sample's
ray (the lens distortion of the device applied exactly at pixel centres, :func:`sellip.render.undistort_normalized`,
and by the local Jacobian within a pixel), its hit on a plane or a sphere, and the full three-lobe pBRDF of the
project (:func:`sellip.pbrdf.full_stokes`) under the flash at ``light.position_m`` polarized at
``light.polarizer_deg``. A plane's shading is smooth and is evaluated on a grid of every 4th pixel
(interpolated bilinearly), its printed texture (checkers, patches) per sample (3x3 per pixel); spheres are
shaded per sample (2x2). The
light panel behind the spheres is an unpolarized emitter (a backlit outline is what locates a sphere), and the
spheres mirror it (Fresnel-weighted, s-polarized), brightest at their limbs, as real glossy spheres do.
Shadows are not traced (the board and chart are alone in their frames; spheres are placed apart).
The analyzer images go through :func:`sellip.sensor.simulate_raw` (mosaic, colour, shot and read noise,
12-bit rounding, saturation) with the device's sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sellip.calibrate.board_spheres import sphere_centre, square_centres
from sellip.calibrate.panel import panel_reflection
from sellip.capture.scenes import DEVICE_FX_PX, DEVICE_WIDTH_PX
from sellip.capture.sensor import SensorModel, sensor_from_device
from sellip.model.render import undistort_normalized

DEVICE_DISTORTION = (-0.12, 0.25, 4e-4, -3e-4, 0.0)
"""OpenCV (k1, k2, p1, p2, k3) of the synthetic device's lens (a 25 mm C-mount lens is of this order)."""

DEVICE_FLASH_M = (0.0, 0.05, 0.0)
"""The flash 5 cm below the lens (the paper's rig), camera coordinates."""

SPHERE_RADIUS_M = 0.02
"""Radius of the synthetic glossy spheres (40 mm balls)."""

SPHERE_PARAMS = {"eta": 1.5, "rho_d": (0.06, 0.06, 0.06), "rho_s": 1.0, "sigma_s": 0.08, "rho_ss": (0.0, 0.0, 0.0),
                 "sigma_ss": 0.3}
"""A black glossy dielectric ball (a snooker ball, a glazed ceramic sphere): faint diffuse, one sharp lobe."""

SHADE_STEP = 4
"""A plane's shading is evaluated every this many pixels and interpolated (it is smooth; its texture is not)."""

SHADE_CHUNK = 1 << 18
"""Samples shaded per jitted call."""


def true_device(width: int = 2448, height: int = 2048, polarizer_deg: float = 0.0) -> dict:
    """The synthetic device (device.yaml sections sensor, camera, light): the IMX250MYR sensor, the 25 mm lens
    of docs/design.md §3's notes scaled to ``width``, a principal point off the centre, :data:`DEVICE_DISTORTION`,
    the sensor simulator's colour matrix, and the flash 5 cm below the lens."""
    sensor = SensorModel(width=width, height=height)
    f = DEVICE_FX_PX * width / DEVICE_WIDTH_PX
    return {
        "sensor": sensor.capture_sensor(),
        "camera": {"fx": float(f), "fy": float(f * 1.0004), "cx": float(width / 2 + 13.7 * width / 2448),
                   "cy": float(height / 2 - 9.2 * width / 2448), "distortion": list(DEVICE_DISTORTION),
                   "color_matrix": [list(map(float, row)) for row in sensor.color_matrix]},
        "light": {"position_m": list(DEVICE_FLASH_M), "polarizer_deg": float(polarizer_deg)},
    }


def _sensor(device: dict) -> SensorModel:
    return sensor_from_device(device["sensor"], device["camera"]["color_matrix"])


# --------------------------------------------------------------------------- rays


class _Rays:
    """Undistorted normalized coordinates (x, y) of sub-pixel samples of one device's camera.

    Exact (:func:`sellip.render.undistort_normalized`) at every pixel centre of a block of rows; a sample at
    offset (du, dv) from its pixel's centre moves by the local Jacobian (finite differences of the centres),
    which is exact to 1e-3 px for the distortion of any lens here.
    """

    def __init__(self, camera: dict, width: int, height: int):
        key = (tuple(float(camera[k]) for k in ("fx", "fy", "cx", "cy")),
               tuple(map(float, camera.get("distortion", [0.0] * 5))), width, height)
        if key not in _RAY_CACHE:  # one device's centres serve all its frames
            _RAY_CACHE.clear()
            u, v = np.meshgrid(np.arange(-1, width + 1, dtype=np.float64), np.arange(-1, height + 1, dtype=np.float64))
            xd, yd = (u - camera["cx"]) / camera["fx"], (v - camera["cy"]) / camera["fy"]
            distortion = camera.get("distortion", [0.0] * 5)
            _RAY_CACHE[key] = (undistort_normalized(xd, yd, distortion, iterations=30) if np.any(distortion)
                               else (xd, yd))
        self.x, self.y = _RAY_CACHE[key]

    def block(self, rows: slice, supersample: int) -> tuple[np.ndarray, np.ndarray]:
        """(x, y), each (h, W, s*s), for the s x s samples of every pixel of ``rows``."""
        x = self.x[rows.start:rows.stop + 2]
        y = self.y[rows.start:rows.stop + 2]
        dxdu, dydu = (x[1:-1, 2:] - x[1:-1, :-2]) / 2, (y[1:-1, 2:] - y[1:-1, :-2]) / 2
        dxdv, dydv = (x[2:, 1:-1] - x[:-2, 1:-1]) / 2, (y[2:, 1:-1] - y[:-2, 1:-1]) / 2
        x, y = x[1:-1, 1:-1], y[1:-1, 1:-1]
        offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
        du, dv = (o.ravel() for o in np.meshgrid(offsets, offsets))
        xs = x[..., None] + dxdu[..., None] * du + dxdv[..., None] * dv
        ys = y[..., None] + dydu[..., None] * du + dydv[..., None] * dv
        return xs, ys


_RAY_CACHE: dict = {}


# --------------------------------------------------------------------------- shading


def _light_axis(device: dict) -> np.ndarray:
    angle = np.radians(float(device["light"]["polarizer_deg"]))
    return np.array([np.cos(angle), -np.sin(angle), 0.0])  # image up is -y (sellip.conventions)


def _shade(points: np.ndarray, normals: np.ndarray, device: dict, params: dict) -> np.ndarray:
    """Analyzer intensities (N, 4, 3) of surface points (N, 3) with normals (N, 3) (camera coordinates) under
    the device's unit flash, from :func:`sellip.pbrdf.full_stokes`. ``params``: PBRDFParams fields, each a
    scalar / (3,) or (N,) / (N, 3)."""
    import jax.numpy as jnp

    from sellip.model.conventions import stokes_to_analyzers
    from sellip.model.pbrdf import PBRDFParams, full_stokes

    kernel = _jitted(full_stokes)
    light = np.asarray(device["light"]["position_m"], np.float64)
    axis = _light_axis(device)
    count = points.shape[0]
    out = np.zeros((count, 4, 3), np.float32)
    for start in range(0, count, SHADE_CHUNK):
        stop = min(count, start + SHADE_CHUNK)
        n = SHADE_CHUNK
        def pad(a, start=start, stop=stop, n=n):
            return np.pad(a[start:stop], [(0, n - (stop - start))] + [(0, 0)] * (a.ndim - 1), mode="edge")

        p = pad(points)
        to_light = light - p
        distance = np.linalg.norm(to_light, axis=-1)
        to_light /= distance[:, None]
        to_camera = -p / np.linalg.norm(p, axis=-1, keepdims=True)
        fields = {}
        for name, value in params.items():
            value = np.asarray(value, np.float64)
            per_point = value.ndim == 2 or (value.ndim == 1 and name in ("eta", "rho_s", "sigma_s", "sigma_ss"))
            fields[name] = jnp.asarray(pad(value) if per_point else np.broadcast_to(value, (n,) + value.shape),
                                       jnp.float32)
        stokes = kernel(jnp.asarray(pad(normals), jnp.float32), jnp.asarray(to_light, jnp.float32),
                        jnp.asarray(to_camera, jnp.float32), jnp.asarray(distance, jnp.float32),
                        jnp.asarray(np.broadcast_to(axis, (n, 3)), jnp.float32),
                        jnp.asarray(np.broadcast_to([0.0, -1.0, 0.0], (n, 3)), jnp.float32), PBRDFParams(**fields))
        out[start:stop] = np.asarray(stokes_to_analyzers(stokes, axis=-2))[: stop - start]
    return out


_JITTED: dict = {}


def _jitted(fn):
    if fn not in _JITTED:
        import jax

        _JITTED[fn] = jax.jit(fn)
    return _JITTED[fn]


# --------------------------------------------------------------------------- planes: board and chart


@dataclass(frozen=True)
class BoardSpec:
    """A printed checkerboard: ``cols`` x ``rows`` inner corners, squares of ``square_m`` metres, a white
    margin of one square around the (cols + 1) x (rows + 1) squares. Board coordinates: origin at the first
    inner corner, x along a row of corners, y down the columns, z into the board (away from the camera)."""

    cols: int = 14
    rows: int = 10
    square_m: float = 0.010

    def corners(self) -> np.ndarray:
        """(rows * cols, 3) inner corners in board coordinates, row by row (OpenCV's order)."""
        j, i = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.stack([j.ravel() * self.square_m, i.ravel() * self.square_m, np.zeros(j.size)], axis=-1)

    def outline(self) -> np.ndarray:
        """(4, 3) corners of the board's paper, margin included."""
        s = self.square_m
        x0, x1 = -2 * s, (self.cols + 1) * s
        y0, y1 = -2 * s, (self.rows + 1) * s
        return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float64)

    def albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(...) albedo of board points: 0.03 (black squares), 0.8 (white squares and margin), 0 off the paper."""
        s = self.square_m
        i, j = np.floor(y / s) + 1, np.floor(x / s) + 1  # square index, 0 at the first square
        squares = (i >= 0) & (i <= self.rows) & (j >= 0) & (j <= self.cols)
        black = squares & ((i + j) % 2 == 0)
        on_paper = (x >= -2 * s) & (x <= (self.cols + 1) * s) & (y >= -2 * s) & (y <= (self.rows + 1) * s)
        return np.where(on_paper, np.where(black, 0.03, 0.8), 0.0)


def project(device: dict, points_cam: np.ndarray) -> np.ndarray:
    """Raw-pixel (u, v) (..., 2) of camera-coordinate points (..., 3), distortion included."""
    from sellip.model.render import distort_normalized

    cam = device["camera"]
    x, y = points_cam[..., 0] / points_cam[..., 2], points_cam[..., 1] / points_cam[..., 2]
    x, y = distort_normalized(x, y, cam["distortion"])
    return np.stack([cam["fx"] * x + cam["cx"], cam["fy"] * y + cam["cy"]], axis=-1)


def _render_plane(device: dict, rotation: np.ndarray, translation: np.ndarray, texture, supersample: int,
                  params: dict) -> np.ndarray:
    """Analyzers (H, W, 4, 3) of a textured plane z_plane = 0 at pose (R, t) (plane -> camera); texture(x, y)
    -> albedo (...) or (..., 3) in linear sRGB. Shading (rho_d = 1) on a grid, texture averaged per pixel."""
    import cv2

    sensor, cam = device["sensor"], device["camera"]
    width, height = sensor["width"], sensor["height"]
    rays = _Rays(cam, width, height)
    normal_cam = rotation[:, 2]
    offset = float(normal_cam @ translation)

    def hit(x, y):
        direction = np.stack([x, y, np.ones_like(x)], axis=-1)
        depth = offset / (direction @ normal_cam)
        points = direction * depth[..., None]
        local = (points - translation) @ rotation  # R^T (p - t) for row vectors
        return points, local, depth

    # plane coordinates of a normalized ray (x, y, 1): the inverse of the homography [r1 r2 t]
    inverse = np.linalg.inv(np.column_stack([rotation[:, 0], rotation[:, 1], translation]))

    def texture_at(x, y):
        w = inverse[2, 0] * x + inverse[2, 1] * y + inverse[2, 2]
        px = (inverse[0, 0] * x + inverse[0, 1] * y + inverse[0, 2]) / w
        py = (inverse[1, 0] * x + inverse[1, 1] * y + inverse[1, 2]) / w
        albedo = np.asarray(texture(px, py), np.float32)
        if albedo.ndim == x.ndim:
            albedo = albedo[..., None]
        return np.where((w > 0)[..., None], albedo, np.float32(0)).mean(axis=2)  # (h, W, 3 or 1)

    # Shading of the bare plane (rho_d = 1) at raw pixels (SHADE_STEP g + (SHADE_STEP - 1) / 2), so that
    # cv2.resize (pixel-centre convention) interpolates it bilinearly onto every pixel. Distortion changes
    # where a smooth shading lands by a few pixels at most: the grid uses the pinhole rays of those pixels.
    gu = SHADE_STEP * np.arange(width // SHADE_STEP) + (SHADE_STEP - 1) / 2
    gv = SHADE_STEP * np.arange(height // SHADE_STEP) + (SHADE_STEP - 1) / 2
    u, v = np.meshgrid(gu, gv)
    points, _, _ = hit((u - cam["cx"]) / cam["fx"], (v - cam["cy"]) / cam["fy"])
    facing = -np.sign(normal_cam[2]) * normal_cam  # towards the camera
    shade = _shade(points.reshape(-1, 3), np.broadcast_to(facing, (points.size // 3, 3)), device,
                   {**params, "rho_d": (1.0, 1.0, 1.0)}).reshape(len(gv), len(gu), 12)
    shade = cv2.resize(shade, (width, height), interpolation=cv2.INTER_LINEAR).reshape(height, width, 4, 3)
    out = np.empty((height, width, 4, 3), np.float32)
    for top in range(0, height, 128):
        rows = slice(top, min(height, top + 128))
        albedo = texture_at(*rays.block(rows, supersample))
        out[rows] = shade[rows] * albedo[:, :, None, :]
    return out


def board_poses(spec: BoardSpec, device: dict, count: int, rng: np.random.Generator,
                distance_m: tuple[float, float] = (0.45, 0.6), tilt_deg: tuple[float, float] = (20.0, 50.0),
                margin_px: float | None = None, max_tries: int = 100_000) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` board poses (R, t) (board -> camera) that a user would take: tilted 20-50 deg about a random
    axis in the board plane, rolled up to 30 deg, at 0.45-0.6 m, anywhere in the frame with the whole paper
    at least ``margin_px`` inside it (default 40 px, and on sensors narrower than 612 px the same share of the
    width as 40 px of 612, which the frame can hold). ValueError when ``max_tries`` draws per pose find none."""
    from scipy.spatial.transform import Rotation
    size = np.array([device["sensor"]["width"], device["sensor"]["height"]])
    margin_px = 40.0 * min(1.0, size[0] / 612) if margin_px is None else margin_px
    outline, half_fov = spec.outline(), 0.5 * size[0] / device["camera"]["fx"]
    low, high = np.array([(0, 2 * np.pi), tilt_deg, (-30, 30), distance_m, (-0.5, 0.5), (-0.5, 0.5)]).T

    def draw(u):  # (..., 6) uniform draws (Generator.uniform's formula), a try each -> R (..., 3, 3), t (..., 3)
        a, tilt, roll, distance, x, y = np.moveaxis(low + (high - low) * u, -1, 0)
        rotation = (Rotation.from_rotvec(np.radians(tilt)[..., None] * np.stack([np.cos(a), np.sin(a), 0 * a], -1))
                    * Rotation.from_rotvec(np.stack([0 * a, 0 * a, np.radians(roll)], -1))).as_matrix()
        target = np.stack([x * half_fov * distance, y * half_fov * distance * size[1] / size[0], distance], -1)
        return rotation, target - rotation @ outline.mean(axis=0)

    # 4096 tries (six draws each) at a time; the generator is left after the accepted try's draws: one seed, one set.
    poses, tries = [], 0
    while len(poses) < count and tries < max_tries * (len(poses) + 1):
        state, u = rng.bit_generator.state, rng.random((min(4096, max_tries * (len(poses) + 1) - tries), 6))
        rotation, translation = draw(u)
        pixels = project(device, np.einsum("kj,nij->nki", outline, rotation) + translation[:, None])
        found = np.flatnonzero(np.all((pixels > margin_px) & (pixels < size - margin_px), axis=(1, 2)))
        take = int(found[0]) + 1 if len(found) else len(u)
        tries, rng.bit_generator.state = tries + take, state
        rng.random((take, 6))  # the generator where one try at a time leaves it
        poses += [draw(u[take - 1])] if len(found) else []
    if len(poses) < count:
        raise ValueError(f"no board pose at {distance_m} m keeps the whole board {margin_px:.0f} px inside a "
                         f"{size[0]}x{size[1]} frame; expected a smaller board or margin")
    return poses


MATTE = {"eta": 1.5, "rho_s": 0.0, "sigma_s": 0.3, "rho_ss": (0.0, 0.0, 0.0), "sigma_ss": 0.3}
"""Printed paper: diffuse only (its diffuse polarization from Fresnel transmission is kept)."""


def render_board(device: dict, spec: BoardSpec, rotation: np.ndarray, translation: np.ndarray,
                 supersample: int = 3, blur_px: float = 0.0) -> np.ndarray:
    """Analyzer images (H, W, 4, 3) of the checkerboard at pose (R, t); ``blur_px`` > 0 adds a Gaussian
    defocus of that standard deviation (raw pixels)."""
    out = _render_plane(device, rotation, translation, spec.albedo, supersample, MATTE)
    if blur_px > 0:
        out = ndimage.gaussian_filter(out, sigma=(blur_px, blur_px, 0, 0))
    return out


# --------------------------------------------------------------------------- spheres


def render_spheres(device: dict, spheres: list[tuple[np.ndarray, float]], supersample: int = 2,
                   panel: float = 0.5, params: dict | None = None, reflect_panel: bool = True,
                   background: np.ndarray | None = None) -> np.ndarray:
    """Analyzer images (H, W, 4, 3) of glossy spheres (centre (3,) camera coordinates, radius) in front of an
    unpolarized light panel of radiance ``panel`` (analyzer images read panel / 2 each). With ``reflect_panel``
    the spheres mirror the panel (:func:`panel_reflection`), as real glossy spheres do at their limbs.
    ``background`` (H, W, 4, 3): what is seen where no sphere is, instead of the panel (the board the spheres
    stand on, :func:`render_board`; exact when every sphere lies on the camera's side of it)."""
    params = params or SPHERE_PARAMS
    sensor = device["sensor"]
    width, height = sensor["width"], sensor["height"]
    rays = _Rays(device["camera"], width, height)
    out = np.empty((height, width, 4, 3), np.float32)
    n_sub = supersample * supersample
    for top in range(0, height, 128):
        rows = slice(top, min(height, top + 128))
        x, y = rays.block(rows, supersample)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        t_best = np.full(x.shape, np.inf)
        which = np.full(x.shape, -1)
        for k, (centre, radius) in enumerate(spheres):
            b = d @ np.asarray(centre, np.float64)
            disc = b * b - (np.dot(centre, centre) - radius * radius)
            t = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
            closer = t < t_best
            t_best = np.where(closer, t, t_best)
            which = np.where(closer, k, which)
        if background is None:
            samples = np.full(x.shape + (4, 3), panel / 2, np.float32)
        else:
            samples = np.repeat(background[rows][:, :, None], n_sub, axis=2).astype(np.float32)
        hit = np.isfinite(t_best)
        if hit.any():
            points = d[hit] * t_best[hit][:, None]
            centres = np.asarray([s[0] for s in spheres], np.float64)[which[hit]]
            radii = np.asarray([s[1] for s in spheres], np.float64)[which[hit]]
            normals = (points - centres) / radii[:, None]
            shaded = _shade(points, normals, device, params)
            if reflect_panel and panel > 0:
                shaded += panel_reflection(points, normals, float(params["eta"]), panel)[:, :, None]
            samples[hit] = shaded
        out[rows] = samples.reshape(samples.shape[0], width, n_sub, 4, 3).mean(axis=2)
    return out


def _placeable(device: dict, centres: list[np.ndarray], radius: float, margin_px: float) -> bool:
    """Whether spheres of ``radius`` at ``centres`` (camera coordinates) are each wholly in view, ``margin_px``
    inside the frame, and apart from one another in the image."""
    sensor, cam = device["sensor"], device["camera"]
    ok = True
    for c in centres:
        r_px = cam["fx"] * radius / c[2] * 1.15
        u, v = project(device, c)
        ok &= margin_px + r_px < u < sensor["width"] - margin_px - r_px
        ok &= margin_px + r_px < v < sensor["height"] - margin_px - r_px
    for a in range(len(centres)):
        for b in range(a):
            gap = np.linalg.norm(project(device, centres[a]) - project(device, centres[b]))
            ok &= gap > cam["fx"] * radius * (1 / centres[a][2] + 1 / centres[b][2]) * 1.3
    return bool(ok)


def sphere_layouts(device: dict, frames: int, rng: np.random.Generator, radius: float = SPHERE_RADIUS_M,
                   per_frame: int = 3, distance_m: tuple[float, float] = (0.4, 0.55), margin_px: float | None = None,
                   max_tries: int = 100000) -> list[list[np.ndarray]]:
    """Sphere centres (camera coordinates) for ``frames`` frames, ``per_frame`` spheres each, spread over the
    field (a 3x3 grid of cells, one sphere per cell), wholly in view and not overlapping in the image."""
    sensor, cam = device["sensor"], device["camera"]
    margin_px = 60.0 * sensor["width"] / 2448 if margin_px is None else margin_px
    layouts = []
    cells = [(i, j) for i in range(3) for j in range(3)]
    for _ in range(max_tries):
        if len(layouts) == frames:
            break
        chosen = rng.choice(len(cells), size=per_frame, replace=False)
        centres = []
        for index in chosen:
            i, j = cells[index]
            z = rng.uniform(*distance_m)
            u = (j + rng.uniform(0.25, 0.75)) * sensor["width"] / 3
            v = (i + rng.uniform(0.25, 0.75)) * sensor["height"] / 3
            centres.append(np.array([(u - cam["cx"]) / cam["fx"] * z, (v - cam["cy"]) / cam["fy"] * z, z]))
        if _placeable(device, centres, radius, margin_px):
            layouts.append(centres)
    else:
        raise ValueError(f"cannot place {per_frame} spheres of radius {radius} m wholly in a {sensor['width']}x"
                         f"{sensor['height']} frame at {distance_m} m; fewer or smaller spheres")
    return layouts


def board_sphere_layouts(spec: BoardSpec, device: dict, frames: int, rng: np.random.Generator, radius: float,
                         per_frame: int = 3, max_tries: int = 100000
                         ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``frames`` layouts of ``per_frame`` spheres resting on the board at square centres
    (:func:`sellip.calibrate.board_spheres.square_centres`),
    each (R, t, marks (per_frame, 2)): the board at a pose of :func:`board_poses`, every sphere wholly in view
    and apart from the others in the image."""
    sensor = device["sensor"]
    margin = 20.0 * sensor["width"] / 2448
    marks = square_centres(spec.cols, spec.rows, spec.square_m)
    layouts = []
    for _ in range(max_tries):
        if len(layouts) == frames:
            return layouts
        rotation, translation = board_poses(spec, device, 1, rng)[0]
        chosen = marks[rng.choice(len(marks), size=per_frame, replace=False)]
        centres = [sphere_centre(rotation, translation, m, radius) for m in chosen]
        if _placeable(device, centres, radius, margin):
            layouts.append((rotation, translation, chosen))
    raise ValueError(f"cannot set {per_frame} spheres of radius {radius} m on the board wholly in a "
                     f"{sensor['width']}x{sensor['height']} frame; fewer or smaller spheres")


# --------------------------------------------------------------------------- colour chart


def chart_reference_srgb() -> np.ndarray:
    """(24, 3) linear sRGB (D65) of the ColorChecker 24 patches (colour-science's 'ColorChecker24 - After
    November 2014', Bradford-adapted from D50), row by row from dark skin to black."""
    import colour
    checker = colour.CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"]
    xyy = np.array(list(checker.data.values()))
    xyz = colour.xyY_to_XYZ(xyy)
    return colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], illuminant=checker.illuminant,
                             chromatic_adaptation_transform="Bradford", apply_cctf_encoding=False)


CHART_PATCH_M = 0.04
"""Patch pitch of the synthetic chart (the real ColorChecker Classic: 41 mm), 6 x 4 patches; patches are
0.8 of the pitch with black borders."""


def chart_corners_board() -> np.ndarray:
    """(4, 3) the chart's patch-area corners in chart coordinates: top-left (dark skin's outer corner), top-right,
    bottom-right, bottom-left."""
    w, h = 6 * CHART_PATCH_M, 4 * CHART_PATCH_M
    return np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], np.float64)


def chart_texture(reference: np.ndarray):
    def texture(x, y):
        j, i = np.floor(x / CHART_PATCH_M), np.floor(y / CHART_PATCH_M)
        fx, fy = x / CHART_PATCH_M - j, y / CHART_PATCH_M - i
        inside = (j >= 0) & (j < 6) & (i >= 0) & (i < 4)
        in_patch = inside & (np.abs(fx - 0.5) < 0.4) & (np.abs(fy - 0.5) < 0.4)
        index = np.clip(i * 6 + j, 0, 23).astype(np.int64)
        on_card = (x > -0.01) & (x < 6 * CHART_PATCH_M + 0.01) & (y > -0.01) & (y < 4 * CHART_PATCH_M + 0.01)
        base = np.where(on_card, 0.02, 0.0)[..., None] * np.ones(3)
        return np.where(in_patch[..., None], reference[index], base)
    return texture


CHART_SHEEN = {"rho_s": 1.0, "sigma_s": 0.1}
"""The chart's surface sheen at ``render_chart(..., sheen=1)``: a specular lobe (a printed chart's semi-matte
varnish) that mirrors the polarized flash where the chart faces it; facing the camera squarely at 0.9 m with
the flash 5 cm below the lens, its patches' light is 10 % polarized (median; 24 % the darkest)."""


def render_chart(device: dict, rotation: np.ndarray, translation: np.ndarray, supersample: int = 2,
                 shadow: float = 1.0, sheen: float = 0.0) -> np.ndarray:
    """Analyzer images (H, W, 4, 3) of a ColorChecker at pose (R, t) (chart -> camera) under the flash (its
    fall-off across the chart included); ``shadow`` < 1 dims the flash on it (a chart in shadow); ``sheen``
    scales :data:`CHART_SHEEN`'s lobe (0, the default: matte)."""
    params = {**MATTE, "rho_s": CHART_SHEEN["rho_s"] * sheen, "sigma_s": CHART_SHEEN["sigma_s"]}
    out = _render_plane(device, rotation, translation, chart_texture(chart_reference_srgb()), supersample, params)
    return out * np.float32(shadow)


# --------------------------------------------------------------------------- exposure and the folder


def expose(analyzers: np.ndarray, device: dict, peak_dn: float, rng: np.random.Generator,
           reference: float | None = None) -> np.ndarray:
    """Raw mosaic (H, W) uint16: ``analyzers`` scaled so that ``reference`` (default: their 99.9th percentile)
    reads ``peak_dn`` above black, through :func:`sellip.sensor.simulate_raw` with the device's sensor."""
    from sellip.capture.sensor import simulate_raw

    if reference is None:
        reference = float(np.percentile(analyzers, 99.9))
    return simulate_raw(analyzers, _sensor(device), peak_dn / reference, rng)


def look_at(target: np.ndarray, tilt_deg: float, rng: np.random.Generator) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = rng.uniform(0, 2 * np.pi)
    return Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(axis), np.sin(axis), 0.0])).as_matrix()
