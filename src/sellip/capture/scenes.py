"""Procedural test scenes with known ground truth (no downloads) and handheld camera orbits.

Public API::

    SCENES: tuple of scene names ("demo", "demo_fine", "demo_feathers", "sphere_ior", "tiny", "tiny_dark",
            "tiny_white", "tiny_mirror", "tiny_bumpy", "tiny_relief", "tiny_speckle", "uniform_dark",
            "uniform_bright", "cow", "cow_painted", "tiny_plain", "pplastic_set", "bowl")
    build_scene(name) -> Scene                       # mesh with per-vertex pBRDF parameters, fixed per name
    handheld_orbit(views, width, height, rng, ...) -> list[Camera]
    device_intrinsics(width, height) -> (3, 3) K    # the 25 mm lens on the IMX250 scaled to width

World frame: metres, z up, the object centred near the origin. Each scene's
geometry and materials are fixed by its name (an internal seed), so "demo" is
always the same object; the capture seed only moves the cameras and the noise.

Scenes:

- ``demo``: an owl-like blob about 12 cm tall: ear tufts, eye sockets with 12 mm eyes and
  a beak, a facial disc, wing creases (concavities that cast flash shadows); its
  feathers are in the albedo. Three materials (DEMO_MATERIALS): plumage
  (eta 1.48, sigma_s 0.28), facial disc and belly with single scattering
  (eta 1.36, sigma_s 0.42), glossy amber eyes and beak (eta 1.62, sigma_s 0.09).
  The albedo is soft feather patches of about 9 mm: detail the demo's 6k-vertex
  model can carry at 612x512.
- ``demo_fine``: the demo until 2026-11-25, with detail finer than its model: 3 mm
  feather cells with dark edges and a speckle at the HDR pixel, 2 mm eyeballs in deep
  sockets, dark eyes (DEMO_FINE_MATERIALS): a hard case (docs/accuracy.md).
- ``demo_feathers``: demo_fine with a feather relief (0.35 mm ridges between 3 mm
  cells) finer than its pixels: a hard case (docs/accuracy.md: it biases eta low).
- ``sphere_ior``: a 6 cm-radius textured sphere split into seven wedges with
  the refractive indices of the paper's Table 1 (SPHERE_IOR_ETAS).
- ``tiny``: a 4 cm-radius sphere with two materials, coarse mesh, for tests.
- ``tiny_dark``, ``tiny_white``, ``tiny_mirror``: the tiny sphere in the materials of the paper's
  failure cases (§6, docs/benchmarks.md): very dark (rho_d 0.02-0.05), white and rough (rho_d about
  0.8, sigma_s 0.55-0.6, single scattering on one half), and a near-mirror (sigma_s 0.03-0.05 over
  a dark diffuse albedo). Same flash power as ``tiny``: the rig, not the object, sets it.
- ``tiny_bumpy``: the ``tiny`` materials on a sphere with three 4 mm bumps and three 4 mm dents (finer
  mesh, 10242 vertices): shape detail for the initial-mesh cases of the stability suite.
- ``tiny_relief``: the ``tiny`` materials with the demo_feathers relief (40962 vertices): sub-pixel
  surface detail for the stability suite.
- ``tiny_speckle``: the ``tiny`` materials with demo_fine's albedo speckle in 1 mm cells (40962 vertices):
  texture finer than the model and the pixels, for the stability suite.
- ``uniform_dark``, ``uniform_bright``: the tiny sphere in one material with no texture (rho_d 0.04 glossy;
  rho_d 0.7): degenerate statistics (every albedo one value) for the stability suite.
- ``cow``: a cow-like figure (body, head, four legs, concavities) in one material painted with flat black
  and white patches with sharp edges: many identical albedo rows, for the stability suite.
- ``cow_painted``: the cow's shape on a finer mesh, painted with a base coat and 2,000 sharp-edged dabs about
  3 mm across in random colours: a textured figure that SfM can register (issue #36 item 4).
- ``cow_dark``: the cow's shape on the finer mesh in one very dark glossy material (rho_d 0.045) with no texture:
  a dark uniform figure.
- ``tiny_plain``: ``tiny`` without its single scattering (the rough half's ρ_ss is 0), and ``pplastic_set``: a
  4 cm sphere with four wedges of PPLASTIC_SET_MATERIALS (η 1.33-2.0, σ_s 0.1-0.4, among them the η 1.663 / α 0.25
  material that gained a false single-scattering lobe in issue #36): scenes both renderers draw (Mitsuba's pplastic
  has no single scattering; sellip.capture.mitsuba_capture), so any fitted ρ_ss is a false positive.
- ``bowl``: a 4 cm ball with a bowl-shaped hollow 14 mm deep and about 25 mm across, opening 35 deg above the
  horizon where the cameras look into it, in one textured material: a concavity that no silhouette reveals, so a
  visual hull bridges it (its convex hull lies up to 6 mm above it; issue #53 item 6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from sellip.geometry.meshes import vertex_normals
from sellip.model.pbrdf import PBRDFParams
from sellip.model.render import Camera, ParamMesh

SCENES = ("demo", "demo_fine", "demo_feathers", "sphere_ior", "tiny", "tiny_dark", "tiny_white", "tiny_mirror",
          "tiny_bumpy", "tiny_relief", "tiny_speckle", "uniform_dark", "uniform_bright", "cow", "cow_painted",
          "tiny_plain", "pplastic_set", "bowl", "cow_dark")

DEVICE_WIDTH_PX = 2448
DEVICE_FX_PX = 7246.0
"""IMX250 (3.45 um pixels) behind a 25 mm lens: fx at the full sensor width (docs/design.md §4 notes)."""

SPHERE_IOR_ETAS = (1.463, 1.485, 1.503, 1.462, 2.295, 1.303, 1.663)
"""Refractive indices of the paper's Table 1, one per wedge of the sphere_ior scene."""


@dataclass(frozen=True)
class Material:
    """pBRDF parameters shared by one region; rho_d is the region's mean diffuse albedo (RGB)."""

    name: str
    eta: float
    rho_d: tuple[float, float, float]
    rho_s: float
    sigma_s: float
    rho_ss: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sigma_ss: float = 0.5


DEMO_MATERIALS = (
    Material("plumage", eta=1.48, rho_d=(0.22, 0.14, 0.075), rho_s=1.0, sigma_s=0.28),
    Material("facial_disc", eta=1.36, rho_d=(0.28, 0.25, 0.19), rho_s=0.8, sigma_s=0.42,
             rho_ss=(0.30, 0.18, 0.09), sigma_ss=0.55),
    Material("eyes_beak", eta=1.62, rho_d=(0.42, 0.28, 0.06), rho_s=1.0, sigma_s=0.09),
)
"""The demo owl's materials; its eyes and beak are amber (demo_fine's are dark, DEMO_FINE_MATERIALS)."""

DEMO_FINE_MATERIALS = DEMO_MATERIALS[:2] + (
    Material("eyes_beak", eta=1.62, rho_d=(0.20, 0.13, 0.02), rho_s=1.0, sigma_s=0.09),)
"""The demo_fine owl's materials (the demo's until 2026-11-25): dark glossy eyes and beak."""


@dataclass(frozen=True)
class Scene:
    """A ground-truth object and how to photograph it.

    mesh: the object; materials: the region list (mesh.material indexes it);
    flash_power: raw DN above black per unit of full_stokes intensity at flash_level 1
    (chosen so that the brightest highlights saturate at flash 1/4 in some views);
    distance_m: (min, max) camera distance of the orbit; elevation_deg: (min, max) orbit elevation.
    """

    name: str
    mesh: ParamMesh
    materials: tuple[Material, ...]
    flash_power: float
    distance_m: tuple[float, float] = (0.8, 1.0)
    elevation_deg: tuple[float, float] = (-15.0, 65.0)


# --------------------------------------------------------------------------- geometry helpers


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: vertices (V, 3) on the unit sphere and faces (F, 3), counter-clockwise from outside."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    if subdivisions:
        mesh = mesh.subdivide_midpoint(subdivisions)
    vertices = np.asarray(mesh.vertices, np.float64)
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    faces = np.asarray(mesh.triangles, np.int64)
    # Orient outward: the signed volume must be positive.
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:
        faces = faces[:, ::-1]
    return vertices, np.ascontiguousarray(faces)


def random_unit_vectors(count: int, rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def cellular(directions: np.ndarray, cells: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Worley noise on the unit sphere: (F1, F2 - F1, cell index), distances in radians, for (N, 3) unit directions."""
    sites = random_unit_vectors(cells, rng)
    distance, index = cKDTree(sites).query(directions, k=2)
    angle = 2 * np.arcsin(np.clip(distance / 2, 0, 1))
    return angle[:, 0], angle[:, 1] - angle[:, 0], index[:, 0]


def bump(directions: np.ndarray, center, width_rad: float) -> np.ndarray:
    """Gaussian of the angle between each direction (N, 3) and ``center`` (3,), 1 at the centre."""
    center = np.asarray(center, np.float64)
    center = center / np.linalg.norm(center)
    angle = np.arccos(np.clip(directions @ center, -1, 1))
    return np.exp(-0.5 * (angle / width_rad) ** 2)


def _direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector at an azimuth from +x towards +y and an elevation towards +z (degrees)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _params_from_regions(materials, region: np.ndarray, rho_d: np.ndarray) -> PBRDFParams:
    """Per-vertex PBRDFParams (numpy, float64) from region labels and a per-vertex diffuse albedo (V, 3)."""
    def column(attr):
        return np.array([getattr(m, attr) for m in materials], np.float64)[region]

    return PBRDFParams(eta=column("eta"), rho_d=rho_d, rho_s=column("rho_s"), sigma_s=column("sigma_s"),
                       rho_ss=np.array([m.rho_ss for m in materials], np.float64)[region],
                       sigma_ss=column("sigma_ss"))


# --------------------------------------------------------------------------- scenes


FEATHER_RELIEF_M = 0.00035
"""Height of the demo_feathers relief (ridges between ~3 mm feather cells, slopes up to ~16 deg): the demo's
owl had it until the accuracy ladder showed it is finer than a 612x512 pixel (0.5 mm), so every pixel
averages several normals and the polarization it sees is depolarized (docs/accuracy.md)."""


def feather_relief(f1: np.ndarray, edge: np.ndarray, cell_rad: float, height_m: float) -> np.ndarray:
    """Radius offset (N,) metres of cellular feathers from :func:`cellular`'s F1 and F2 - F1 (radians):
    ridges of ``height_m`` between cells of angular size ``cell_rad``, a dimple of 4/7 of that at each centre."""
    return height_m * (np.clip(edge / (0.35 * cell_rad), 0, 1) - 4 / 7 * np.exp(-(f1 / (0.25 * cell_rad)) ** 2))


def _demo(relief_m: float = 0.0, name: str = "demo", fine: bool = False) -> Scene:
    """The owl-like blob (see the module docstring). Facing +x, z up, about 12 cm tall.

    ``fine=False`` (the demo): feathers in soft patches of about 9 mm and eyes of 12 mm, detail that the demo's
    6k-vertex model (2.3 mm edges) and 612x512 pixels (0.5 mm) can carry. ``fine=True`` (demo_fine, the demo
    until 2026-11-25): 3 mm feather cells with dark edges and a speckle of 12,000 cells at the HDR pixel, 2 mm
    eyeballs in deep sockets. ``relief_m``: height of a feather relief between the 3 mm cells (0: none).

    Long: one object built part by part (shape, eyes, beak, disc, feathers, materials), read top to bottom."""
    rng = np.random.default_rng(20220804)
    d, faces = icosphere(7)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]

    # Egg-shaped body: wider at the bottom, a slightly flattened face.
    radius = 0.046 / np.sqrt((x / 1.0) ** 2 + (y / 0.96) ** 2 + (z / 1.28) ** 2)
    radius *= 1 - 0.06 * z - 0.05 * np.clip(x, 0, None) ** 3
    ears = [_direction(30, 52), _direction(-30, 52)]
    eyes = [_direction(24, 22), _direction(-24, 22)]
    beak = _direction(0, 8)
    radius += sum(0.017 * bump(d, e, 0.13) for e in ears)
    # Eye sockets with eyeballs inside, and the beak: (socket depth, eyeball height, eyeball width, eye region
    # width, beak height, beak width, beak region width) in metres and radians.
    socket, eyeball, eyeball_rad, eye_rad, beak_m, beak_rad, beak_region_rad = (
        (0.0065, 0.0022, 0.05, 0.075, 0.006, 0.07, 0.06) if fine else (0.0025, 0.003, 0.12, 0.12, 0.006, 0.12, 0.09))
    radius -= sum(socket * bump(d, e, 0.16) for e in eyes)
    radius += sum(eyeball * bump(d, e, eyeball_rad) for e in eyes)
    radius += beak_m * bump(d, beak, beak_rad)
    radius += sum(0.002 * bump(d, e, 0.33) - 0.0025 * bump(d, e, 0.22) for e in eyes)  # facial disc rim
    # Wing creases: a concave groove along each flank, 3.5 mm deep; demo_fine's is 2.8 mm wide (sigma) and ends in a
    # step at z = 0.5; the demo's is 4.6 mm wide and fades out between z = 0.35 and 0.55 (a model of 2.3 mm edges
    # can follow it).
    crease_rad = 0.06 if fine else 0.1
    fade = np.clip((0.55 - z) / 0.2, 0, 1)
    crease_end = (z < 0.5) if fine else fade**2 * (3 - 2 * fade)  # smoothstep
    for side in (1, -1):
        wing = np.arccos(np.clip(d @ _direction(side * 100, -10), -1, 1))
        radius -= 0.0035 * np.exp(-0.5 * ((wing - 0.75) / crease_rad) ** 2) * crease_end
    radius += sum(0.004 * bump(d, _direction(side * 25, -72), 0.12) for side in (1, -1))  # feet

    # Feather cells of ~3 mm (the fine albedo below; with relief_m, ridges between them).
    f1, edge, cell = cellular(d, 2500, rng)
    cell_size = np.sqrt(4 * np.pi / 2500)
    radius += feather_relief(f1, edge, cell_size, relief_m)
    vertices = d * radius[:, None]

    # Regions: 0 plumage, 1 facial disc and belly, 2 eyes and beak.
    region = np.zeros(len(d), np.int64)
    disc = sum(bump(d, e, 0.3) for e in eyes) > 0.45
    belly = (bump(d, _direction(0, -25), 0.55) > 0.55) & (x > 0)
    region[disc | belly] = 1
    region[(sum(bump(d, e, eye_rad) for e in eyes) > 0.5) | (bump(d, beak, beak_region_rad) > 0.5)] = 2

    materials = DEMO_FINE_MATERIALS if fine else DEMO_MATERIALS
    base = np.array([m.rho_d for m in materials])[region]
    pupils = sum(bump(d, e, 0.03) for e in eyes) > 0.5
    if fine:
        # Per-feather brightness, darker feather edges and a speckle at the HDR pixel.
        feather_gain = rng.uniform(0.6, 1.35, size=2500)[cell]
        _, fine_edge, fine_cell = cellular(d, 12000, rng)
        speckle = rng.uniform(0.75, 1.2, size=12000)[fine_cell]
        edge_shade = 0.55 + 0.45 * np.clip(edge / (0.25 * cell_size), 0, 1)
        pattern = np.where(region == 2, speckle, feather_gain * edge_shade * speckle)
        bars = 40.0
    else:
        # Soft feather patches: 300 cells' brightness blended over a Gaussian of 0.07 rad (3 mm), and a shade
        # that darkens each patch smoothly towards its edges.
        sites = random_unit_vectors(300, rng)
        gain = rng.uniform(0.65, 1.3, size=300)
        distance, index = cKDTree(sites).query(d, k=8)
        weight = np.exp(-0.5 * (2 * np.arcsin(np.clip(distance / 2, 0, 1)) / 0.07) ** 2) + 1e-12
        blended = (weight * gain[index]).sum(axis=1) / weight.sum(axis=1)
        patch_size = np.sqrt(4 * np.pi / 300)
        _, patch_edge, _ = cellular(d, 300, np.random.default_rng(7))
        shade = 0.8 + 0.2 * np.sin(0.5 * np.pi * np.clip(patch_edge / (0.5 * patch_size), 0, 1)) ** 2
        pattern = np.where(region == 2, 1.0, blended * shade)
        bars = 12.0
    albedo = base * pattern[:, None]
    albedo[pupils] = 0.01
    albedo[region == 1] *= (0.8 + 0.35 * np.cos(bars * z[region == 1]) ** 2)[:, None]  # chevron bars
    albedo = np.clip(albedo, 0.005, 0.6)

    mesh = ParamMesh(vertices=vertices, faces=faces, normals=vertex_normals(vertices, faces, area_weighted=True),
                     params=_params_from_regions(materials, region, albedo), material=region)
    return Scene(name, mesh, materials, flash_power=64000.0)


def _sphere_ior() -> Scene:
    """A textured 6 cm sphere with seven wedges (about the z axis), one per index of SPHERE_IOR_ETAS."""
    rng = np.random.default_rng(1303)
    d, faces = icosphere(6)
    hues = np.array([[0.25, 0.08, 0.05], [0.06, 0.2, 0.08], [0.06, 0.09, 0.25], [0.24, 0.2, 0.06],
                     [0.2, 0.2, 0.2], [0.22, 0.08, 0.2], [0.05, 0.2, 0.22]])
    materials = tuple(Material(f"eta_{eta:.3f}", eta=eta, rho_d=tuple(hue), rho_s=1.0, sigma_s=0.2)
                      for eta, hue in zip(SPHERE_IOR_ETAS, hues))
    azimuth = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    region = np.minimum((azimuth / (2 * np.pi) * len(materials)).astype(np.int64), len(materials) - 1)
    _, edge, cell = cellular(d, 3000, rng)
    gain = rng.uniform(0.55, 1.4, size=3000)[cell] * (0.6 + 0.4 * np.clip(edge / 0.02, 0, 1))
    albedo = np.clip(hues[region] * gain[:, None], 0.005, 0.6)
    vertices = 0.06 * d
    mesh = ParamMesh(vertices=vertices, faces=faces, normals=d.copy(),
                     params=_params_from_regions(materials, region, albedo), material=region)
    return Scene("sphere_ior", mesh, materials, flash_power=20000.0)


TINY_FLASH_POWER = 30000.0
"""Flash power (DN per unit intensity at flash level 1) of the tiny sphere scenes."""


TINY_BUMPS = (((0, 30), 0.004), ((120, -20), 0.004), ((240, 45), 0.004),
              ((60, -35), -0.004), ((180, 10), -0.004), ((300, -5), -0.004))
"""tiny_bumpy: ((azimuth, elevation) in degrees, height in metres) of its Gaussian bumps (> 0) and dents (< 0)."""

TINY_BUMP_WIDTH_RAD = 0.2
"""Standard deviation (angle on the sphere) of the tiny_bumpy bumps: 8 mm on the 4 cm sphere."""


def _two_material_sphere(name: str, materials: tuple[Material, Material], checker_gain: tuple[float, float],
                         flash_power: float = TINY_FLASH_POWER, subdivisions: int = 4, bumps=(),
                         relief_m: float = 0.0, speckle_m: float = 0.0) -> Scene:
    """A 4 cm sphere (icosphere of ``subdivisions``: 4 gives 2562 vertices), ``materials`` on the top and bottom
    halves, and a checker texture (12 azimuth sectors x 8 bands) that scales each material's rho_d by
    ``checker_gain`` (dark, light). ``bumps``: ((azimuth, elevation) deg, height m) Gaussian bumps of
    TINY_BUMP_WIDTH_RAD added to the radius; ``relief_m``: :func:`feather_relief` of that height between cells
    of 3.3 mm (as the demo_feathers owl's) added too (with either, the normals are the surface's); ``speckle_m``:
    the albedo also scaled per cell of this size by a gain in 0.75-1.2 (demo_fine's speckle)."""
    d, faces = icosphere(subdivisions)
    region = (d[:, 2] < 0).astype(np.int64)
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    checker = ((np.floor(azimuth / (np.pi / 6)) + np.floor(d[:, 2] / 0.25)) % 2).astype(np.int64)
    albedo = np.array([m.rho_d for m in materials])[region] * np.asarray(checker_gain, np.float64)[checker][:, None]
    if speckle_m:
        cells = round(4 * np.pi / (speckle_m / 0.04) ** 2)
        rng = np.random.default_rng(11)
        _, _, cell = cellular(d, cells, rng)
        albedo = albedo * rng.uniform(0.75, 1.2, size=cells)[cell][:, None]
    radius = 0.04 + sum(height * bump(d, _direction(*where), TINY_BUMP_WIDTH_RAD) for where, height in bumps)
    if relief_m:
        cell_rad = 0.0033 / 0.04
        f1, edge, _ = cellular(d, round(4 * np.pi / cell_rad**2), np.random.default_rng(7))
        radius = radius + feather_relief(f1, edge, cell_rad, relief_m)
    shaped = bool(bumps) or bool(relief_m)
    vertices = radius[:, None] * d if shaped else 0.04 * d
    normals = vertex_normals(vertices, faces, area_weighted=True) if shaped else d.copy()
    mesh = ParamMesh(vertices=vertices, faces=faces, normals=normals,
                     params=_params_from_regions(materials, region, albedo), material=region)
    return Scene(name, mesh, materials, flash_power=flash_power)


TINY_MATERIALS = (Material("glossy", eta=1.6, rho_d=(0.2, 0.12, 0.08), rho_s=1.0, sigma_s=0.12),
                  Material("rough", eta=1.4, rho_d=(0.1, 0.18, 0.22), rho_s=0.6, sigma_s=0.35,
                           rho_ss=(0.1, 0.06, 0.03), sigma_ss=0.5))


def _tiny() -> Scene:
    """A 4 cm sphere, coarse mesh, two materials (top and bottom halves) with a checker texture."""
    return _two_material_sphere("tiny", TINY_MATERIALS, (0.6, 1.2))


def _tiny_bumpy() -> Scene:
    """The tiny sphere's materials on a finer sphere (10242 vertices) with three 4 mm bumps and three 4 mm dents
    (TINY_BUMPS): shape detail that an over-smoothed initial mesh loses and a visual hull cannot carve."""
    return _two_material_sphere("tiny_bumpy", TINY_MATERIALS, (0.6, 1.2), subdivisions=5, bumps=TINY_BUMPS)


def _tiny_relief() -> Scene:
    """The tiny sphere with the demo_feathers relief (0.35 mm ridges between 3.3 mm cells, 40962 vertices): surface
    detail finer than a pixel of the stability suite's 320x256 (about 1 mm), which depolarizes what a pixel sees."""
    return _two_material_sphere("tiny_relief", TINY_MATERIALS, (0.6, 1.2), subdivisions=6, relief_m=FEATHER_RELIEF_M)


def _tiny_speckle() -> Scene:
    """The tiny sphere with demo_fine's albedo speckle at the pixel of the stability suite's 320x256: cells of 1 mm
    (gain 0.75-1.2), 40962 vertices: texture finer than the model (2,500 vertices) and the pixels."""
    return _two_material_sphere("tiny_speckle", TINY_MATERIALS, (0.6, 1.2), subdivisions=6, speckle_m=0.001)


def _demo_fine() -> Scene:
    """The demo owl until 2026-11-25: detail finer than the demo's model (3 mm feathers, a speckle at the pixel,
    2 mm eyeballs)."""
    return _demo(0.0, "demo_fine", fine=True)


def _demo_feathers() -> Scene:
    """demo_fine with its feather relief (FEATHER_RELIEF_M)."""
    return _demo(FEATHER_RELIEF_M, "demo_feathers", fine=True)


def _tiny_dark() -> Scene:
    """The tiny sphere, very dark (rho_d 0.02-0.05, paper §6: the DoP drowns in noise), glossy and rough halves."""
    materials = (Material("dark_glossy", eta=1.55, rho_d=(0.05, 0.04, 0.035), rho_s=1.0, sigma_s=0.15),
                 Material("dark_rough", eta=1.45, rho_d=(0.035, 0.045, 0.05), rho_s=0.8, sigma_s=0.3))
    return _two_material_sphere("tiny_dark", materials, (0.6, 1.0))


def _tiny_white() -> Scene:
    """The tiny sphere, white and rough (rho_d about 0.8, sigma_s 0.55-0.6); the bottom half adds single
    scattering with a lobe as wide as the specular one (paper §6: specular and single scattering blur)."""
    materials = (Material("white_rough", eta=1.5, rho_d=(0.82, 0.8, 0.76), rho_s=1.0, sigma_s=0.6),
                 Material("white_scattering", eta=1.45, rho_d=(0.76, 0.8, 0.82), rho_s=0.8, sigma_s=0.55,
                          rho_ss=(0.3, 0.3, 0.3), sigma_ss=0.6))
    return _two_material_sphere("tiny_white", materials, (0.85, 1.0))


def _tiny_mirror() -> Scene:
    """The tiny sphere as a near-mirror: sigma_s 0.03 and 0.05 (paper §6: dominant specularity) over a dark
    diffuse albedo (0.03-0.08)."""
    materials = (Material("mirror_03", eta=1.6, rho_d=(0.08, 0.06, 0.05), rho_s=1.0, sigma_s=0.03),
                 Material("mirror_05", eta=1.5, rho_d=(0.05, 0.06, 0.08), rho_s=1.0, sigma_s=0.05))
    return _two_material_sphere("tiny_mirror", materials, (0.6, 1.0))


def _uniform_sphere(name: str, material: Material) -> Scene:
    """The tiny 4 cm sphere (2562 vertices) in one material with no texture at all: every vertex has the same
    parameters, so the fitted albedos of a material are one value up to noise (degenerate statistics)."""
    d, faces = icosphere(4)
    region = np.zeros(len(d), np.int64)
    albedo = np.tile(np.asarray(material.rho_d, np.float64), (len(d), 1))
    mesh = ParamMesh(vertices=0.04 * d, faces=faces, normals=d.copy(),
                     params=_params_from_regions((material,), region, albedo), material=region)
    return Scene(name, mesh, (material,), flash_power=TINY_FLASH_POWER)


def _uniform_dark() -> Scene:
    """The tiny sphere, one uniformly coloured very dark glossy material (rho_d 0.04: the paper's failure case)."""
    return _uniform_sphere("uniform_dark", Material("uniform_dark", eta=1.5, rho_d=(0.04, 0.04, 0.04), rho_s=1.0,
                                                    sigma_s=0.15))


def _uniform_bright() -> Scene:
    """The tiny sphere, one uniformly coloured bright material (rho_d 0.7, sigma_s 0.25)."""
    return _uniform_sphere("uniform_bright", Material("uniform_bright", eta=1.5, rho_d=(0.72, 0.7, 0.66), rho_s=0.8,
                                                      sigma_s=0.25))


COW_PATCH_ALBEDO = ((0.03, 0.03, 0.03), (0.8, 0.78, 0.74))
"""The cow's two flat patch colours (black, white): the rows of its fitted albedo features repeat."""


def _cow_shape(subdivisions: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cow's unit directions (N, 3), vertices (N, 3) metres and faces of an icosphere of ``subdivisions``: an
    elongated body, a head, four legs (radial bumps on an ellipsoid), star-shaped about the origin."""
    d, faces = icosphere(subdivisions)
    body = 1 / np.sqrt((d[:, 0] / 0.05) ** 2 + (d[:, 1] / 0.026) ** 2 + (d[:, 2] / 0.03) ** 2)
    legs = sum(bump(d, _direction(azimuth, -62), 0.13) for azimuth in (35, 145, -35, -145))
    radius = body + 0.028 * legs + 0.02 * bump(d, _direction(0, 18), 0.2)
    return d, radius[:, None] * d, faces


def _one_material_mesh(name: str, material: Material, d: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                       albedo: np.ndarray) -> Scene:
    region = np.zeros(len(d), np.int64)
    mesh = ParamMesh(vertices=vertices, faces=faces, normals=vertex_normals(vertices, faces, area_weighted=True),
                     params=_params_from_regions((material,), region, albedo), material=region)
    return Scene(name, mesh, (material,), flash_power=TINY_FLASH_POWER)


def _cow() -> Scene:
    """A cow-like figure about 10 cm long, one material (eta 1.5, sigma_s 0.2) painted with large flat black and
    white patches with sharp edges (Worley cells, each black or white): an elongated body, a head, four legs
    (radial bumps on an ellipsoid, 10242 vertices), with concavities between the legs and at the neck that a visual
    hull does not carve. Star-shaped about the origin, so the radial mesh never folds."""
    d, vertices, faces = _cow_shape(5)
    _, _, cell = cellular(d, 28, np.random.default_rng(5))
    black = np.random.default_rng(6).random(28) < 0.4
    albedo = np.asarray(COW_PATCH_ALBEDO, np.float64)[np.where(black[cell], 0, 1)]
    material = Material("cow", eta=1.5, rho_d=COW_PATCH_ALBEDO[1], rho_s=0.8, sigma_s=0.2)
    return _one_material_mesh("cow", material, d, vertices, faces, albedo)


def _cow_painted() -> Scene:
    """The cow's shape (40962 vertices, 0.6 mm apart) in one material (eta 1.5, sigma_s 0.2) with a painted texture
    that SfM can match: a base coat of 28 large patches in three colours, and over it 2,000 sharp-edged dabs about
    3 mm across (Worley cells), half of them painted in random colours of albedo 0.1-0.75 (issue #36 item 4: the
    textured figure, from SfM's poses)."""
    d, vertices, faces = _cow_shape(6)
    rng = np.random.default_rng(7)
    _, _, coat_cell = cellular(d, 28, rng)
    coats = np.array([(0.62, 0.5, 0.36), (0.75, 0.73, 0.7), (0.25, 0.16, 0.1)])
    albedo = coats[rng.integers(0, len(coats), 28)][coat_cell]
    _, _, dab_cell = cellular(d, 2000, rng)
    painted = rng.random(2000) < 0.5
    colours = rng.uniform(0.1, 0.75, (2000, 3))
    albedo = np.where(painted[dab_cell][:, None], colours[dab_cell], albedo)
    material = Material("cow_painted", eta=1.5, rho_d=tuple(coats[0]), rho_s=0.8, sigma_s=0.2)
    return _one_material_mesh("cow_painted", material, d, vertices, faces, albedo)


def _cow_dark() -> Scene:
    """The cow's shape (40962 vertices) in one uniformly coloured very dark glossy material (rho_d 0.045, eta 1.5,
    sigma_s 0.15) with no texture at all: the dark uniform figure of issue #53 (legs, concavities, a head), where
    the fit has the least diffuse light to go on and SfM nothing to match."""
    d, vertices, faces = _cow_shape(6)
    material = Material("cow_dark", eta=1.5, rho_d=(0.045, 0.045, 0.045), rho_s=1.0, sigma_s=0.15)
    albedo = np.tile(np.asarray(material.rho_d, np.float64), (len(d), 1))
    return _one_material_mesh("cow_dark", material, d, vertices, faces, albedo)


PPLASTIC_SET_MATERIALS = (
    Material("polypropylene", eta=1.49, rho_d=(0.25, 0.1, 0.05), rho_s=1.0, sigma_s=0.1),
    Material("issue36_1663", eta=1.663, rho_d=(0.08, 0.15, 0.25), rho_s=1.0, sigma_s=0.25),
    Material("water_rough", eta=1.33, rho_d=(0.3, 0.3, 0.25), rho_s=0.8, sigma_s=0.4),
    Material("high_index", eta=2.0, rho_d=(0.05, 0.2, 0.1), rho_s=1.0, sigma_s=0.15),
)
"""pplastic_set's materials: no single scattering (what Mitsuba's pplastic can render)."""


def _tiny_plain() -> Scene:
    """The tiny sphere with no single scattering: both renderers can draw it."""
    plain = tuple(Material(m.name, eta=m.eta, rho_d=m.rho_d, rho_s=m.rho_s, sigma_s=m.sigma_s) for m in TINY_MATERIALS)
    return _two_material_sphere("tiny_plain", plain, (0.6, 1.2))


def _pplastic_set() -> Scene:
    """A 4 cm sphere (2562 vertices) in four azimuth wedges of PPLASTIC_SET_MATERIALS, each with the tiny sphere's
    checker texture (gain 0.6 / 1.2)."""
    d, faces = icosphere(4)
    azimuth = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    count = len(PPLASTIC_SET_MATERIALS)
    region = np.minimum((azimuth / (2 * np.pi) * count).astype(np.int64), count - 1)
    checker = ((np.floor(azimuth / (np.pi / 6)) + np.floor(d[:, 2] / 0.25)) % 2).astype(np.int64)
    albedo = np.array([m.rho_d for m in PPLASTIC_SET_MATERIALS])[region] * np.array([0.6, 1.2])[checker][:, None]
    mesh = ParamMesh(vertices=0.04 * d, faces=faces, normals=d.copy(),
                     params=_params_from_regions(PPLASTIC_SET_MATERIALS, region, albedo), material=region)
    return Scene("pplastic_set", mesh, PPLASTIC_SET_MATERIALS, flash_power=TINY_FLASH_POWER)


BOWL_AXIS = (0.0, 35.0)
"""Azimuth and elevation (degrees) of the bowl scene's hollow."""
BOWL_DEPTH_M = 0.014
BOWL_WIDTH_RAD = 0.3


def _bowl() -> Scene:
    """A 4 cm ball (10242 vertices) with a hollow BOWL_DEPTH_M deep (a Gaussian dent of BOWL_WIDTH_RAD, its rim at
    full radius all round, so no silhouette shows it and a visual hull bridges it), opening at BOWL_AXIS, where the
    cameras' elevations reach into it. One material (eta 1.5, sigma_s 0.2) painted with 400 sharp-edged patches
    (about 7 mm across) of two greys and a tan: texture that multi-view matching can use. Star-shaped about the
    origin: it never folds."""
    d, faces = icosphere(5)
    radius = 0.04 - BOWL_DEPTH_M * bump(d, _direction(*BOWL_AXIS), BOWL_WIDTH_RAD)
    _, _, cell = cellular(d, 400, np.random.default_rng(8))
    colours = np.array([(0.2, 0.2, 0.2), (0.7, 0.68, 0.64), (0.55, 0.4, 0.25)])
    albedo = colours[np.random.default_rng(9).integers(0, len(colours), 400)][cell]
    material = Material("bowl", eta=1.5, rho_d=tuple(colours[1]), rho_s=0.8, sigma_s=0.2)
    return _one_material_mesh("bowl", material, d, radius[:, None] * d, faces, albedo)


_BUILDERS = {"demo": _demo, "demo_fine": _demo_fine, "demo_feathers": _demo_feathers, "sphere_ior": _sphere_ior,
             "tiny": _tiny,
             "tiny_dark": _tiny_dark, "tiny_white": _tiny_white, "tiny_mirror": _tiny_mirror, "tiny_bumpy": _tiny_bumpy,
             "tiny_relief": _tiny_relief, "tiny_speckle": _tiny_speckle, "uniform_dark": _uniform_dark,
             "uniform_bright": _uniform_bright, "cow": _cow, "cow_painted": _cow_painted, "tiny_plain": _tiny_plain,
             "pplastic_set": _pplastic_set, "bowl": _bowl, "cow_dark": _cow_dark}


def build_scene(name: str) -> Scene:
    """The named scene (one of SCENES); the same object every time."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; expected one of {list(SCENES)}")
    return _BUILDERS[name]()


# --------------------------------------------------------------------------- cameras


def device_intrinsics(width: int, height: int) -> np.ndarray:
    """(3, 3) K of the capture device's 25 mm lens scaled to a ``width`` x ``height`` raw mosaic."""
    f = DEVICE_FX_PX * width / DEVICE_WIDTH_PX
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def look_at_rotation(center: np.ndarray, target: np.ndarray, roll_rad: float = 0.0,
                     up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """cam_from_world rotation (3, 3) of an OpenCV camera at ``center`` looking at ``target``, image up
    towards ``up`` (world z by default), rolled by ``roll_rad`` about its optical axis."""
    forward = np.asarray(target, np.float64) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    return np.stack([c * right + s * down, -s * right + c * down, forward])


def handheld_orbit(views: int, width: int, height: int, rng: np.random.Generator,
                   distance_m: tuple[float, float] = (0.8, 1.0),
                   elevation_deg: tuple[float, float] = (-15.0, 65.0),
                   roll_deg: float = 20.0, target_jitter_m: float = 0.008,
                   distortion=None) -> list[Camera]:
    """Cameras on an irregular handheld loop around the origin.

    Azimuths advance by 360/views with jitter; elevations wander between ``elevation_deg``
    (three slow up-and-down sweeps plus noise) so that top and sides are covered; distances are
    uniform in ``distance_m``; roll is uniform in +-``roll_deg``; the aim point is jittered.
    """
    step = 360.0 / views
    azimuth = np.arange(views) * step + rng.uniform(-0.35, 0.35, views) * step + rng.uniform(0, 360)
    low, high = elevation_deg
    sweep = 0.5 + 0.5 * np.sin(2 * np.pi * 3 * np.arange(views) / views + rng.uniform(0, 2 * np.pi))
    elevation = np.clip(low + (high - low) * sweep + rng.normal(0, 6, views), low, high)
    distance = rng.uniform(*distance_m, views)
    roll = np.radians(rng.uniform(-roll_deg, roll_deg, views))
    target = rng.uniform(-target_jitter_m, target_jitter_m, (views, 3))
    intrinsics = device_intrinsics(width, height)
    cameras = []
    for k in range(views):
        center = distance[k] * _direction(azimuth[k], elevation[k])
        rotation = look_at_rotation(center, target[k], roll[k])
        cameras.append(Camera(intrinsics=intrinsics, rotation=rotation, translation=-rotation @ center,
                              width=width, height=height,
                              distortion=None if distortion is None else np.asarray(distortion, np.float64)))
    return cameras
