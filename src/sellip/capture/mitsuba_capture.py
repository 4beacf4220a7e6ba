"""An independent renderer for synthetic captures: Mitsuba 3's ``pplastic`` under the rig's polarized flash.

Public API::

    MITSUBA_VARIANTS                                   # preferred first: ("llvm_ad_mono_polarized",
                                                       #                   "scalar_spectral_polarized")
    mitsuba_available() -> bool                        # is the ``mitsuba`` package importable (the ``test`` extra)
    choose_variant(requested=None) -> str              # the variant to use (sets DRJIT_LIBLLVM_PATH when it can)
    PPlasticMaterial(eta, alpha, specular)             # one pplastic material (Mitsuba's units)
    pplastic_materials(mesh) -> (materials, face_material (F,))   # raises PPlasticError if pplastic cannot render it
    mitsuba_camera(camera) -> dict                     # a ``perspective`` sensor dict for a sellip Camera
    MitsubaRenderer(mesh, variant=None, seed=0).render(camera, light, supersample=2) -> MitsubaResult
    MitsubaResult.stokes (H, W, 4, 3), .analyzers (H, W, 4, 3)
    mesh_shape(name, vertices, faces, normals=None, albedo=None, bsdf=None, texcoords=None) -> mi.Mesh
    flash_scene(camera, light, intensity, supersample, seed, polarizer, variant, max_depth=2) -> dict
    render_stokes(scene, camera, variant) -> (H, W, 4)  # one channel's Stokes image of a scene dict

The generator beside :mod:`sellip.model.render` (``sellip synth --renderer mitsuba``,
:func:`sellip.capture.synthetic.synthesize_capture`): the same scene, cameras, flash, sensor and files, rendered
by code that shares nothing with sellip's pBRDF. Mitsuba is imported lazily; it is a test extra, never a
dependency of the workflow. docs/synthetic.md states the conventions; each is tested in
tests/capture/test_mitsuba_capture.py against sellip's renderer.

Conventions (checked against Mitsuba 3.9.1's source: ``src/integrators/stokes.cpp``, ``src/bsdfs/pplastic.cpp``,
``src/bsdfs/polarizer.cpp``, ``src/sensors/perspective.cpp``, ``include/mitsuba/render/mueller.h``):

- Stokes frame: the ``stokes`` integrator rotates each pixel's Stokes vector to the basis
  x = cross(ray direction, sensor up) (= image right), observed looking back along the beam (y = image up):
  sellip's frame (:mod:`sellip.model.conventions`); its 12 AOV channels are S0..S3 x RGB.
- Camera: an OpenCV camera (x right, y down, z forward) is Mitsuba's (x left, y up, z forward) turned by 180°
  about z; ``fov`` from fx over the width (fy = fx: square pixels); the principal point by
  ``principal_point_offset_x/y`` = 0.5 - (c + 0.5) / size (Mitsuba's pixel centres are at i + 0.5, OpenCV's at
  i); a box reconstruction filter over a stratified s x s sample pattern, as sellip's supersampling.
- Flash: a ``point`` emitter (unpolarized) behind an ideal linear ``polarizer`` sheet (a 2 cm rectangle 1 cm in
  front of it, facing the camera's optical axis; transmission axis = the rectangle's local x = the flash's
  polarizer axis). The ``volpath`` integrator carries the shadow ray through the sheet (a null BSDF);
  ``max_depth`` 2: direct light only, as sellip's renderer. The polarizer halves the power: intensity x 2.
- pplastic: ``distribution: ggx`` (Mitsuba's default is Beckmann), ``alpha`` = sellip's sigma_s (both are the GGX
  alpha), ``eta`` = η; its diffuse term has a 1/π that sellip's ρ_d has not, so the flash intensity is x π and
  ``specular_reflectance`` = ρ_s / π: the image is the one sellip's renderer makes of the same ρ_d, ρ_s (no free
  scale between the two). pplastic has no single scattering: a mesh with ρ_ss > 0 is refused.
- Texture: pplastic's ``diffuse_reflectance`` cannot be a per-vertex attribute (``mesh_attribute`` has no
  ``mean()``), so a small Python BSDF evaluates Mitsuba's pplastic twice (its specular component, and its diffuse
  component at reflectance 1) and scales the diffuse by the mesh's per-vertex albedo, interpolated over the
  triangle as sellip's renderer does. η, alpha and ρ_s are per material (one Mitsuba shape each); a triangle
  takes the material of most of its vertices.
- Colour: ``llvm_ad_mono_polarized`` renders one pass per RGB channel (exact colours, no spectral noise);
  ``scalar_spectral_polarized`` (the fallback without a usable libLLVM; about 10x slower) renders grey passes and
  takes the luminance of its sRGB output.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sellip.model.conventions import stokes_to_analyzers
from sellip.model.render import FLASH_STOKES, Camera, Light, ParamMesh

log = logging.getLogger(__name__)

MITSUBA_VARIANTS = ("llvm_ad_mono_polarized", "scalar_spectral_polarized")
"""The polarized variants this generator runs, preferred first (Mitsuba's pip wheels have no RGB polarized one)."""

POLARIZER_OFFSET_M = 0.01
"""The polarizer sheet sits this far in front of the flash, along the camera's optical axis."""

POLARIZER_HALF_SIZE_M = 0.01
"""Half the side of the square polarizer sheet: it covers +-45° around the optical axis from the flash."""

MAX_DEPTH = 2
"""``volpath`` max_depth: camera ray + one bounce to the light (direct illumination, as sellip's renderer)."""

ALBEDO_ATTRIBUTE = "vertex_rho"
"""The mesh attribute that holds one colour channel of the per-vertex diffuse albedo."""

_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


class PPlasticError(ValueError):
    """A scene that Mitsuba's pplastic cannot render as sellip's pBRDF (single scattering, or parameters that vary
    inside a material); the message names the material and the parameter."""


def mitsuba_available() -> bool:
    """True when the ``mitsuba`` package (pyproject's ``test`` extra) can be imported."""
    import importlib.util

    return importlib.util.find_spec("mitsuba") is not None


def _llvm_library() -> str | None:
    """A libLLVM new enough for Dr.Jit: $DRJIT_LIBLLVM_PATH, else the ``karellen-llvm-core`` wheel's in this
    environment's lib/ (Debian 12's libLLVM 15 crashes Dr.Jit's code generator)."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    for name in ("libLLVM.so", "libLLVM.dylib"):
        candidate = Path(sys.prefix) / "lib" / name
        if candidate.is_file():
            return str(candidate)
    return None


def choose_variant(requested: str | None = None) -> str:
    """Set and return the Mitsuba variant: ``requested`` if given, else llvm_ad_mono_polarized when a suitable
    libLLVM is known (:func:`_llvm_library`, exported as DRJIT_LIBLLVM_PATH), else scalar_spectral_polarized.

    A crash of the LLVM back end aborts the process rather than raising, so the choice is made up front, not by
    trying; set DRJIT_LIBLLVM_PATH (or request the scalar variant) to override it. The path must be set before
    Dr.Jit first uses LLVM: call this before anything else in the process renders with an LLVM variant.
    """
    library = _llvm_library()
    if library:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", library)  # read when Dr.Jit starts its LLVM back end
    if requested is None:
        requested = MITSUBA_VARIANTS[0] if library else MITSUBA_VARIANTS[1]
    elif requested.startswith("llvm") and library is None:
        log.warning("Mitsuba variant %s without DRJIT_LIBLLVM_PATH or the karellen-llvm-core wheel: Dr.Jit uses the "
                    "system's libLLVM, which may be too old (Debian 12's 15 aborts the process)", requested)
    import mitsuba as mi

    if requested not in MITSUBA_VARIANTS:
        raise ValueError(f"Mitsuba variant {requested!r} is not supported; expected one of {list(MITSUBA_VARIANTS)}")
    if requested not in mi.variants():
        raise ValueError(f"this Mitsuba build has no variant {requested!r}; it has {mi.variants()}")
    mi.set_variant(requested)
    if requested.startswith("llvm"):
        import drjit as dr

        # Start the LLVM back end now: once open3d has built a ray-casting scene in this process, Dr.Jit's code
        # generation aborts it (measured with open3d 0.19 and libLLVM 23; the cause was not found).
        dr.eval(mi.Float([1.0]) + 1.0)
    return requested


# --------------------------------------------------------------------------- scene description


@dataclass(frozen=True)
class PPlasticMaterial:
    """One pplastic material in Mitsuba's units: eta (η), alpha (GGX, = sellip's sigma_s), specular
    (``specular_reflectance`` = ρ_s / π)."""

    eta: float
    alpha: float
    specular: float


def pplastic_materials(mesh: ParamMesh, tolerance: float = 1e-6) -> tuple[list[PPlasticMaterial], np.ndarray]:
    """The pplastic materials of ``mesh`` and each triangle's material index (F,).

    Materials are ``mesh.material``'s labels (or the distinct (η, σ_s, ρ_s) triples without labels); each must have
    one η, σ_s and ρ_s, and ρ_ss must be 0 everywhere (pplastic has no single scattering): else PPlasticError.
    A triangle takes the label of most of its vertices (of its first vertex when all three differ).
    """
    params = mesh.params
    eta, sigma, rho_s = (np.asarray(getattr(params, k), np.float64).reshape(-1) for k in ("eta", "sigma_s", "rho_s"))
    rho_ss = np.asarray(params.rho_ss, np.float64).reshape(mesh.num_vertices, -1)
    if np.any(rho_ss > tolerance):
        vertex = int(np.argmax(rho_ss.max(axis=1)))
        raise PPlasticError(f"vertex {vertex} has single scattering rho_ss {rho_ss[vertex].tolist()}: pplastic has no "
                            "single-scattering lobe; render a scene without it")
    if mesh.material is not None:
        label = np.asarray(mesh.material, np.int64)
    else:
        _, label = np.unique(np.round(np.stack([eta, sigma, rho_s], 1), 9), axis=0, return_inverse=True)
        label = label.reshape(-1)
    materials, index = [], {}
    for value in np.unique(label):
        members = label == value
        for name, column in (("eta", eta), ("sigma_s", sigma), ("rho_s", rho_s)):
            spread = float(np.ptp(column[members]))
            if spread > tolerance:
                raise PPlasticError(f"material {int(value)}: {name} varies from {column[members].min():.6g} to "
                                    f"{column[members].max():.6g} over its vertices; pplastic needs one value per "
                                    "material")
        first = int(np.flatnonzero(members)[0])
        index[int(value)] = len(materials)
        materials.append(PPlasticMaterial(eta=float(eta[first]), alpha=float(sigma[first]),
                                          specular=float(rho_s[first] / np.pi)))
    corners = label[np.asarray(mesh.faces, np.int64)]
    majority = np.where(corners[:, 1] == corners[:, 2], corners[:, 1], corners[:, 0])
    return materials, np.vectorize(index.__getitem__, otypes=[np.int64])(majority)


def mitsuba_camera(camera: Camera) -> dict:
    """The ``perspective`` sensor (pose, field of view, principal point) of a distortion-free sellip Camera, without
    film and sampler (Mitsuba's camera frame is OpenCV's turned by 180° about the optical axis)."""
    import mitsuba as mi

    if camera.distortion is not None and np.any(camera.distortion):
        raise ValueError("Mitsuba's perspective camera has no lens distortion; render distortion-free captures")
    k = np.asarray(camera.intrinsics, np.float64)
    if abs(k[0, 0] - k[1, 1]) > 1e-6 * k[0, 0] or abs(k[0, 1]) > 1e-9:
        raise ValueError(f"Mitsuba's perspective camera needs square pixels and no skew, got K = {k.tolist()}")
    rotation = np.asarray(camera.rotation, np.float64)
    to_world = np.eye(4)
    to_world[:3, :3] = rotation.T @ np.diag([-1.0, -1.0, 1.0])
    to_world[:3, 3] = camera.center
    return {"type": "perspective", "fov_axis": "x",
            "fov": float(np.degrees(2 * np.arctan(camera.width / (2 * k[0, 0])))),
            "principal_point_offset_x": float(0.5 - (k[0, 2] + 0.5) / camera.width),
            "principal_point_offset_y": float(0.5 - (k[1, 2] + 0.5) / camera.height),
            "near_clip": 0.01, "far_clip": 100.0, "to_world": mi.ScalarTransform4f(to_world.tolist())}


def _polarizer_sheet(camera: Camera, light: Light) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(4, 3) corners, (2, 3) triangles and (4, 2) texture coordinates of the polarizer sheet in front of the
    flash, facing the camera's optical axis. The texture's u runs along the light's axis on both triangles, so
    that Mitsuba's dp/du (the polarizer's local x, its transmission axis) is that axis everywhere: without
    texture coordinates a mesh's dp/du is each triangle's first edge, the diagonal on the second triangle."""
    forward = np.asarray(camera.rotation, np.float64)[2]
    axis = np.asarray(light.axis, np.float64)
    axis = axis - np.dot(axis, forward) * forward
    axis /= np.linalg.norm(axis)
    other = np.cross(forward, axis)
    center = np.asarray(light.position, np.float64) + POLARIZER_OFFSET_M * forward
    h = POLARIZER_HALF_SIZE_M
    corners = np.stack([center + h * (sx * axis + sy * other) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    texcoords = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return corners, np.array([[0, 1, 2], [0, 2, 3]]), texcoords


# --------------------------------------------------------------------------- the Python BSDF


_REGISTERED = set()


def _register_textured_pplastic(variant: str) -> None:
    """Register ``sellip_pplastic`` for the active variant: Mitsuba's pplastic with the diffuse component scaled
    by the shape's per-vertex attribute ALBEDO_ATTRIBUTE (see the module docstring)."""
    import mitsuba as mi

    if variant in _REGISTERED:
        return

    class TexturedPPlastic(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.inner = mi.load_dict({"type": "pplastic", "diffuse_reflectance": 1.0, "distribution": "ggx",
                                       "alpha": props["alpha"], "eta": props["eta"],
                                       "specular_reflectance": props["specular_reflectance"]})
            self.m_flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [self.m_flags]

        def eval(self, ctx, si, wo, active=True):
            specular = mi.BSDFContext(ctx.mode, mi.BSDFFlags.GlossyReflection, 0)
            diffuse = mi.BSDFContext(ctx.mode, mi.BSDFFlags.DiffuseReflection, 1)
            albedo = si.shape.eval_attribute_1(ALBEDO_ATTRIBUTE, si, active)
            return self.inner.eval(specular, si, wo, active) + self.inner.eval(diffuse, si, wo, active) * albedo

        def sample(self, ctx, si, sample1, sample2, active=True):
            # Only continues paths past max_depth (a point light cannot be hit): the inner lobe's sample suffices.
            return self.inner.sample(ctx, si, sample1, sample2, active)

        def pdf(self, ctx, si, wo, active=True):
            return self.inner.pdf(ctx, si, wo, active)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def traverse(self, callback):
            pass

        def to_string(self):
            return "SellipTexturedPPlastic"

    mi.register_bsdf("sellip_pplastic", lambda props: TexturedPPlastic(props))
    _REGISTERED.add(variant)


def mesh_shape(name: str, vertices, faces, normals=None, albedo=None, bsdf=None, texcoords=None):
    """A mi.Mesh from numpy arrays (vertices (V, 3), faces (F, 3), optional normals (V, 3), one albedo channel
    (V,) as ALBEDO_ATTRIBUTE and texture coordinates (V, 2)), with ``bsdf``."""
    import mitsuba as mi

    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    shape = mi.Mesh(name, len(vertices), len(faces), props=props, has_vertex_normals=normals is not None,
                    has_vertex_texcoords=texcoords is not None)
    params = mi.traverse(shape)
    floats, indices = type(params["vertex_positions"]), type(params["faces"])  # dynamic arrays, also in scalar variants
    params["vertex_positions"] = floats(np.asarray(vertices, np.float32).ravel())
    params["faces"] = indices(np.asarray(faces, np.uint32).ravel())
    if normals is not None:
        params["vertex_normals"] = floats(np.asarray(normals, np.float32).ravel())
    if texcoords is not None:
        params["vertex_texcoords"] = floats(np.asarray(texcoords, np.float32).ravel())
    if albedo is not None:
        shape.add_attribute(ALBEDO_ATTRIBUTE, 1, floats(np.asarray(albedo, np.float32).ravel()))
    params.update()
    return shape


# --------------------------------------------------------------------------- renderer


@dataclass
class MitsubaResult:
    """One view rendered by Mitsuba: stokes (H, W, 4, 3) float32 in sellip's camera frame (s3 included)."""

    stokes: np.ndarray

    @property
    def analyzers(self) -> np.ndarray:
        """(H, W, 4, 3) intensities behind the 0/45/90/135 degree analyzers."""
        return stokes_to_analyzers(self.stokes, axis=-2)


class MitsubaRenderer:
    """Renders a :class:`~sellip.model.render.ParamMesh` with Mitsuba 3's pplastic, as
    :class:`sellip.model.render.Renderer` renders it with sellip's pBRDF (same call, same units).

    variant: a name of MITSUBA_VARIANTS or None (:func:`choose_variant`); seed: the sampler seed of view k is
    seed * 100003 + k (the pixel sample jitter is the only randomness).
    """

    def __init__(self, mesh: ParamMesh, variant: str | None = None, seed: int = 0):
        import mitsuba as mi

        self.variant = choose_variant(variant)
        self.description = f"mitsuba {mi.__version__} {self.variant}"
        self.materials, self.face_material = pplastic_materials(mesh)
        self.mesh = mesh
        self.seed = int(seed)
        self._views = 0
        _register_textured_pplastic(self.variant)
        self._bsdfs = [mi.load_dict({"type": "sellip_pplastic", "eta": m.eta, "alpha": m.alpha,
                                     "specular_reflectance": m.specular}) for m in self.materials]
        self._polarizer = mi.load_dict({"type": "polarizer", "theta": 0.0})

    def _shapes(self, channel: int) -> dict:
        """The object's shapes, one per material, with albedo channel ``channel`` (spectral variants: grey)."""
        albedo = np.asarray(self.mesh.params.rho_d, np.float64).reshape(self.mesh.num_vertices, 3)[:, channel]
        faces = np.asarray(self.mesh.faces, np.int64)
        shapes = {}
        for index, bsdf in enumerate(self._bsdfs):
            own = faces[self.face_material == index]
            if not len(own):
                continue
            used, local = np.unique(own, return_inverse=True)
            shapes[f"material_{index}"] = mesh_shape(
                f"material_{index}", self.mesh.vertices[used], local.reshape(-1, 3), self.mesh.normals[used],
                albedo[used], bsdf)
        return shapes

    def render(self, camera: Camera, light: Light, supersample: int = 2) -> MitsubaResult:
        """Render one view: Stokes (H, W, 4, 3) per pixel in sellip's camera frame (docs/design.md §3)."""
        seed = self.seed * 100003 + self._views
        self._views += 1
        stokes = np.zeros((camera.height, camera.width, 4, 3), np.float32)
        for channel in range(3):
            scene = {**flash_scene(camera, light, 2.0 * np.pi * float(light.intensity), supersample, seed,
                                   self._polarizer, self.variant), **self._shapes(channel)}
            stokes[..., channel] = render_stokes(scene, camera, self.variant)
        return MitsubaResult(stokes=stokes)


def flash_scene(camera: Camera, light: Light, intensity: float, supersample: int, seed: int, polarizer,
                variant: str, max_depth: int = MAX_DEPTH) -> dict:
    """The parts of a Mitsuba scene dict every sellip render shares: the ``stokes`` integrator over ``volpath``
    (``max_depth``), the camera (:func:`mitsuba_camera`, a box filter over s x s stratified samples), the flash (a
    ``point`` emitter of ``intensity`` W/sr) and its polarizer sheet (:func:`_polarizer_sheet`; ``polarizer`` a
    loaded ``polarizer`` BSDF). Add the shapes and emitters of the scene and pass it to :func:`render_stokes`."""
    if not np.allclose(np.asarray(light.stokes, np.float64), FLASH_STOKES):
        raise ValueError(f"the Mitsuba generator renders the rig's flash (Stokes {FLASH_STOKES}), got {light.stokes}")
    mono = "mono" in variant
    corners, triangles, texcoords = _polarizer_sheet(camera, light)
    sensor = {**mitsuba_camera(camera),
              "film": {"type": "hdrfilm", "width": int(camera.width), "height": int(camera.height),
                       "rfilter": {"type": "box"}, "pixel_format": "luminance" if mono else "rgb"},
              "sampler": {"type": "stratified", "sample_count": int(supersample) ** 2, "seed": int(seed)}}
    return {"type": "scene",
            "integrator": {"type": "stokes", "nested": {"type": "volpath", "max_depth": int(max_depth)}},
            "sensor": sensor,
            "flash": {"type": "point", "position": [float(v) for v in light.position],
                      "intensity": intensity if mono else {"type": "spectrum", "value": intensity}},
            "polarizer": mesh_shape("polarizer", corners, triangles, bsdf=polarizer, texcoords=texcoords)}


def render_stokes(scene: dict, camera: Camera, variant: str) -> np.ndarray:
    """Render a scene dict (:func:`flash_scene` plus shapes): one channel's Stokes image (H, W, 4) in sellip's
    camera frame (mono variants: the rendered channel; spectral: the luminance of the sRGB output)."""
    import mitsuba as mi

    image = np.asarray(mi.render(mi.load_dict(scene)), np.float64)
    aov = image[..., -12:].reshape(camera.height, camera.width, 4, 3)  # S0..S3 x (R, G, B)
    return (aov[..., 0] if "mono" in variant else aov @ _LUMINANCE).astype(np.float32)


# --------------------------------------------------------------------------- a fresh process


def render_in_subprocess(mesh: ParamMesh, views: list[tuple[Camera, Light]], supersample: int = 2,
                         variant: str | None = None, seed: int = 0, timeout_s: float = 600.0) -> np.ndarray:
    """Stokes images (N, H, W, 4, 3) of ``views`` ((camera, light) pairs of one size) rendered by
    :class:`MitsubaRenderer` in a new Python process.

    Dr.Jit's LLVM back end must start before open3d builds a ray-casting scene in the same process (after it,
    code generation aborts the process: measured with Mitsuba 3.9.1 and open3d 0.19); a process that has used
    open3d (a test session, a notebook) renders here instead.
    """
    import pickle
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(prefix="sellip-mitsuba-") as folder:
        job, result = Path(folder) / "job.pkl", Path(folder) / "stokes.npy"
        job.write_bytes(pickle.dumps({"mesh": mesh, "views": views, "supersample": supersample, "variant": variant,
                                      "seed": seed}))
        done = subprocess.run([sys.executable, "-m", "sellip.capture.mitsuba_capture", str(job), str(result)],
                              capture_output=True, text=True, timeout=timeout_s, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"the Mitsuba render process failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
        return np.load(result)


def _render_job(job_path: str, out_path: str) -> None:
    """The other side of :func:`render_in_subprocess`: read the pickled job, render, write the .npy."""
    import pickle

    job = pickle.loads(Path(job_path).read_bytes())
    choose_variant(job["variant"])
    renderer = MitsubaRenderer(job["mesh"], variant=job["variant"], seed=job["seed"])
    stokes = np.stack([renderer.render(camera, light, job["supersample"]).stokes for camera, light in job["views"]])
    np.save(out_path, stokes)


if __name__ == "__main__":
    _render_job(sys.argv[1], sys.argv[2])
