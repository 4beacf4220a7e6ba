"""Capture I/O: write -> read round trips, DNG through rawpy, and one specific error per bad input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from sellip.capture import files, writer
from sellip.capture import reader as capture_reader
from sellip.model import ply as model_ply

WIDTH, HEIGHT = 32, 24


def _config(**sensor_overrides):
    sensor = {"width": WIDTH, "height": HEIGHT, "bit_depth": 12, "black_level": 64, "white_level": 4095,
              "polarizer_layout": [[90, 45], [135, 0]], "color_layout": "RGGB"}
    sensor.update(sensor_overrides)
    return {"sensor": sensor,
            "camera": {"fx": 90.0, "fy": 90.0, "cx": 16.0, "cy": 12.0, "distortion": [0.01, 0, 0, 0, 0],
                       "color_matrix": [[1.5, -0.3, -0.2], [-0.2, 1.4, -0.2], [0, -0.4, 1.4]]},
            "light": {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0},
            "scene": {"distance_m": 0.9}}


def _frames(flash_levels=(0.25, 0.125, 0.0625), views=("a", "b")):
    rows = [{"frame_id": f"{v}_{k}", "view_id": v, "file": "", "flash_level": level, "exposure_s": 0.01}
            for v in views for k, level in enumerate(flash_levels)]
    return pd.DataFrame(rows)


def _raws(frames, seed=0, high=4096):
    rng = np.random.default_rng(seed)
    return {fid: rng.integers(0, high, (HEIGHT, WIDTH)).astype(np.uint16) for fid in frames["frame_id"]}


def _poses(views=("a", "b")):
    rows = [[v, 0.5, 0.5, -0.5, 0.5, 0.01 * k, -0.02, 0.9] for k, v in enumerate(views)]
    return pd.DataFrame(rows, columns=files.POSE_COLUMNS)


def _write(tmp_path, raw_format="dng", **kw):
    frames = _frames()
    raws = _raws(frames)
    path = writer.write_capture(tmp_path / "cap", _config(), frames, raws, _poses(), raw_format=raw_format, **kw)
    return path, frames, raws


def _listing(root: Path):
    return sorted((str(p.relative_to(root)), p.stat().st_size) for p in root.rglob("*"))


@pytest.mark.parametrize("raw_format", ["dng", "tiff", "png"])
def test_capture_round_trip(tmp_path, raw_format):
    path, frames, raws = _write(tmp_path, raw_format)
    capture = capture_reader.read_capture(path, check_raw=True)
    assert capture.config["sensor"] == _config()["sensor"]
    assert capture.config["camera"]["distortion"] == [0.01, 0, 0, 0, 0]
    assert capture.view_ids == ["a", "b"] and len(capture.frames_of("b")) == 3
    np.testing.assert_allclose(capture.frames["flash_level"], frames["flash_level"])
    for fid, raw in raws.items():
        np.testing.assert_array_equal(capture_reader.read_raw_frame(capture, fid), raw)
    np.testing.assert_allclose(capture.poses[["qw", "qx", "qy", "qz"]].to_numpy(), _poses().iloc[:, 1:5].to_numpy())
    rotation, translation = capture.pose("b")
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(translation, [0.01, -0.02, 0.9])
    assert capture.layout.period == 4
    # No temporary folders left beside the capture.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]


def test_dng_round_trips_bit_exact_through_rawpy(tmp_path):
    import rawpy

    sensor = {"black_level": 64, "white_level": 65535}
    raw = np.random.default_rng(3).integers(0, 65536, (48, 64)).astype(np.uint16)
    raw[0, :4] = [0, 1, 65534, 65535]
    writer.write_raw_file(tmp_path / "frame.dng", raw, sensor)
    with rawpy.imread(str(tmp_path / "frame.dng")) as image:
        np.testing.assert_array_equal(image.raw_image, raw)
        assert image.raw_image.dtype == np.uint16


def test_rewriting_a_capture_replaces_it_whole(tmp_path):
    path, _, _ = _write(tmp_path)
    frames = _frames(views=("z",))
    writer.write_capture(path, _config(), frames, _raws(frames, seed=9))
    capture = capture_reader.read_capture(path)
    assert capture.view_ids == ["z"] and capture.poses is None
    assert sorted(p.name for p in (path / "raw").iterdir()) == ["z_0.dng", "z_1.dng", "z_2.dng"]


def test_param_mesh_ply_round_trip(tmp_path):
    from sellip.model.pbrdf import PBRDFParams
    from sellip.model.render import ParamMesh

    rng = np.random.default_rng(0)
    v = 7
    mesh = ParamMesh(vertices=rng.normal(size=(v, 3)), faces=np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6]]),
                     normals=rng.normal(size=(v, 3)),
                     params=PBRDFParams(eta=rng.uniform(1.3, 1.7, v), rho_d=rng.uniform(size=(v, 3)),
                                        rho_s=rng.uniform(size=v), sigma_s=rng.uniform(size=v),
                                        rho_ss=rng.uniform(size=(v, 3)), sigma_ss=rng.uniform(size=v)),
                     material=np.arange(v) % 3)
    model_ply.write_param_mesh(tmp_path / "m.ply", mesh)
    vertex, faces = model_ply.read_ply(tmp_path / "m.ply")
    assert list(vertex)[:16] == list(model_ply.MODEL_VERTEX_PROPERTIES)
    assert all(vertex[name].dtype == np.float32 for name in model_ply.MODEL_VERTEX_PROPERTIES)
    back = model_ply.read_param_mesh(tmp_path / "m.ply")
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.params.rho_d, mesh.params.rho_d, rtol=1e-6)
    np.testing.assert_allclose(back.params.sigma_ss, mesh.params.sigma_ss, rtol=1e-6)
    np.testing.assert_array_equal(back.material, mesh.material)
    import open3d as o3d  # an independent reader agrees on the geometry

    o3d_mesh = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    np.testing.assert_allclose(np.asarray(o3d_mesh.vertices), mesh.vertices, rtol=1e-6)


# --------------------------------------------------------------------------- bad inputs: reading


def _edit_yaml(path, edit):
    config = yaml.safe_load((path / "capture.yaml").read_text())
    edit(config)
    (path / "capture.yaml").write_text(yaml.safe_dump(config))


def _edit_csv(path, name, edit):
    table = pd.read_csv(path / name, dtype=str, keep_default_na=False)
    table = edit(table)
    table.to_csv(path / name, index=False)


def _drop_key(section, key):
    return lambda c: c[section].pop(key)


def _set_key(section, key, value):
    return lambda c: c[section].__setitem__(key, value)


def _write_raw(name, data):
    def corrupt(path):
        (path / "raw" / name).write_bytes(data) if isinstance(data, bytes) else writer.write_raw_file(
            path / "raw" / name, data, {"black_level": 64, "white_level": 4095})
    return corrupt


BAD_READS = {
    "missing capture.yaml": (lambda p: (p / "capture.yaml").unlink(), files.MissingFileError, "capture.yaml"),
    "missing frames.csv": (lambda p: (p / "frames.csv").unlink(), files.MissingFileError, "frames.csv"),
    "missing raw file": (lambda p: (p / "raw" / "a_1.dng").unlink(), files.MissingFileError, "row 1 (line 3)"),
    "missing key": (lambda p: _edit_yaml(p, _drop_key("camera", "fx")), files.ConfigError, "camera.fx"),
    "unknown key": (lambda p: _edit_yaml(p, _set_key("light", "colour", 1)), files.ConfigError, "light.colour"),
    "white level above bit depth": (lambda p: _edit_yaml(p, _set_key("sensor", "white_level", 65520)),
                                    files.ConfigError, "sensor.white_level"),
    "unknown color layout": (lambda p: _edit_yaml(p, _set_key("sensor", "color_layout", "RGBW")),
                             files.UnknownLayoutError, "sensor.color_layout"),
    "unknown polarizer layout": (lambda p: _edit_yaml(p, _set_key("sensor", "polarizer_layout", [[0, 45], [90, 90]])),
                                 files.UnknownLayoutError, "sensor.polarizer_layout"),
    "duplicate frame_id": (lambda p: _edit_csv(p, "frames.csv", lambda t: t.assign(
        frame_id=t["frame_id"].where(t.index != 4, "a_0"))), files.DuplicateFrameError, "'a_0'"),
    "flash level zero": (lambda p: _edit_csv(p, "frames.csv", lambda t: t.assign(
        flash_level=t["flash_level"].where(t.index != 2, "0"))), files.FlashLevelError,
        "row 2 (line 4), column 'flash_level'"),
    "flash level above one": (lambda p: _edit_csv(p, "frames.csv", lambda t: t.assign(
        flash_level=t["flash_level"].where(t.index != 5, "1.5"))), files.FlashLevelError, "(0, 1]"),
    "missing column": (lambda p: _edit_csv(p, "frames.csv", lambda t: t.drop(columns="exposure_s")),
                       files.FramesError, "exposure_s"),
    "view without frames": (lambda p: _edit_csv(p, "poses.csv", lambda t: pd.concat(
        [t, t.iloc[[0]].assign(view_id="ghost")])), files.ViewWithoutFramesError, "'ghost'"),
    "bad quaternion": (lambda p: _edit_csv(p, "poses.csv", lambda t: t.assign(qw="2")), files.PosesError,
                       "unit quaternion"),
}

BAD_RAWS = {
    "raw file unreadable": (_write_raw("a_0.dng", b"not a dng at all" * 10), "cannot be read"),
    "raw file of the wrong size": (_write_raw("a_0.dng", np.zeros((HEIGHT, WIDTH + 4), np.uint16)),
                                   "got shape (24, 36)"),
    "raw file of the wrong bit depth": (_write_raw("a_0.dng", np.full((HEIGHT, WIDTH), 65520, np.uint16)),
                                        "12-bit values"),
}


@pytest.mark.parametrize("case", sorted(BAD_READS))
def test_bad_capture_raises_its_specific_error_and_writes_nothing(tmp_path, case):
    path, _, _ = _write(tmp_path)
    corrupt, error, where = BAD_READS[case]
    corrupt(path)
    before = _listing(tmp_path)
    with pytest.raises(error) as info:
        capture_reader.read_capture(path)
    assert where in str(info.value)
    assert info.value.file.endswith((".yaml", ".csv", ".dng"))  # names the file
    assert _listing(tmp_path) == before


@pytest.mark.parametrize("case", sorted(BAD_RAWS))
def test_bad_raw_frame_raises_raw_frame_error(tmp_path, case):
    path, _, _ = _write(tmp_path)
    corrupt, message = BAD_RAWS[case]
    corrupt(path)
    capture = capture_reader.read_capture(path)  # the tables are fine
    with pytest.raises(files.RawFrameError) as info:
        capture_reader.read_raw_frame(capture, "a_0")
    assert message in str(info.value) and "a_0.dng" in str(info.value)
    with pytest.raises(files.RawFrameError):
        capture_reader.read_capture(path, check_raw=True)


def test_eight_bit_png_for_a_twelve_bit_sensor_is_rejected(tmp_path):
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "f.png", np.zeros((HEIGHT, WIDTH), np.uint8))
    with pytest.raises(files.RawFrameError, match="uint8"):
        capture_reader.read_raw_file(tmp_path / "f.png", _config()["sensor"])


# --------------------------------------------------------------------------- bad inputs: writing


BAD_WRITES = {
    "flash level outside (0, 1]": (lambda f, r, c: (f.assign(flash_level=[0.25, 0.125, 2.0, 0.25, 0.125, 0.0625]),
                                                    r, c),
                                   files.FlashLevelError),
    "duplicate frame_id": (lambda f, r, c: (f.assign(frame_id=["x", "y", "z", "x", "v", "w"]),
                                            {k: r["a_0"] for k in "xyzvw"}, c), files.DuplicateFrameError),
    "raw of the wrong size": (lambda f, r, c: (f, {**r, "b_2": r["b_2"][:, :-4]}, c), files.RawFrameError),
    "raw above the bit depth": (lambda f, r, c: (f, {**r, "b_1": r["b_1"] | np.uint16(0x8000)}, c),
                                files.RawFrameError),
    "unknown layout": (lambda f, r, c: (f, r, {**c, "sensor": {**c["sensor"], "color_layout": "RGB"}}),
                       files.UnknownLayoutError),
}


@pytest.mark.parametrize("case", sorted(BAD_WRITES))
def test_a_failed_write_leaves_nothing(tmp_path, case):
    frames = _frames()
    bad, error = BAD_WRITES[case]
    frames, raws, config = bad(frames, _raws(frames), _config())
    with pytest.raises(error):
        writer.write_capture(tmp_path / "cap", config, frames, raws, _poses())
    assert list(tmp_path.iterdir()) == []


def test_a_failed_rewrite_keeps_the_old_capture(tmp_path):
    path, _, raws = _write(tmp_path)
    before = _listing(path)
    frames = _frames().assign(flash_level=1.5)
    with pytest.raises(files.FlashLevelError):
        writer.write_capture(path, _config(), frames, raws)
    assert _listing(path) == before and sorted(os.listdir(tmp_path)) == ["cap"]


def test_view_in_poses_without_frames_is_rejected_on_write(tmp_path):
    frames = _frames(views=("a",))
    with pytest.raises(files.ViewWithoutFramesError):
        writer.write_capture(tmp_path / "cap", _config(), frames, _raws(frames), _poses(("a", "b")))
    assert list(tmp_path.iterdir()) == []
