"""The Mitsuba 3 capture generator (sellip.capture.mitsuba_capture) against sellip's own renderer and physics:
a textured flat patch under the flash pixel by pixel (every Stokes component, two flash polarizer angles), the
AoLP of a specular highlight along the flash polarizer, the diffuse DoP on a sphere's limb against Fresnel, the
pplastic material checks, and a whole capture written by ``sellip synth --renderer mitsuba``.

Mitsuba renders in a fresh process (render_in_subprocess): its LLVM back end cannot start after open3d has built
a ray-casting scene in this test session. Skipped where mitsuba is not installed (the ``test`` extra).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from sellip.capture.mitsuba_capture import (
    PPlasticError,
    pplastic_materials,
    render_in_subprocess,
)
from sellip.capture.scenes import icosphere, look_at_rotation
from sellip.model.fresnel import diffuse_dop
from sellip.model.pbrdf import PBRDFParams
from sellip.model.render import Camera, ParamMesh, Renderer, flash_light, pixel_rays

pytestmark = pytest.mark.slow  # the whole module: `make test-fast` leaves it out

REPO = Path(__file__).resolve().parents[2]


def _params(count, eta=1.5, rho_d=(0.3, 0.2, 0.1), rho_s=1.0, sigma_s=0.2):
    rho_d = np.broadcast_to(np.asarray(rho_d, np.float64), (count, 3)).copy()
    return PBRDFParams(eta=np.full(count, eta), rho_d=rho_d, rho_s=np.full(count, rho_s),
                       sigma_s=np.full(count, sigma_s), rho_ss=np.zeros((count, 3)), sigma_ss=np.full(count, 0.5))


def _patch(size_m=0.08, cells=12) -> ParamMesh:
    """A flat square patch in the z = 0 plane (normal +z), a grid of (cells + 1)^2 vertices with an albedo ramp."""
    u = np.linspace(-size_m / 2, size_m / 2, cells + 1)
    x, y = np.meshgrid(u, u, indexing="xy")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange(x.size).reshape(cells + 1, cells + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    ramp = 0.5 + (vertices[:, 0] - vertices[:, 1]) / size_m  # 0 .. 1 across the diagonal
    rho_d = np.stack([0.1 + 0.3 * ramp, 0.25 - 0.1 * ramp, 0.15 + 0.05 * ramp], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (len(vertices), 1))
    return ParamMesh(vertices=vertices, faces=faces, normals=normals, params=_params(len(vertices), rho_d=rho_d))


def _sphere(**material) -> ParamMesh:
    d, faces = icosphere(4)
    return ParamMesh(vertices=0.04 * d, faces=faces, normals=d.copy(), params=_params(len(d), **material))


def _camera(center, width=96, height=80, focal=700.0, roll_rad=0.0) -> Camera:
    center = np.asarray(center, np.float64)
    rotation = look_at_rotation(center, np.zeros(3), roll_rad)
    k = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    return Camera(intrinsics=k, rotation=rotation, translation=-rotation @ center, width=width, height=height)


def test_flat_patch_matches_sellips_renderer_pixel_by_pixel():
    """Every Stokes component of the fully covered pixels (two pixels in from the patch's edge) of a textured glossy
    patch seen at 40° from its normal, with the flash polarizer at 0° and at 30°: Mitsuba's pplastic = sellip's
    pBRDF within 0.2 % of the brightest s0 on every pixel, 0.05 % in the median.

    Measured (Mitsuba 3.9.1, llvm_ad_mono_polarized): median 0.015 %, worst pixel 0.09 %. At 0° part of the patch
    is lit through the second triangle of the polarizer sheet; before the sheet had texture coordinates, that
    triangle polarized at 45° from the axis and those pixels were up to 2.7 % of the brightest s0 off
    (docs/synthetic.md)."""
    from scipy.ndimage import binary_dilation, binary_erosion

    mesh = _patch()
    camera = _camera([0.0, -0.32, 0.38], roll_rad=0.3)
    views = [(camera, flash_light(camera, (0.0, 0.05, 0.0), polarizer_deg=angle)) for angle in (0.0, 30.0)]
    theirs = render_in_subprocess(mesh, views, supersample=4)
    renderer = Renderer(mesh)
    for (cam, light), mitsuba in zip(views, theirs, strict=True):
        result = renderer.render(cam, light, supersample=4)
        inside = binary_erosion(result.coverage == 1, iterations=2, border_value=0)
        assert inside.sum() > 5000
        ours = result.stokes[inside][:, :3]  # (P, 3 Stokes, RGB)
        scale = ours[:, 0].max()
        difference = np.abs(mitsuba[inside][:, :3] - ours).max(axis=(1, 2)) / scale  # per pixel, worst component
        assert difference.max() < 0.002, difference.max()
        assert np.median(difference) < 0.0005
        # The polarized parts are not vanishingly small: the comparison sees the frames.
        assert np.abs(ours[:, 1:]).max() > 0.02 * scale  # 4x the tolerance: a wrong sign or axis would show
        far = ~binary_dilation(result.coverage > 0, iterations=2)
        assert np.abs(mitsuba[far]).max() < 1e-6  # background black in both


def _aolp_deg(stokes):
    return np.degrees(0.5 * np.arctan2(stokes[..., 2], stokes[..., 1])) % 180.0


@pytest.mark.parametrize("polarizer_deg", [0.0, 60.0])
def test_highlight_aolp_follows_the_flash_polarizer(polarizer_deg):
    """Near retro-reflection a specular highlight keeps the flash's linear polarization: the AoLP of the brightest
    pixel of a glossy sphere (sigma 0.05 over a dark diffuse) is the polarizer angle, in both renderers."""
    mesh = _sphere(rho_d=(0.02, 0.02, 0.02), sigma_s=0.05)
    camera = _camera([0.55, 0.3, 0.4], roll_rad=-0.2)
    light = flash_light(camera, (0.0, 0.05, 0.0), polarizer_deg=polarizer_deg)
    mitsuba = render_in_subprocess(mesh, [(camera, light)], supersample=2)[0]
    ours = Renderer(mesh).render(camera, light, supersample=2).stokes
    for image in (mitsuba, ours):
        peak = np.unravel_index(np.argmax(image[..., 0, 1]), image.shape[:2])
        error = (_aolp_deg(image[peak][:, 1]) - polarizer_deg + 90.0) % 180.0 - 90.0
        assert abs(error) < 2.0, (peak, error)
        assert np.hypot(image[peak][1, 1], image[peak][2, 1]) > 0.9 * image[peak][0, 1]  # nearly fully polarized


def test_diffuse_dop_follows_fresnel_out_to_the_limb():
    """A purely diffuse sphere (rho_s 0, eta 1.6): Mitsuba's DoP at each pixel is |T-/T+| at the pixel's exit angle
    (sellip.model.fresnel.diffuse_dop), from the centre to 75° on the limb."""
    eta = 1.6
    mesh = _sphere(eta=eta, rho_s=0.0, rho_d=(0.5, 0.4, 0.3))
    camera = _camera([0.0, -0.5, 0.2], width=120, height=100, focal=1100.0)
    light = flash_light(camera)
    mitsuba = render_in_subprocess(mesh, [(camera, light)], supersample=2)[0]
    renderer = Renderer(mesh)
    normals, coverage = renderer.interpolate(camera, mesh.normals, supersample=2)
    _, directions = pixel_rays(camera, supersample=1)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    cos_o = -np.sum(normals * directions[:, :, 0], axis=-1)
    usable = (coverage == 1) & (cos_o > np.cos(np.radians(75.0)))
    dop = np.hypot(mitsuba[..., 1, 1], mitsuba[..., 2, 1]) / np.maximum(mitsuba[..., 0, 1], 1e-12)
    expected = np.asarray(diffuse_dop(cos_o, eta))
    assert usable.sum() > 2000 and expected[usable].max() > 0.15
    assert np.abs(dop - expected)[usable].max() < 0.01
    # The diffuse AoLP lies along the normal's azimuth in the image (transmission favours p).
    limb = usable & (expected > 0.08)
    rotation = np.asarray(camera.rotation)
    n_cam = normals @ rotation.T  # OpenCV camera axes
    normal_angle = np.degrees(np.arctan2(-n_cam[..., 1], n_cam[..., 0])) % 180.0  # from image x towards image up
    error = (_aolp_deg(mitsuba[..., :, 1]) - normal_angle + 90.0) % 180.0 - 90.0
    assert np.percentile(np.abs(error[limb]), 95) < 3.0


def test_pplastic_materials_refuses_what_pplastic_cannot_render():
    mesh = _sphere()
    materials, face_material = pplastic_materials(mesh)
    assert len(materials) == 1 and np.all(face_material == 0)
    assert materials[0].alpha == pytest.approx(0.2) and materials[0].specular == pytest.approx(1 / np.pi)
    with_ss = mesh.params._replace(rho_ss=np.full((mesh.num_vertices, 3), 0.1))
    with pytest.raises(PPlasticError, match="single scattering"):
        pplastic_materials(ParamMesh(mesh.vertices, mesh.faces, mesh.normals, with_ss))
    eta = np.linspace(1.4, 1.6, mesh.num_vertices)
    with pytest.raises(PPlasticError, match="eta varies"):
        pplastic_materials(ParamMesh(mesh.vertices, mesh.faces, mesh.normals, mesh.params._replace(eta=eta),
                                     material=np.zeros(mesh.num_vertices, np.int64)))
    # Two labelled materials: each face takes the label of most of its corners.
    label = (mesh.vertices[:, 2] < 0).astype(np.int64)
    params = mesh.params._replace(eta=np.where(label == 1, 1.4, 1.6))
    materials, face_material = pplastic_materials(ParamMesh(mesh.vertices, mesh.faces, mesh.normals, params, label))
    assert [m.eta for m in materials] == [1.6, 1.4]
    corners = label[mesh.faces]
    assert np.all(face_material[corners.sum(1) == 3] == 1) and np.all(face_material[corners.sum(1) == 0] == 0)


def test_synth_with_mitsuba_writes_the_same_kind_of_capture(tmp_path):
    """``sellip synth --renderer mitsuba``: a capture folder ingest reads (raw DNG frames through the sensor model,
    poses, ground truth), whose noiseless signal is the sellip-rendered capture's within 2 %."""
    from sellip.capture.reader import read_capture, read_raw_frame

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")])}
    folders = {}
    for renderer in ("sellip", "mitsuba"):
        folders[renderer] = tmp_path / renderer
        subprocess.run([sys.executable, "-m", "sellip.cli", "synth", "--scene", "tiny_plain", "--out",
                        str(folders[renderer]), "--views", "2", "--width", "96", "--height", "80", "--seed", "1",
                        "--noise-scale", "0.001", "--renderer", renderer, "--no-progress"],
                       check=True, env=env, capture_output=True, timeout=600)
    captures = {name: read_capture(folder) for name, folder in folders.items()}
    assert "mitsuba" in captures["mitsuba"].config["synthetic"]["renderer"]
    assert (folders["mitsuba"] / "ground_truth" / "model.ply").is_file()
    assert (folders["mitsuba"] / "poses.csv").read_text() == (folders["sellip"] / "poses.csv").read_text()
    for frame in captures["sellip"].frames.itertuples():
        ours = read_raw_frame(captures["sellip"], frame.frame_id).astype(np.float64) - 64
        theirs = read_raw_frame(captures["mitsuba"], frame.frame_id).astype(np.float64) - 64
        lit = ours > 20
        assert lit.sum() > 200
        assert abs(theirs[lit].sum() / ours[lit].sum() - 1) < 0.02
