"""Per-vertex, per-view observations for the pBRDF fit (docs/design.md §2 observe, §5).

Public API::

    ObserveSettings(vertex_chunk, view_chunk, ..., missing_poses, max_views)  # config observe (declared there)
    ObserveMesh(vertices, normals, faces);  read_mesh(path) -> ObserveMesh
    project_points(camera, points) -> (pixels (N, 2), depth (N,))
    inside_image(pixels, width, height) -> (N,) bool
    bilinear_footprint(pixels, width, height) -> Footprint (.valid(mask), .sample(image), .take(rows))
    bilinear_sample(image, valid, pixels) -> (values (n, ...), ok (n,))
    segments_clear(scene, origins, targets, stop=1.0, threads=0) -> (n,) bool
    Observer(mesh, settings).observe(camera, light_position, analyzers, valid) -> ViewObservations
    ObservationWriter(path, mesh, view_ids, {"camera_up": ..., "light_axis": ...}, settings)
    load_observations(path, start, stop) -> VertexObservations(observations, vertices, normals)

For every vertex p (unit normal n) of the mesh and every view (camera centre c,
flash position f, both world), in this order, each test only where all earlier
ones passed:

1. ``in_image``: in front of the camera, and the projection (OpenCV pinhole at the
   HDR resolution, pixel centres at integer coordinates) lies inside
   [0, W-1] x [0, H-1], so that its four bilinear neighbours exist;
2. ``front_facing``: n . w_o > ``min_cos`` with w_o = (c - p) / |c - p|;
3. ``valid_pixels``: all four bilinear neighbours are valid HDR pixels;
4. ``unoccluded``: the segment c -> p meets no triangle before
   (1 - ``occlusion_tolerance``) of its length (the vertex's own triangles are hit at
   the full length);
5. ``lit``: n . w_i > ``min_cos`` with w_i = (f - p) / |f - p|, and the segment from
   p + ``shadow_offset`` * (median edge length) * n to f meets no triangle.

``usable`` = all five. The observations I_d, I_alpha, I_s
(:func:`sellip.model.conventions.observations_from_analyzers`) are bilinear samples of the
four analyzer images; they are 0 where a view is not usable. The geometry (w_i, w_o,
|f - p|) is stored for every vertex and view. Mono HDR images (C = 1) are repeated
to three channels.

Observation store (zarr v3, one directory), N vertices, V views::

    diffuse, diffuse_pol, specular   (N, V, 3) float32   I_d, I_alpha, I_s (HDR units)
    to_light, to_camera              (N, V, 3) float32   unit vectors surface -> flash / camera (world)
    light_distance                   (N, V)    float32   metres
    usable                           (N, V)    bool
    camera_up, light_axis            (V, 3)    float32   camera up axes, flash polarizer axes (world)
    vertices, normals                (N, 3)    float32   the mesh the observations belong to
    attrs: view_ids, num_vertices, num_views, settings, shadow_offset_m, units

Per-(vertex, view) arrays are chunked (vertex_chunk, view_chunk, ...): a fit shard
reads only the chunks of its rows, and the writer stores one group of ``view_chunk``
views at a time, so each chunk is written once and whole.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from sellip.geometry.silhouettes import DEFAULT_SILHOUETTE
from sellip.model.conventions import camera_forward, observations_from_analyzers
from sellip.settings import setting

PER_VIEW_ARRAYS: dict[str, tuple[tuple[int, ...], str]] = {
    "diffuse": ((3,), "float32"),
    "diffuse_pol": ((3,), "float32"),
    "specular": ((3,), "float32"),
    "to_light": ((3,), "float32"),
    "to_camera": ((3,), "float32"),
    "light_distance": ((), "float32"),
    "usable": ((), "bool"),
}
"""The (N, V, ...) arrays of the observation store: name -> (trailing shape, dtype)."""

VIEW_AXES = ("camera_up", "light_axis")
"""The (V, 3) arrays of the observation store: one world direction per view."""

BYTES_PER_OBSERVATION = sum(4 * int(np.prod(shape)) if dtype == "float32" else 1
                            for shape, dtype in PER_VIEW_ARRAYS.values())
"""Bytes of one (vertex, view) entry over all per-view arrays (65)."""


class ObserveError(ValueError):
    """An input of the observe stage that cannot be used; the message names the file."""

    def __init__(self, file, problem: str):
        self.file = str(file)
        super().__init__(f"{self.file}: {problem}")


MISSING_POSES = ("skip", "error")
"""What observe does with HDR views that cameras.csv has no pose for (``ObserveSettings.missing_poses``)."""


@dataclass(frozen=True)
class ObserveSettings:
    """Settings of the observe stage (config section ``observe``; each declared once here, :mod:`sellip.settings`).

    ``mask_threshold`` (the silhouette's, config ``silhouette.threshold``) and ``threads`` (the job's, Snakemake's
    ``observe.threads``) are not settings of the section: the stage passes them.
    """

    vertex_chunk: int = setting(4096, "vertices per chunk of observations.zarr: a fit shard reads the chunks of its "
                                "rows", minimum=1)
    view_chunk: int = setting(8, "views per chunk of the store, processed together (memory holds vertices x this "
                              "observations, 65 B each)", minimum=1)
    occlusion_tolerance: float = setting(1e-3, "a vertex is hidden when the mesh is hit before (1 - this) of its "
                                         "distance from the camera", unit="fraction of the distance", minimum=0,
                                         exclusive_maximum=1)
    shadow_offset: float = setting(0.5, "shadow rays towards the flash start this far above the vertex (along its "
                                   "normal)", unit="median edge lengths", minimum=0)
    min_cos: float = setting(0.0, "front-facing / lit: the cosine between the normal and the direction to the camera "
                             "/ flash exceeds this", minimum=-1, exclusive_maximum=1)
    edge_margin: float = setting(2.0, "a sample lies at least this far inside the object's silhouette (nearer, the "
                                 "kernels mix object and background: false polarization, docs/accuracy.md); 0: no "
                                 "test", unit="HDR pixels", minimum=0)
    mask_threshold: float = DEFAULT_SILHOUETTE.threshold
    max_slope: float = setting(0.0, "leave out a sample where a corner of its bilinear footprint has a larger "
                               "intensity slope (|grad S0| / S0, relative_slope; docs/observe.md); 0: no test",
                               unit="per HDR pixel", minimum=0)
    missing_poses: str = setting("skip", "HDR views without a pose in cameras.csv (SfM did not register them): leave "
                                 "them out (skip), or stop (error)", choices=MISSING_POSES)
    max_views: int | None = setting(None, "observe only this many views, spread evenly over the capture order after "
                                    "the held-out views (null: all; the initial mesh still uses every view)",
                                    minimum=1)
    threads: int = 0

    def __post_init__(self):
        if self.vertex_chunk < 1 or self.view_chunk < 1:
            raise ValueError(f"vertex_chunk and view_chunk must be >= 1, got {self.vertex_chunk}, {self.view_chunk}")
        if not 0 <= self.occlusion_tolerance < 1:
            raise ValueError(f"occlusion_tolerance must be in [0, 1), got {self.occlusion_tolerance}")
        if self.edge_margin < 0 or not 0 < self.mask_threshold < 1:
            raise ValueError(f"need edge_margin >= 0 and mask_threshold in (0, 1), got {self.edge_margin}, "
                             f"{self.mask_threshold}")
        if self.max_slope < 0:
            raise ValueError(f"max_slope must be >= 0 (0: off), got {self.max_slope}")
        if self.missing_poses not in MISSING_POSES:
            raise ValueError(f"missing_poses must be one of {MISSING_POSES}, got {self.missing_poses!r}")
        if self.max_views is not None and self.max_views < 1:
            raise ValueError(f"max_views must be at least 1 (None: all), got {self.max_views}")
        if self.shadow_offset < 0 or not -1 <= self.min_cos < 1:
            raise ValueError(f"need shadow_offset >= 0 and min_cos in [-1, 1), got {self.shadow_offset}, "
                             f"{self.min_cos}")


# --------------------------------------------------------------------------- mesh


@dataclass(frozen=True)
class ObserveMesh:
    """vertices (N, 3) metres, normals (N, 3) unit (0 where the file's normal has no length), faces (F, 3)."""

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])


def read_mesh(path: str | Path) -> ObserveMesh:
    """Read a binary PLY mesh with vertex normals (x y z nx ny nz) and triangles (:func:`sellip.model.ply.read_ply`).

    Raises ObserveError naming the file when normals or faces are missing, or values are not finite.
    """
    from sellip.model.ply import PlyError, read_ply

    path = Path(path)
    if not path.is_file():
        raise ObserveError(path, "mesh file does not exist")
    try:
        vertex, faces = read_ply(path)
    except PlyError as exc:
        raise ObserveError(path, f"cannot read the mesh ({exc.problem})") from None
    for names, what in ((("x", "y", "z"), "positions"), (("nx", "ny", "nz"), "vertex normals")):
        missing = [name for name in names if name not in vertex]
        if missing:
            raise ObserveError(path, f"the mesh has no {what}: vertex properties {missing} are missing "
                                     f"(found {list(vertex)})")
    if faces is None or len(faces) == 0:
        raise ObserveError(path, "the mesh has no triangles (element face); occlusion tests need them")
    vertices = np.stack([vertex[k].astype(np.float64) for k in ("x", "y", "z")], axis=-1)
    normals = np.stack([vertex[k].astype(np.float64) for k in ("nx", "ny", "nz")], axis=-1)
    if not (np.isfinite(vertices).all() and np.isfinite(normals).all()):
        raise ObserveError(path, "vertex positions or normals are not finite")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ObserveError(path, f"face indices outside [0, {len(vertices)})")
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return ObserveMesh(vertices=vertices, normals=normals, faces=np.asarray(faces, np.int64))


def median_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Median length (metres) of the triangle edges (each interior edge counted twice)."""
    edges = vertices[np.roll(faces, -1, axis=1)] - vertices[faces]
    return float(np.median(np.linalg.norm(edges.reshape(-1, 3), axis=-1)))


def raycasting_scene(vertices: np.ndarray, faces: np.ndarray):
    """An open3d ``RaycastingScene`` holding one triangle mesh (float32 positions)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene


def segments_clear(scene, origins: np.ndarray, targets: np.ndarray, stop: float = 1.0, threads: int = 0) -> np.ndarray:
    """(n,) bool: no triangle of ``scene`` on the segments origin -> origin + stop * (target - origin).

    origins (n, 3) or (3,), targets (n, 3), world metres. One any-hit query per segment.
    """
    import open3d as o3d

    origins = np.broadcast_to(origins, targets.shape)
    rays = np.concatenate([origins, targets - origins], axis=-1).astype(np.float32)
    if len(rays) == 0:
        return np.zeros(0, bool)
    hit = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=float(stop), nthreads=threads)
    return ~hit.numpy().astype(bool)


# --------------------------------------------------------------------------- images


def project_points(camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) (u = column, v = row) and depth along the optical axis (N,) of world points (N, 3).

    ``camera``: a :class:`sellip.model.render.Camera` at the resolution of the images to sample.
    """
    depth = (points - camera.center) @ camera_forward(np.asarray(camera.rotation, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = camera.project(points)
    return pixels, depth


def inside_image(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: pixels (N, 2) inside [0, W-1] x [0, H-1], where all four bilinear neighbours exist."""
    u, v = pixels[:, 0], pixels[:, 1]
    with np.errstate(invalid="ignore"):
        return (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)


class Footprint(NamedTuple):
    """Bilinear footprints of n pixels: corners (n, 4) flat pixel indices (row * W + column) of the
    neighbours (u0, v0), (u0 + 1, v0), (u0, v0 + 1), (u0 + 1, v0 + 1) and their weights (n, 4)."""

    corners: np.ndarray
    weights: np.ndarray

    def take(self, rows) -> Footprint:
        return Footprint(self.corners[rows], self.weights[rows])

    def valid(self, valid: np.ndarray) -> np.ndarray:
        """(n,) bool: all four neighbours valid in ``valid`` (H, W)."""
        return np.asarray(valid, bool).reshape(-1)[self.corners].all(axis=-1)

    def sample(self, image: np.ndarray) -> np.ndarray:
        """(n, ...) bilinear samples of ``image`` (H, W, ...) in its dtype."""
        flat = image.reshape((-1,) + image.shape[2:])
        weights = self.weights.astype(image.dtype)[(...,) + (None,) * (image.ndim - 2)]
        return sum(weights[:, k] * flat[self.corners[:, k]] for k in range(4))


def bilinear_footprint(pixels: np.ndarray, width: int, height: int) -> Footprint:
    """The :class:`Footprint` of pixels (n, 2) (u, v; pixel centres at integers) inside the image
    (see :func:`inside_image`; pixels outside give meaningless corners)."""
    if height < 2 or width < 2:
        raise ValueError(f"bilinear sampling needs an image of at least 2x2 pixels, got {width}x{height}")
    u = np.nan_to_num(pixels[:, 0], nan=0.0, posinf=0.0, neginf=0.0).clip(0, width - 1)
    v = np.nan_to_num(pixels[:, 1], nan=0.0, posinf=0.0, neginf=0.0).clip(0, height - 1)
    u0 = np.minimum(u.astype(np.intp), width - 2)
    v0 = np.minimum(v.astype(np.intp), height - 2)
    fu, fv = u - u0, v - v0
    top = v0 * width + u0
    corners = np.stack([top, top + 1, top + width, top + width + 1], axis=-1)
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=-1)
    return Footprint(corners, weights)


def bilinear_sample(image: np.ndarray, valid: np.ndarray | None, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``image`` (H, W, ...) at pixels (n, 2) (u, v; pixel centres at integers).

    Returns values (n, ...) in the image's dtype and ok (n,) bool: inside the image and, when
    ``valid`` (H, W) is given, all four neighbours valid. Values are 0 where not ok.
    """
    height, width = image.shape[:2]
    index = np.flatnonzero(inside_image(pixels, width, height))
    footprint = bilinear_footprint(pixels[index], width, height)
    if valid is not None:
        good = footprint.valid(valid)
        index, footprint = index[good], footprint.take(good)
    ok = np.zeros(len(pixels), bool)
    ok[index] = True
    values = np.zeros((len(pixels),) + image.shape[2:], image.dtype)
    values[index] = footprint.sample(image)
    return values, ok


def silhouette_distance(analyzers: np.ndarray, valid: np.ndarray | None,
                        threshold: float = DEFAULT_SILHOUETTE.threshold) -> np.ndarray:
    """(H, W) float32: each pixel's distance (pixels) to the nearest pixel outside the object's silhouette.

    The silhouette is that of :func:`sellip.geometry.silhouettes.silhouette_masks` on I_d = 2 I90 of ``analyzers``
    (H, W, 4, C); 0 outside it. A sample closer to the silhouette than the demosaicing and bilinear
    kernels reach mixes the object with the background, differently in each analyzer image: false
    polarization where the diffuse DoP that eta rests on is largest (docs/observe.md).
    """
    from scipy import ndimage

    from sellip.geometry.silhouettes import silhouette_masks

    diffuse = 2 * np.asarray(analyzers[..., 2, :], np.float32)
    mask = silhouette_masks(diffuse[None], None if valid is None else np.asarray(valid, bool)[None],
                            threshold=threshold)[0]
    return ndimage.distance_transform_edt(mask).astype(np.float32)


def relative_slope(analyzers: np.ndarray) -> np.ndarray:
    """(H, W) float32: each pixel's intensity slope relative to its intensity, |grad S0| / S0 per HDR pixel
    (central differences of the mono total intensity S0 = (I0 + I45 + I90 + I135) / 2 of ``analyzers``
    (H, W, 4, C)); inf where S0 <= 0, NaN next to an invalid (NaN) pixel.

    The fit models a sample as the reflection at one point; the pixel it comes from averages a
    footprint, and each analyzer image was interpolated from its own mosaic cells, a pixel apart
    (:func:`sellip.capture.ingest.demosaic`). Where the intensity changes fast against itself (a glossy
    highlight on a curved surface, a texture or shadow edge) neither holds: the four analyzers see
    different parts of the slope, and the DoP that eta rests on (a few percent) carries false
    polarization of the order of slope x offset (docs/observe.md).
    """
    s0 = 0.5 * np.asarray(analyzers, np.float32).sum(axis=-2).mean(axis=-1)
    rows, columns = np.gradient(s0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(s0 > 0, np.hypot(rows, columns) / s0, np.inf).astype(np.float32)


# --------------------------------------------------------------------------- one view


class Visibility(NamedTuple):
    """The tests of one view, (N,) bool each, in order; a test is False wherever an earlier one failed,
    so ``lit`` is the usable mask and the counts show where vertices drop out."""

    in_image: np.ndarray
    front_facing: np.ndarray
    valid_pixels: np.ndarray
    unoccluded: np.ndarray
    lit: np.ndarray


class ViewObservations(NamedTuple):
    """Observations of N vertices in one view.

    diffuse, diffuse_pol, specular: (N, 3) float32 I_d, I_alpha, I_s (0 where not usable);
    to_light, to_camera: (N, 3) float32 unit (world); light_distance: (N,) float32 metres;
    usable: (N,) bool; visibility: the individual tests.
    """

    diffuse: np.ndarray
    diffuse_pol: np.ndarray
    specular: np.ndarray
    to_light: np.ndarray
    to_camera: np.ndarray
    light_distance: np.ndarray
    usable: np.ndarray
    visibility: Visibility


def _unit_and_length(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    length = np.linalg.norm(offsets, axis=-1)
    return offsets / np.maximum(length, np.finfo(np.float64).tiny)[:, None], length


class Observer:
    """Observes one mesh in many views; the ray-casting structure is built once.

    mesh: the current mesh; settings: :class:`ObserveSettings`.
    """

    def __init__(self, mesh: ObserveMesh, settings: ObserveSettings = ObserveSettings()):
        self.mesh = mesh
        self.settings = settings
        self.scene = raycasting_scene(mesh.vertices, mesh.faces)
        self.shadow_offset_m = settings.shadow_offset * median_edge_length(mesh.vertices, mesh.faces)

    def observe(self, camera, light_position: np.ndarray, analyzers: np.ndarray,
                valid: np.ndarray | None) -> ViewObservations:
        """Observations of every vertex in one view.

        camera: :class:`sellip.model.render.Camera` at the HDR resolution; light_position (3,) world metres;
        analyzers (H, W, 4, C) float32 (I0, I45, I90, I135); valid (H, W) bool or None (all valid).
        """
        settings, points, normals = self.settings, self.mesh.vertices, self.mesh.normals
        count = self.mesh.num_vertices
        height, width = analyzers.shape[:2]
        if (width, height) != (camera.width, camera.height):
            raise ValueError(f"camera is {camera.width}x{camera.height} but the images are {width}x{height}")
        center = camera.center
        light_position = np.asarray(light_position, np.float64)
        to_camera, _ = _unit_and_length(center - points)
        to_light, light_distance = _unit_and_length(light_position - points)

        pixels, depth = project_points(camera, points)
        in_image = (depth > 0) & inside_image(pixels, width, height)
        front_facing = in_image & (np.einsum("nc,nc->n", normals, to_camera) > settings.min_cos)
        candidates = np.flatnonzero(front_facing)
        footprint = bilinear_footprint(pixels[candidates], width, height)
        rows = np.flatnonzero(footprint.valid(valid)) if valid is not None else np.arange(len(candidates))
        if settings.edge_margin > 0:
            inside = silhouette_distance(analyzers, valid, settings.mask_threshold)
            near = np.rint(pixels[candidates[rows]]).astype(np.intp)
            rows = rows[inside[near[:, 1], near[:, 0]] >= settings.edge_margin]
        if settings.max_slope > 0:  # NaN (next to an invalid pixel) fails the test
            slope = relative_slope(analyzers).reshape(-1)
            rows = rows[np.max(slope[footprint.take(rows).corners], axis=-1) <= settings.max_slope]
        index = candidates[rows]  # the vertices still in the running; rows: their footprints
        valid_pixels = np.zeros(count, bool)
        valid_pixels[index] = True

        clear = segments_clear(self.scene, center, points[index], 1.0 - settings.occlusion_tolerance, settings.threads)
        rows, index = rows[clear], index[clear]
        unoccluded = np.zeros(count, bool)
        unoccluded[index] = True

        facing_light = np.einsum("nc,nc->n", normals[index], to_light[index]) > settings.min_cos
        rows, index = rows[facing_light], index[facing_light]
        starts = points[index] + self.shadow_offset_m * normals[index]
        clear = segments_clear(self.scene, starts, np.broadcast_to(light_position, starts.shape), 1.0,
                               settings.threads)
        rows, index = rows[clear], index[clear]
        lit = np.zeros(count, bool)
        lit[index] = True

        samples = footprint.take(rows).sample(np.asarray(analyzers, np.float32))  # (n, 4, C), only where usable
        observed = [np.zeros((count, 3), np.float32) for _ in range(3)]
        for out, value in zip(observed, observations_from_analyzers(samples, axis=-2)):
            out[index] = value  # (n, C) with C = 3, or C = 1 repeated
        return ViewObservations(*observed, to_light=to_light.astype(np.float32),
                                to_camera=to_camera.astype(np.float32),
                                light_distance=light_distance.astype(np.float32), usable=lit,
                                visibility=Visibility(in_image, front_facing, valid_pixels, unoccluded, lit))


# --------------------------------------------------------------------------- the store


def _codec():
    from zarr.codecs import BloscCodec

    return BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")


class ObservationWriter:
    """Writes an observation store (layout in the module docstring) one group of views at a time.

    path: a new store directory; mesh: the observed mesh; view_ids: V names; view_axes: the
    :data:`VIEW_AXES` arrays, (V, 3) world each.
    """

    def __init__(self, path: str | Path, mesh: ObserveMesh, view_ids: list[str], view_axes: dict[str, np.ndarray],
                 settings: ObserveSettings, attrs: dict | None = None):
        import zarr

        self.num_vertices, self.num_views = mesh.num_vertices, len(view_ids)
        self.settings = settings
        vertex_chunk = min(settings.vertex_chunk, max(self.num_vertices, 1))
        view_chunk = min(settings.view_chunk, max(self.num_views, 1))
        self.group = zarr.open_group(str(path), mode="w")
        self.arrays = {}
        for name, (trailing, dtype) in PER_VIEW_ARRAYS.items():
            self.arrays[name] = self.group.create_array(
                name, shape=(self.num_vertices, self.num_views) + trailing,
                chunks=(vertex_chunk, view_chunk) + trailing, dtype=dtype,
                fill_value=False if dtype == "bool" else 0.0, compressors=_codec())
        for name, values in (("vertices", mesh.vertices), ("normals", mesh.normals)):
            self.group.create_array(name, shape=values.shape, chunks=(vertex_chunk, 3), dtype="float32",
                                    compressors=_codec())[...] = values.astype(np.float32)
        for name in VIEW_AXES:
            self.group.create_array(name, shape=(self.num_views, 3), dtype="float32")[...] = \
                np.asarray(view_axes[name], np.float32).reshape(self.num_views, 3)
        self.group.attrs.update({"view_ids": list(view_ids), "num_vertices": self.num_vertices,
                                 "num_views": self.num_views, "settings": asdict(settings),
                                 **(attrs or {})})

    def buffers(self) -> dict[str, np.ndarray]:
        """Empty view-major (view_chunk, N, ...) arrays to fill with one group of views (see :meth:`fill`)."""
        width = min(self.settings.view_chunk, self.num_views)
        return {name: np.zeros((width, self.num_vertices) + trailing, dtype)
                for name, (trailing, dtype) in PER_VIEW_ARRAYS.items()}

    @staticmethod
    def fill(buffers: dict[str, np.ndarray], slot: int, view: ViewObservations) -> None:
        """Copy one view into slot ``slot`` of the group buffers."""
        for name, values in buffers.items():
            values[slot] = getattr(view, name)

    def write_views(self, start: int, buffers: dict[str, np.ndarray], count: int) -> None:
        """Store the first ``count`` slots of ``buffers`` as views start .. start + count - 1."""
        for name, values in buffers.items():
            self.arrays[name][:, start:start + count] = np.moveaxis(values[:count], 0, 1)


class VertexObservations(NamedTuple):
    """Rows of an observation store: observations (:class:`sellip.fit.records.Observations`, (n, V, ...)),
    vertices (n, 3) and normals (n, 3) float32."""

    observations: object
    vertices: np.ndarray
    normals: np.ndarray


def open_observations(path: str | Path):
    """The zarr group of an observation store; ObserveError naming ``path`` if it is not one."""
    import zarr

    path = Path(path)
    if not (path / "zarr.json").is_file():
        raise ObserveError(path, "not an observation store (no zarr.json); run `sellip observe` first")
    group = zarr.open_group(str(path), mode="r")
    missing = [name for name in [*PER_VIEW_ARRAYS, *VIEW_AXES, "vertices", "normals"] if name not in group]
    if missing:
        raise ObserveError(path, f"observation store lacks arrays {missing}")
    return group


def load_observations(path: str | Path, start: int = 0, stop: int | None = None) -> VertexObservations:
    """Rows [start, stop) of an observation store (stop None: to the end).

    Returns :class:`VertexObservations`: ``observations`` is a :class:`sellip.fit.records.Observations` of numpy
    arrays (n, V, ...) with ``camera_up`` and ``light_axis`` repeated to (n, V, 3); vertices and normals (n, 3).
    Only the chunks holding these rows are read.
    """
    from sellip.fit.records import Observations

    group = open_observations(path)
    total = int(group.attrs["num_vertices"])
    stop = total if stop is None else stop
    if not 0 <= start <= stop <= total:
        raise ObserveError(path, f"rows [{start}, {stop}) outside the store's {total} vertices")
    rows = slice(start, stop)
    per_view = {name: np.asarray(group[name][rows]) for name in PER_VIEW_ARRAYS}
    for name in VIEW_AXES:
        per_view[name] = np.repeat(np.asarray(group[name][...])[None], stop - start, axis=0)
    return VertexObservations(observations=Observations(**per_view), vertices=np.asarray(group["vertices"][rows]),
                              normals=np.asarray(group["normals"][rows]))
