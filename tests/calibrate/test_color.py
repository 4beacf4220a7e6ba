"""The colour step on rendered ColorChecker frames (612x512, the sensor simulator's noise): the chart found
without corners and its order checked, the flash's fall-off and sheen taken out, and a frame that cannot give
a colour matrix failing with its cause."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sellip.calibrate import color, synthetic
from sellip.calibrate.intrinsics import CalibrationError

W, H = 612, 512


def _chart(tilt_deg=(10.0, 0.0), fill=0.8, peak=0.6, shadow=1.0, sheen=0.0, seed=0, roll_deg=0.0):
    """(device, raw, true corners (4, 2), (R, t)) of a chart turned by ``roll_deg`` in its plane and tilted by
    ``tilt_deg`` (about x, y), whose patch area spans ``fill`` of the frame's width (its long side), exposed so
    that the lit chart's 99.9th percentile reads ``peak`` of full scale."""
    device = synthetic.true_device(W, H)
    rotation = Rotation.from_euler("zxy", (roll_deg, *tilt_deg), degrees=True).as_matrix()
    distance = 6 * synthetic.CHART_PATCH_M * device["camera"]["fx"] / (fill * W)
    translation = np.array([0.0, 0.0, distance]) - rotation @ synthetic.chart_corners_board().mean(axis=0)
    lit = synthetic.render_chart(device, rotation, translation, sheen=sheen)
    shown = lit * np.float32(shadow)
    white = device["sensor"]["white_level"] - float(np.max(device["sensor"]["black_level"]))
    raw = synthetic.expose(shown, device, peak * white, np.random.default_rng(seed),
                           reference=float(np.percentile(lit, 99.9)))
    corners = synthetic.project(device, synthetic.chart_corners_board() @ rotation.T + translation)
    return device, raw, corners, (rotation, translation)


@pytest.fixture(scope="module")
def tilted():
    """A chart tilted 25° at 0.6 m, the flash 5 cm below the lens: its irradiance varies by about 20 %."""
    return _chart(tilt_deg=(25.0, 8.0), fill=0.75)


def test_chart_found_without_corners_in_the_documented_order(tilted):
    device, raw, corners, _ = tilted
    result = color.calibrate_color(raw, device)  # no corners: cv2.mcc finds the chart, the colours fix its order
    # dark skin's corner first, then clockwise: each found corner lies by its true one (a patch pitch is ~75 px)
    assert np.linalg.norm(result.corners_px - corners, axis=1).max() < 10.0
    assert np.nanmean(result.delta_e) <= 1.5 and not result.left_out


@pytest.mark.parametrize("roll_deg", [180.0, 90.0])
def test_a_chart_upside_down_or_on_its_side_is_found_in_the_documented_order(roll_deg):
    device, raw, corners, _ = _chart(roll_deg=roll_deg, fill=0.8 if roll_deg == 180 else 0.55)
    result = color.calibrate_color(raw, device)
    assert np.linalg.norm(result.corners_px - corners, axis=1).max() < 15.0  # dark skin's corner is still first
    assert np.nanmean(result.delta_e) <= 1.5


def test_falloff_follows_the_charts_pose_and_is_divided_out(tilted):
    device, raw, corners, (rotation, translation) = tilted
    falloff = color.chart_falloff(corners, device, synthetic.CHART_PATCH_M)
    i, j = np.divmod(np.arange(24), 6)
    centres = np.stack([(j + 0.5), (i + 0.5), np.zeros(24)], -1) * synthetic.CHART_PATCH_M @ rotation.T + translation
    to_light = np.asarray(device["light"]["position_m"]) - centres
    d = np.linalg.norm(to_light, axis=-1)
    truth = np.abs(to_light @ rotation[:, 2]) / d ** 3
    np.testing.assert_allclose(falloff, truth / truth.mean(), rtol=2e-3)
    assert falloff.max() / falloff.min() > 1.15  # a fall-off that matters
    result = color.calibrate_color(raw, device, corners)
    assert np.nanmean(result.delta_e) <= 0.5
    # without the correction (a flat fall-off) the same frame fits far worse
    stats = color.patch_stats(color.analyzer_images(raw, device["sensor"]), corners)
    reference = color.reference_srgb()
    m = color.fit_color_matrix(stats.rgb, reference)
    assert np.mean(color.delta_e_2000(stats.rgb @ m.T, reference)) > 2 * np.nanmean(result.delta_e)


def test_given_corners_in_another_order_are_named(tilted):
    device, raw, corners, _ = tilted
    result = color.calibrate_color(raw, device, corners[::-1])
    assert np.nanmean(result.delta_e) > 5
    causes = color.corner_order_causes(raw, device, corners[::-1], 1.5)
    assert causes and "counter-clockwise, dark skin's corner given as number 4" in causes[0]


def test_sheen_of_the_polarized_flash_is_taken_out():
    device, raw, corners, _ = _chart(tilt_deg=(0.0, 0.0), sheen=1.0)  # facing the camera: the flash mirrored
    stats = color.patch_stats(color.analyzer_images(raw, device["sensor"]), corners)
    assert np.median(stats.polarized[:, 1] / stats.rgb[:, 1]) > 2 * color.SHEEN_MIN
    result = color.calibrate_color(raw, device, corners)
    assert np.nanmean(result.delta_e) <= 0.5 and np.nanmax(result.sheen) > color.SHEEN_MIN
    # with the sheen left in (the fall-off still divided out) the fit misses the target
    reference = color.reference_srgb()
    camera = stats.rgb / color.chart_falloff(corners, device, synthetic.CHART_PATCH_M)[:, None]
    m = color.fit_color_matrix(camera, reference)
    assert np.mean(color.delta_e_2000(camera @ m.T, reference)) > 1.5
    # a patch more than 20 % polarized (the black one here) is named as a cause when a fit misses its target
    assert "reflect the flash's polarized sheen (" in color.corner_order_causes(raw, device, corners, 1.5)[0]


@pytest.mark.parametrize("case, match", [
    ("dark", r"too dark"),  # found or not, each frame's cause is named
    ("saturated", r"\(saturated samples\): lower the flash|of the frame is saturated: lower the flash"),
    ("small", r"no ColorChecker 24 found.*fill a good part of the frame"),
])
def test_a_chart_that_cannot_be_found_fails_naming_the_cause(case, match):
    kwargs = {"dark": {"shadow": 0.02}, "saturated": {"peak": 6.0}, "small": {"fill": 0.12}}[case]
    device, raw, corners, _ = _chart(**kwargs)
    with pytest.raises(CalibrationError, match=match):
        color.calibrate_color(raw, device)


def test_given_corners_of_a_chart_too_small_dark_or_saturated_name_the_patches():
    device, raw, corners, _ = _chart(fill=0.08)
    with pytest.raises(CalibrationError, match=r"too small: \d+ cells sampled, expected at least 16"):
        color.calibrate_color(raw, device, corners)
    device, raw, corners, _ = _chart(peak=6.0)
    with pytest.raises(CalibrationError, match=r"clipped \(saturated samples\): lower the flash"):
        color.calibrate_color(raw, device, corners)


def test_color_command_finds_the_chart_gates_and_records(tmp_path, tilted):
    """``sellip calibrate color`` without --corners writes the matrix, ΔE and the corners it found; a dark frame
    fails naming the cause and leaves device.yaml as it was."""
    import subprocess
    import sys

    import yaml

    from sellip.capture import writer

    device, raw, corners, _ = tilted
    device_path = tmp_path / "device.yaml"
    device_path.write_text(yaml.safe_dump({k: device[k] for k in ("sensor", "camera", "light")}, sort_keys=False))
    writer.write_raw_file(tmp_path / "chart.dng", raw, device["sensor"])
    run = [sys.executable, "-m", "sellip.cli", "calibrate", "color", "--device", str(device_path)]
    subprocess.run(run + [str(tmp_path / "chart.dng")], check=True, capture_output=True, text=True)
    record = yaml.safe_load(device_path.read_text())["calibration"]["color"]
    assert record["ok"] and record["delta_e2000_mean"] <= 1.5 and record["targets"]["delta_e_mean"] == 1.5
    assert np.abs(np.asarray(record["corners_px"]) - corners).max() < 10.0
    assert record["falloff_range"][1] / record["falloff_range"][0] > 1.15
    before = device_path.read_bytes()
    _, dark, _, _ = _chart(tilt_deg=(25.0, 8.0), fill=0.75, shadow=0.02)
    writer.write_raw_file(tmp_path / "dark.dng", dark, device["sensor"])
    failed = subprocess.run(run + [str(tmp_path / "dark.dng")], check=False, capture_output=True, text=True)
    assert failed.returncode != 0 and "too dark" in failed.stderr and device_path.read_bytes() == before
    # a target the fit cannot meet: the step fails, names the target, writes nothing
    failed = subprocess.run(run + [str(tmp_path / "chart.dng"), "--max-delta-e-mean", "0.01"], check=False,
                            capture_output=True, text=True)
    assert failed.returncode != 0 and "(--max-delta-e-mean)" in failed.stderr and device_path.read_bytes() == before
