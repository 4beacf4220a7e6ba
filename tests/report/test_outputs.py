"""Outputs: the Mueller block against full_mueller, parameter maps, novel cameras, and `sellip render-outputs`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sellip.capture import ingest
from sellip.capture.files import GROUND_TRUTH_MESH
from sellip.capture.reader import read_capture
from sellip.capture.synthetic import synthesize_capture
from sellip.geometry.cameras import hdr_camera
from sellip.model.pbrdf import PBRDFParams, full_mueller
from sellip.model.ply import read_param_mesh
from sellip.model.render import Camera, Light, ParamMesh, Renderer, flash_light
from sellip.report import outputs

FLASH_CAM = (0.0, 0.05, 0.0)


# --------------------------------------------------------------------------- a tiny run (shared with test_evaluate)


def write_hdr(path: Path, view_ids: list[str], analyzers: np.ndarray, valid: np.ndarray, intrinsics: dict) -> Path:
    """An hdr.zarr store in the layout of sellip.stages.merge_hdr (analyzers (V, H, W, 4, 3), valid, attrs)."""
    import zarr

    group = zarr.open_group(str(path), mode="w")
    group.create_array("analyzers", data=analyzers.astype(np.float32), chunks=(1,) + analyzers.shape[1:])
    group.create_array("valid", data=valid, chunks=(1,) + valid.shape[1:])
    group.attrs.update({"view_id": view_ids, "intrinsics": intrinsics, "analyzer_angles_deg": [0, 45, 90, 135],
                        "channels": 3})
    return path


def make_tiny_run(root: Path, views: int = 4, raw_width: int = 192, raw_height: int = 144,
                  flash_power: float = 7.0) -> dict:
    """A synthetic 'tiny' capture and the results of a perfect reconstruction of it.

    hdr.zarr holds noise-free renders of the ground truth (times ``flash_power``) at the HDR grid of the
    capture (ingest.output_intrinsics); cameras.csv holds poses.csv; final/model.ply is the ground truth.
    """
    from sellip.geometry.cameras import write_cameras

    capture = synthesize_capture("tiny", root / "capture", views=views, width=raw_width, height=raw_height, seed=5,
                                 supersample=1, raw_format="png", progress=False)
    info = read_capture(capture)
    results = root / "results"
    results.mkdir()
    intrinsics = ingest.output_intrinsics(info.config["camera"], raw_height, raw_width)
    poses = [info.pose(v) for v in info.view_ids]
    write_cameras(results / "cameras.csv", info.view_ids, np.stack([r for r, _ in poses]),
                  np.stack([t for _, t in poses]))
    truth = read_param_mesh(capture / GROUND_TRUTH_MESH)
    renderer = Renderer(truth)
    images = []
    for rotation, translation in poses:
        camera = hdr_camera(intrinsics, rotation, translation, "hdr")
        images.append(flash_power * renderer.render(camera, flash_light(camera, FLASH_CAM), supersample=2).analyzers)
    analyzers = np.stack(images)
    write_hdr(results / "hdr.zarr", info.view_ids, analyzers, np.ones(analyzers.shape[:3], bool), intrinsics)
    (results / "final").mkdir()
    model = results / "final" / "model.ply"
    model.write_bytes((capture / GROUND_TRUTH_MESH).read_bytes())
    return {"capture": capture, "results": results, "model": model, "cameras": results / "cameras.csv",
            "hdr": results / "hdr.zarr", "view_ids": info.view_ids, "truth": truth, "intrinsics": intrinsics}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return make_tiny_run(tmp_path_factory.mktemp("tiny_run"))


# --------------------------------------------------------------------------- physics


def _params(count, **values) -> PBRDFParams:
    defaults = {"eta": 1.6, "rho_d": (0.5, 0.3, 0.2), "rho_s": 0.8, "sigma_s": 0.25, "rho_ss": (0.1, 0.05, 0.02),
                "sigma_ss": 0.5}
    defaults.update(values)
    full = {k: np.broadcast_to(np.asarray(v, np.float64), (count,) + np.shape(v)).copy() for k, v in defaults.items()}
    return PBRDFParams(**full)


def _tilted_plane():
    """A 0.8 m square at z = 1 (filling the view) tilted about the y axis (normal (sin 25°, 0, -cos 25°)), camera at
    the origin."""
    tilt = np.radians(25.0)
    normal = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    u = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    v = np.array([0.0, 1.0, 0.0])
    corners = np.array([[0, 0, 1.0] + 0.4 * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    mesh = ParamMesh(corners, faces, np.tile(normal, (4, 1)), _params(4))
    camera = Camera(np.array([[120.0, 0, 32], [0, 120.0, 24], [0, 0, 1]]), np.eye(3), np.zeros(3), 64, 48)
    return mesh, camera, normal


@pytest.mark.slow
def test_mueller_block_of_the_renderer_matches_full_mueller_at_each_pixel():
    """Three renders with incident Stokes basis states give the pBRDF's 3x3 Mueller block, pixel by pixel."""
    mesh, camera, normal = _tilted_plane()
    light = flash_light(camera, FLASH_CAM, polarizer_deg=30.0, intensity=2.0)
    block = outputs.mueller_image(Renderer(mesh), camera, light, supersample=1)
    v, u = np.mgrid[4:44:5, 4:60:6]
    rays = np.stack([(u - 32) / 120.0, (v - 24) / 120.0, np.ones_like(u, dtype=np.float64)], -1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    t = (np.array([0, 0, 1.0]) @ normal) / (rays @ normal)  # exact ray-plane hits
    points = t[:, None] * rays
    to_light = light.position - points
    distance = np.linalg.norm(to_light, axis=-1)
    expected = 2.0 * np.asarray(full_mueller(
        np.tile(normal, (len(points), 1)), to_light / distance[:, None], -rays, distance,
        np.tile(light.axis, (len(points), 1)), np.tile(camera.up, (len(points), 1)), _params(len(points))))
    rendered = block[v.ravel(), u.ravel()]  # (N, 3, 3, 3)
    assert np.abs(expected[..., :3, :3]).max() > 0
    np.testing.assert_allclose(rendered, expected[..., :3, :3], rtol=2e-3, atol=2e-6 * np.abs(expected).max())
    # The flash's own state [1, 1, 0, 0] through the block is what the plain render gives.
    plain = Renderer(mesh).render(camera, light, supersample=1).stokes[..., :3, :]
    np.testing.assert_allclose(block[..., 0] + block[..., 1], np.moveaxis(plain, -1, -2), rtol=1e-4, atol=1e-9)


def test_parameter_maps_interpolate_vertex_values_and_rotate_normals_into_the_camera_frame():
    mesh, camera, normal = _tilted_plane()
    eta = 1.3 + mesh.vertices[:, 0]  # linear in x: barycentric interpolation is exact
    mesh = ParamMesh(mesh.vertices, mesh.faces, mesh.normals, mesh.params._replace(eta=eta))
    maps, coverage = outputs.parameter_maps(Renderer(mesh), camera)
    assert coverage.min() == 1
    v, u = np.mgrid[2:46:6, 2:62:6]
    ray = np.stack([(u - 32) / 120.0, (v - 24) / 120.0, np.ones(u.shape)], -1)
    x_hit = ray[..., 0] * (np.array([0, 0, 1.0]) @ normal) / (ray @ normal)
    np.testing.assert_allclose(maps["eta"][v, u, 0], 1.3 + x_hit, atol=1e-5)
    # Camera frame of the maps: x right, y up, z towards the camera (OpenCV camera = world here).
    np.testing.assert_allclose(maps["normal"][10, 10], normal * [1, -1, -1], atol=1e-6)
    assert set(maps) == set(outputs.MAP_SPECS)


def test_unpolarized_light_on_a_diffuse_patch_gives_the_fresnel_dop_and_p_polarized_aolp():
    """Diffuse only, incident [1, 0, 0, 0]: DoP = |T-/T+|(theta_o, eta), AoLP along the normal's image azimuth."""
    mesh, camera, normal = _tilted_plane()
    mesh = ParamMesh(mesh.vertices, mesh.faces, mesh.normals, _params(4, rho_s=0.0, rho_ss=(0.0, 0.0, 0.0)))
    light = flash_light(camera, FLASH_CAM)
    stokes = Renderer(mesh).render(camera, Light(light.position, light.axis, stokes=(1.0, 0.0, 0.0, 0.0)),
                                   supersample=1).stokes
    dop, aolp = outputs.polarization_images(stokes)
    u = np.arange(4, 60, 5)
    rays = np.stack([(u - 32) / 120.0, np.zeros(u.shape), np.ones(u.shape)], -1)  # image row 24: y = 0
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos_o = -rays @ normal
    sin2 = 1 - cos_o ** 2
    cos_t = np.sqrt(1 - sin2 / 1.6 ** 2)
    r_s = ((cos_o - 1.6 * cos_t) / (cos_o + 1.6 * cos_t)) ** 2
    r_p = ((1.6 * cos_o - cos_t) / (1.6 * cos_o + cos_t)) ** 2
    np.testing.assert_allclose(dop[24, u], (r_s - r_p) / (2 - r_s - r_p), rtol=2e-3)
    # The normal leans towards image +x: p-polarized exit means AoLP 0 (mod 180 deg) on this row.
    assert np.degrees(np.abs(np.angle(np.exp(2j * aolp[24, u])) / 2)).max() < 0.05


def test_novel_camera_is_between_two_captured_views_and_looks_at_the_target():
    rng = np.random.default_rng(0)
    from sellip.capture.scenes import handheld_orbit

    cameras = handheld_orbit(12, 64, 48, rng)
    novel = outputs.novel_camera(cameras, np.zeros(3), reference=3, elevate_deg=10.0)
    centers = np.stack([c.center for c in cameras])
    assert np.min(np.linalg.norm(centers - novel.center, axis=1)) > 0.02  # not a captured position
    np.testing.assert_allclose(novel.project(np.zeros(3)), [32, 24], atol=1e-9)
    np.testing.assert_allclose(novel.rotation @ novel.rotation.T, np.eye(3), atol=1e-12)
    up = np.mean([c.up for c in cameras], axis=0)
    assert novel.up @ up > 0.9 * np.linalg.norm(up)


def test_fit_scale_recovers_a_global_factor():
    rng = np.random.default_rng(1)
    estimate = rng.random((5, 6, 4, 3))
    mask = rng.random((5, 6)) > 0.3
    assert outputs.fit_scale(3.5 * estimate, estimate, mask) == pytest.approx(3.5)


# --------------------------------------------------------------------------- the stage


@pytest.mark.slow
def test_render_outputs_cli_writes_the_documented_files(tiny_run, tmp_path):
    out = tmp_path / "renders"
    views = tiny_run["view_ids"][1:3]
    subprocess.run([sys.executable, "-m", "sellip.cli", "render-outputs", "--model", str(tiny_run["model"]),
                    "--cameras", str(tiny_run["cameras"]), "--hdr", str(tiny_run["hdr"]),
                    "--capture", str(tiny_run["capture"]), "--output", str(out),
                    "--settings", json.dumps({"render_views": views, "supersample": 1})], check=True)
    index = json.loads((out / "index.json").read_text())
    expected = {f"view_{v}.png" for v in views} | {f"view_{v}_measured.png" for v in views} | {
        "novel_view.png", "new_light.png", "mueller.png", "mueller.npz", "aolp.png", "dop.png", "maps.png"} | {
        f"map_{name}.png" for name in outputs.MAP_SPECS}
    assert {f["file"] for f in index["files"]} == expected
    assert {p.name for p in out.iterdir()} == expected | {"index.json"}
    assert index["reference_view"] == views[0]
    import imageio.v3 as iio

    render = iio.imread(out / f"view_{views[0]}.png")
    measured = iio.imread(out / f"view_{views[0]}_measured.png")
    h, w = tiny_run["intrinsics"]["height"], tiny_run["intrinsics"]["width"]
    assert render.shape == (h, w, 3) and render.max() > 200
    # The measured view is the ground truth's render: after the global scale it matches the model's render.
    assert np.abs(render.astype(int) - measured.astype(int)).mean() < 3
    mueller = np.load(out / "mueller.npz")["mueller"]
    assert mueller.shape == (h, w, 3, 3, 3) and np.abs(mueller).max() > 0
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


@pytest.mark.slow
def test_render_outputs_names_a_missing_model(tiny_run, tmp_path):
    missing = tmp_path / "nothing.ply"
    run = subprocess.run([sys.executable, "-m", "sellip.cli", "render-outputs", "--model", str(missing),
                          "--cameras", str(tiny_run["cameras"]), "--hdr", str(tiny_run["hdr"]),
                          "--capture", str(tiny_run["capture"]), "--output", str(tmp_path / "r")],
                         check=False, capture_output=True, text=True)
    assert run.returncode == 1 and str(missing) in run.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_render_outputs_skips_views_without_a_pose_and_defaults_when_none_is_given(tiny_run, tmp_path):
    from sellip.report import outputs as report_outputs

    index = report_outputs.render_outputs(tiny_run["model"], tiny_run["cameras"], tiny_run["hdr"], tiny_run["capture"],
                                     tmp_path / "r", views=["v999", tiny_run["view_ids"][2]], supersample=1)
    assert index["views"] == [tiny_run["view_ids"][2]]
    assert report_outputs.default_views(list("abcdefg"), 3) == ["a", "d", "g"]
