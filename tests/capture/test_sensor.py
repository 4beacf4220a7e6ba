"""Sensor simulation: mosaic sampling, levels, saturation, noise statistics, colour matrix."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.capture.sensor import DEFAULT_COLOR_MATRIX, SensorModel, camera_rgb_from_srgb, mosaic_sample, simulate_raw


def _labelled_analyzers(height, width):
    """Analyzer images whose value encodes (analyzer a, colour c) as 100 * (a + 1) + 10 * (c + 1)."""
    a = np.arange(4)[:, None]
    c = np.arange(3)[None, :]
    return np.broadcast_to(100.0 * (a + 1) + 10.0 * (c + 1), (height, width, 4, 3)).copy()


def test_mosaic_follows_the_imx250myr_layout():
    """2x2 polarizer cell [[90, 45], [135, 0]] under an RGGB Bayer of 2x2 cells (docs/design.md §3)."""
    sensor = SensorModel(width=8, height=8)
    raw = mosaic_sample(_labelled_analyzers(8, 8), sensor.layout)
    angle_index = {0: 0, 45: 1, 90: 2, 135: 3}
    for row, col, angle, colour in [(0, 0, 90, 0), (0, 1, 45, 0), (1, 0, 135, 0), (1, 1, 0, 0),
                                    (0, 2, 90, 1), (2, 0, 90, 1), (2, 3, 45, 2), (3, 3, 0, 2), (7, 7, 0, 2)]:
        assert raw[row, col] == 100 * (angle_index[angle] + 1) + 10 * (colour + 1), (row, col)


def test_mono_sensor_sees_luminance_with_a_2x2_period():
    sensor = SensorModel(width=8, height=8, color_layout="mono")
    analyzers = np.zeros((8, 8, 4, 3))
    analyzers[..., 0, :] = 1.0  # only I0, white
    raw = simulate_raw(analyzers, sensor, scale=1000.0, rng=None, noise=False)
    assert raw[1, 1] == 64 + 1000 and raw[3, 3] == 64 + 1000 and raw[0, 0] == 64


def test_noise_free_levels_black_white_and_colour_matrix():
    sensor = SensorModel(width=16, height=16, black_level=[[60 + i + 4 * j for i in range(4)] for j in range(4)])
    white = np.ones((16, 16, 4, 3))
    raw = simulate_raw(white * 0.0, sensor, scale=1000.0, rng=None, noise=False)
    np.testing.assert_array_equal(raw, sensor.black_map())
    raw = simulate_raw(white, sensor, scale=1000.0, rng=None, noise=False)
    expected_rgb = np.rint(camera_rgb_from_srgb(np.ones(3), DEFAULT_COLOR_MATRIX) * 1000)
    assert expected_rgb == pytest.approx([550, 1000, 750], abs=1)
    colour = sensor.layout.color_map(16, 16)
    np.testing.assert_array_equal(raw, np.rint(expected_rgb[colour] + sensor.black_map()))
    saturated = simulate_raw(white, sensor, scale=1e6, rng=np.random.default_rng(0))
    assert np.all(saturated == sensor.white_level)


def test_shot_and_read_noise_statistics():
    sensor = SensorModel(width=256, height=256, color_layout="mono", gain_e_per_dn=2.5, read_noise_e=3.0)
    analyzers = np.full((256, 256, 4, 3), 1.0)  # every analyzer sees 1 -> 500 DN at scale 500
    raw = simulate_raw(analyzers, sensor, scale=500.0, rng=np.random.default_rng(1)).astype(np.float64)
    signal = raw - 64
    expected_var = 500 / 2.5 + (3.0 / 2.5) ** 2 + 1 / 12  # shot + read + quantisation, in DN^2
    assert signal.mean() == pytest.approx(500, abs=0.2)
    assert signal.var() == pytest.approx(expected_var, rel=0.03)
    dark = simulate_raw(analyzers * 0, sensor, scale=500.0, rng=np.random.default_rng(2)).astype(np.float64)
    assert dark.std() == pytest.approx(np.sqrt((3.0 / 2.5) ** 2 + 1 / 12), rel=0.1)


def test_same_seed_same_raw_and_different_seed_different_raw():
    sensor = SensorModel(width=32, height=32)
    analyzers = np.random.default_rng(0).uniform(0, 1, (32, 32, 4, 3))
    a = simulate_raw(analyzers, sensor, 2000.0, np.random.default_rng(5))
    b = simulate_raw(analyzers, sensor, 2000.0, np.random.default_rng(5))
    c = simulate_raw(analyzers, sensor, 2000.0, np.random.default_rng(6))
    assert a.dtype == np.uint16 and np.array_equal(a, b) and not np.array_equal(a, c)


def test_capture_sensor_section_is_valid_capture_yaml():
    from sellip.capture.capture_yaml import validate_config

    sensor = SensorModel(width=64, height=48)
    config = {"sensor": sensor.capture_sensor(), "camera": {"fx": 60.0, "fy": 60.0, "cx": 32.0, "cy": 24.0},
              "light": {"position_m": [0, 0.05, 0], "polarizer_deg": 0}, "scene": {"distance_m": 0.9}}
    assert validate_config(config)["sensor"]["polarizer_layout"] == [[90, 45], [135, 0]]
