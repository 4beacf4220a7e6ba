"""How careful a calibration must be, on whole reconstructions (issue #39 item 7): the workflow run on one synthetic
capture of ``sphere_ior`` shot by the synthetic device of ``sellip synth-calibration``, once per description of that
device: the truth (with two noise seeds, the noise floor), the truth with one error put in (flash position,
flash polarizer angle, fx, a colour matrix from a noisy chart), and the description ``sellip calibrate`` measured on
a synthetic calibration set of the same device (docs/calibration.md, "How careful to be").

Public API::

    Perturbation(label, change)                       # one row: a change of the capture.yaml description
    PERTURBATIONS                                     # the rows of the table, in the order they run (telling first)
    FULL_SIZE_ERRORS                                  # what the calibration got wrong at 2448x2048, seed 1
    MITSUBA_FULL_SIZE_ERRORS                          # likewise on Mitsuba 3's frames, seed 0
    perturb_description(config, change, width=None) -> dict       # capture.yaml's dict with ``change`` applied
    perturbed_capture(capture, out, change) -> Path   # a capture sharing the frames, capture.yaml changed
    noisy_chart_matrix(device, noise_scale, seed) -> (matrix (3, 3), delta_e_mean)
    calibrate_synthetic_set(folder, spec=BoardSpec()) -> (device, record)   # the four steps on a synth set
    description_errors(device, truth) -> dict         # fx %, cx/cy px, flash mm, polarizer deg of a description
    sensitivity_config(capture, views, max_vertices, iterations, jax_cache) -> dict   # the workflow's override
    sensitivity_row(label, results, capture, wall_s, cpu_s) -> dict            # figures of one finished run
    sensitivity_markdown(rows) -> str
    run_sensitivity(work, views=36, width=612, height=512, ...) -> list[dict]   # everything, resumable

A ``change`` (mapping) may hold: ``flash_mm`` (dx, dy, dz added to light.position_m, camera coordinates),
``polarizer_deg`` (added to light.polarizer_deg), ``fx_rel`` (fx and fy times 1 + this), ``cx_px`` / ``cy_px``
(added, in raw pixels at 2448 wide: scaled to the capture's width), ``color_matrix`` (3x3, replaces
camera.color_matrix) and ``device`` (sensor / camera / light sections replacing the description's: a calibrated
device.yaml). Keys are applied in that order.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

log = logging.getLogger(__name__)

DEVICE_WIDTH_PX = 2448


class Perturbation(NamedTuple):
    """One row of the table: its label and the change of the description (module docstring); ``noise_seed`` of
    the capture it runs on (the frames' noise), ``kind`` "fixed" or "chart" (a colour matrix calibrated on a noisy
    chart) or "calibrated" (the description measured by :func:`calibrate_synthetic_set`)."""

    label: str
    change: Mapping = {}
    noise_seed: int = 0
    kind: str = "fixed"


FULL_SIZE_ERRORS = {"fx_rel": -0.00004, "cx_px": -0.31, "cy_px": -0.93, "flash_mm": (-0.09, -0.05, 1.32),
                    "polarizer_deg": 0.002}
"""The errors of ``sellip calibrate`` on the synthetic device at its full size (2448x2048), seed 1, the worse of
the two measured sets (docs/calibration.md, "Measured accuracy"): fx -0.004 %, cx -0.31 px, cy -0.93 px, the
flash (-0.09, -0.05, +1.32) mm, the polarizer 0.002 deg."""

MITSUBA_FULL_SIZE_ERRORS = {"fx_rel": -0.000013, "cx_px": 0.07, "cy_px": 0.35, "flash_mm": (0.00, 0.14, -0.73),
                            "polarizer_deg": 0.03}
"""The errors of ``sellip calibrate`` on Mitsuba 3's frames of the synthetic device at its full size (2448x2048,
seed 0, the recommended protocol: 96 board poses, spheres resting on the board, bracketed sphere frames;
docs/calibration.md, "An independent renderer at full size"): fx -0.001 %, cx +0.07 px, cy +0.35 px, the flash
(+0.00, +0.14, -0.73) mm, the polarizer +0.03 deg; measured before the corners were refined on the full-resolution
mosaic (the same set now: cx -0.17 px, cy +0.05 px)."""

PERTURBATIONS: tuple[Perturbation, ...] = (
    Perturbation("true description", {}),
    Perturbation("true description, noise seed 1", {}, noise_seed=1),
    Perturbation("calibrated at 612x512 (sellip calibrate)", kind="calibrated"),
    Perturbation("full-size calibration's errors (seed 1)", FULL_SIZE_ERRORS),
    Perturbation("flash 10 mm off (x)", {"flash_mm": (10.0, 0.0, 0.0)}),
    Perturbation("polarizer 3 deg off", {"polarizer_deg": 3.0}),
    Perturbation("fx 2 % off", {"fx_rel": 0.02}),
    Perturbation("colour matrix from a noisy chart", kind="chart"),
    Perturbation("fx 0.5 % off", {"fx_rel": 0.005}),
    Perturbation("flash 5 mm off (x)", {"flash_mm": (5.0, 0.0, 0.0)}),
    Perturbation("polarizer 1 deg off", {"polarizer_deg": 1.0}),
    Perturbation("flash 2 mm off (x)", {"flash_mm": (2.0, 0.0, 0.0)}),
    Perturbation("flash 5 mm off (z)", {"flash_mm": (0.0, 0.0, 5.0)}),
    Perturbation("Mitsuba full-size calibration's errors (seed 0)", MITSUBA_FULL_SIZE_ERRORS),
)

CHART_NOISE_SCALE = 8.0
"""The noisy chart: the real sensor's noise x this at the same exposure (1/64 of the photons)."""


def perturb_description(config: Mapping, change: Mapping, width: int | None = None) -> dict:
    """A copy of capture.yaml's dict ``config`` with ``change`` applied (module docstring); ``width``: the raw width
    the pixel offsets are scaled to (default: the config's sensor width)."""
    config = copy.deepcopy(dict(config))
    if "device" in change:
        for section in ("sensor", "camera", "light"):
            if section in change["device"]:
                config[section] = {**config.get(section, {}), **copy.deepcopy(change["device"][section])}
    if "flash_mm" in change:
        config["light"]["position_m"] = [
            float(p) + float(d) / 1000 for p, d in zip(config["light"]["position_m"], change["flash_mm"], strict=True)]
    if "polarizer_deg" in change:
        config["light"]["polarizer_deg"] = float(config["light"].get("polarizer_deg", 0.0)) + change["polarizer_deg"]
    if "fx_rel" in change:
        for key in ("fx", "fy"):
            config["camera"][key] = float(config["camera"][key]) * (1 + float(change["fx_rel"]))
    scale = (width or int(config["sensor"]["width"])) / DEVICE_WIDTH_PX
    for key in ("cx", "cy"):
        if f"{key}_px" in change:
            config["camera"][key] = float(config["camera"][key]) + float(change[f"{key}_px"]) * scale
    if "color_matrix" in change:
        config["camera"]["color_matrix"] = [[float(v) for v in row] for row in np.asarray(change["color_matrix"])]
    return config


def perturbed_capture(capture: str | Path, out: str | Path, change: Mapping) -> Path:
    """A capture folder at ``out`` sharing ``capture``'s frames, poses and ground truth (symlinks), with
    capture.yaml changed by :func:`perturb_description`."""
    import yaml

    capture, out = Path(capture).resolve(), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("frames.csv", "poses.csv", "raw", "ground_truth"):
        if (capture / name).exists() and not (out / name).exists():
            os.symlink(capture / name, out / name)
    config = perturb_description(yaml.safe_load((capture / "capture.yaml").read_text()), change)
    (out / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return out


def noisy_chart_matrix(device: Mapping, noise_scale: float = CHART_NOISE_SCALE, seed: int = 0
                       ) -> tuple[np.ndarray, float]:
    """The colour matrix :func:`sellip.calibrate.color.calibrate_color` fits to a ColorChecker frame of ``device``
    shot as ``sellip synth-calibration`` shoots it, with the sensor noise x ``noise_scale``; and its mean ΔE2000."""
    from sellip.calibrate import synthetic
    from sellip.calibrate.color import calibrate_color
    from sellip.capture.sensor import sensor_from_device, simulate_raw

    device = copy.deepcopy(dict(device))
    width = int(device["sensor"]["width"])
    rng = np.random.default_rng([seed, 30])
    rotation = synthetic.look_at(np.zeros(3), 10.0, rng)
    distance = 1.1 * 6 * synthetic.CHART_PATCH_M * device["camera"]["fx"] / (0.8 * width)
    translation = np.array([0.0, 0.0, distance]) - rotation @ synthetic.chart_corners_board().mean(axis=0)
    analyzers = synthetic.render_chart(device, rotation, translation)
    white = device["sensor"]["white_level"] - float(np.max(device["sensor"]["black_level"]))
    sensor = sensor_from_device(device["sensor"], device["camera"]["color_matrix"]).with_noise_scale(noise_scale)
    raw = simulate_raw(analyzers, sensor, 0.6 * white / float(np.percentile(analyzers, 99.9)),
                       np.random.default_rng([seed, 31]))
    corners = synthetic.project(device, synthetic.chart_corners_board() @ rotation.T + translation)
    result = calibrate_color(raw, device, corners)
    return np.asarray(result.matrix), float(np.mean(result.delta_e))


def calibrate_synthetic_set(folder: str | Path, spec=None) -> tuple[dict, dict]:
    """The four steps of ``sellip calibrate`` (intrinsics, flash -- on the spheres resting on the board when the
    folder has them --, polarization with --write, colour) on a folder of ``sellip synth-calibration``, from its
    sensor.yaml; returns the device (sensor, camera, light) and a record of
    each step's residuals."""
    import yaml

    from sellip.calibrate import synthetic
    from sellip.calibrate.board_spheres import calibrate_flash_on_board
    from sellip.calibrate.color import calibrate_color
    from sellip.calibrate.flash import calibrate_flash
    from sellip.calibrate.intrinsics import calibrate_intrinsics
    from sellip.calibrate.polarization import check_polarization
    from sellip.capture.reader import read_raw_file

    folder = Path(folder)
    spec = spec or synthetic.BoardSpec()
    truth = yaml.safe_load((folder / "truth.yaml").read_text())
    device = {"sensor": yaml.safe_load((folder / "sensor.yaml").read_text())["sensor"]}

    def frames(sub: str) -> dict:
        return {p.name: read_raw_file(p, device["sensor"]) for p in sorted((folder / sub).iterdir())}

    board = calibrate_intrinsics(frames("board"), device["sensor"], spec.cols, spec.rows, spec.square_m)
    device["camera"] = board.camera()
    radius = float(truth["spheres"]["radius_m"])
    spheres = frames("spheres")
    device["calibration"] = {"intrinsics": {"std_px": board.std}}
    if (folder / "board_spheres").is_dir():  # spheres resting on the board: their centres from its pose
        flash = calibrate_flash_on_board(frames("board_spheres"), device, radius, spec.cols, spec.rows, spec.square_m)
    else:
        flash = calibrate_flash(spheres, device, radius)
    del device["calibration"]
    device["light"] = {"position_m": flash.position_m.tolist(), "polarizer_deg": 0.0}
    report = check_polarization(spheres, device, radius)
    device["sensor"]["polarizer_layout"] = report.best_layout
    device["light"]["polarizer_deg"] = float(report.polarizer_deg)
    chart = truth["chart"]
    color = calibrate_color(read_raw_file(folder / "chart" / chart["file"], device["sensor"]), device,
                            np.asarray(chart["corners_px"], np.float64))
    device["camera"]["color_matrix"] = np.asarray(color.matrix).tolist()
    record = {"board_rms_px": float(board.rms_px), "flash_rms_mm": float(flash.rms_mm),
              "layout_ok": bool(report.ok), "delta_e_mean": float(np.mean(color.delta_e))}
    return device, record


def description_errors(device: Mapping, truth: Mapping) -> dict:
    """What a description gets wrong against the true one: fx and fy (%), cx and cy (raw px), the flash position
    (mm, per axis and its length), the flash polarizer (deg)."""
    cam, true_cam = device["camera"], truth["camera"]
    flash = 1000 * (np.asarray(device["light"]["position_m"], float) - np.asarray(truth["light"]["position_m"], float))
    return {"fx_pct": 100 * (cam["fx"] / true_cam["fx"] - 1), "fy_pct": 100 * (cam["fy"] / true_cam["fy"] - 1),
            "cx_px": cam["cx"] - true_cam["cx"], "cy_px": cam["cy"] - true_cam["cy"],
            "flash_mm": flash.tolist(), "flash_error_mm": float(np.linalg.norm(flash)),
            "polarizer_deg": (float(device["light"].get("polarizer_deg", 0.0))
                              - float(truth["light"].get("polarizer_deg", 0.0)) + 90) % 180 - 90}


def sensitivity_config(capture: str | Path, views: int, max_vertices: int, iterations: int,
                       jax_cache: str | Path, held_out: int = 4) -> dict:
    """The override of config/config.yaml for one row: the capture, ``iterations`` iterations, at most
    ``max_vertices`` vertices, ``held_out`` views held out (evenly spread), the shared XLA cache."""
    from sellip.bench.stability import held_out_views

    return {"capture": str(capture), "name": "run", "iterations": int(iterations),
            "init": {"max_vertices": int(max_vertices)}, "fit": {"compilation_cache": str(jax_cache)},
            "evaluate": {"held_out_views": held_out_views(views, held_out), "render_views": ["v000"], "supersample": 1}}


def sensitivity_row(label: str, results: str | Path, capture: str | Path, wall_s: float, cpu_s: float) -> dict:
    """One row from a finished run (results/NAME with metrics.json): η per material (mean and worst error of the
    per-material medians, %), η per vertex median (%), normal median (deg), held-out PSNR (dB), ρd relative RMSE,
    Chamfer distance (mm), and the description's errors against the capture's true one
    (``synthetic.true_description``)."""
    import yaml

    from sellip.report.metrics import headline_figures

    metrics = json.loads((Path(results) / "metrics.json").read_text())
    figures = headline_figures(metrics)
    config = yaml.safe_load((Path(capture) / "capture.yaml").read_text())
    truth = config.get("synthetic", {}).get("true_description")
    return {"label": label, **{k: v for k, v in figures.items() if k != "eta_per_material"},
            "eta_per_material": {k: v["error_pct"] for k, v in
                                 ((figures["eta_per_material"] or {}).get("materials") or {}).items()},
            "rho_d_relative_rmse": metrics.get("rho_d_relative_rmse"),
            "chamfer_mm": (metrics.get("geometry") or {}).get("chamfer_mm"),
            "vertices": (metrics.get("vertices") or {}).get("model"),
            "errors": description_errors(config, truth) if truth else None, "wall_s": wall_s, "cpu_s": cpu_s}


def _fmt(value, spec: str = ".2f") -> str:
    return "–" if value is None or (isinstance(value, float) and not np.isfinite(value)) else format(value, spec)


def sensitivity_markdown(rows: list[Mapping]) -> str:
    """The table of docs/calibration.md: one line per row."""
    header = ("| description | η per material: mean / worst error % | η per vertex median % | normal median ° | "
              "held-out PSNR dB | ρd rel. RMSE | Chamfer mm | wall min |")
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rho = r.get("rho_d_relative_rmse")
        rho = rho.get("relative_rmse") if isinstance(rho, Mapping) else rho
        lines.append(f"| {r['label']} | {_fmt(r['eta_per_material_mean_pct'])} / {_fmt(r['eta_per_material_max_pct'])}"
                     f" | {_fmt(r['eta_vertex_median_pct'])} | {_fmt(r['normal_median_deg'])} | "
                     f"{_fmt(r['held_out_psnr_db'])} | {_fmt(rho, '.3f')} | {_fmt(r.get('chamfer_mm'), '.3f')} | "
                     f"{_fmt(r['wall_s'] / 60, '.1f')} |")
    return "\n".join(lines) + "\n"


def _true_capture(work: Path, scene: str, views: int, device: Mapping, noise_seed: int) -> Path:
    import yaml

    from sellip.capture.synthetic import synthesize_capture

    capture = work / f"capture_noise{noise_seed}"
    if not (capture / "capture.yaml").is_file():
        synthesize_capture(scene, capture, views=views, device=device, noise_seed=noise_seed, progress=False)
        config = yaml.safe_load((capture / "capture.yaml").read_text())
        # copies: the same objects would be written as YAML aliases, read back as one dict, and perturbed together
        config["synthetic"]["true_description"] = copy.deepcopy({k: config[k] for k in ("sensor", "camera", "light")})
        (capture / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return capture


def run_sensitivity(work: str | Path, scene: str = "sphere_ior", views: int = 36, width: int = 612,
                    height: int = 512, max_vertices: int = 10000, iterations: int = 2, cores: int = 2,
                    rows: tuple[Perturbation, ...] = PERTURBATIONS, calibration_seed: int = 0) -> list[dict]:
    """Every row of ``rows`` (resumable: a row whose ``rows/<k>/row.json`` exists is read back; k its index in
    :data:`PERTURBATIONS`, else in ``rows``), one workflow run
    each on the capture of its noise seed (:func:`_true_capture`: ``scene`` shot by the synthetic device of
    ``sellip synth-calibration`` at ``width`` x ``height``), capture.yaml changed; writes ``work/rows.json`` and
    ``work/table.md``; returns the rows.

    Long: it drives the whole benchmark (captures, the calibration set, the noisy chart, one run per row)."""
    import yaml

    from sellip.calibrate import synthetic

    work = Path(work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    device = synthetic.true_device(width, height)
    done = []
    for k, row in enumerate(rows):
        folder = work / "rows" / f"{PERTURBATIONS.index(row) if row in PERTURBATIONS else k:02d}"
        if (folder / "row.json").is_file():
            kept = json.loads((folder / "row.json").read_text())
            if kept["label"] == row.label:  # its figures read again from its run (columns added since get filled)
                fresh = sensitivity_row(row.label, folder / "results" / "run", folder / "capture", kept["wall_s"],
                                        kept["cpu_s"])
                done.append({**kept, **fresh})
                (folder / "row.json").write_text(json.dumps(done[-1], indent=1))
                continue
        try:
            done.append(_run_row(work, folder, row, f"[{k + 1}/{len(rows)}]", scene, views, max_vertices, iterations,
                                 cores, device, calibration_seed))
        except Exception:  # one failed row must not lose the others: logged, no row.json, re-run next time
            log.exception("%s failed", row.label)
            continue
        _write_tables(work, done)
    _write_tables(work, done)
    (work / "size.yaml").write_text(yaml.safe_dump({"scene": scene, "views": views, "width": width, "height": height,
                                                    "max_vertices": max_vertices, "iterations": iterations,
                                                    "cores": cores, "at": time.strftime("%Y-%m-%d %H:%M")}))
    return done


def _run_row(work: Path, folder: Path, row: Perturbation, tag: str, scene: str, views: int, max_vertices: int,
             iterations: int, cores: int, device: Mapping, calibration_seed: int) -> dict:
    from sellip.bench.sweep import SnakemakeRunner
    from sellip.calibrate import synthetic_set

    width, height = int(device["sensor"]["width"]), int(device["sensor"]["height"])
    capture = _true_capture(work, scene, views, device, row.noise_seed)
    change = dict(row.change)
    extra = {}
    if row.kind == "calibrated":
        calib = work / "calibration"
        if not (calib / "truth.yaml").is_file():
            synthetic_set.synthesize_calibration(calib, width, height, seed=calibration_seed, raw_format="tiff")
        calibrated, extra = calibrate_synthetic_set(calib)
        change["device"] = calibrated
    elif row.kind == "chart":
        change["color_matrix"], delta_e = noisy_chart_matrix(device)
        extra = {"delta_e_mean": delta_e, "chart_noise_scale": CHART_NOISE_SCALE}
    described = perturbed_capture(capture, folder / "capture", change)
    config = sensitivity_config(described, views, max_vertices, iterations, work / "jax_cache")
    log.info("%s %s: snakemake, log %s", tag, row.label, folder / "snakemake.log")
    wall, cpu = SnakemakeRunner(folder, cores=cores)(config, [], folder / "snakemake.log")
    result = sensitivity_row(row.label, folder / "results" / "run", described, wall, cpu)
    result.update(extra)
    (folder / "row.json").write_text(json.dumps(result, indent=1))
    log.info("%s: %s", row.label, json.dumps({key: result[key] for key in (
        "eta_per_material_mean_pct", "eta_per_material_max_pct", "normal_median_deg", "held_out_psnr_db", "wall_s")}))
    return result


def _write_tables(work: Path, rows: list[dict]) -> None:
    (work / "rows.json").write_text(json.dumps(rows, indent=1))
    (work / "table.md").write_text(sensitivity_markdown(rows))
