"""Observation store: visibility, HDR samples and geometry per vertex and view (sellip.fit.observe, sellip observe).

The scene: a 4 cm sphere with a small sphere in front of it (it hides part of the big one from the
first camera and, with the flash 10 cm to the side, shadows another part), rendered with the real
renderer at the HDR resolution; ground truth for visibility from exact sphere geometry.
"""

from __future__ import annotations

import logging

import jax.numpy as jnp
import numpy as np
import pytest

from sellip.capture.scenes import icosphere, look_at_rotation
from sellip.capture.sensor import SensorModel
from sellip.capture.writer import CaptureWriter
from sellip.fit.observe import (
    ObserveError,
    ObserveMesh,
    Observer,
    ObserveSettings,
    bilinear_sample,
    load_observations,
    read_mesh,
    relative_slope,
    silhouette_distance,
)
from sellip.fit.observe_mesh import observe_mesh as run_stage
from sellip.fit.observe_mesh import pair_views
from sellip.geometry.cameras import hdr_camera, read_cameras, write_cameras
from sellip.model.conventions import observations_from_analyzers, stokes_to_analyzers
from sellip.model.pbrdf import PBRDFParams, full_stokes
from sellip.model.ply import write_ply
from sellip.model.render import Camera, ParamMesh, Renderer, flash_light

WIDTH, HEIGHT, FOCAL = 200, 160, 900.0
RADIUS = 0.04
OCCLUDER_RADIUS, OCCLUDER_CENTER = 0.012, np.array([0.0, -0.1, 0.0])
FLASH_CAM = np.array([0.1, 0.0, 0.0])  # 10 cm right of the lens: the occluder's shadow falls beside what it hides
CAMERA_CENTERS = (np.array([0.0, -0.5, 0.0]), np.array([0.5, 0.0, 0.0]), np.array([-0.3, -0.25, 0.3]))
CAMERA_TARGETS = (np.zeros(3), np.array([0.0, 0.06, 0.0]), np.zeros(3))  # view 1: the sphere leaves the image
CAMERA_ROLLS = (0.0, 0.2, -0.4)
INVALID_BLOCK = (slice(60, 80), slice(90, 110))  # rows, columns of invalid pixels in view 2
MARGIN_M = 1.5e-3


def _params(count: int) -> PBRDFParams:
    def full(value, channels=None):
        return np.broadcast_to(np.asarray(value, np.float64), (count,) if channels is None else (count, channels))

    return PBRDFParams(eta=full(1.5), rho_d=full((0.5, 0.35, 0.2), 3), rho_s=full(0.6), sigma_s=full(0.3),
                       rho_ss=full((0.0, 0.0, 0.0), 3), sigma_ss=full(0.6))


def _scene_mesh() -> tuple[ParamMesh, int]:
    """Big sphere (its vertices first) + occluder sphere; returns the mesh and the big sphere's vertex count."""
    big, big_faces = icosphere(5)
    small, small_faces = icosphere(3)
    vertices = np.concatenate([RADIUS * big, OCCLUDER_CENTER + OCCLUDER_RADIUS * small])
    faces = np.concatenate([big_faces, small_faces + len(big)])
    normals = np.concatenate([big, small])
    return ParamMesh(vertices=vertices, faces=faces, normals=normals, params=_params(len(vertices))), len(big)


def _cameras() -> list[Camera]:
    k = np.array([[FOCAL, 0.0, (WIDTH - 1) / 2], [0.0, FOCAL, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])
    cameras = []
    for center, target, roll in zip(CAMERA_CENTERS, CAMERA_TARGETS, CAMERA_ROLLS):
        rotation = look_at_rotation(center, target, roll)
        cameras.append(Camera(k, rotation, -rotation @ center, WIDTH, HEIGHT))
    return cameras


@pytest.fixture(scope="module")
def rendered():
    """mesh, big-sphere vertex count, cameras, flash positions (world), analyzers (V, H, W, 4, 3), valid (V, H, W)."""
    mesh, n_big = _scene_mesh()
    cameras = _cameras()
    renderer = Renderer(mesh)
    lights = [flash_light(camera, FLASH_CAM) for camera in cameras]
    analyzers = np.stack([renderer.render(c, light, supersample=2).analyzers for c, light in zip(cameras, lights)])
    valid = np.ones(analyzers.shape[:3], bool)
    valid[(2,) + INVALID_BLOCK] = False
    return dict(mesh=mesh, n_big=n_big, cameras=cameras, lights=lights, analyzers=analyzers, valid=valid)


@pytest.fixture(scope="module")
def observed(rendered):
    """ViewObservations of every view, from the in-memory mesh."""
    mesh = rendered["mesh"]
    # edge_margin 0: every sample (the edge margin's own test compares with these)
    observer = Observer(ObserveMesh(mesh.vertices, mesh.normals, mesh.faces),
                        ObserveSettings(threads=2, edge_margin=0.0))
    return [observer.observe(camera, light.position, rendered["analyzers"][k], rendered["valid"][k])
            for k, (camera, light) in enumerate(zip(rendered["cameras"], rendered["lights"]))]


def _segment_distance(starts, ends, point):
    """Distance (n,) from ``point`` (3,) to the segments starts (n, 3) -> ends (n, 3)."""
    d = ends - starts
    t = np.clip(np.einsum("nc,nc->n", point - starts, d) / np.einsum("nc,nc->n", d, d), 0, 1)
    return np.linalg.norm(starts + t[:, None] * d - point, axis=-1)


def _truth(rendered, k):
    """Exact per-vertex facts of the big sphere in view k: dict of (n_big,) arrays."""
    n = rendered["n_big"]
    points = rendered["mesh"].vertices[:n]
    normals = points / RADIUS
    camera, flash = rendered["cameras"][k], rendered["lights"][k].position
    to_camera = camera.center - points
    to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
    to_flash = flash - points
    to_flash /= np.linalg.norm(to_flash, axis=-1, keepdims=True)
    pixels = camera.project(points)
    hidden = _segment_distance(np.broadcast_to(camera.center, points.shape), points, OCCLUDER_CENTER) - OCCLUDER_RADIUS
    shadow = _segment_distance(points, np.broadcast_to(flash, points.shape), OCCLUDER_CENTER) - OCCLUDER_RADIUS
    return dict(cos_view=np.einsum("nc,nc->n", normals, to_camera), cos_light=np.einsum("nc,nc->n", normals, to_flash),
                pixels=pixels, hidden=hidden, shadow=shadow,
                inside=(pixels[:, 0] > 1) & (pixels[:, 0] < WIDTH - 2) & (pixels[:, 1] > 1)
                & (pixels[:, 1] < HEIGHT - 2),
                outside=(pixels[:, 0] < -1) | (pixels[:, 0] > WIDTH) | (pixels[:, 1] < -1) | (pixels[:, 1] > HEIGHT))


def _touches_invalid_block(truth, k):
    """(n,) bool: the bilinear footprint of the vertex includes an invalid pixel (view 2 only)."""
    if k != 2:
        return np.zeros(len(truth["pixels"]), bool)
    rows, cols = INVALID_BLOCK
    u, v = truth["pixels"][:, 0], truth["pixels"][:, 1]
    return (u > cols.start - 1) & (u < cols.stop) & (v > rows.start - 1) & (v < rows.stop)


def _clearly_visible(truth):
    return (truth["inside"] & (truth["cos_view"] > 0.2) & (truth["cos_light"] > 0.2) & (truth["hidden"] > MARGIN_M)
            & (truth["shadow"] > MARGIN_M))


# --------------------------------------------------------------------------- kernels


def test_bilinear_sample_is_exact_for_affine_images_and_needs_four_valid_neighbours():
    rows, cols = np.mgrid[0:12, 0:16].astype(np.float32)
    image = np.stack([1 + 0.5 * cols + 0.25 * rows, 3 - 0.1 * cols + rows], axis=-1)  # (H, W, 2)
    valid = np.ones((12, 16), bool)
    valid[5, 7] = False
    pixels = np.array([[0.0, 0.0], [15.0, 11.0], [3.3, 8.6], [6.5, 4.5], [7.9, 5.9], [8.0, 6.0], [-0.01, 3.0],
                       [15.01, 3.0], [2.0, 11.5], [np.nan, 1.0]])
    values, ok = bilinear_sample(image, valid, pixels)
    assert ok.tolist() == [True, True, True, False, False, True, False, False, False, False]
    expected = np.stack([1 + 0.5 * pixels[:, 0] + 0.25 * pixels[:, 1], 3 - 0.1 * pixels[:, 0] + pixels[:, 1]], -1)
    np.testing.assert_allclose(values[ok], expected[ok], rtol=1e-6)
    assert np.all(values[~ok] == 0)
    # Without a mask only the image bounds count.
    assert bilinear_sample(image, None, pixels)[1].tolist() == [True] * 6 + [False] * 4


def test_samples_at_visible_vertices_agree_with_the_model(rendered, observed):
    """I_d, I_alpha, I_s at clearly visible vertices = full pBRDF at the vertex, within interpolation error."""
    mesh = rendered["mesh"]
    columns = {name: [] for name in ("vertex", "to_light", "to_camera", "distance", "light_axis", "camera_up",
                                     "diffuse", "diffuse_pol", "specular")}
    for k, view in enumerate(observed):
        truth = _truth(rendered, k)
        visible = _clearly_visible(truth) & ~_touches_invalid_block(truth, k)
        assert view.usable[: len(visible)][visible].all()
        # Away from the limb (steep foreshortening: interpolation error grows to ~3% at cos 0.2) and from
        # the occluder's and its shadow's edges.
        chosen = np.flatnonzero(visible & (truth["cos_view"] > 0.4) & (truth["hidden"] > 3 * MARGIN_M)
                                & (truth["shadow"] > 3 * MARGIN_M))
        camera, light = rendered["cameras"][k], rendered["lights"][k]
        points = mesh.vertices[chosen]
        expected = (camera.center - points) / np.linalg.norm(camera.center - points, axis=-1, keepdims=True)
        np.testing.assert_allclose(view.to_camera[chosen], expected, atol=1e-6)
        np.testing.assert_allclose(view.light_distance[chosen], np.linalg.norm(light.position - points, axis=-1),
                                   rtol=1e-6)
        for name, value in (("vertex", chosen), ("to_light", view.to_light[chosen]),
                            ("to_camera", view.to_camera[chosen]), ("distance", view.light_distance[chosen]),
                            ("light_axis", np.broadcast_to(light.axis, (len(chosen), 3))),
                            ("camera_up", np.broadcast_to(camera.up, (len(chosen), 3))),
                            *((name, getattr(view, name)[chosen]) for name in ("diffuse", "diffuse_pol", "specular"))):
            columns[name].append(value)
    c = {name: np.concatenate(values) for name, values in columns.items()}
    assert len(c["vertex"]) > 0.25 * rendered["n_big"]
    params = PBRDFParams(*[jnp.asarray(np.asarray(p)[c["vertex"]]) for p in mesh.params])
    as_f64 = lambda x: jnp.asarray(x, jnp.float64)
    stokes = full_stokes(as_f64(mesh.normals[c["vertex"]]), as_f64(c["to_light"]), as_f64(c["to_camera"]),
                         as_f64(c["distance"]), as_f64(c["light_axis"]), as_f64(c["camera_up"]), params)
    model = observations_from_analyzers(np.asarray(stokes_to_analyzers(stokes, axis=-2)))
    level = model[0].mean(axis=-1, keepdims=True)  # each vertex's diffuse level
    for name, predicted in zip(("diffuse", "diffuse_pol", "specular"), model):
        error = np.abs(c[name] - predicted) / level
        assert np.median(error) < 0.002, (name, np.median(error))
        assert error.max() < 0.01, (name, error.max())


def test_occluded_vertices_are_not_usable(rendered, observed):
    truth = _truth(rendered, 0)
    view = observed[0]
    hidden = truth["inside"] & (truth["cos_view"] > 0.2) & (truth["hidden"] < -MARGIN_M)
    assert hidden.sum() > 100
    assert not view.usable[: rendered["n_big"]][hidden].any()
    assert not view.visibility.unoccluded[: rendered["n_big"]][hidden].any()
    assert view.visibility.valid_pixels[: rendered["n_big"]][hidden].all()  # they fail at the occlusion test
    assert view.usable[: rendered["n_big"]][_clearly_visible(truth)].all()
    # The far side of the sphere: not front-facing, never usable.
    back = truth["cos_view"] < -0.05
    assert back.sum() > 1000 and not view.visibility.front_facing[: rendered["n_big"]][back].any()


def test_flash_shadowed_vertices_are_not_usable(rendered, observed):
    truth = _truth(rendered, 0)
    view = observed[0]
    shadowed = (truth["inside"] & (truth["cos_view"] > 0.2) & (truth["cos_light"] > 0.2)
                & (truth["hidden"] > MARGIN_M) & (truth["shadow"] < -MARGIN_M))
    assert shadowed.sum() > 30
    n = rendered["n_big"]
    assert view.visibility.unoccluded[:n][shadowed].all()
    assert not view.usable[:n][shadowed].any()
    # The rendered image agrees: those vertices are dark in I_d (shadowed pixels are black).
    image_id = observations_from_analyzers(rendered["analyzers"][0])[0].mean(-1)
    pixels = np.rint(truth["pixels"][shadowed]).astype(int)
    assert np.all(image_id[pixels[:, 1], pixels[:, 0]] < 0.05 * image_id.max())


def test_out_of_image_and_invalid_pixel_vertices_are_not_usable(rendered, observed):
    n = rendered["n_big"]
    truth = _truth(rendered, 1)
    outside = truth["outside"] & (truth["cos_view"] > 0.2)
    assert outside.sum() > 300 and (truth["inside"] & (truth["cos_view"] > 0.2)).sum() > 300
    assert not observed[1].usable[:n][outside].any()
    assert observed[1].usable[:n][_clearly_visible(truth)].all()
    # View 2: vertices whose bilinear footprint touches the invalid block.
    truth = _truth(rendered, 2)
    touching = _touches_invalid_block(truth, 2)
    assert (touching & _clearly_visible(truth)).sum() > 10
    assert not observed[2].usable[:n][touching].any()
    assert observed[2].usable[:n][_clearly_visible(truth) & ~touching].all()
    assert np.all(observed[2].diffuse[:n][touching] == 0)


def test_mono_images_give_the_same_observation_in_every_channel(rendered, observed):
    mesh = rendered["mesh"]
    observer = Observer(ObserveMesh(mesh.vertices, mesh.normals, mesh.faces), ObserveSettings(edge_margin=0.0))
    mono = rendered["analyzers"][0][..., 1:2]  # the green channel as a mono camera
    view = observer.observe(rendered["cameras"][0], rendered["lights"][0].position, mono, rendered["valid"][0])
    np.testing.assert_array_equal(view.usable, observed[0].usable)
    for name in ("diffuse", "diffuse_pol", "specular"):
        values = getattr(view, name)
        np.testing.assert_array_equal(values, np.repeat(values[:, 1:2], 3, axis=1))
        np.testing.assert_allclose(values[:, 1], getattr(observed[0], name)[:, 1], rtol=1e-6, atol=1e-9)


# --------------------------------------------------------------------------- the stage and the store


def _write_inputs(folder, rendered, camera_views=None, normals=True):
    """Stage inputs in their documented formats: mesh.ply, cameras.csv, hdr.zarr, capture/. Returns paths."""
    import zarr

    mesh = rendered["mesh"]
    view_ids = [f"v{k:03d}" for k in range(len(rendered["cameras"]))]
    vertex = {name: mesh.vertices[:, k].astype(np.float32) for k, name in enumerate("xyz")}
    if normals:
        vertex.update({name: mesh.normals[:, k].astype(np.float32) for k, name in enumerate(("nx", "ny", "nz"))})
    write_ply(folder / "mesh.ply", vertex, mesh.faces)

    camera_views = range(len(view_ids)) if camera_views is None else camera_views
    cameras = rendered["cameras"]
    write_cameras(folder / "cameras.csv", [f"v{k:03d}" for k in camera_views],
                  np.stack([cameras[k].rotation for k in camera_views]),
                  np.stack([cameras[k].translation for k in camera_views]))

    analyzers = rendered["analyzers"].astype(np.float32)
    group = zarr.open_group(str(folder / "hdr.zarr"), mode="w")
    group.create_array("analyzers", shape=analyzers.shape, chunks=(1,) + analyzers.shape[1:],
                       dtype="float32")[...] = analyzers
    group.create_array("valid", shape=rendered["valid"].shape, chunks=(1,) + rendered["valid"].shape[1:],
                       dtype="bool")[...] = rendered["valid"]
    k = cameras[0].intrinsics
    group.attrs.update({"view_id": view_ids, "intrinsics": {
        "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "width": WIDTH, "height": HEIGHT,
        "distortion": [0.0] * 5}, "analyzer_angles_deg": [0, 45, 90, 135], "channels": 3})

    sensor = SensorModel(width=8, height=8)
    config = {"sensor": sensor.capture_sensor(), "camera": {"fx": 2 * FOCAL, "fy": 2 * FOCAL, "cx": 4.0, "cy": 4.0},
              "light": {"position_m": FLASH_CAM.tolist(), "polarizer_deg": 0}, "scene": {"distance_m": 0.5}}
    with CaptureWriter(folder / "capture", config, raw_format="png") as writer:
        for view in view_ids:
            writer.add_frame(f"{view}_f0", view, np.full((8, 8), 100, np.uint16), flash_level=0.25, exposure_s=0.005)
        writer.finish()
    return dict(mesh=folder / "mesh.ply", cameras=folder / "cameras.csv", hdr=folder / "hdr.zarr",
                capture=folder / "capture")


def test_store_round_trip_equals_in_memory_observations(tmp_path, rendered):
    paths = _write_inputs(tmp_path, rendered)
    settings = ObserveSettings(vertex_chunk=1000, view_chunk=2, edge_margin=0.0, threads=2)
    output = tmp_path / "iter" / "0" / "observations.zarr"
    summary = run_stage(paths["mesh"], paths["cameras"], paths["hdr"], paths["capture"], output, settings)
    assert summary["views"] == 3 and summary["vertices"] == rendered["mesh"].num_vertices
    assert not list(output.parent.glob(".*tmp*"))

    # The same views in memory, from the same files.
    mesh = read_mesh(paths["mesh"])
    view_ids, rotations, translations = read_cameras(paths["cameras"])
    observer = Observer(mesh, settings)
    intrinsics = {"fx": FOCAL, "fy": FOCAL, "cx": (WIDTH - 1) / 2, "cy": (HEIGHT - 1) / 2, "width": WIDTH,
                  "height": HEIGHT}
    views = []
    for k in range(3):
        camera = hdr_camera(intrinsics, rotations[k], translations[k], paths["hdr"])
        flash = flash_light(camera, FLASH_CAM).position
        views.append(observer.observe(camera, flash, rendered["analyzers"][k].astype(np.float32),
                                      rendered["valid"][k]))

    start, stop = 2500, 7300
    rows = load_observations(output, start, stop)
    obs = rows.observations
    for name in ("diffuse", "diffuse_pol", "specular", "to_light", "to_camera", "light_distance", "usable"):
        expected = np.stack([getattr(v, name)[start:stop] for v in views], axis=1)
        np.testing.assert_array_equal(np.asarray(getattr(obs, name)), expected, err_msg=name)
    ups = np.stack([hdr_camera(intrinsics, r, t, paths["hdr"]).up for r, t in zip(rotations, translations)])
    np.testing.assert_allclose(obs.camera_up, np.broadcast_to(ups[None], (stop - start, 3, 3)), atol=1e-7)
    axes = np.stack([flash_light(hdr_camera(intrinsics, r, t, paths["hdr"]), FLASH_CAM).axis
                     for r, t in zip(rotations, translations)])
    np.testing.assert_allclose(obs.light_axis, np.broadcast_to(axes[None], (stop - start, 3, 3)), atol=1e-7)
    np.testing.assert_array_equal(rows.vertices, mesh.vertices[start:stop].astype(np.float32))
    np.testing.assert_allclose(rows.normals, mesh.normals[start:stop], atol=1e-6)
    assert obs.usable.dtype == bool and obs.diffuse.shape == (stop - start, 3, 3)

    import zarr

    group = zarr.open_group(str(output), mode="r")
    assert group.attrs["view_ids"] == ["v000", "v001", "v002"]
    assert group.attrs["num_vertices"] == mesh.num_vertices and group.attrs["num_views"] == 3
    assert group["diffuse"].chunks == (1000, 2, 3) and group["usable"].chunks == (1000, 2)
    whole = load_observations(output)
    assert whole.observations.usable.shape == (mesh.num_vertices, 3)
    np.testing.assert_array_equal(whole.observations.usable, np.stack([v.usable for v in views], axis=1))
    with pytest.raises(ObserveError, match="observations.zarr"):
        load_observations(output, 0, mesh.num_vertices + 1)


def test_cameras_missing_a_view_of_the_hdr_store(tmp_path, rendered):
    paths = _write_inputs(tmp_path, rendered, camera_views=[0, 2])
    output = tmp_path / "observations.zarr"
    with pytest.raises(ObserveError, match=r"cameras\.csv.*no pose for 1 view.*v001"):
        run_stage(paths["mesh"], paths["cameras"], paths["hdr"], paths["capture"], output,
                  ObserveSettings(missing_poses="error"))
    assert not output.exists()
    run_stage(paths["mesh"], paths["cameras"], paths["hdr"], paths["capture"], output,
              ObserveSettings(missing_poses="skip"))
    import zarr

    assert zarr.open_group(str(output), mode="r").attrs["view_ids"] == ["v000", "v002"]


def test_held_out_views_are_left_out_of_the_store(tmp_path, rendered):
    import zarr

    paths = _write_inputs(tmp_path, rendered)
    output = tmp_path / "observations.zarr"
    run_stage(paths["mesh"], paths["cameras"], paths["hdr"], paths["capture"], output, exclude_views=("v001",))
    assert zarr.open_group(str(output), mode="r").attrs["view_ids"] == ["v000", "v002"]
    with pytest.raises(ObserveError, match=r"hdr\.zarr.*v009"):
        run_stage(paths["mesh"], paths["cameras"], paths["hdr"], paths["capture"], tmp_path / "o2.zarr",
                  exclude_views=("v009",))


def test_bad_inputs_raise_errors_naming_the_file(tmp_path, rendered, caplog):
    from sellip.cli import main

    paths = _write_inputs(tmp_path, rendered, normals=False)
    output = tmp_path / "observations.zarr"
    with pytest.raises(ObserveError, match=r"mesh\.ply: the mesh has no vertex normals"):
        run_stage(paths["mesh"], paths["cameras"], paths["hdr"], paths["capture"], output)
    argv = ["observe", "--mesh", str(paths["mesh"]), "--cameras", str(paths["cameras"]), "--hdr", str(paths["hdr"]),
            "--capture", str(paths["capture"]), "--output", str(output)]
    with caplog.at_level(logging.ERROR):
        assert main(argv) == 1
    assert "mesh.ply: the mesh has no vertex normals" in caplog.text and not output.exists()
    # A cameras.csv view that hdr.zarr does not have.
    with pytest.raises(ObserveError, match=r"cameras\.csv: view\(s\) \['v009'\] are not in .*hdr\.zarr"):
        pair_views(["v000", "v001"], ["v000", "v009"], paths["hdr"], paths["cameras"], "skip")
    with pytest.raises(ObserveError, match="not an observation store"):
        load_observations(tmp_path / "nowhere.zarr")


def test_edge_margin_drops_samples_near_the_silhouette(rendered, observed):
    """With ``edge_margin`` a sample must lie that many pixels inside the object's silhouette in the image:
    the ones nearer (grazing views of the sphere's rim, whose bilinear and demosaicing kernels reach the
    background) are dropped, every other usable sample stays, and its values are unchanged."""
    mesh = rendered["mesh"]
    observer = Observer(ObserveMesh(mesh.vertices, mesh.normals, mesh.faces),
                        ObserveSettings(threads=2, edge_margin=3.0))
    dropped_total = 0
    for k, (camera, light) in enumerate(zip(rendered["cameras"], rendered["lights"])):
        view = observer.observe(camera, light.position, rendered["analyzers"][k], rendered["valid"][k])
        plain = observed[k]
        assert not np.any(view.usable & ~plain.usable)
        np.testing.assert_array_equal(view.diffuse[view.usable], plain.diffuse[view.usable])
        distance = silhouette_distance(rendered["analyzers"][k], rendered["valid"][k])
        pixels = np.rint(camera.project(mesh.vertices)).astype(int)
        inside = np.zeros(len(pixels), bool)
        ok = plain.usable
        inside[ok] = distance[pixels[ok, 1], pixels[ok, 0]] >= 3.0
        np.testing.assert_array_equal(view.usable, plain.usable & inside)
        dropped = plain.usable & ~view.usable
        # What is dropped is mostly the rim (grazing views at the sphere's silhouette); the rest borders
        # the occluder's cast shadow, a dark hole in the silhouette where the kernels mix lit and unlit.
        n = rendered["n_big"]
        truth = _truth(rendered, k)
        rim_or_shadow = (truth["cos_view"] < 0.5) | (truth["shadow"] < 0.01)
        assert np.mean(rim_or_shadow[:n][dropped[:n]]) > 0.95
        dropped_total += int(dropped.sum())
    assert dropped_total > 50


def test_relative_slope_is_the_log_intensity_gradient():
    """|grad S0| / S0 by central differences: sinh(a) on an exponential ramp exp(a x) (a for small a), in
    either direction, the same in every colour and analyzer mix; inf where S0 is 0, NaN beside a NaN."""
    a = 0.3
    x = np.arange(12, dtype=np.float64)
    ramp = np.exp(a * x)[None, :, None, None] * np.array([1.0, 0.8, 0.6, 0.8])[:, None] * np.ones((9, 1, 4, 3))
    slope = relative_slope(ramp.astype(np.float32))
    np.testing.assert_allclose(slope[:, 1:-1], np.sinh(a), rtol=1e-5)
    np.testing.assert_allclose(relative_slope(np.swapaxes(ramp, 0, 1).astype(np.float32))[1:-1, :], np.sinh(a),
                               rtol=1e-5)
    flat = np.ones((5, 5, 4, 3), np.float32)
    flat[2, 2] = 0.0
    flat[0, 4] = np.nan
    slope = relative_slope(flat)
    assert np.isinf(slope[2, 2]) and np.isnan(slope[1, 4]) and slope[4, 0] == 0


def test_max_slope_drops_the_samples_on_steep_intensity(rendered, observed):
    """With ``max_slope`` a sample is dropped where a corner of its footprint has a relative slope above it
    (the rim, shadow edges, the highlight's flanks); every other usable sample stays, with its values."""
    mesh = rendered["mesh"]
    observer = Observer(ObserveMesh(mesh.vertices, mesh.normals, mesh.faces),
                        ObserveSettings(threads=2, edge_margin=0.0, max_slope=0.4))
    dropped_total, kept_total = 0, 0
    for k, (camera, light) in enumerate(zip(rendered["cameras"], rendered["lights"])):
        view = observer.observe(camera, light.position, rendered["analyzers"][k], rendered["valid"][k])
        plain = observed[k]
        assert not np.any(view.usable & ~plain.usable)
        np.testing.assert_array_equal(view.specular[view.usable], plain.specular[view.usable])
        slope = relative_slope(rendered["analyzers"][k])
        height, width = slope.shape
        low = np.floor(camera.project(mesh.vertices[plain.usable])).astype(int)
        low = np.minimum(low, [width - 2, height - 2])  # the bilinear footprint's top-left corner
        steepest = np.max([slope[low[:, 1] + dy, low[:, 0] + dx] for dy in (0, 1) for dx in (0, 1)], axis=0)
        np.testing.assert_array_equal(view.usable[plain.usable], steepest <= 0.4)
        dropped_total += int(np.sum(plain.usable & ~view.usable))
        kept_total += int(view.usable.sum())
    assert dropped_total > 20 and kept_total > 2 * dropped_total
