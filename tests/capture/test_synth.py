"""Synthetic captures: the CLI end to end on a tiny scene, determinism, atomic writes, scene and orbit properties."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from sellip.capture import files, reader
from sellip.capture import synthetic as capture_synthetic
from sellip.capture.scenes import (
    SPHERE_IOR_ETAS,
    build_scene,
    device_intrinsics,
    handheld_orbit,
    look_at_rotation,
)
from sellip.capture.sensor import SensorModel, simulate_raw
from sellip.model import ply
from sellip.model.render import Camera, Renderer, flash_light

TINY = dict(views=3, width=64, height=48, supersample=1, progress=False)


@pytest.fixture(scope="module")
def demo_scene():
    return build_scene("demo")


def _files(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_cli_writes_a_valid_capture_with_ground_truth(tmp_path):
    out = tmp_path / "captures" / "tiny"
    subprocess.run([sys.executable, "-m", "sellip.cli", "synth", "--scene", "tiny", "--out", str(out), "--views", "3",
                    "--width", "64", "--height", "48", "--seed", "1", "--no-progress"], check=True)
    capture = reader.read_capture(out, check_raw=True)
    assert len(capture.frames) == 9 and capture.view_ids == ["v000", "v001", "v002"]
    assert sorted(capture.frames["flash_level"].unique()) == [0.0625, 0.125, 0.25]
    assert capture.config["synthetic"]["scene"] == "tiny"
    assert capture.config["light"]["position_m"] == [0.0, 0.05, 0.0]
    assert list(capture.poses["view_id"]) == capture.view_ids
    raw = reader.read_raw_frame(capture, "v000_f0")
    assert raw.dtype == np.uint16 and raw.max() > 200 + 64  # the object is visible
    vertex, faces = ply.read_ply(out / files.GROUND_TRUTH_MESH)
    assert all(vertex[name].dtype == np.float32 for name in ply.MODEL_VERTEX_PROPERTIES)
    mesh = ply.read_param_mesh(out / files.GROUND_TRUTH_MESH)
    # The object projects where the poses say: the ground-truth centre lands inside the image.
    k = capture.intrinsics()
    rotation, translation = capture.pose("v001")
    centre = k @ (rotation @ mesh.vertices.mean(0) + translation)
    assert 0 < centre[0] / centre[2] < 64 and 0 < centre[1] / centre[2] < 48


@pytest.mark.slow
def test_same_seed_gives_byte_identical_files(tmp_path):
    a = capture_synthetic.synthesize_capture("tiny", tmp_path / "a", seed=3, **TINY)
    b = capture_synthetic.synthesize_capture("tiny", tmp_path / "b", seed=3, **TINY)
    c = capture_synthetic.synthesize_capture("tiny", tmp_path / "c", seed=4, **TINY)
    files_a, files_b, files_c = _files(a), _files(b), _files(c)
    assert files_a == files_b
    assert files_a["raw/v000_f0.dng"] != files_c["raw/v000_f0.dng"]
    assert files_a["poses.csv"] != files_c["poses.csv"]


def test_a_failed_run_leaves_no_capture(tmp_path, monkeypatch):
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 4:
            raise RuntimeError("simulated crash")
        return simulate_raw(*args, **kwargs)

    monkeypatch.setattr(capture_synthetic, "simulate_raw", failing)
    with pytest.raises(RuntimeError, match="simulated crash"):
        capture_synthetic.synthesize_capture("tiny", tmp_path / "cap", seed=0, **TINY)
    assert list(tmp_path.iterdir()) == []


def test_demo_scene_meets_the_brief(demo_scene):
    scene = demo_scene
    mesh = scene.mesh
    extent = np.ptp(mesh.vertices, axis=0)
    assert 0.10 <= extent.max() <= 0.15
    etas = {m.eta for m in scene.materials}
    assert len(scene.materials) >= 3 and all(1.3 <= eta <= 1.7 for eta in etas) and len(etas) == len(scene.materials)
    assert len({m.sigma_s for m in scene.materials}) == len(scene.materials)
    assert sum(max(m.rho_ss) > 0 for m in scene.materials) == 1
    assert set(np.unique(mesh.material)) == set(range(len(scene.materials)))
    # Concavities: some vertices lie inside the convex hull by more than 3 mm.
    import open3d as o3d

    hull, _ = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                        o3d.utility.Vector3iVector(mesh.faces)).compute_convex_hull()
    inside = o3d.t.geometry.RaycastingScene()
    inside.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(hull))
    depth = inside.compute_distance(o3d.core.Tensor(mesh.vertices.astype(np.float32))).numpy()
    assert depth.max() > 0.003
    # Texture: the plumage's albedo varies (soft patches) but is smooth between neighbouring vertices of the true
    # mesh (0.6 mm apart: 1.3 % median, demo_fine 12 %), so that the demo's 6k-vertex model can carry it.
    plumage = mesh.material == 0
    assert np.std(np.log(mesh.params.rho_d[plumage, 1])) > 0.1
    edges = mesh.faces[:, :2]
    contrast = np.abs(np.log(mesh.params.rho_d[edges[:, 0], 1] / mesh.params.rho_d[edges[:, 1], 1]))
    assert np.median(contrast) < 0.03


def test_demo_fine_keeps_the_texture_at_the_pixel():
    """demo_fine (the demo until 2026-11-25): neighbouring vertices differ in albedo (detail for SIFT, finer than
    the demo's model), and its eyes are dark."""
    mesh = build_scene("demo_fine").mesh
    edges = mesh.faces[:, :2]
    contrast = np.abs(np.log(mesh.params.rho_d[edges[:, 0], 1] / mesh.params.rho_d[edges[:, 1], 1]))
    assert np.median(contrast) > 0.06
    assert np.all(build_scene("demo_fine").materials[2].rho_d < build_scene("demo").materials[2].rho_d)


def test_the_config_schema_offers_every_scene():
    """demo.scene in config.schema.yaml lists exactly sellip.capture.scenes.SCENES (a scene missing there fails
    validation)."""
    from pathlib import Path

    import yaml

    from sellip.capture.scenes import SCENES

    schema = yaml.safe_load((Path(__file__).parents[2] / "config" / "config.schema.yaml").read_text())
    assert schema["properties"]["demo"]["properties"]["scene"]["enum"] == list(SCENES)
    for name in ("demo_fine", "tiny_speckle"):
        assert build_scene(name).name == name


def test_the_painted_cow_is_the_cow_with_a_texture_sfm_can_match():
    """cow_painted has the cow's shape (same extent, finer mesh), one material, and a texture of many colours in
    dabs a few millimetres across (hundreds of distinct albedos; neighbouring vertices mostly share one)."""
    cow, painted = build_scene("cow").mesh, build_scene("cow_painted").mesh
    assert len(painted.vertices) == 40962 and len(cow.vertices) == 10242
    np.testing.assert_allclose(np.abs(painted.vertices).max(axis=0), np.abs(cow.vertices).max(axis=0), rtol=0.01)
    albedo = np.asarray(painted.params.rho_d)
    assert len(np.unique(albedo.round(4), axis=0)) > 500 and albedo.min() >= 0.1 and albedo.max() <= 0.75
    edges = np.asarray(painted.faces)[:, :2]
    same = np.all(albedo[edges[:, 0]] == albedo[edges[:, 1]], axis=1).mean()
    assert 0.7 < same < 0.98  # sharp-edged dabs spanning several vertices
    assert set(np.asarray(painted.material).tolist()) == {0}


def test_the_dark_cow_is_the_painted_cows_shape_in_one_dark_albedo():
    """cow_dark: the painted cow's vertices and faces exactly, one material, every vertex the same dark albedo."""
    painted, dark = build_scene("cow_painted").mesh, build_scene("cow_dark").mesh
    np.testing.assert_array_equal(dark.vertices, painted.vertices)
    np.testing.assert_array_equal(dark.faces, painted.faces)
    rho_d = np.asarray(dark.params.rho_d)
    assert rho_d.shape == (len(dark.vertices), 3) and np.all(rho_d == 0.045)
    assert set(np.asarray(dark.material).tolist()) == {0} and np.allclose(np.asarray(dark.params.eta), 1.5)


def test_the_bowl_is_a_ball_with_a_hollow_its_silhouettes_never_show():
    """bowl: a 4 cm ball whose deepest point, 14 mm in, lies on the hollow's axis; the rim around the hollow is at
    full radius, so its convex hull (the most that silhouettes from every side can carve) lies 6 mm above the
    surface there (the chord across the hollow) and nowhere else; one material; no self-intersection."""
    import open3d as o3d

    from sellip.capture import BOWL_AXIS, BOWL_DEPTH_M

    mesh = build_scene("bowl").mesh
    radius = np.linalg.norm(mesh.vertices, axis=1)
    deepest = mesh.vertices[np.argmin(radius)] / radius.min()
    azimuth, elevation = np.radians(BOWL_AXIS)
    axis = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    assert abs(radius.min() - (0.04 - BOWL_DEPTH_M)) < 2e-4 and deepest @ axis > 0.999
    triangles = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                          o3d.utility.Vector3iVector(mesh.faces))
    assert triangles.is_watertight() and not triangles.is_self_intersecting()
    hull = triangles.compute_convex_hull()[0]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(hull))
    gap = np.abs(scene.compute_signed_distance(o3d.core.Tensor(mesh.vertices.astype(np.float32))).numpy())
    assert 0.005 < gap.max() < 0.007 and np.all(gap[radius > 0.0399] < 5e-4)
    assert set(np.asarray(mesh.material).tolist()) == {0}


def test_sphere_ior_has_the_table_1_indices():
    scene = build_scene("sphere_ior")
    assert sorted(np.unique(np.round(scene.mesh.params.eta, 3))) == sorted(SPHERE_IOR_ETAS)


def test_handheld_orbit_is_irregular_and_frames_the_object():
    cameras = handheld_orbit(24, 612, 512, np.random.default_rng(0))
    centres = np.array([c.center for c in cameras])
    distance = np.linalg.norm(centres, axis=1)
    assert distance.min() >= 0.8 and distance.max() <= 1.0
    elevation = np.degrees(np.arcsin(centres[:, 2] / distance))
    assert elevation.min() < 10 and elevation.max() > 45
    rolls = [np.degrees(np.arctan2(c.rotation[0, 2], -c.rotation[1, 2])) for c in cameras]  # image angle of world up
    assert np.ptp(rolls) > 10
    for camera in cameras:
        u, v = camera.project(np.zeros(3))
        assert 0.35 * 612 < u < 0.65 * 612 and 0.35 * 512 < v < 0.65 * 512


@pytest.mark.slow
def test_demo_highlights_saturate_at_the_strongest_flash_while_diffuse_stays_in_range(demo_scene):
    """Looking straight at the owl's face: the glossy eyes saturate at flash 1/4; at 1/16 the object is mid-range."""
    scene = demo_scene
    width, height = 612, 512  # the default demo size: smaller pixels average the eye highlights away
    centre = np.array([0.9, 0.0, 0.25])
    rotation = look_at_rotation(centre, np.array([0.0, 0.0, 0.02]))
    camera = Camera(device_intrinsics(width, height), rotation, -rotation @ centre, width, height)
    analyzers = Renderer(scene.mesh).render(camera, flash_light(camera), supersample=2).analyzers
    sensor = SensorModel(width=width, height=height)
    strong = simulate_raw(analyzers, sensor, scene.flash_power / 4, np.random.default_rng(0))
    weak = simulate_raw(analyzers, sensor, scene.flash_power / 16, np.random.default_rng(1))
    assert np.sum(strong >= sensor.white_level) >= 2
    on_object = analyzers[..., 2, 1] > 0
    level = np.median(weak[on_object].astype(float) - 64)
    assert 50 < level < 1000
    assert np.mean(weak[on_object] >= sensor.white_level) == 0


@pytest.mark.slow
def test_png_frames_and_lens_distortion(tmp_path):
    distortion = [-0.1, 0.02, 0.0, 0.0, 0.0]
    path = capture_synthetic.synthesize_capture("tiny", tmp_path / "cap", seed=0, raw_format="png",
                                                distortion=distortion, **{**TINY, "views": 1})
    capture = reader.read_capture(path, check_raw=True)
    assert capture.config["camera"]["distortion"] == distortion
    assert capture.frames["file"].str.endswith(".png").all()


@pytest.mark.slow
def test_a_described_device_shoots_the_capture(tmp_path):
    """--device: the frames are shot with the device's lens, flash and polarizer, and capture.yaml describes it;
    --noise-seed changes the noise alone (same orbit); a size other than the device's is refused."""
    from sellip.calibrate.synthetic import true_device

    device = true_device(96, 80, polarizer_deg=30.0)
    device["light"]["position_m"] = [0.01, 0.04, 0.0]
    device_file = tmp_path / "device.yaml"
    device_file.write_text(yaml.safe_dump({"device": device}))  # synth-calibration's truth.yaml keeps it under device
    out = tmp_path / "a"
    subprocess.run([sys.executable, "-m", "sellip.cli", "synth", "--scene", "tiny", "--out", str(out), "--views", "2",
                    "--device", str(device_file), "--no-progress"], check=True)
    capture = reader.read_capture(out, check_raw=True)
    assert capture.config["sensor"] == device["sensor"] and capture.config["light"] == device["light"]
    for key, value in device["camera"].items():
        assert np.allclose(capture.config["camera"][key], value), key
    assert np.allclose(capture.intrinsics(), [[device["camera"]["fx"], 0, device["camera"]["cx"]],
                                              [0, device["camera"]["fy"], device["camera"]["cy"]], [0, 0, 1]])
    b = capture_synthetic.synthesize_capture("tiny", tmp_path / "b", views=2, device=device, progress=False)
    noisy = capture_synthetic.synthesize_capture("tiny", tmp_path / "n", views=2, device=device, noise_seed=7,
                                                 progress=False)
    upright = capture_synthetic.synthesize_capture("tiny", tmp_path / "u", views=2, progress=False,
                                                   device={**device,
                                                           "light": {**device["light"], "polarizer_deg": 0.0}})
    files_a, files_b, files_n = _files(out), _files(b), _files(noisy)
    assert files_a["raw/v000_f0.dng"] == files_b["raw/v000_f0.dng"]  # the CLI and the library agree
    assert files_n["poses.csv"] == files_a["poses.csv"] and files_n["raw/v000_f0.dng"] != files_a["raw/v000_f0.dng"]
    # the flash polarizer turned by 30 deg moves signal between the analyzers, beyond the noise
    raw_a = reader.read_raw_frame(capture, "v000_f0").astype(float)
    raw_n = reader.read_raw_frame(reader.read_capture(noisy), "v000_f0").astype(float)
    raw_u = reader.read_raw_frame(reader.read_capture(upright), "v000_f0").astype(float)
    def by_analyzer(diff):  # signed sum per position of the 2x2 polarizer cell: noise cancels, a shift does not
        return np.abs([diff[i::2, j::2].sum() for i in range(2) for j in range(2)]).max()

    assert by_analyzer(raw_u - raw_a) > 5 * by_analyzer(raw_n - raw_a)
    with pytest.raises(ValueError, match="the device's sensor is 96x80"):
        capture_synthetic.synthesize_capture("tiny", tmp_path / "x", views=1, width=64, height=48, device=device)
