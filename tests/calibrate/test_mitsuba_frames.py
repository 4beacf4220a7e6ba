"""Calibration frames drawn by Mitsuba 3 (sellip.calibrate.renderers, an independent renderer) are read by the
``sellip calibrate`` commands as the docs give them. Skipped without mitsuba (the ``test`` extra)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

pytest.importorskip("mitsuba")

W, H = 612, 512


def test_mitsuba_board_lands_where_sellips_does():
    """The same board pose drawn by both renderers (320x256, the pinhole device): the same image up to the paper's
    brightness (Mitsuba's diffuse has the 1/pi that sellip's albedo has not, and no diffuse polarization): camera,
    principal point and texture conventions agree (correlation of s0 > 0.99; OpenCV's corners of the two within
    0.08 px on average: measured 0.037, at most 0.23)."""
    import cv2

    from sellip.calibrate import synthetic
    from sellip.calibrate.renderers import frame_renderer

    spec = synthetic.BoardSpec()
    with frame_renderer("mitsuba") as mitsuba:
        device = mitsuba.device(320, 256, 0.0)
        rotation, translation = synthetic.board_poses(spec, device, 1, np.random.default_rng(3))[0]
        drawn = mitsuba.board(device, spec, rotation, translation).sum(axis=(2, 3))
    own = synthetic.render_board(device, spec, rotation, translation).sum(axis=(2, 3))
    assert np.corrcoef(drawn.ravel(), own.ravel())[0, 1] > 0.99
    corners = []
    for image in (drawn, own):
        found, points = cv2.findChessboardCornersSB(np.uint8(np.clip(255 * image / image.max(), 0, 255)),
                                                    (spec.cols, spec.rows), flags=cv2.CALIB_CB_ACCURACY)
        assert found
        corners.append(points.reshape(-1, 2))
    offset = np.linalg.norm(corners[0] - corners[1], axis=1)
    assert offset.mean() < 0.08, offset  # a half-pixel slip of the principal point's convention gives 0.5


@pytest.mark.slow
def test_mitsuba_calibration_set_is_read_by_the_calibrate_commands(tmp_path):
    """``sellip synth-calibration --renderer mitsuba`` writes the folder of sellip's renderer (8 board poses and a
    chart, 612x512); ``calibrate intrinsics`` finds fx within 1 % of the truth (measured: −0.13 %) and the lens
    without distortion; ``calibrate color`` finds the varnished chart and fits it within ΔE2000 1.5 (measured 0.59)."""
    folder = tmp_path / "calib"
    subprocess.run([sys.executable, "-m", "sellip.cli", "synth-calibration", "--out", str(folder), "--width", str(W),
                    "--height", str(H), "--board-frames", "8", "--sphere-frames", "0", "--board-sphere-frames", "0",
                    "--renderer", "mitsuba"], check=True, timeout=900)
    truth = yaml.safe_load((folder / "truth.yaml").read_text())
    assert truth["renderer"].startswith("mitsuba")
    camera = truth["device"]["camera"]
    assert camera["distortion"] == [0.0] * 5 and camera["fx"] == camera["fy"]
    boards = sorted(str(p) for p in (folder / "board").iterdir())
    assert len(boards) == 8 and all(b.endswith(".dng") for b in boards)
    device_path = tmp_path / "device.yaml"
    device_path.write_text((folder / "sensor.yaml").read_text())
    run = [sys.executable, "-m", "sellip.cli", "calibrate"]
    # 8 poses at a quarter of the device's size: the principal point's 1-sigma is a few pixels; relaxed
    subprocess.run(run + ["intrinsics", *boards, "--device", str(device_path), "--board", "14x10", "--square-mm", "10",
                          "--max-c-std-px", "10", "--max-f-std-pct", "1"], check=True, timeout=600)
    device = yaml.safe_load(device_path.read_text())
    assert abs(device["camera"]["fx"] / camera["fx"] - 1) < 0.01, device["camera"]
    assert abs(device["camera"]["fy"] / camera["fy"] - 1) < 0.01, device["camera"]
    assert abs(device["camera"]["distortion"][0]) < 0.1, device["camera"]["distortion"]
    subprocess.run(run + ["color", str(folder / "chart" / truth["chart"]["file"]), "--device", str(device_path)],
                   check=True, timeout=600)
    record = yaml.safe_load(device_path.read_text())["calibration"]["color"]
    assert record["ok"] and record["delta_e2000_mean"] <= 1.5
    found = np.asarray(record["corners_px"])
    assert np.abs(found - np.asarray(truth["chart"]["corners_px"])).max() < 15
