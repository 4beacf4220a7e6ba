"""Renders, Mueller-matrix images, AoLP/DoP images and parameter maps of a model (docs/design.md §1 outputs,
paper Fig. 10).

Public API::

    object_center(mesh) -> (3,)                          # centre of the vertices' bounding box
    novel_camera(cameras, target, reference=0, elevate_deg=20.0) -> Camera
    moved_flash(camera, flash_position_cam, offset_cam=NEW_LIGHT_OFFSET_M, polarizer_deg=0.0) -> Light
    mueller_image(renderer, camera, light, supersample=1, shadows=True) -> (H, W, 3, 3, 3)
    polarization_images(stokes) -> (dop (H, W), aolp (H, W) radians)
    parameter_maps(renderer, camera, supersample=1, extra=None) -> ({name: (H, W, C)}, coverage (H, W))
    fit_scale(reference, estimate, mask) -> float       # least-squares k with reference ≈ k estimate
    tone_map(analyzers, mask, scale=None) -> (uint8 (H, W, 3), scale)
    map_figure(...), mueller_figure(...), polarization_figure(...), grid_figure(...), timings_figure(...)
    write_renders(mesh, cameras, flash_position_cam, polarizer_deg, views, output, ...) -> index (dict)

Images are batch-first, channels last: Stokes (H, W, 4, 3) (s0..s3, then RGB) in each pixel ray's camera
frame (x = image right, y = image up, :mod:`sellip.model.conventions`); Mueller blocks (H, W, C, 3, 3) with C = RGB,
rows = exitant (s0, s1, s2) in the camera frame, columns = incident (s0, s1, s2) in the flash's frame
(x = its polarizer axis), as :func:`sellip.model.pbrdf.full_mueller`. Units are those of the renderer (unit flash
intensity); the model's albedos are relative, so images are shown tone-mapped, never in absolute units.

The renderer is linear in the light's Stokes vector, so the 3x3 linear block is exact from three renders:
incident [1, 0, 0, 0] gives column 0; [1, 1, 0, 0] gives column 0 + column 1; [1, 0, 1, 0] gives column 0 +
column 2 (:class:`sellip.model.render.Light` ``stokes``).

Figures use matplotlib's object API (``matplotlib.figure.Figure``, Agg canvas): no pyplot state.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from sellip.capture.reader import read_capture
from sellip.capture.scenes import look_at_rotation
from sellip.geometry.cameras import load_cameras
from sellip.jobs import atomic_file
from sellip.model.ply import read_param_mesh, read_ply
from sellip.model.render import Camera, Light, ParamMesh, Renderer, flash_light
from sellip.report.previews import WHITE_PERCENTILE, dolp_aolp, srgb_encode, to_uint8
from sellip.settings import setting

log = logging.getLogger(__name__)

NEW_LIGHT_OFFSET_M = (0.2, 0.0, 0.0)
"""Where the "new light" goes: this offset (camera coordinates, metres; +x = image right) from the flash."""

NOVEL_ELEVATION_DEG = 20.0
"""The novel view is raised by this angle (towards the cameras' mean up) above the midpoint of two views."""

MUELLER_BASIS = ((1.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.0, 0.0), (1.0, 0.0, 1.0, 0.0))
"""Incident Stokes vectors (flash frame) rendered to recover the 3x3 Mueller block: unpolarized, 0 deg, 45 deg."""

DARK_FRACTION = 0.01
"""AoLP, DoP and normalized Mueller elements are masked where s0 (or M00) is below this fraction of white."""

MAP_SPECS = {
    # name: (vertex attribute, title, colour map or "rgb"/"normal")
    "eta": ("refractive index η", "viridis"),
    "rho_d": ("diffuse albedo ρ_d (relative)", "rgb"),
    "rho_s": ("specular albedo ρ_s (relative)", "magma"),
    "sigma_s": ("specular roughness σ_s", "cividis"),
    "rho_ss": ("single-scattering albedo ρ_ss (relative)", "rgb"),
    "sigma_ss": ("single-scattering roughness σ_ss", "cividis"),
    "normal": ("normal (camera frame: x right, y up, z to camera)", "normal"),
}
"""The parameter maps (``map_<name>.png``) in this order; ``confidence`` is added when the model has it."""


# --------------------------------------------------------------------------- cameras and lights


def object_center(mesh: ParamMesh) -> np.ndarray:
    """Centre (3,) of the axis-aligned bounding box of the mesh's vertices."""
    vertices = np.asarray(mesh.vertices, np.float64)
    return 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))


def novel_camera(cameras: list[Camera], target: np.ndarray, reference: int = 0,
                 elevate_deg: float = NOVEL_ELEVATION_DEG) -> Camera:
    """A camera no capture used: between ``cameras[reference]`` and its angular nearest neighbour, raised.

    Direction from ``target``: the normalized sum of the two cameras' directions, rotated by ``elevate_deg``
    towards the cameras' mean up axis (never past it); distance: the mean of the two; image up: the mean up.
    Intrinsics and size of ``cameras[reference]``.
    """
    base = cameras[reference]
    centers = np.stack([c.center for c in cameras])
    directions = centers - target
    distances = np.linalg.norm(directions, axis=1)
    directions /= distances[:, None]
    up = np.mean([c.up for c in cameras], axis=0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else base.up
    cosines = directions @ directions[reference]
    cosines[reference] = -np.inf
    neighbour = int(np.argmax(cosines)) if len(cameras) > 1 else reference
    middle = directions[reference] + directions[neighbour]
    middle = middle / np.linalg.norm(middle) if np.linalg.norm(middle) > 1e-9 else directions[reference]
    elevation = np.arcsin(np.clip(middle @ up, -1, 1))
    new_elevation = min(elevation + np.radians(elevate_deg), np.radians(85.0))
    horizontal = middle - (middle @ up) * up
    horizontal = horizontal / np.linalg.norm(horizontal) if np.linalg.norm(horizontal) > 1e-9 else base.rotation[0]
    direction = np.cos(new_elevation) * horizontal + np.sin(new_elevation) * up
    center = target + 0.5 * (distances[reference] + distances[neighbour]) * direction
    rotation = look_at_rotation(center, target, up=up)
    return Camera(intrinsics=base.intrinsics, rotation=rotation, translation=-rotation @ center,
                  width=base.width, height=base.height)


def moved_flash(camera: Camera, flash_position_cam, offset_cam=NEW_LIGHT_OFFSET_M,
                polarizer_deg: float = 0.0) -> Light:
    """The rig's flash moved by ``offset_cam`` (camera coordinates, metres), same polarizer: a new light."""
    position = np.asarray(flash_position_cam, np.float64) + np.asarray(offset_cam, np.float64)
    return flash_light(camera, position, polarizer_deg=polarizer_deg)


# --------------------------------------------------------------------------- polarimetric images


def mueller_image(renderer: Renderer, camera: Camera, light: Light, supersample: int = 1,
                  shadows: bool = True) -> np.ndarray:
    """The linear 3x3 Mueller block per pixel and colour, (H, W, 3, 3, 3) float32: [..., c, row, column].

    Exact by linearity from renders with incident Stokes :data:`MUELLER_BASIS` (module docstring);
    ``light`` gives the position, the frame (its axis) and the intensity.
    """
    columns = [renderer.render(camera, replace(light, stokes=basis), supersample=supersample,
                               shadows=shadows).stokes[..., :3, :] for basis in MUELLER_BASIS]  # (H, W, 3, C)
    unpolarized = columns[0]
    block = np.stack([unpolarized, columns[1] - unpolarized, columns[2] - unpolarized], axis=-1)  # (H, W, 3, C, 3)
    return np.moveaxis(block, -2, 2).astype(np.float32)


def polarization_images(stokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """DoP and AoLP of the colour-averaged Stokes image (H, W, 4, C): (dop (H, W) in [0, 1], aolp in [0, pi)).

    DoP = sqrt(s1^2 + s2^2 + s3^2) / s0; AoLP counter-clockwise from image x (:func:`sellip.report.previews.dolp_aolp`).
    """
    mean = np.asarray(stokes, np.float32).mean(axis=-1)  # (H, W, 4)
    dolp, aolp = dolp_aolp(mean[..., :3])
    s0 = mean[..., 0]
    circular = np.where(s0 > 0, np.abs(mean[..., 3]) / np.where(s0 > 0, s0, 1), 0)
    return np.clip(np.hypot(dolp, circular), 0, 1).astype(np.float32), aolp


def parameter_maps(renderer: Renderer, camera: Camera, supersample: int = 1,
                   extra: dict[str, np.ndarray] | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-pixel model parameters seen from ``camera``: {name: (H, W, C) float32} and coverage (H, W).

    Names: those of :data:`MAP_SPECS` (the normal unit, in the camera frame x right, y up, z towards the
    camera) plus ``extra`` per-vertex arrays (V,) or (V, C). Values are barycentric interpolations of the
    vertex values at each pixel's hits (:meth:`sellip.model.render.Renderer.interpolate`); 0 where nothing is hit.
    """
    mesh = renderer.mesh
    n = mesh.num_vertices
    columns = {name: np.asarray(getattr(mesh.params, name), np.float64).reshape(n, -1)
               for name in MAP_SPECS if name != "normal"}
    columns["normal"] = np.asarray(mesh.normals, np.float64)
    for name, values in (extra or {}).items():
        columns[name] = np.asarray(values, np.float64).reshape(n, -1)
    names = list(columns)
    widths = [columns[name].shape[1] for name in names]
    values, coverage = renderer.interpolate(camera, np.concatenate([columns[k] for k in names], axis=1),
                                            supersample=supersample)
    maps = dict(zip(names, np.split(values, np.cumsum(widths)[:-1], axis=-1)))
    normal_cam = maps["normal"] @ np.asarray(camera.rotation, np.float32).T  # OpenCV camera axes
    normal_cam *= np.array([1.0, -1.0, -1.0], np.float32)  # -> x right, y up, z towards the camera
    length = np.linalg.norm(normal_cam, axis=-1, keepdims=True)
    maps["normal"] = np.where(length > 0, normal_cam / np.where(length > 0, length, 1), 0).astype(np.float32)
    return maps, coverage


# --------------------------------------------------------------------------- tone mapping


def fit_scale(reference: np.ndarray, estimate: np.ndarray, mask: np.ndarray) -> float:
    """Least-squares k minimizing ||reference - k estimate||^2 over the pixels in ``mask`` (H, W).

    reference, estimate: (H, W, ...) of the same shape (all trailing values count). 1.0 when estimate is 0 there.
    """
    ref = np.asarray(reference, np.float64)[mask]
    est = np.asarray(estimate, np.float64)[mask]
    denominator = float(np.sum(est * est))
    return float(np.sum(ref * est) / denominator) if denominator > 0 else 1.0


def tone_map(analyzers: np.ndarray, mask: np.ndarray, scale: float | None = None) -> tuple[np.ndarray, float]:
    """sRGB uint8 (H, W, 3) of s0 = (I0 + I45 + I90 + I135) / 2 from analyzers (H, W, 4, C).

    ``scale`` maps to white; by default the :data:`sellip.report.previews.WHITE_PERCENTILE` of the colour-averaged
    s0 inside ``mask`` (as the HDR previews). Returns the image and the scale used.
    """
    s0 = 0.5 * np.asarray(analyzers, np.float32).sum(axis=-2)  # (H, W, C)
    if scale is None:
        inside = s0.mean(axis=-1)[mask]
        scale = float(np.percentile(inside, WHITE_PERCENTILE)) if inside.size else 1.0
        scale = scale if scale > 0 else 1.0
    return to_uint8(srgb_encode(s0 / scale)), scale


# --------------------------------------------------------------------------- figures


def _figure(rows: int, cols: int, height_px: int, width_px: int, panel_in: float = 3.2):
    """A matplotlib Figure (Agg) with a grid of axes sized for images of height_px x width_px."""
    from matplotlib.figure import Figure

    aspect = height_px / max(width_px, 1)
    fig = Figure(figsize=(cols * panel_in * 1.25, rows * panel_in * aspect + 0.5 * rows), dpi=110,
                 layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False))
    return fig, axes


def _robust_range(values: np.ndarray, low: float = 1.0, high: float = 99.0) -> tuple[float, float]:
    if values.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(values, [low, high]))
    if hi - lo < 1e-6 * max(abs(hi), 1.0):
        lo, hi = lo - 0.05 * max(abs(lo), 1e-3), hi + 0.05 * max(abs(hi), 1e-3)
    return lo, hi


def draw_map(ax, name: str, image: np.ndarray, mask: np.ndarray, title: str | None = None) -> None:
    """Draw one parameter map (H, W, C) on ``ax`` with a colour bar; pixels outside ``mask`` are white."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    label, kind = MAP_SPECS.get(name, (name, "viridis"))
    ax.set_title(title or label, fontsize=8)
    ax.set_axis_off()
    fig = ax.get_figure()
    if kind == "normal":
        rgb = np.where(mask[..., None], 0.5 * (image + 1), 1.0)
        ax.imshow(np.clip(rgb, 0, 1), interpolation="nearest")
        fig.colorbar(ScalarMappable(Normalize(-1, 1), colormaps["gray"]), ax=ax, shrink=0.8,
                     label="component (R = x, G = y, B = z)")
    elif kind == "rgb":
        _, vmax = _robust_range(image.max(axis=-1)[mask], 0.0, 99.0)
        vmax = vmax if vmax > 0 else 1.0
        ax.imshow(np.where(mask[..., None], np.clip(image / vmax, 0, 1), 1.0), interpolation="nearest")
        fig.colorbar(ScalarMappable(Normalize(0, vmax), colormaps["gray"]), ax=ax, shrink=0.8,
                     label="per channel")
    else:
        scalar = image[..., 0]
        vmin, vmax = _robust_range(scalar[mask])
        ax.imshow(np.ma.masked_where(~mask, scalar), cmap=kind, vmin=vmin, vmax=vmax, interpolation="nearest")
        fig.colorbar(ScalarMappable(Normalize(vmin, vmax), colormaps[kind]), ax=ax, shrink=0.8)


def map_figure(name: str, image: np.ndarray, mask: np.ndarray):
    """Figure of one parameter map with its colour bar."""
    fig, axes = _figure(1, 1, *image.shape[:2])
    draw_map(axes[0, 0], name, image, mask)
    return fig


def grid_figure(maps: dict[str, np.ndarray], mask: np.ndarray, cols: int = 4):
    """All parameter maps in a grid, each with its colour bar."""
    names = list(maps)
    rows = -(-len(names) // cols)
    fig, axes = _figure(rows, cols, *next(iter(maps.values())).shape[:2], panel_in=2.6)
    for ax, name in zip(axes.ravel(), names):
        draw_map(ax, name, maps[name], mask)
    for ax in axes.ravel()[len(names):]:
        ax.set_axis_off()
    return fig


def mueller_figure(mueller: np.ndarray, coverage: np.ndarray):
    """3x3 grid of the colour-averaged Mueller block: M00 tone-mapped (relative to its 99.5th percentile),
    the other elements normalized by M00 in [-1, 1] (diverging colours; blank where M00 is dark)."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    block = np.asarray(mueller, np.float32).mean(axis=2)  # (H, W, 3, 3)
    m00 = block[..., 0, 0]
    inside = coverage > 0
    white = float(np.percentile(m00[inside], WHITE_PERCENTILE)) if inside.any() else 1.0
    white = white if white > 0 else 1.0
    bright = inside & (m00 > DARK_FRACTION * white)
    fig, axes = _figure(3, 3, *m00.shape, panel_in=2.4)
    for i in range(3):
        for j in range(3):
            ax = axes[i, j]
            ax.set_axis_off()
            if i == 0 and j == 0:
                ax.set_title("M00 (relative)", fontsize=8)
                ax.imshow(np.clip(m00 / white, 0, 1), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
                fig.colorbar(ScalarMappable(Normalize(0, 1), colormaps["gray"]), ax=ax, shrink=0.8)
                continue
            ratio = np.where(bright, block[..., i, j] / np.where(bright, m00, 1), np.nan)
            ax.set_title(f"M{i}{j} / M00", fontsize=8)
            ax.imshow(np.ma.masked_invalid(ratio), cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
            fig.colorbar(ScalarMappable(Normalize(-1, 1), colormaps["RdBu_r"]), ax=ax, shrink=0.8)
    return fig


def polarization_figure(kind: str, dop: np.ndarray, aolp: np.ndarray, s0: np.ndarray, coverage: np.ndarray):
    """``kind`` "dop" (viridis, [0, 1]) or "aolp" (cyclic hsv, [0, 180) deg); blank where s0 is dark."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    inside = coverage > 0
    white = float(np.percentile(s0[inside], WHITE_PERCENTILE)) if inside.any() else 1.0
    bright = inside & (s0 > DARK_FRACTION * max(white, 1e-30))
    fig, axes = _figure(1, 1, *s0.shape)
    ax = axes[0, 0]
    ax.set_axis_off()
    if kind == "dop":
        values, cmap, norm, label = dop, "viridis", Normalize(0, 1), "degree of polarization"
    else:
        values, cmap, norm, label = np.degrees(aolp), "hsv", Normalize(0, 180), "AoLP (deg, from image x, ccw)"
    ax.set_title(label, fontsize=8)
    ax.imshow(np.ma.masked_where(~bright, values), cmap=cmap, norm=norm, interpolation="nearest")
    fig.colorbar(ScalarMappable(norm, colormaps[cmap]), ax=ax, shrink=0.8, label=label)
    return fig


def timings_figure(rules: dict[str, dict]):
    """Horizontal bar chart of the wall time per rule (``{rule: {"s": seconds, "jobs": n}}``), longest first."""
    from matplotlib.figure import Figure

    order = sorted(rules, key=lambda r: rules[r]["s"])
    fig = Figure(figsize=(6.4, 0.8 + 0.32 * max(len(order), 1)), dpi=110, layout="constrained")
    ax = fig.subplots()
    seconds = [rules[r]["s"] for r in order]
    ax.barh(range(len(order)), seconds, color="tab:blue")
    ax.set_yticks(range(len(order)), [f"{r} ({rules[r]['jobs']} jobs)" for r in order], fontsize=8)
    ax.set_xlabel("wall time per rule, summed over its jobs (s)")
    for k, s in enumerate(seconds):
        ax.text(s, k, f" {s:.1f}", va="center", fontsize=7)
    return fig


def convergence_figure(rows: list[dict]):
    """The geometry over the loop (rows of :func:`sellip.report.figures_of_merit.geometry_series`): Chamfer to the
    previous mesh and to the truth (mm, left), median normal error of the mesh and of the fitted normals (deg,
    right)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 3.2), dpi=110, layout="constrained")
    left, right = fig.subplots(1, 2)
    x = [row["mesh"] for row in rows]

    def series(key, sub=None):
        values = [row.get(key) for row in rows]
        values = [v.get(sub) if isinstance(v, dict) else v for v in values] if sub else values
        return [np.nan if v is None else v for v in values]

    left.plot(x, series("chamfer_to_previous_mm"), "o-", label="to the previous mesh")
    if any(row.get("chamfer_mm") is not None for row in rows):
        left.plot(x, series("chamfer_mm"), "s-", label="to the ground truth")
    left.set(xlabel="mesh (0: initial; i: after iteration i-1)", ylabel="Chamfer distance (mm)")
    left.legend(fontsize=8)
    if any(row.get("mesh_normal_deg") for row in rows):
        right.plot(x, series("mesh_normal_deg", "median"), "s-", label="mesh normals")
        right.plot(x, series("fitted_normal_deg", "median"), "o-", label="fitted normals (confident)")
        right.set(xlabel="mesh", ylabel="normal error, median (deg)")
        right.legend(fontsize=8)
    else:
        right.set_axis_off()
        right.text(0.5, 0.5, "no ground truth", ha="center", va="center")
    return fig


def save_figure(fig, path: str | Path) -> Path:
    """Write a matplotlib figure as PNG."""
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


# --------------------------------------------------------------------------- the renders folder


def write_renders(mesh: ParamMesh, cameras: dict[str, Camera], flash_position_cam, polarizer_deg: float,
                  views: list[str], output: str | Path, supersample: int = 2, measured=None,
                  extra_maps: dict[str, np.ndarray] | None = None,
                  new_light_offset_cam=NEW_LIGHT_OFFSET_M) -> dict:
    """Write the renders of a model into the existing folder ``output``; returns the index (also index.json).

    cameras: every captured camera by view id (cameras.csv poses, HDR-resolution intrinsics); views: the ones
    to re-render (the first is the reference view of the novel view, the new light, the Mueller, AoLP/DoP
    images and the maps); measured: optional ``view_id -> (analyzers (H, W, 4, C), valid (H, W))`` for the
    measured counterpart of each re-rendered view. File names: see docs/outputs.md.
    Long: one image per kind and view, written in a fixed order (docs/outputs.md's list).
    """
    import imageio.v3 as iio

    output = Path(output)
    renderer = Renderer(mesh)
    files: list[dict] = []

    def add(name: str, kind: str, description: str, **details) -> None:
        files.append({"file": name, "kind": kind, "description": description, **details})
        log.debug("wrote %s", output / name)

    def flash(camera: Camera) -> Light:
        return flash_light(camera, flash_position_cam, polarizer_deg=polarizer_deg)

    reference = views[0]
    reference_result = None
    for view_id in views:
        camera = cameras[view_id]
        result = renderer.render(camera, flash(camera), supersample=supersample)
        inside = result.coverage > 0
        image, scale = tone_map(result.analyzers, inside)
        iio.imwrite(output / f"view_{view_id}.png", image)
        add(f"view_{view_id}.png", "render", "captured view re-rendered with the model under the flash", view=view_id,
            white=scale)
        if measured is not None:
            analyzers, valid = measured(view_id)
            k = fit_scale(analyzers, result.analyzers, valid & inside)
            k = k if k > 0 else 1.0  # nothing in common (e.g. an empty render): show the measured view as it is
            image, _ = tone_map(np.asarray(analyzers) / k, valid, scale=scale)
            iio.imwrite(output / f"view_{view_id}_measured.png", image * valid[..., None].astype(np.uint8))
            add(f"view_{view_id}_measured.png", "measured",
                "the measured HDR view, exposed like the render after one global scale", view=view_id, scale=k)
        if view_id == reference:
            reference_result = result
    base = cameras[reference]
    ordered = list(cameras.values())
    novel = novel_camera(ordered, object_center(mesh), reference=list(cameras).index(reference))
    result = renderer.render(novel, flash(novel), supersample=supersample)
    iio.imwrite(output / "novel_view.png", tone_map(result.analyzers, result.coverage > 0)[0])
    add("novel_view.png", "render", f"a view no capture used (between {reference} and its nearest captured "
        f"neighbour, raised {NOVEL_ELEVATION_DEG:g} deg), flash on that camera",
        camera_center=novel.center.tolist())
    light = moved_flash(base, flash_position_cam, new_light_offset_cam, polarizer_deg)
    result = renderer.render(base, light, supersample=supersample)
    iio.imwrite(output / "new_light.png", tone_map(result.analyzers, result.coverage > 0)[0])
    add("new_light.png", "render", f"view {reference} with the polarized flash moved by {list(new_light_offset_cam)} m "
        "(camera coordinates)", view=reference, light_position=light.position.tolist())

    mueller = mueller_image(renderer, base, flash(base), supersample=supersample)
    np.savez_compressed(output / "mueller.npz", mueller=mueller, coverage=reference_result.coverage)
    save_figure(mueller_figure(mueller, reference_result.coverage), output / "mueller.png")
    add("mueller.png", "mueller", "3x3 linear Mueller matrix of each pixel (colour-averaged), flash frame -> "
        "camera frame", view=reference)
    add("mueller.npz", "data", "mueller (H, W, 3 RGB, 3 rows, 3 columns) float32 and coverage (H, W)",
        view=reference)
    dop, aolp = polarization_images(reference_result.stokes)
    s0 = reference_result.stokes[..., 0, :].mean(axis=-1)
    for kind in ("aolp", "dop"):
        save_figure(polarization_figure(kind, dop, aolp, s0, reference_result.coverage), output / f"{kind}.png")
        add(f"{kind}.png", kind, f"{kind.upper()} of the re-rendered view under the flash", view=reference)

    maps, coverage = parameter_maps(renderer, base, supersample=1, extra=extra_maps)
    inside = coverage > 0
    for name, image in maps.items():
        save_figure(map_figure(name, image, inside), output / f"map_{name}.png")
        add(f"map_{name}.png", "map", MAP_SPECS.get(name, (name,))[0], view=reference)
    save_figure(grid_figure(maps, inside), output / "maps.png")
    add("maps.png", "maps", "all parameter maps", view=reference)
    index = {"reference_view": reference, "views": list(views), "supersample": supersample,
             "flash_position_cam_m": list(map(float, flash_position_cam)), "polarizer_deg": float(polarizer_deg),
             "files": files}
    (output / "index.json").write_text(json.dumps(index, indent=2))
    return index


DEFAULT_VIEWS = 3
"""Views re-rendered when none are named (evenly spread over cameras.csv)."""


@dataclass(frozen=True)
class EvaluateSettings:
    """Settings of the final renders and the figures of merit (config section ``evaluate``; each declared once here,
    :mod:`sellip.settings`): ``sellip render-outputs`` takes ``render_views`` and ``supersample``, ``sellip evaluate``
    ``held_out_views``, ``metrics_supersample`` and ``geometry_samples``. ``held_out_views`` is also read by the
    workflow: the observe and geometry jobs leave those views out (``--exclude-views``)."""

    held_out_views: tuple[str, ...] = setting((), "captured views never used in the fit (left out of every "
                                              "observation store); the evaluate job re-renders them for PSNR")
    render_views: tuple[str, ...] = setting((), "captured views re-rendered in final/renders; the first also gives "
                                            "the Mueller, AoLP/DoP and maps ([]: DEFAULT_VIEWS spread evenly)")
    supersample: int = setting(1, "supersampling of the renders of final/renders (render-outputs)",
                               unit="samples per pixel per axis", minimum=1, maximum=4)
    metrics_supersample: int = setting(2, "supersampling of the evaluate job's renders (held-out PSNR, the "
                                       "ground-truth comparisons)", unit="samples per pixel per axis", minimum=1,
                                       maximum=4)
    geometry_samples: int = setting(50000, "surface samples per mesh for the Chamfer and Hausdorff distances",
                                    minimum=1)



class OutputsError(ValueError):
    """An input of render-outputs or evaluate that is missing or inconsistent (the message names the file)."""



def default_views(view_ids: list[str], count: int = DEFAULT_VIEWS) -> list[str]:
    """``count`` view ids evenly spread over ``view_ids`` (all of them when there are fewer)."""
    picks = np.unique(np.linspace(0, len(view_ids) - 1, min(count, len(view_ids))).round().astype(int))
    return [view_ids[i] for i in picks]



def model_confidence(model_path: str | Path) -> np.ndarray | None:
    """The ``confidence`` vertex property of a model PLY (V,) float64, None when it has none."""
    vertex, _ = read_ply(model_path)
    return vertex["confidence"].astype(np.float64) if "confidence" in vertex else None



def render_outputs(model_path: str | Path, cameras_path: str | Path, hdr_path: str | Path, capture_path: str | Path,
              output: str | Path, views: list[str] | None = None,
              supersample: int = EvaluateSettings.supersample) -> dict:
    """Write the renders folder (module docstring); returns its index."""
    from sellip.jobs import atomic_directory

    started = time.perf_counter()
    if not Path(model_path).is_file():
        raise OutputsError(f"{model_path}: model does not exist")
    mesh = read_param_mesh(model_path)
    light = read_capture(capture_path, check_files=False).config["light"]  # no raw frame is read here
    cameras, hdr = load_cameras(cameras_path, hdr_path)
    unknown = [v for v in views or [] if v not in cameras]
    if unknown:  # e.g. views SfM could not register: render the others
        log.warning("%s has no pose for requested view(s) %s; they are skipped", cameras_path, unknown)
    views = [v for v in views or [] if v in cameras] or default_views(list(cameras))
    confidence = model_confidence(model_path)
    extra = {"confidence": confidence} if confidence is not None else None
    log.info("%s: %d vertices; rendering views %s at %dx%d (supersample %d)", model_path, mesh.num_vertices, views,
             cameras[views[0]].width, cameras[views[0]].height, supersample)
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        index = write_renders(mesh, cameras, light["position_m"], float(light["polarizer_deg"]), views, tmp,
                              supersample=supersample, measured=hdr.view, extra_maps=extra)
    log.info("wrote %s (%d files) in %.1f s", output, len(index["files"]) + 1, time.perf_counter() - started)
    return index
