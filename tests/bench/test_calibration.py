"""The calibration-sensitivity benchmark's pieces (sellip.bench.calibration): the description perturbed as each row
says, a capture sharing the frames, what a description gets wrong, the noisy chart's matrix, the table."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from sellip.bench import calibration
from sellip.calibrate.synthetic import true_device


def _config(width=612):
    device = true_device(width, width * 512 // 612)
    return {**device, "scene": {"distance_m": 0.9}}


def test_every_change_lands_where_it_says():
    config = _config()
    flash = calibration.perturb_description(config, {"flash_mm": (2.0, 0.0, -5.0)})
    assert flash["light"]["position_m"] == pytest.approx([0.002, 0.05, -0.005])
    assert config["light"]["position_m"] == [0.0, 0.05, 0.0]  # the input is not changed
    turned = calibration.perturb_description(config, {"polarizer_deg": 3.0})
    assert turned["light"]["polarizer_deg"] == 3.0 and turned["camera"] == config["camera"]
    fx = calibration.perturb_description(config, {"fx_rel": 0.02})
    assert fx["camera"]["fx"] == pytest.approx(1.02 * config["camera"]["fx"])
    assert fx["camera"]["fy"] == pytest.approx(1.02 * config["camera"]["fy"])
    assert fx["camera"]["cx"] == config["camera"]["cx"]
    # pixel offsets are given at the device's full width and scaled to the capture's: 0.93 px at 2448 is 0.2325 at 612
    shifted = calibration.perturb_description(config, {"cx_px": -0.31, "cy_px": -0.93})
    assert shifted["camera"]["cy"] - config["camera"]["cy"] == pytest.approx(-0.93 / 4)
    assert shifted["camera"]["cx"] - config["camera"]["cx"] == pytest.approx(-0.31 / 4)
    colour = calibration.perturb_description(config, {"color_matrix": np.eye(3)})
    assert colour["camera"]["color_matrix"] == np.eye(3).tolist()
    # a whole calibrated device replaces the description's sections, the scene stays
    device = true_device(612, 512, polarizer_deg=1.0)
    device["camera"]["fx"] = 1800.0
    replaced = calibration.perturb_description(config, {"device": device})
    assert replaced["camera"]["fx"] == 1800.0 and replaced["light"]["polarizer_deg"] == 1.0
    assert replaced["scene"] == config["scene"]


def test_description_errors_of_the_full_size_row():
    truth = _config()
    wrong = calibration.perturb_description(truth, calibration.FULL_SIZE_ERRORS)
    errors = calibration.description_errors(wrong, truth)
    assert errors["fx_pct"] == pytest.approx(-0.004) and errors["cy_px"] == pytest.approx(-0.93 / 4)
    assert errors["flash_mm"] == pytest.approx([-0.09, -0.05, 1.32])
    assert errors["flash_error_mm"] == pytest.approx(np.linalg.norm([0.09, 0.05, 1.32]))
    assert errors["polarizer_deg"] == pytest.approx(0.002)
    # a polarizer angle is an axis: 179.9 deg is 0.1 deg from 0
    wrapped = calibration.perturb_description(truth, {"polarizer_deg": 179.9})
    assert calibration.description_errors(wrapped, truth)["polarizer_deg"] == pytest.approx(-0.1)


def test_perturbed_capture_shares_the_frames(tmp_path):
    capture = tmp_path / "capture"
    (capture / "raw").mkdir(parents=True)
    (capture / "raw" / "v000_f0.dng").write_bytes(b"frame")
    (capture / "frames.csv").write_text("frame_id\n")
    (capture / "capture.yaml").write_text(yaml.safe_dump(_config()))
    out = calibration.perturbed_capture(capture, tmp_path / "row" / "capture", {"fx_rel": 0.005})
    assert (out / "raw").is_symlink() and (out / "raw" / "v000_f0.dng").read_bytes() == b"frame"
    assert (out / "frames.csv").is_symlink() and not (out / "poses.csv").exists()
    changed = yaml.safe_load((out / "capture.yaml").read_text())
    assert changed["camera"]["fx"] == pytest.approx(1.005 * _config()["camera"]["fx"])


@pytest.mark.slow
def test_a_noisy_chart_gives_a_worse_matrix():
    """A chart shot with 8x the sensor noise: the fitted matrix moves off the true one and its mean ΔE2000 grows
    (measured at 612x512: 0.77 for the calibration set's chart, 1.31 for this one)."""
    device = true_device(612, 512)
    clean, clean_de = calibration.noisy_chart_matrix(device, noise_scale=1.0)
    noisy, noisy_de = calibration.noisy_chart_matrix(device, noise_scale=8.0)
    truth = np.asarray(device["camera"]["color_matrix"])
    assert noisy_de > clean_de and np.abs(noisy - truth).max() > np.abs(clean - truth).max()
    assert noisy_de < 3.0


def test_markdown_has_a_line_per_row():
    row = {"label": "true description", "eta_per_material_mean_pct": 0.5, "eta_per_material_max_pct": 1.2,
           "eta_vertex_median_pct": 1.0, "normal_median_deg": 0.8, "held_out_psnr_db": 26.1,
           "rho_d_relative_rmse": {"relative_rmse": 0.05}, "chamfer_mm": 0.031, "wall_s": 300.0}
    text = calibration.sensitivity_markdown([row, {**row, "label": "fx 2 % off", "held_out_psnr_db": None}])
    lines = text.splitlines()
    assert len(lines) == 4
    assert lines[2] == "| true description | 0.50 / 1.20 | 1.00 | 0.80 | 26.10 | 0.050 | 0.031 | 5.0 |"
    assert "| – |" in lines[3]
