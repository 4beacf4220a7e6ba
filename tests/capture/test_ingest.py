"""Ingest (issue 4): raw decoding levels, demosaic geometry, HDR merge, stages, a real sensor frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from sellip.capture import ingest
from sellip.capture.files import CaptureError
from sellip.capture.hdr import merge_capture, read_hdr
from sellip.capture.linearize import linearize_capture
from sellip.capture.mosaic import mosaic_layout
from sellip.capture.reader import read_capture, read_raw_file, read_raw_frame
from sellip.capture.sensor import SensorModel, camera_rgb_from_srgb, simulate_raw
from sellip.capture.writer import CaptureWriter, write_capture
from sellip.model.conventions import ANALYZER_ANGLES_DEG, analyzers_to_stokes, stokes_to_analyzers

REAL_FRAME = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "polarizer_IMX250MZR.png"
IMX250 = [[90, 45], [135, 0]]
LEVELS = (1 / 4, 1 / 8, 1 / 16)
EXPOSURE_S = 0.005


def plain_camera(width, height, f=80.0, distortion=(0.0,) * 5, color_matrix=None):
    camera = {"fx": f, "fy": f, "cx": (width - 1) / 2, "cy": (height - 1) / 2, "distortion": list(distortion)}
    if color_matrix is not None:
        camera["color_matrix"] = [list(map(float, row)) for row in color_matrix]
    return camera


def capture_config(sensor: SensorModel, camera: dict) -> dict:
    camera = {"color_matrix": [list(map(float, r)) for r in sensor.color_matrix], **camera}
    return {"sensor": sensor.capture_sensor(), "camera": camera,
            "light": {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0}, "scene": {"distance_m": 0.9}}


def cell_centres(height, width):
    """Raw (x, y) of the output pixel centres: (2j + 0.5, 2i + 0.5)."""
    j, i = np.meshgrid(np.arange(width // 2), np.arange(height // 2))
    return 2 * j + 0.5, 2 * i + 0.5


def stokes_field(x, y, width, height):
    """A smooth polarized HDR scene in linear sRGB: analyzers (..., 4, 3) at raw positions (x, y).

    s0 spans ~30x, with a bright blob that saturates at flash 1/4 but not at 1/8; DoLP up to 0.5.
    """
    u, v = x / width, y / height
    s0 = 0.15 + 0.3 * u + 0.15 * np.sin(2 * np.pi * v) ** 2
    s0 = s0 + 3.2 * np.exp(-((u - 0.7) ** 2 + (v - 0.45) ** 2) / (2 * 0.15 ** 2))
    dolp = 0.5 * (0.2 + 0.8 * v)
    aolp = np.pi * (u + 0.3 * v)
    stokes = np.stack([s0, s0 * dolp * np.cos(2 * aolp), s0 * dolp * np.sin(2 * aolp)], axis=-1)
    albedo = np.array([0.9, 0.7, 0.5])
    return stokes_to_analyzers(stokes, axis=-1)[..., None] * albedo


# --------------------------------------------------------------------------- levels


def test_black_level_map_follows_raster_position():
    pattern = np.arange(16, dtype=np.float32).reshape(4, 4) + 60
    black = ingest.black_level_map(pattern.tolist(), 8, 12)
    assert black.shape == (8, 12)
    assert black[5, 9] == pattern[1, 1] and black[7, 4] == pattern[3, 0]
    assert np.all(ingest.black_level_map(64, 4, 4) == 64)
    with pytest.raises(ingest.IngestError, match="tiles"):
        ingest.black_level_map(np.zeros((3, 3)), 8, 8)


def write_dng_with_black_pattern(path, raw, cfa, black2x2, white):
    """A CFA DNG whose BlackLevel repeats over 2x2 pixels (BlackLevelRepeatDim), in raster order."""
    import tifffile

    tag = {"DNGVersion": (50706, "B", 4, (1, 4, 0, 0)), "UniqueCameraModel": (50708, "s", 0, "test"),
           "CFARepeatPatternDim": (33421, "H", 2, (2, 2)), "CFAPattern": (33422, "B", 4, cfa),
           "BlackLevelRepeatDim": (50713, "H", 2, (2, 2)), "BlackLevel": (50714, "H", 4, tuple(black2x2)),
           "WhiteLevel": (50717, "H", 1, white),
           "ColorMatrix1": (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1))}
    tifffile.imwrite(path, raw, photometric=32803, compression=None, subfiletype=0, metadata=None,
                     extratags=[(*t, True) for t in tag.values()])


@pytest.mark.parametrize("cfa", [(0, 1, 1, 2), (2, 1, 1, 0), (1, 0, 2, 1), (1, 2, 0, 1)])
def test_rawpy_black_levels_map_to_raster_positions(tmp_path, cfa):
    import rawpy

    path = tmp_path / "frame.dng"
    write_dng_with_black_pattern(path, np.full((24, 32), 500, np.uint16), cfa, (10, 20, 30, 40), 4095)
    black = ingest.rawpy_black_level(path)
    np.testing.assert_array_equal(black, np.tile([[10, 20], [30, 40]], (12, 16)))
    with rawpy.imread(str(path)) as raw:  # the trap: rawpy lists them by colour index, not by position
        assert raw.black_level_per_channel != [10, 20, 30, 40]


def test_linearize_per_position_black_saturated_and_dead():
    black = ingest.black_level_map([[60, 62], [64, 66]], 4, 4)
    raw = (black + 1000).astype(np.uint16)
    raw[0, 1], raw[2, 2], raw[1, 1] = 4095, 0, 66 + 3945  # saturated, dead, just below 98% of its range
    linear, invalid = ingest.linearize(raw, black, 4095, saturation=0.98)
    ok = ~invalid
    np.testing.assert_allclose(linear[ok & (raw < 4000)], 1000 / (4095 - 63), rtol=1e-6)
    assert invalid[0, 1] and invalid[2, 2] and invalid.sum() == 2


# --------------------------------------------------------------------------- demosaic and geometry


@pytest.mark.parametrize("color_layout, polarizer_layout",
                         [("RGGB", IMX250), ("GBRG", IMX250), ("BGGR", [[0, 45], [90, 135]]), ("mono", IMX250)])
def test_demosaic_is_exact_for_affine_fields_per_analyzer(color_layout, polarizer_layout):
    """Each analyzer sees its own affine field, each colour a gain of it (the colour ratio per analyzer and
    colour): output at the cell centres must equal it. Any mixing of analyzers or colours, or a phase
    error, breaks the equality (colour-ratio demosaicing is exact where the ratio to G is constant)."""
    layout = mosaic_layout(polarizer_layout, color_layout)
    height, width, channels = 32, 48, layout.channels
    rng = np.random.default_rng(1)
    coef = rng.uniform(0.1, 0.3, (4, 1, 3)) * [1, 3e-3, 4e-3] * rng.uniform(0.5, 1.5, (4, channels, 1))
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    a, c = layout.analyzer_map(height, width), layout.color_map(height, width)
    field = coef[a, c, 0] + coef[a, c, 1] * x + coef[a, c, 2] * y
    raw = np.rint(100 + field * (65535 - 100)).astype(np.uint16)
    sensor = {"width": width, "height": height, "black_level": 100, "white_level": 65535}
    plan = ingest.make_ingest_plan(sensor, plain_camera(width, height), layout)
    out = ingest.process_frame(raw, plan)
    assert out.shape == (height // 2, width // 2, 4, channels)
    xc, yc = cell_centres(height, width)
    truth = coef[..., 0] + coef[..., 1] * xc[..., None, None] + coef[..., 2] * yc[..., None, None]
    # three cells in: G's own interpolation at the border cells (zero padding) is not exact, and R and B use it
    np.testing.assert_allclose(out[3:-3, 3:-3], truth[3:-3, 3:-3], atol=2e-5)


@pytest.mark.parametrize("color_layout", ["RGGB", "mono"])
def test_one_analyzer_plan_develops_that_analyzer_alone(color_layout):
    """analyzer_plan(plan, k) develops a mosaic (distorted lens: the remap too) into analyzer k of the full
    plan's output, and reads nothing of the other analyzers' pixels (they may be anything)."""
    layout = mosaic_layout(IMX250, color_layout)
    height, width = 32, 48
    rng = np.random.default_rng(4)
    mosaic = rng.uniform(0.1, 0.9, (height, width)).astype(np.float32)
    camera = {**plain_camera(width, height), "distortion": [-0.1, 0.02, 0.001, -0.001, 0.0]}
    plan = ingest.make_ingest_plan({"width": width, "height": height, "black_level": 0, "white_level": 65535},
                                   camera, layout)
    full = ingest.develop(mosaic, plan)
    for k in range(4):
        others = mosaic.copy()
        elsewhere = layout.analyzer_map(height, width) != k
        others[elsewhere] = rng.uniform(0, 5, np.sum(elsewhere))
        one = ingest.develop(others, ingest.analyzer_plan(plan, k))
        assert one.shape == full[..., k:k + 1, :].shape
        np.testing.assert_allclose(one, full[..., k:k + 1, :], rtol=1e-6, atol=1e-7)


def test_colours_share_the_guide_resolution_and_polarization():
    """A texture of period 16 raw pixels (8 cells), one hue, uniform partial polarization: interpolated by
    their ratio to G, R and B are as sharp as G and carry about G's polarization; bilinear on their own (every
    second cell) they are blurred and their DoP is off twice as much as G's. Measured (RMS over the
    interior): intensity 1.6 / 2.0 % guided, 9.2 / 9.6 % bilinear (G 6.2 %); DoP error 0.0079 / 0.0085
    guided, 0.0132 / 0.0135 bilinear (G 0.0068)."""
    import dataclasses

    layout = mosaic_layout(IMX250, "RGGB")
    height, width, period = 64, 96, 16.0
    hue = np.array([0.7, 1.0, 0.45])
    polarization = 1 + 0.2 * np.cos(np.radians(2 * (np.array(ANALYZER_ANGLES_DEG) - 30.0)))
    texture = lambda x, y: 0.6 + 0.3 * np.sin(2 * np.pi * x / period) * np.cos(2 * np.pi * y / (1.3 * period))
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    a, c = layout.analyzer_map(height, width), layout.color_map(height, width)
    linear = (0.5 * texture(x, y) * hue[c] * polarization[a]).astype(np.float32)
    sensor = {"width": width, "height": height, "black_level": 0, "white_level": 4095}
    plan = ingest.make_ingest_plan(sensor, plain_camera(width, height), layout)
    xc, yc = cell_centres(height, width)
    truth = (0.5 * texture(xc, yc)[..., None, None] * polarization[:, None] * hue)[3:-3, 3:-3]

    def dop(v):  # (H, W, 4, C) -> (H, W, C)
        i0, i45, i90, i135 = (v[:, :, ANALYZER_ANGLES_DEG.index(angle)] for angle in (0, 45, 90, 135))
        return np.hypot(i0 - i90, i45 - i135) / (i0 + i90)

    errors = {}
    for name, demosaic_plan in (("guided", plan.demosaic),
                                ("bilinear", dataclasses.replace(plan.demosaic, guide=None))):
        out = ingest.remap(ingest.demosaic(linear, demosaic_plan), plan.remap)[3:-3, 3:-3]
        errors[name] = (np.sqrt(np.mean(((out - truth) / truth) ** 2, axis=(0, 1, 2))),
                        np.sqrt(np.mean((dop(out) - dop(truth)) ** 2, axis=(0, 1))))
    (intensity, dop_error), (intensity_bilinear, dop_bilinear) = errors["guided"], errors["bilinear"]
    assert plan.demosaic.guide == 1
    assert np.all(intensity[[0, 2]] < 0.4 * intensity_bilinear[[0, 2]])
    assert np.all(dop_error[[0, 2]] < 1.35 * dop_error[1]) and np.all(dop_bilinear[[0, 2]] > 1.8 * dop_error[1])


def test_invalid_pixel_spoils_only_its_own_analyzer_neighbourhood():
    layout = mosaic_layout(IMX250, "RGGB")
    sensor = {"width": 48, "height": 32, "black_level": 0, "white_level": 4095}
    plan = ingest.make_ingest_plan(sensor, plain_camera(48, 32), layout)
    raw = np.full((32, 48), 1000, np.uint16)
    raw[16, 21] = 4095  # one saturated pixel: row 16 -> dy 0, column 21 -> dx 1: the 45 deg analyzer
    out = ingest.process_frame(raw, plan)
    bad = np.isnan(out).any(axis=-1)  # (H, W, 4)
    rows, cols = np.nonzero(bad[..., ANALYZER_ANGLES_DEG.index(45)])
    # a red cell: the 3x3-cell tent of the Bayer interpolation, widened to 4x4 by the half-pixel alignment
    assert rows.size == 16 and np.ptp(rows) == 3 and np.ptp(cols) == 3 and 8 in rows and 10 in cols
    assert bad.sum() == 16
    np.testing.assert_allclose(out[~np.isnan(out)], 1000 / 4095, rtol=1e-5)


def test_output_intrinsics_put_pixel_centres_on_cell_centres():
    camera = {"fx": 7246.0, "fy": 7250.0, "cx": 1223.5, "cy": 1023.5, "distortion": [0.0] * 5}
    out = ingest.output_intrinsics(camera, 2048, 2448)
    assert (out["width"], out["height"]) == (1224, 1024)
    point = np.array([0.031, -0.017, 0.9])  # camera coordinates, metres
    u, v = camera["fx"] * point[0] / point[2] + camera["cx"], camera["fy"] * point[1] / point[2] + camera["cy"]
    u2, v2 = out["fx"] * point[0] / point[2] + out["cx"], out["fy"] * point[1] / point[2] + out["cy"]
    assert (u, v) == pytest.approx((2 * u2 + 0.5, 2 * v2 + 0.5))
    x, y = ingest.source_positions(camera, 2048, 2448)
    xc, yc = cell_centres(2048, 2448)
    np.testing.assert_allclose(x, xc, atol=1e-9)
    np.testing.assert_allclose(y, yc, atol=1e-9)


def test_source_positions_follow_opencv_distortion():
    import cv2  # test dependency (through polanalyser)

    camera = {"fx": 300.0, "fy": 310.0, "cx": 95.5, "cy": 63.5, "distortion": [-0.2, 0.08, 1e-3, -2e-3, -0.01]}
    x, y = ingest.source_positions(camera, 128, 192)
    out = ingest.output_intrinsics(camera, 128, 192)
    j, i = np.meshgrid(np.arange(out["width"]), np.arange(out["height"]))
    rays = np.stack([(j - out["cx"]) / out["fx"], (i - out["cy"]) / out["fy"], np.ones_like(j, float)], -1)
    k = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]])
    projected, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k,
                                     np.array(camera["distortion"]))
    np.testing.assert_allclose(x.ravel(), projected[:, 0, 0], atol=1e-6)
    np.testing.assert_allclose(y.ravel(), projected[:, 0, 1], atol=1e-6)


def test_undistorted_output_matches_output_intrinsics():
    """A scene affine in undistorted normalized coordinates, seen through a distorting lens, comes out
    affine in the output grid's normalized coordinates."""
    from sellip.model.render import undistort_normalized

    height, width = 96, 128
    camera = plain_camera(width, height, f=110.0, distortion=(-0.25, 0.05, 1e-3, 5e-4, 0.0))
    layout = mosaic_layout(IMX250, "mono")
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    xn, yn = undistort_normalized((x - camera["cx"]) / camera["fx"], (y - camera["cy"]) / camera["fy"],
                                  camera["distortion"])
    scene = lambda xn, yn: 0.4 + 0.25 * xn - 0.2 * yn
    raw = np.rint(scene(xn, yn) * 65535).astype(np.uint16)
    plan = ingest.make_ingest_plan({"width": width, "height": height, "black_level": 0, "white_level": 65535},
                                   camera, layout)
    out = ingest.process_frame(raw, plan)[..., 0]  # (H/2, W/2, 4)
    k = plan.intrinsics
    j, i = np.meshgrid(np.arange(k["width"]), np.arange(k["height"]))
    truth = scene((j - k["cx"]) / k["fx"], (i - k["cy"]) / k["fy"])
    inner = (slice(4, -4), slice(4, -4))
    err = out[inner] - truth[inner][..., None]
    assert np.nanmax(np.abs(err)) < 2e-4  # half a raw pixel of misplacement would be ~1e-3
    assert np.isnan(out).sum() < 0.2 * out.size  # rays leaving the sensor near the corners are invalid


def test_color_matrix_maps_camera_rgb_and_spreads_invalidity():
    matrix = np.array([[1.6, -0.4, -0.2], [-0.3, 1.5, -0.2], [0.1, -0.5, 1.4]])
    rgb = np.array([[0.2, 0.5, 0.3], [0.1, np.nan, 0.4]], np.float32)
    out = ingest.apply_color_matrix(rgb, matrix)
    np.testing.assert_allclose(out[0], matrix @ rgb[0], rtol=1e-6)
    assert np.isnan(out[1]).all()


# --------------------------------------------------------------------------- HDR merge


def test_hdr_weight_favours_mid_range():
    w = ingest.hdr_weight(np.array([np.nan, -0.1, 0.0, 0.1, 0.5, 0.9, 0.97], np.float32))
    assert w[0] == 0 and w[1] == w[2] == pytest.approx(ingest.HDR_WEIGHT_FLOOR)
    assert w[4] == pytest.approx(1.0) and w[3] < w[4] and w[5] < w[4] and 0 < w[6] < w[5]


def test_merge_of_dark_noisy_frames_is_unbiased():
    """Frames at flash 1/4, 1/8, 1/16 of a black background and of a dim surface (10 DN in the brightest frame)
    with read and shot noise: the merged mean is the radiance to 5 % of the merged noise sd. Weights from each
    sample's own value (h rises from black) made it 0.3 sd high at black and 0.2 sd at the dim surface."""
    rng = np.random.default_rng(0)
    read_noise = 2.4e-4  # 1 DN of 4031
    for radiance in (0.0, 0.01):
        frames = []
        for level in LEVELS:
            sd = np.sqrt(read_noise**2 + radiance * level / (2.58 * 4031))
            frames.append((radiance * level + sd * rng.standard_normal((128, 128, 4, 3))).astype(np.float32))
        merged, valid = ingest.merge_hdr(frames, LEVELS)
        assert valid.all()
        assert abs(merged.mean() - radiance) < 0.05 * merged.std(), (radiance, merged.mean(), merged.std())


def test_merge_recovers_pixel_saturated_at_quarter_flash():
    radiance = np.array([0.4, 5.0, 7.0, 40.0], np.float32)  # 5 and 7 saturate at 1/4 only, 40 at all levels
    frames = []
    for level in LEVELS:
        linear = radiance * level
        frames.append(np.where(linear >= ingest.DEFAULT_SATURATION, np.nan, linear)[:, None, None]
                      * np.ones((1, 4, 3), np.float32))
    merged, valid = ingest.merge_hdr(frames, LEVELS)
    assert np.isnan(frames[0][1]).all() and np.isfinite(frames[1][1]).all()
    assert valid.tolist() == [True, True, True, False]
    np.testing.assert_allclose(merged[:3, 0, 0], radiance[:3], rtol=1e-6)
    assert (merged[3] == 0).all()


# --------------------------------------------------------------------------- stages on captures


def simulated_capture(path, width=128, height=96, views=2, raw_format="dng", noise=True, black_level=64,
                      distortion=(0.0,) * 5, seed=0):
    """Every view the same :func:`stokes_field` scene through sellip's sensor simulator with its own noise.

    Returns (capture path, true merged analyzers (H/2, W/2, 4, 3) at the output pixel centres).
    """
    sensor = SensorModel(width=width, height=height, black_level=black_level)
    config = capture_config(sensor, plain_camera(width, height, distortion=distortion))
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    analyzers = stokes_field(x, y, width, height)
    peak = camera_rgb_from_srgb(analyzers, sensor.color_matrix).max()
    power = 1.5 * (sensor.white_level - np.max(black_level)) / (peak * LEVELS[0])  # DN per unit radiance at flash 1
    rng = np.random.default_rng(seed)
    frames, raws = [], {}
    for v in range(views):
        for f, level in enumerate(LEVELS):
            frame_id = f"v{v}_f{f}"
            raws[frame_id] = simulate_raw(analyzers, sensor, power * level, rng, noise=noise)
            frames.append({"frame_id": frame_id, "view_id": f"v{v}", "file": "", "flash_level": level,
                           "exposure_s": EXPOSURE_S})
    write_capture(path, config, pd.DataFrame(frames), raws, raw_format=raw_format)
    unit = power / ((sensor.white_level - np.mean(black_level)) * EXPOSURE_S)
    return path, stokes_field(*cell_centres(height, width), width, height) * unit


def run_ingest(capture, out_dir, **kwargs):
    linear = linearize_capture(capture, out_dir / "linear.zarr", **kwargs)
    return read_hdr(merge_capture(linear, out_dir / "hdr.zarr"))


def test_round_trip_through_simulated_dng_frames(tmp_path):
    """Known HDR Stokes -> sensor simulator (noise, clipping) -> DNG -> linearize + merge -> recovered within noise.

    Two views see the same scene with independent noise: their difference measures the noise, and the
    error against the truth must be no larger than that noise plus the demosaic's interpolation error.
    """
    import zarr

    capture, truth = simulated_capture(tmp_path / "capture")
    hdr = run_ingest(capture, tmp_path / "out", threads=2)
    assert hdr.view_ids == ["v0", "v1"] and hdr.intrinsics["width"] == 64
    assert hdr.analyzers.chunks == (1, 48, 64, 4, 3)
    linear = zarr.open_group(str(tmp_path / "out" / "linear.zarr"), mode="r")["linear"]
    blob = np.isnan(linear[0]).any(axis=(-2, -1))  # saturated at flash 1/4 ...
    assert blob.sum() >= 20 and np.isfinite(linear[1][blob]).all()  # ... but not at 1/8

    inner = (slice(2, -2), slice(2, -2))
    (merged, valid), (other, _) = hdr.view("v0"), hdr.view("v1")
    assert valid.all()
    s0_true = analyzers_to_stokes(truth, axis=-2)[..., 0, :]
    s0, s0_other = (analyzers_to_stokes(m, axis=-2)[..., 0, :] for m in (merged, other))
    error = (s0 / s0_true - 1)[inner]
    noise = np.sqrt(np.mean(((s0 - s0_other) / s0_true)[inner] ** 2) / 2)
    assert 0.003 < noise < 0.03
    assert abs(np.median(error)) < 0.004  # unbiased
    assert np.sqrt(np.mean(error ** 2)) < 1.15 * np.hypot(noise, 0.008)  # 0.008: bilinear interpolation (RMS)
    assert np.sqrt(np.mean((s0 / s0_true - 1)[blob] ** 2)) < 1.15 * np.hypot(noise, 0.008)

    stokes, stokes_true = analyzers_to_stokes(merged, axis=-2), analyzers_to_stokes(truth, axis=-2)
    dolp, dolp_true = (np.hypot(s[..., 1, :], s[..., 2, :]) / s[..., 0, :] for s in (stokes, stokes_true))
    assert np.median(np.abs(dolp - dolp_true)[inner]) < 0.01


def test_per_position_black_levels_leave_no_false_polarization(tmp_path):
    """A 4x4 black-level pattern in capture.yaml, a flat unpolarized grey scene: a mis-mapped black level
    would show up as polarization."""
    black = (np.arange(16).reshape(4, 4) * 7 + 40).tolist()
    sensor = SensorModel(width=48, height=32, black_level=tuple(map(tuple, black)))
    config = capture_config(sensor, plain_camera(48, 32))
    flat = np.full((32, 48, 4, 3), 0.02)  # dark, so black-level errors matter
    raws = {f"f{i}": simulate_raw(flat, sensor, 4000 * level, None, noise=False) for i, level in enumerate(LEVELS)}
    frames = pd.DataFrame({"frame_id": list(raws), "view_id": "v", "file": "", "flash_level": LEVELS,
                           "exposure_s": EXPOSURE_S})
    write_capture(tmp_path / "c", config, frames, raws, raw_format="tiff")
    merged, valid = run_ingest(tmp_path / "c", tmp_path / "out").view("v")
    assert valid.all()
    stokes = analyzers_to_stokes(merged, axis=-2)
    assert np.abs(stokes[..., 1:, :]).max() < 0.01 * stokes[..., 0, :].min()


def test_black_levels_from_raw_file_metadata(tmp_path):
    """--black-level-from file: a DNG's own 2x2 black levels, mapped through raw_colors, replace capture.yaml's."""
    pattern = [[40, 80], [120, 160]]
    sensor = SensorModel(width=48, height=32, black_level=0)
    config = capture_config(sensor, plain_camera(48, 32))
    with CaptureWriter(tmp_path / "c", config, raw_format="dng") as writer:
        for i, level in enumerate(LEVELS):
            signal = np.rint(np.full((32, 48), 2000 * level) + ingest.black_level_map(pattern, 32, 48))
            writer.add_frame(f"f{i}", "v", signal.astype(np.uint16), flash_level=level, exposure_s=EXPOSURE_S)
            write_dng_with_black_pattern(writer.path_in_capture(f"raw/f{i}.dng"), signal.astype(np.uint16),
                                         (0, 1, 1, 2), np.ravel(pattern), 4095)
        writer.finish()
    merged, _ = run_ingest(tmp_path / "c", tmp_path / "file",
                           settings=ingest.IngestSettings(black_level_from="file")).view("v")
    camera_rgb = merged[..., 0, :] @ np.linalg.inv(np.asarray(sensor.color_matrix)).T
    np.testing.assert_allclose(camera_rgb, 2000 / ((4095 - np.mean(pattern)) * EXPOSURE_S), rtol=1e-3)
    spread = lambda a: np.ptp(a[..., 0]) / np.mean(a[..., 0])  # 4 analyzers of red, one pixel
    assert spread(merged[10, 10]) < 1e-3
    merged_capture, _ = run_ingest(tmp_path / "c", tmp_path / "capture").view("v")
    assert spread(merged_capture[10, 10]) > 0.01  # with capture.yaml's black 0 the pattern leaks in


def test_msb_aligned_sixteen_bit_png_gives_the_same_hdr_as_twelve_bit_tiff(tmp_path):
    """12-bit data shifted to the top of 16-bit PNGs (bit_depth 16, white 65520, black x 16) ingests identically."""
    twelve = read_capture(simulated_capture(tmp_path / "c12", views=1, raw_format="tiff")[0])
    config = dict(twelve.config)
    config["sensor"] = {**twelve.sensor, "bit_depth": 16, "white_level": 65520, "black_level": 64 * 16}
    raws = {row.frame_id: read_raw_frame(twelve, row._asdict()) << 4 for row in twelve.frames.itertuples()}
    write_capture(tmp_path / "c16", config, twelve.frames, raws, raw_format="png")
    expected, valid = run_ingest(twelve.root, tmp_path / "o12").view("v0")
    merged, valid16 = run_ingest(tmp_path / "c16", tmp_path / "o16").view("v0")
    np.testing.assert_allclose(merged, expected, rtol=1e-5, atol=1e-3)
    assert (valid16 == valid).all()


# --------------------------------------------------------------------------- a real sensor frame


def test_real_mono_frame_agrees_with_polanalyser():
    """The IMX250MZR frame (shared/data): Stokes, DoLP and AoLP against polanalyser's demosaicing."""
    import polanalyser as pa  # test dependency (it needs OpenCV: opencv-python-headless)

    if not REAL_FRAME.is_file():
        pytest.skip(f"{REAL_FRAME} not present")
    sensor = {"width": 2448, "height": 2048, "bit_depth": 8, "black_level": 0, "white_level": 255}
    raw = read_raw_file(REAL_FRAME, sensor)
    plan = ingest.make_ingest_plan(sensor, {"fx": 2000.0, "fy": 2000.0, "cx": 1223.5, "cy": 1023.5},
                                   mosaic_layout(IMX250, "mono"), saturation=1.0)
    ours = analyzers_to_stokes(ingest.process_frame(raw, plan)[..., 0].astype(np.float64), axis=-1)

    images = pa.demosaicing(raw.astype(np.uint8), pa.COLOR_PolarMono)  # full resolution, I0 I45 I90 I135
    theirs = pa.calcLinearStokes([im / 255.0 for im in images], np.radians(ANALYZER_ANGLES_DEG))
    theirs = 0.25 * (theirs[0::2, 0::2] + theirs[1::2, 0::2] + theirs[0::2, 1::2] + theirs[1::2, 1::2])

    usable = np.isfinite(ours[..., 0]) & (theirs[..., 0] > 0.05) & (theirs[..., 0] < 0.9)
    assert usable.mean() > 0.5
    for k in range(3):
        diff = np.abs(ours[..., k] - theirs[..., k])[usable]
        assert np.median(diff) < 0.003 and np.percentile(diff, 99) < 0.01, k
    dolp = np.hypot(ours[..., 1], ours[..., 2]) / ours[..., 0]
    dolp_pa = pa.cvtStokesToDoLP(theirs)
    assert np.all((dolp[usable] >= 0) & (dolp[usable] <= 1))
    diff = np.abs(dolp - dolp_pa)[usable]
    assert np.median(diff) < 0.005 and np.percentile(diff, 99) < 0.03
    polarized = usable & (dolp_pa > 0.1)
    assert polarized.mean() > 0.1
    angle = np.abs(np.angle(np.exp(2j * (0.5 * np.arctan2(ours[..., 2], ours[..., 1])
                                         - pa.cvtStokesToAoLP(theirs)))) / 2)[polarized]
    assert np.degrees(np.median(angle)) < 0.5 and np.degrees(np.percentile(angle, 95)) < 3


def test_previews_code_aolp_as_hue_and_keep_dolp_in_range():
    from sellip.report.previews import dolp_aolp, preview_images

    angles = np.radians([0.0, 60.0, 120.0])
    stokes = np.stack([np.ones(3), 0.5 * np.cos(2 * angles), 0.5 * np.sin(2 * angles)], axis=-1)
    analyzers = np.repeat(stokes_to_analyzers(stokes, axis=-1)[None, :, :, None], 3, axis=-1)  # (1, 3, 4, 3)
    images = preview_images(analyzers, np.ones((1, 3), bool))
    np.testing.assert_array_equal(images["aolp"][0], [[255, 0, 0], [0, 255, 0], [0, 0, 255]])
    assert set(images) == {"s0", "dolp", "aolp", "diffuse", "specular"}
    inconsistent = np.array([1.0, 1.0, 0.0, 0.0])  # I0 = I45 = 1, I90 = I135 = 0: sqrt(s1^2 + s2^2) / s0 = 1.41
    dolp, aolp = dolp_aolp(analyzers_to_stokes(inconsistent))
    assert dolp == 1.0 and aolp == pytest.approx(np.pi / 8)


# --------------------------------------------------------------------------- bad inputs, CLI


def corrupt(capture: Path, how: str) -> str:
    """Damage frame v1_f1 of a 128x96 capture; returns the file name the error must mention."""
    target = capture / "raw" / "v1_f1.dng"
    if how == "truncated":
        target.write_bytes(target.read_bytes()[: target.stat().st_size // 3])
    elif how == "missing":
        target.unlink()
    else:  # a TIFF of another size in its place: transposed, or a few rows more than its view's other frames
        import tifffile

        target = target.with_suffix(".tiff")
        tifffile.imwrite(target, np.zeros({"wrong size": (128, 96), "mismatched sizes in a view": (100, 128)}[how],
                                          np.uint16))
        frames = pd.read_csv(capture / "frames.csv")
        frames.loc[frames["frame_id"] == "v1_f1", "file"] = "raw/v1_f1.tiff"
        frames.to_csv(capture / "frames.csv", index=False)
    return target.name


@pytest.mark.parametrize("how", ["truncated", "wrong size", "mismatched sizes in a view", "missing"])
def test_bad_frames_raise_naming_the_file_and_leave_nothing(tmp_path, how):
    capture, _ = simulated_capture(tmp_path / "capture", noise=False)
    name = corrupt(capture, how)
    output = tmp_path / "out" / "linear.zarr"
    with pytest.raises(CaptureError, match=name.replace(".", r"\.")):
        linearize_capture(capture, output, threads=2)
    assert not output.exists() and (not output.parent.exists() or list(output.parent.iterdir()) == [])


def test_cli_writes_stores_and_previews(tmp_path):
    import imageio.v3 as iio
    import zarr

    from sellip.cli import main
    from sellip.report.previews import PREVIEW_KINDS

    capture, _ = simulated_capture(tmp_path / "capture", views=1, raw_format="png",
                                   distortion=(-0.1, 0.02, 0.0, 0.0, 0.0))
    out = tmp_path / "results"
    assert main(["linearize", "--capture", str(capture), "--output", str(out / "linear.zarr"), "--threads", "2"]) == 0
    assert main(["merge-hdr", "--linear", str(out / "linear.zarr"), "--output", str(out / "hdr.zarr")]) == 0
    assert main(["hdr-previews", "--hdr", str(out / "hdr.zarr"), "--output", str(out / "previews")]) == 0
    group = zarr.open_group(str(out / "hdr.zarr"), mode="r")
    assert group["analyzers"].shape == (1, 48, 64, 4, 3) and group["analyzers"].dtype == np.float32
    assert group["valid"].shape == (1, 48, 64) and group["valid"].dtype == bool
    assert group.attrs["view_id"] == ["v0"] and group.attrs["intrinsics"]["cx"] == pytest.approx((63.5 - 0.5) / 2)
    names = sorted(p.name for p in (out / "previews").iterdir())
    assert names == sorted(f"v0_{kind}.png" for kind in PREVIEW_KINDS)
    s0 = iio.imread(out / "previews" / "v0_s0.png")
    assert s0.shape == (48, 64, 3) and s0.dtype == np.uint8 and s0.max() == 255
    assert main(["linearize", "--capture", str(tmp_path / "nowhere"), "--output", str(out / "x.zarr")]) == 1
