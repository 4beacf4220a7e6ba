"""Issue #40 without a browser: the materials table (pandera, against the ground truth it was built from), the glTF
export read back with an independent reader (pygltflib) attribute by attribute against model.ply, the map PLYs,
the viewer folder (its model.js decoded back to model.ply's arrays), and the bad inputs (no model; an older
model.ply without some properties)."""

from __future__ import annotations

import base64
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from viewer_helpers import FLASH, write_results


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    return write_results(tmp_path_factory.mktemp("viewer"))


@pytest.fixture(scope="module")
def written(results):
    from sellip.report.viewer import export_results as run_stage

    return run_stage(results)


def test_materials_table_recovers_the_scene_materials(results, written):
    from sellip.capture.scenes import TINY_MATERIALS
    from sellip.report.materials import read_materials

    table = read_materials(written["materials"])
    assert list(table["cluster"]) == [0, 1]
    assert table["vertices"].sum() == 2562 and abs(table["area_share"].sum() - 1) < 1e-9
    for row in table.itertuples():
        truth = TINY_MATERIALS[row.cluster]
        # Own eta = truth + N(0, 0.02): the median of ~1300 vertices is within 0.003 of the truth, and the 95 %
        # interval (the scatter, +-1.96 * 1.25 * 0.02 / sqrt(1300) ~ 0.0014, and the shared error, +-1.96 * 0.15 *
        # 0.02 ~ 0.006) contains it.
        assert abs(row.eta - truth.eta) < 0.004 and row.eta_ci_low <= truth.eta <= row.eta_ci_high
        assert 0.015 < row.eta_spread < 0.025 and row.eta_fit_std == pytest.approx(0.02)
        assert row.model == (1 if row.cluster == 0 else 3)
    assert "gt_eta" not in table  # no capture: no ground truth columns


def test_materials_table_with_ground_truth_and_its_checks(results):
    from sellip.capture.scenes import build_scene
    from sellip.model.params import read_params
    from sellip.report.materials import MaterialsError, material_table, validate_materials

    truth = build_scene("tiny").mesh
    store = read_params(results / "final" / "params.zarr")
    table = material_table(store, truth.faces, ground_truth=truth)
    assert list(table["gt_material"]) == [0, 1] and list(table["gt_eta"]) == pytest.approx([1.6, 1.4])
    assert np.allclose(table["gt_eta"], table["eta"], atol=0.004)
    bad = table.copy()
    bad.loc[1, "eta_ci_low"] = 2.0  # above eta
    with pytest.raises(MaterialsError, match="materials.csv"):
        validate_materials(bad)
    bad = table.copy()
    bad.loc[0, "model"] = 7
    with pytest.raises(MaterialsError, match=r"row 0, column 'model'"):
        validate_materials(bad)


def test_material_eta_interval_is_seeded_and_covers_its_median():
    from sellip.report.materials import median_interval

    values = np.random.default_rng(1).normal(1.5, 0.05, 400)
    low, high = median_interval(values)
    assert (low, high) == median_interval(values) and low < np.median(values) < high
    assert 0.005 < high - low < 0.02  # ~ 2 * 1.96 * 1.25 * 0.05 / 20 = 0.012


def test_glb_read_back_by_pygltflib_matches_model_ply(results, written):
    pygltflib = pytest.importorskip("pygltflib")
    from sellip.model.ply import read_ply
    from sellip.report.export import GLTF_ATTRIBUTES

    vertex, faces = read_ply(results / "final" / "model.ply")
    gltf = pygltflib.GLTF2().load(str(written["glb"]))
    blob = gltf.binary_blob()
    assert gltf.asset.version == "2.0"

    def accessor_array(index):
        accessor = gltf.accessors[index]
        view = gltf.bufferViews[accessor.bufferView]
        dtype = {5126: np.float32, 5125: np.uint32}[accessor.componentType]
        width = {"SCALAR": 1, "VEC3": 3}[accessor.type]
        data = np.frombuffer(blob, dtype, accessor.count * width, view.byteOffset + (accessor.byteOffset or 0))
        return data.reshape(accessor.count, width) if width > 1 else data

    primitive = gltf.meshes[0].primitives[0]
    attributes = {k: v for k, v in vars(primitive.attributes).items() if v is not None}  # custom ones included
    position = accessor_array(attributes["POSITION"])
    assert np.array_equal(position, np.stack([vertex["x"], vertex["y"], vertex["z"]], -1))
    assert np.array_equal(accessor_array(primitive.indices).reshape(-1, 3), faces)
    normal = accessor_array(attributes["NORMAL"])
    assert np.allclose(normal, np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], -1), atol=1e-6)
    checked = []
    for name, props in GLTF_ATTRIBUTES:
        if not all(p in vertex for p in props):
            continue
        values = accessor_array(attributes[name])
        expected = np.stack([vertex[p] for p in props], -1) if len(props) == 3 else vertex[props[0]]
        assert np.array_equal(values, expected.astype(np.float32)), name
        checked.append(name)
    assert {"_ETA", "_RHO_D", "_RHO_S", "_SIGMA_S", "_RHO_SS", "_SIGMA_SS", "_CONFIDENCE", "_MODEL"} <= set(checked)
    from sellip.model.params import read_params

    cluster = read_params(results / "final" / "params.zarr")["cluster"]  # from params.zarr: model.ply has none
    assert np.array_equal(accessor_array(attributes["_CLUSTER"]), cluster.astype(np.float32))
    color = accessor_array(attributes["COLOR_0"])
    assert color.min() >= 0 and color.max() <= 1 and color.std() > 0
    matrix = np.array(gltf.nodes[0].matrix).reshape(4, 4).T
    assert np.allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-9)


def test_up_rotation_takes_up_to_y():
    from sellip.report.export import up_rotation

    for up in ([0, 0, 1], [0.3, -0.2, 0.9], [0, -1, 0], [0, 1, 0]):
        r = up_rotation(up)
        assert np.allclose(r @ (np.array(up) / np.linalg.norm(up)), [0, 1, 0]) and np.isclose(np.linalg.det(r), 1)


def test_map_plys_are_coloured_meshes(results, written):
    from sellip.model.ply import read_ply

    files = sorted(p.name for p in written["maps"].glob("*.ply"))
    assert files == sorted(f"map_{m}.ply" for m in ("eta", "rho_d", "rho_s", "sigma_s", "rho_ss", "sigma_ss", "normal",
                                                    "confidence", "model", "cluster"))
    vertex, faces = read_ply(written["maps"] / "map_eta.ply")
    assert faces.shape == (5120, 3) and vertex["red"].dtype == np.uint8
    # two etas, two viridis colours
    assert len({tuple(c) for c in np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1)}) == 2


def _decode_model(viewer: Path) -> tuple[dict, bytes]:
    text = (viewer / "model.js").read_text()
    meta_json = text[len("window.SELLIP_MODEL = {meta: "):text.index(', data: "')]
    data = text[text.index(', data: "') + 9:text.rindex('"')]
    return json.loads(meta_json), base64.b64decode(data)


def test_viewer_folder_holds_the_model_arrays(results, written):
    from sellip.model.ply import read_ply

    viewer = written["viewer"].parent
    assert {p.name for p in viewer.iterdir()} == {"index.html", "viewer.js", "shaders.js", "model.js"}
    shaders = (viewer / "shaders.js").read_text()
    assert "#include" not in shaders and "pbrdfLobes" in shaders
    meta, binary = _decode_model(viewer)
    vertex, faces = read_ply(results / "final" / "model.ply")

    def array(name):
        spec = meta["arrays"][name]
        return np.frombuffer(binary, "<u4" if spec["dtype"] == "uint32" else "<f4", spec["length"], spec["offset"])

    assert np.array_equal(array("eta"), vertex["eta"])
    assert np.array_equal(array("rho_d").reshape(-1, 3)[:, 2], vertex["rho_d_b"])
    assert np.array_equal(array("indices").reshape(-1, 3), faces)
    assert meta["light"] == FLASH and len(meta["cameras"]) == 12 and meta["missing"] == {}
    assert meta["intrinsics"]["width"] == 512 and len(meta["materials"]["rows"]) == 2


@pytest.mark.slow
def test_no_finished_model_is_a_clear_error(tmp_path):
    from sellip.report.viewer import ViewerError, load_inputs

    (tmp_path / "results" / "x").mkdir(parents=True)
    with pytest.raises(ViewerError, match=r"final/model.ply: missing: the run has no finished model"):
        load_inputs(tmp_path / "results" / "x")
    out = subprocess.run([sys.executable, "-m", "sellip.cli", "view", str(tmp_path / "results" / "x")],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 1 and "no finished model" in out.stderr


def test_a_moved_capture_is_a_warning_that_names_it_and_the_default_flash(tmp_path, caplog):
    """metrics.json names a capture folder that is gone (moved): load_inputs warns (a WARNING, so it reaches the
    run's summary), naming the missing capture and saying the flash is a default (issue #52; before: an INFO note)."""
    import logging

    from sellip.report.viewer import DEFAULT_FLASH, find_capture, load_inputs

    results = write_results(tmp_path)
    (results / "metrics.json").write_text(json.dumps({"capture": str(tmp_path / "moved away")}))
    with caplog.at_level(logging.INFO):
        inputs = load_inputs(results, find_capture(results))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, caplog.text
    assert f"the capture {str(tmp_path / 'moved away')!r} has no capture.yaml (moved or deleted?)" in warnings[0]
    assert "flash is a DEFAULT" in warnings[0] and "--capture PATH" in warnings[0]
    assert inputs.light == DEFAULT_FLASH


def test_an_older_model_without_some_properties_disables_those_maps(tmp_path):
    from sellip.report.viewer import load_inputs, payload

    results = write_results(tmp_path, drop=("confidence", "rho_ss_r", "rho_ss_g", "rho_ss_b", "model"))
    meta, _ = payload(load_inputs(results))
    assert set(meta["missing"]) == {"confidence", "rho_ss", "model"}
    assert "rho_ss_r" in meta["missing"]["rho_ss"] and "eta" in meta["maps"] and "cluster" in meta["maps"]
    assert "rho_ss" not in meta["arrays"] and "eta" in meta["arrays"]


@pytest.mark.slow
def test_serve_answers_on_localhost(results, written):
    import socket
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    command = [sys.executable, "-m", "sellip.cli", "view", str(results), "--serve", "--port", str(port)]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.time() + 120
        while True:
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{port}/index.html", timeout=5).read().decode()
                break
            except OSError:
                if time.time() > deadline or server.poll() is not None:
                    raise
                time.sleep(0.5)
        assert "sellip viewer" in page and '<script src="model.js">' in page
        model = urllib.request.urlopen(f"http://127.0.0.1:{port}/model.js", timeout=5).read()
        assert model.startswith(b"window.SELLIP_MODEL = {meta: ")
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_a_store_without_clusters_or_stds_is_one_material(results):
    from sellip.capture.scenes import build_scene
    from sellip.model.params import read_params
    from sellip.report.materials import material_table

    store = read_params(results / "final" / "params.zarr")
    for name in ("cluster", "eta_vertex", "eta_std", "model", "eta_source", "lobe_source", "confidence"):
        store.pop(name)
    table = material_table(store, build_scene("tiny").mesh.faces)
    assert len(table) == 1 and table.loc[0, "vertices"] == 2562 and table.loc[0, "area_share"] == pytest.approx(1.0)
    assert table.loc[0, "eta"] == pytest.approx(1.5, abs=0.11) and np.isnan(table.loc[0, "eta_fit_std"])
    assert table.loc[0, "model"] == 3  # the full model when the store has no model codes
    assert np.isnan(table.loc[0, "selection_margin"]) and table.loc[0, "runner_up_model"] == -1  # no selection


def test_materials_table_reports_each_materials_selection_margin(results):
    from sellip.capture.scenes import build_scene
    from sellip.model.params import read_params
    from sellip.report import materials

    store = read_params(results / "final" / "params.zarr")
    cluster = np.asarray(store["cluster"])
    store["selection_margin"] = np.where(cluster == 0, 0.05, 1.0).astype(np.float32)  # a fragile choice, a clear one
    store["selection_runner_up"] = np.where(cluster == 0, 2, 3).astype(np.int8)
    table = materials.material_table(store, build_scene("tiny").mesh.faces)
    assert list(table["selection_margin"]) == pytest.approx([0.05, 1.0]) and list(table["runner_up_model"]) == [2, 3]
    bad = table.copy()
    bad.loc[1, "selection_margin"] = 1.5
    with pytest.raises(materials.MaterialsError, match=r"row 1, column 'selection_margin'"):
        materials.validate_materials(bad)


def test_materials_table_says_which_material_the_clustering_does_not_settle(results):
    """cluster_support / cluster_alternative (issue #49): a material found again in 3 of 10 resamples of its clustering
    and merged into material 0 in the others says so; one without a measured support has NaN and -1; out-of-range
    support is rejected with the row and column."""
    from sellip.capture.scenes import build_scene
    from sellip.model.params import read_params
    from sellip.report import materials

    store = read_params(results / "final" / "params.zarr")
    faces = build_scene("tiny").mesh.faces
    plain = materials.material_table(store, faces)
    assert plain["cluster_support"].isna().all() and list(plain["cluster_alternative"]) == [-1, -1]
    cluster = np.asarray(store["cluster"])
    store["cluster_support"] = np.where(cluster == 1, 0.3, 1.0).astype(np.float32)
    store["cluster_alternative"] = np.where(cluster == 1, 0, -1).astype(np.int32)
    table = materials.material_table(store, faces)
    assert list(table["cluster_support"]) == pytest.approx([1.0, 0.3]) and list(table["cluster_alternative"]) == [-1, 0]
    bad = table.copy()
    bad.loc[1, "cluster_support"] = 1.5
    with pytest.raises(materials.MaterialsError, match=r"row 1, column 'cluster_support'"):
        materials.validate_materials(bad)
