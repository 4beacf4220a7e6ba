"""The synthetic example of docs/calibration.md end to end, on one synthetic device: ``sellip synth-calibration``
(board, spheres, chart at 612x512, real DNG files) -> the four ``sellip calibrate`` commands -> device.yaml; an
object capture shot by that same device (``sellip synth --device truth.yaml``), its raw frames renamed as a camera
names them and turned into a capture by ``sellip capture new`` from the frame files alone -> a real
``snakemake --cores 2`` run of the workflow (one iteration) -> metrics.json against the capture's ground truth."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from helpers import session_jax_cache

REPO = Path(__file__).resolve().parents[2]
VIEWS = 16
FLASH_SETTINGS = {"f0": 4, "f1": 8, "f2": 16}
"""The synthetic capture's frames per view (flash levels 1/4, 1/8, 1/16) as a camera names them: by the flash's
"1/N power" setting, which is all ``sellip capture new --pattern '{view}_f{level}.dng'`` reads."""


def _sellip(*args: str) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "sellip.cli", *args], capture_output=True, text=True, check=False)
    assert result.returncode == 0, \
        f"sellip {' '.join(args[:2])} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


def _config(capture: Path, name: str, jax_cache: Path) -> dict:
    """The workflow's overrides: one iteration, at most 2500 vertices, two shards (tests/workflow/test_workflow.py's
    tiny run, at this capture's 612x512)."""
    return {"capture": str(capture), "name": name, "iterations": 1,
            "init": {"hull_resolution": 64, "max_vertices": 2500},
            "observe": {"vertex_chunk": 256, "max_slope": 0.0},
            "fit": {"shards": 2, "compilation_cache": str(jax_cache), "settings": {"min_views": 6}},
            "augment": {"max_samples": 4096},
            "evaluate": {"held_out_views": ["v003", "v011"], "render_views": ["v000"], "supersample": 1}}


def _snakemake(workdir: Path, config: dict) -> None:
    override = workdir / f"{config['name']}.yaml"
    override.write_text(yaml.safe_dump(config))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--cores", "2", "--configfile", str(REPO / "config" / "config.yaml"), str(override)]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=1500, check=False)
    assert result.returncode == 0, f"snakemake failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"


@pytest.mark.slow
def test_calibrate_capture_new_snakemake_metrics(tmp_path):
    # 1. the calibration set and device.yaml, by the commands of docs/calibration.md
    calib = tmp_path / "calib"
    _sellip("synth-calibration", "--out", str(calib), "--width", "612", "--height", "512", "--board-frames", "16")
    truth = yaml.safe_load((calib / "truth.yaml").read_text())
    device = tmp_path / "device.yaml"
    shutil.copy(calib / "sensor.yaml", device)
    boards = sorted(str(p) for p in (calib / "board").glob("*.dng"))
    spheres = sorted(str(p) for p in (calib / "spheres").glob("*.dng"))
    on_board = sorted(str(p) for p in (calib / "board_spheres").glob("*.dng"))
    radius_mm = str(truth["spheres"]["radius_m"] * 1000)
    # a quarter of the device's size cannot meet the full-size targets (docs/calibration.md): relaxed, as the docs do
    _sellip("calibrate", "intrinsics", *boards, "--device", str(device), "--board", "14x10", "--square-mm", "10",
            "--max-c-std-px", "5")
    # the flash from spheres resting on the board (its pose fixes their centres), relaxed as the docs do at this size
    _sellip("calibrate", "flash", *on_board, "--device", str(device), "--sphere-radius-mm", radius_mm,
            "--board", "14x10", "--square-mm", "10", "--max-flash-std-mm", "10")
    _sellip("calibrate", "polarization", *spheres, "--device", str(device), "--sphere-radius-mm", radius_mm)
    _sellip("calibrate", "color", str(calib / "chart" / truth["chart"]["file"]), "--device", str(device),
            "--corners", *(f"{x},{y}" for x, y in truth["chart"]["corners_px"]))
    calibrated = yaml.safe_load(device.read_text())
    assert set(calibrated["calibration"]) == {"intrinsics", "flash", "polarization", "color"}

    # 2. an object shot by the same device; its raw frames alone make the capture
    shot = tmp_path / "shot"
    _sellip("synth", "--scene", "tiny", "--views", str(VIEWS), "--seed", "3", "--device", str(calib / "truth.yaml"),
            "--out", str(shot), "--no-progress")
    shot_camera = yaml.safe_load((shot / "capture.yaml").read_text())["camera"]
    assert all(np.allclose(shot_camera[key], value) for key, value in truth["device"]["camera"].items())
    capture = tmp_path / "owl"
    (capture / "raw").mkdir(parents=True)
    for path in sorted((shot / "raw").glob("*.dng")):
        view, level = path.stem.rsplit("_", 1)
        shutil.copy(path, capture / "raw" / f"{view}_f{FLASH_SETTINGS[level]}.dng")
    shutil.copy(shot / "poses.csv", capture / "poses.csv")  # a calibrated rig's poses
    shutil.copytree(shot / "ground_truth", capture / "ground_truth")  # for metrics.json only
    _sellip("capture", "new", str(capture / "raw"), "--device", str(device), "--distance-m", "0.9",
            "--pattern", "{view}_f{level}.dng")  # the exposure time: the DNGs' ExposureTime tag
    written = yaml.safe_load((capture / "capture.yaml").read_text())
    assert written["camera"] == calibrated["camera"] and written["light"] == calibrated["light"]
    frames = pd.read_csv(capture / "frames.csv")
    assert len(frames) == 3 * VIEWS and sorted(frames["flash_level"].unique()) == [1 / 16, 1 / 8, 1 / 4]
    assert np.allclose(frames["exposure_s"], 0.005)

    # 3. the workflow on it, to the end; its figures against the capture's ground truth
    work = tmp_path / "work"
    work.mkdir()
    _snakemake(work, _config(capture, "owl", session_jax_cache(tmp_path)))
    metrics = json.loads((work / "results" / "owl" / "metrics.json").read_text())
    assert metrics["capture"] == str(capture) or metrics["capture"].endswith("owl")
    figures = {"normal_median_deg": metrics["normal_error_deg"]["all"]["median"],
               "eta_median_pct": metrics["eta_relative_error_pct"]["median"],
               "chamfer_mm": metrics["geometry"]["chamfer_mm"], "psnr_held_out_db": metrics["psnr_held_out"]["mean_db"]}
    print("calibrated description:", json.dumps(figures))
    # Measured 2026-11-26 (docs/calibration.md, "The synthetic example"), three runs of this test: normal median 5.40-
    # 5.41 deg, eta median 2.5, 5.1 and 4.8 %, Chamfer 1.04-1.05 mm, held-out PSNR 16.9-17.2 dB; the same frames
    # with the TRUE description: 2.5 deg, 0.3 %, 0.17 mm, 19.6 dB. The gap is the quarter-size calibration's corner
    # bias (fx +0.37 %, cx +4.8 px: at 612x512 a board square is 8-15 pixels of the intensity image), not noise; the
    # benchmark's table has it on sphere_ior. Bounds that catch a broken chain (a lost calibration, a wrong unit, a
    # misread flash level), not targets.
    assert figures["normal_median_deg"] < 7.0 and figures["eta_median_pct"] < 8.0
    assert figures["chamfer_mm"] < 1.5 and figures["psnr_held_out_db"] > 15.0
