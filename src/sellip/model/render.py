"""Forward renderer: a mesh with per-vertex pBRDF parameters, seen by a pinhole camera under a polarized point light.

Public API::

    ParamMesh(vertices, faces, normals, params, material=None)      # per-vertex parameters (numpy)
    Camera(intrinsics, rotation, translation, width, height, distortion=None)
    Light(position, axis, intensity=1.0, stokes=(1, 1, 0, 0))        # world coordinates; Stokes in its frame
    flash_light(camera, position_cam=(0, 0.05, 0), polarizer_deg=0.0, intensity=1.0) -> Light
    Renderer(mesh).render(camera, light, supersample=2, shadows=True) -> RenderResult
    Renderer(mesh).interpolate(camera, vertex_values, supersample=1) -> (values (H, W, C), coverage (H, W))
    render_stokes(mesh, camera, light, supersample=2, shadows=True) -> RenderResult
    pixel_rays(camera, supersample=1) -> (origin (3,), directions (H, W, s*s, 3))

Image formation (docs/design.md §6): for every sub-pixel sample, a primary ray finds
the first surface (open3d ``RaycastingScene``); per-vertex normals and pBRDF
parameters are interpolated with the hit's barycentric coordinates; a shadow
ray towards the light decides whether the light reaches the point; the full
three-lobe model (:func:`sellip.model.pbrdf.full_stokes`, exact incident and
exitant frames) gives the Stokes vector in the camera frame of that ray.
Samples are averaged over a regular ``s x s`` grid inside each pixel
(supersampling for anti-aliasing). The background is black.

Units: metres; intrinsics in pixels (OpenCV pinhole, pixel centres at
integer coordinates); light intensity is a multiplier on the unit flash of
``full_stokes`` (Stokes values are then S * pBRDF with S = cos(theta_i) / d^2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from sellip.model.conventions import camera_center, camera_to_world_point, camera_up, stokes_to_analyzers
from sellip.model.pbrdf import PBRDFParams, full_mueller, full_stokes

PARAM_CHANNELS = (("eta", 1), ("rho_d", 3), ("rho_s", 1), ("sigma_s", 1), ("rho_ss", 3), ("sigma_ss", 1))
"""Packing order of the pBRDF parameters in per-vertex attribute arrays: (name, channels)."""

SHADING_CHUNK = 1 << 16
"""Samples shaded per jitted call (one compiled shape for every image size)."""

FLASH_STOKES = (1.0, 1.0, 0.0, 0.0)
"""Stokes vector of a linearly polarized light in its own frame (x = its polarizer axis)."""

SHADOW_EPSILON_M = 1e-4
"""Shadow rays ignore hits closer than this to the surface point or to the light (metres)."""


# --------------------------------------------------------------------------- scene description


@dataclass(frozen=True)
class ParamMesh:
    """A triangle mesh with per-vertex shading normals and pBRDF parameters.

    vertices: (V, 3) metres; faces: (F, 3) int vertex indices (counter-clockwise seen from outside);
    normals: (V, 3) unit shading normals; params: PBRDFParams with batch shape (V,) (numpy arrays);
    material: optional (V,) int region label (ground truth only).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    params: PBRDFParams
    material: np.ndarray | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def packed_params(self) -> np.ndarray:
        """(V, 10) parameters in the order of :data:`PARAM_CHANNELS`."""
        columns = []
        for name, channels in PARAM_CHANNELS:
            value = np.asarray(getattr(self.params, name), dtype=np.float64)
            columns.append(value.reshape(self.num_vertices, channels))
        return np.concatenate(columns, axis=1)


def unpack_params(packed) -> PBRDFParams:
    """PBRDFParams from (..., 10) arrays packed in the order of :data:`PARAM_CHANNELS` (numpy or jax)."""
    values, start = {}, 0
    for name, channels in PARAM_CHANNELS:
        chunk = packed[..., start:start + channels]
        values[name] = chunk[..., 0] if channels == 1 else chunk
        start += channels
    return PBRDFParams(**values)


@dataclass(frozen=True)
class Camera:
    """An OpenCV pinhole camera with COLMAP cam_from_world pose ``x_cam = R x_world + t``.

    intrinsics: (3, 3) K in pixels; rotation (3, 3); translation (3,) metres; image size in pixels;
    distortion: OpenCV (k1, k2, p1, p2[, k3]) or None for none.
    """

    intrinsics: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    width: int
    height: int
    distortion: np.ndarray | None = None

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (3,)."""
        return camera_center(np.asarray(self.rotation, np.float64), np.asarray(self.translation, np.float64))

    @property
    def up(self) -> np.ndarray:
        """The camera's up axis in world coordinates (3,)."""
        return camera_up(np.asarray(self.rotation, np.float64))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of world points (..., 3), distortion included."""
        cam = np.einsum("ij,...j->...i", np.asarray(self.rotation, np.float64), points) + self.translation
        x, y = cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
        if self.distortion is not None and np.any(self.distortion):
            x, y = distort_normalized(x, y, self.distortion)
        k = np.asarray(self.intrinsics, np.float64)
        return np.stack([k[0, 0] * x + k[0, 1] * y + k[0, 2], k[1, 1] * y + k[1, 2]], axis=-1)


@dataclass(frozen=True)
class Light:
    """A point light: position (3,) and polarizer axis (3,) in world coordinates.

    It emits Stokes ``intensity * stokes`` in its own frame, x = the axis projected orthogonal to each beam.
    The default ``stokes`` [1, 1, 0, 0] is the rig's flash, linearly polarized along the axis; any other
    (e.g. [1, 0, 0, 0] unpolarized, [1, 0, 1, 0] at 45 degrees from the axis) is shaded through the
    full Mueller matrices (:func:`sellip.model.pbrdf.full_mueller`), a few times slower.
    """

    position: np.ndarray
    axis: np.ndarray
    intensity: float = 1.0
    stokes: tuple[float, float, float, float] = FLASH_STOKES


def flash_light(camera: Camera, position_cam=(0.0, 0.05, 0.0), polarizer_deg: float = 0.0,
                intensity: float = 1.0) -> Light:
    """The flash of a capture rig: position in camera coordinates (capture.yaml light.position_m) and
    polarizer axis at ``polarizer_deg`` from the image x axis towards image up (sellip.model.conventions)."""
    rotation = np.asarray(camera.rotation, np.float64)
    position = camera_to_world_point(rotation, np.asarray(camera.translation, np.float64),
                                     np.asarray(position_cam, np.float64))
    angle = np.radians(polarizer_deg)
    axis_cam = np.array([np.cos(angle), -np.sin(angle), 0.0])  # image up is -y in OpenCV camera coordinates
    return Light(position=position, axis=rotation.T @ axis_cam, intensity=float(intensity))


# --------------------------------------------------------------------------- camera rays


def distort_normalized(x, y, distortion):
    """OpenCV radial-tangential distortion of normalized image coordinates. (k1, k2, p1, p2[, k3])."""
    k1, k2, p1, p2 = (float(c) for c in distortion[:4])
    k3 = float(distortion[4]) if len(distortion) > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def undistort_normalized(xd, yd, distortion, iterations: int = 20):
    """Inverse of :func:`distort_normalized` by fixed-point iteration (as OpenCV's undistortPoints)."""
    k1, k2, p1, p2 = (float(c) for c in distortion[:4])
    k3 = float(distortion[4]) if len(distortion) > 4 else 0.0
    x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
        y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
    return x, y


def subpixel_offsets(supersample: int) -> np.ndarray:
    """(s*s, 2) offsets (du, dv) of a regular grid of samples inside a pixel centred at 0."""
    grid = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = np.meshgrid(grid, grid, indexing="xy")
    return np.stack([du.ravel(), dv.ravel()], axis=-1)


def pixel_rays(camera: Camera, supersample: int = 1, rows: slice | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and unit world ray directions (h, W, s*s, 3) through sub-pixel samples.

    rows: the image rows to generate (default all).
    """
    rows = rows or slice(0, camera.height)
    v_index = np.arange(camera.height)[rows].astype(np.float64)
    u_index = np.arange(camera.width, dtype=np.float64)
    offsets = subpixel_offsets(supersample)
    u = u_index[None, :, None] + offsets[None, None, :, 0]
    v = v_index[:, None, None] + offsets[None, None, :, 1]
    u, v = np.broadcast_arrays(u, v)
    k = np.asarray(camera.intrinsics, np.float64)
    y = (v - k[1, 2]) / k[1, 1]
    x = (u - k[0, 2] - k[0, 1] * y) / k[0, 0]
    if camera.distortion is not None and np.any(camera.distortion):
        x, y = undistort_normalized(x, y, camera.distortion)
    directions_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    directions_cam /= np.linalg.norm(directions_cam, axis=-1, keepdims=True)
    directions = directions_cam @ np.asarray(camera.rotation, np.float64)  # R^T d for row vectors
    return camera.center, directions


def coverage_masks(vertices: np.ndarray, faces: np.ndarray, cameras: list) -> np.ndarray:
    """(V, H, W) bool: which pixel centres' rays (:func:`pixel_rays`, distortion included) meet the triangle mesh
    (vertices (N, 3) metres, faces (F, 3)), for each :class:`Camera`: a mesh's true silhouettes."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    masks = []
    for camera in cameras:
        centre, directions = pixel_rays(camera)
        rays = np.concatenate([np.broadcast_to(centre, directions.shape), directions], axis=-1)[:, :, 0]
        masks.append(np.isfinite(scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()))
    return np.stack(masks)


# --------------------------------------------------------------------------- shading kernel


def _sample_geometry(points, prim_ids, barycentric, faces, vertex_normals, vertex_params, camera_position,
                     camera_up_axis, light_position, light_axis):
    """The arguments of :func:`sellip.model.pbrdf.full_stokes` / ``full_mueller`` at N hit samples (see
    _shade_samples)."""
    corners = faces[prim_ids]  # (N, 3)
    normal = jnp.einsum("nk,nkc->nc", barycentric, vertex_normals[corners])
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    params = unpack_params(jnp.einsum("nk,nkc->nc", barycentric, vertex_params[corners]))
    to_camera = camera_position - points
    to_camera = to_camera / jnp.linalg.norm(to_camera, axis=-1, keepdims=True)
    to_light = light_position - points
    light_distance = jnp.linalg.norm(to_light, axis=-1)
    to_light = to_light / light_distance[:, None]
    count = points.shape[0]
    return (normal, to_light, to_camera, light_distance, jnp.broadcast_to(light_axis, (count, 3)),
            jnp.broadcast_to(camera_up_axis, (count, 3)), params)


@jax.jit
def _shade_samples(points, prim_ids, barycentric, lit, faces, vertex_normals, vertex_params,
                   camera_position, camera_up_axis, light_position, light_axis):
    """Stokes (N, 4, 3) of N surface samples for a unit flash (pure kernel).

    points (N, 3) hit positions; prim_ids (N,) triangle index; barycentric (N, 3); lit (N,) 1 where the
    light reaches the point (0 in shadow or for padding); faces (F, 3); vertex_normals (V, 3);
    vertex_params (V, 10) packed as PARAM_CHANNELS; the rest (3,) world vectors.
    """
    stokes = full_stokes(*_sample_geometry(points, prim_ids, barycentric, faces, vertex_normals, vertex_params,
                                           camera_position, camera_up_axis, light_position, light_axis))
    return stokes * lit[:, None, None]


@jax.jit
def _shade_samples_incident(points, prim_ids, barycentric, lit, faces, vertex_normals, vertex_params,
                            camera_position, camera_up_axis, light_position, light_axis, incident_stokes):
    """As :func:`_shade_samples` for a light emitting ``incident_stokes`` (4,) in its frame: Mueller @ Stokes."""
    mueller = full_mueller(*_sample_geometry(points, prim_ids, barycentric, faces, vertex_normals, vertex_params,
                                             camera_position, camera_up_axis, light_position, light_axis))
    stokes = jnp.einsum("ncij,j->nic", mueller, incident_stokes.astype(mueller.dtype))  # (N, 4, 3)
    return stokes * lit[:, None, None]


def _padded_rows(array: np.ndarray, start: int, stop: int, dtype) -> jnp.ndarray:
    """Rows start:stop as a jax array of SHADING_CHUNK rows, padded by repeating the last row."""
    rows = np.asarray(array[start:stop], dtype)
    return jnp.asarray(np.pad(rows, [(0, SHADING_CHUNK - rows.shape[0])] + [(0, 0)] * (rows.ndim - 1), mode="edge"))


# --------------------------------------------------------------------------- renderer


@dataclass
class RenderResult:
    """One rendered view.

    stokes: (H, W, 4, 3) float32 Stokes vectors (s0..s3, RGB) in each pixel ray's camera frame,
    averaged over the sub-pixel samples. coverage: (H, W) float32 fraction of samples that hit the
    mesh. lit: (H, W) float32 fraction of samples that hit the mesh and see the light.
    """

    stokes: np.ndarray
    coverage: np.ndarray
    lit: np.ndarray

    @property
    def analyzers(self) -> np.ndarray:
        """(H, W, 4, 3) intensities behind the 0/45/90/135 degree analyzers."""
        return stokes_to_analyzers(self.stokes, axis=-2)


@dataclass
class Renderer:
    """Renders one mesh from many cameras; the ray-casting structure is built once.

    Use :meth:`render` per view. ``rows_per_block`` bounds memory at large resolutions.
    """

    mesh: ParamMesh
    rows_per_block: int = 64
    threads: int = 0
    _scene: object = field(init=False, repr=False)

    def __post_init__(self):
        import open3d as o3d

        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.asarray(self.mesh.vertices, np.float32)),
                                  o3d.core.Tensor(np.asarray(self.mesh.faces, np.uint32)))
        self._faces = jnp.asarray(np.asarray(self.mesh.faces, np.int32))
        self._normals = jnp.asarray(np.asarray(self.mesh.normals, np.float32))
        self._params = jnp.asarray(self.mesh.packed_params().astype(np.float32))

    def _cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        import open3d as o3d

        rays = np.concatenate([origins, directions], axis=-1).astype(np.float32)
        result = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=self.threads)
        return {key: value.numpy() for key, value in result.items()}

    def _visible_from_light(self, points: np.ndarray, light_position: np.ndarray) -> np.ndarray:
        """(N,) bool: no geometry between each point and the light (shadow rays cast from the light)."""
        import open3d as o3d

        offset = points - light_position
        distance = np.linalg.norm(offset, axis=-1)
        rays = np.concatenate([np.broadcast_to(light_position, points.shape), offset / distance[:, None]], axis=-1)
        hit = self._scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)), nthreads=self.threads)
        return hit["t_hit"].numpy() >= distance - SHADOW_EPSILON_M

    def _shade(self, points, prim_ids, barycentric, lit, camera: Camera, light: Light) -> np.ndarray:
        """(N, 4, 3) Stokes of N hit samples, shaded in fixed-size jitted chunks."""
        count = points.shape[0]
        out = np.zeros((count, 4, 3), np.float32)
        constants = [jnp.asarray(np.asarray(v, np.float32)) for v in
                     (camera.center, camera.up, light.position, light.axis)]
        kernel = _shade_samples
        if not np.array_equal(np.asarray(light.stokes, np.float64), FLASH_STOKES):
            constants.append(jnp.asarray(np.asarray(light.stokes, np.float32)))
            kernel = _shade_samples_incident
        for start in range(0, count, SHADING_CHUNK):
            stop = min(start + SHADING_CHUNK, count)
            stokes = kernel(_padded_rows(points, start, stop, np.float32),
                            _padded_rows(prim_ids, start, stop, np.int32),
                            _padded_rows(barycentric, start, stop, np.float32),
                            _padded_rows(lit, start, stop, np.float32),
                            self._faces, self._normals, self._params, *constants)
            out[start:stop] = np.asarray(stokes)[: stop - start]
        return out * np.float32(light.intensity)

    def _hits(self, camera: Camera, supersample: int):
        """The camera rays that hit the mesh, block by block of image rows: yields (sample index (S,) into
        the (H * W * supersample**2) samples, hit points (S, 3), triangle ids (S,), barycentrics (S, 3))."""
        h, w, n_sub = camera.height, camera.width, supersample * supersample
        for top in range(0, h, self.rows_per_block):
            rows = slice(top, min(top + self.rows_per_block, h))
            origin, directions = pixel_rays(camera, supersample, rows)
            flat_dirs = directions.reshape(-1, 3)
            hit = self._cast(np.broadcast_to(origin, flat_dirs.shape), flat_dirs)
            index = np.flatnonzero(np.isfinite(hit["t_hit"]))
            points = origin + hit["t_hit"][index, None].astype(np.float64) * flat_dirs[index]
            uv = hit["primitive_uvs"][index].astype(np.float64)
            yield (index + top * w * n_sub, points, hit["primitive_ids"][index],
                   np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=-1))

    def render(self, camera: Camera, light: Light, supersample: int = 2, shadows: bool = True) -> RenderResult:
        """Render one view. Returns a :class:`RenderResult` (Stokes per pixel, coverage, lit fraction)."""
        h, w, n_sub = camera.height, camera.width, supersample * supersample
        light_position = np.asarray(light.position, np.float64)
        samples, points, prim_ids, barycentric, lit = [], [], [], [], []
        for sample, block_points, block_prims, block_barycentric in self._hits(camera, supersample):
            samples.append(sample)
            points.append(block_points)
            prim_ids.append(block_prims)
            barycentric.append(block_barycentric)
            lit.append(self._visible_from_light(block_points, light_position) if shadows
                       else np.ones(sample.size, bool))
        lit = np.concatenate(lit)
        sample_stokes = self._shade(np.concatenate(points), np.concatenate(prim_ids), np.concatenate(barycentric),
                                    lit, camera, light)
        # Average the samples of each pixel (misses contribute zero).
        pixel = np.concatenate(samples) // n_sub
        stokes = np.empty((h * w, 4, 3), np.float32)
        for component in range(4):
            for channel in range(3):
                stokes[:, component, channel] = np.bincount(
                    pixel, weights=sample_stokes[:, component, channel], minlength=h * w) / n_sub
        coverage = np.bincount(pixel, minlength=h * w) / n_sub
        lit_fraction = np.bincount(pixel, weights=lit, minlength=h * w) / n_sub
        return RenderResult(stokes=stokes.reshape(h, w, 4, 3), coverage=coverage.reshape(h, w).astype(np.float32),
                            lit=lit_fraction.reshape(h, w).astype(np.float32))

    def interpolate(self, camera: Camera, vertex_values: np.ndarray, supersample: int = 1
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-vertex values seen through each pixel, interpolated with the hits' barycentric coordinates.

        vertex_values: (V, C). Returns (values (H, W, C) float32: the mean over the pixel's samples that hit
        the mesh, 0 where none does; coverage (H, W) float32: the fraction of samples that hit).
        """
        values = np.asarray(vertex_values, np.float64).reshape(self.mesh.num_vertices, -1)
        faces = np.asarray(self.mesh.faces)
        h, w, n_sub = camera.height, camera.width, supersample * supersample
        sums = np.zeros((h * w, values.shape[1]))
        hits = np.zeros(h * w)
        for sample_index, _, prim_ids, barycentric in self._hits(camera, supersample):
            sample = np.einsum("nk,nkc->nc", barycentric, values[faces[prim_ids]])
            pixel = sample_index // n_sub
            for column in range(values.shape[1]):
                sums[:, column] += np.bincount(pixel, weights=sample[:, column], minlength=h * w)
            hits += np.bincount(pixel, minlength=h * w)
        mean = sums / np.maximum(hits, 1)[:, None]
        return (mean.reshape(h, w, -1).astype(np.float32), (hits / n_sub).reshape(h, w).astype(np.float32))


def render_stokes(mesh: ParamMesh, camera: Camera, light: Light, supersample: int = 2,
                  shadows: bool = True) -> RenderResult:
    """Render one view of ``mesh`` (see :class:`Renderer`; build a Renderer to render many views)."""
    return Renderer(mesh).render(camera, light, supersample=supersample, shadows=shadows)
