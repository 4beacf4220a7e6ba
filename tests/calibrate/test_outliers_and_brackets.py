"""The flash step drops outlier highlights and refits; the polarization check reads the diffuse light of dark
spheres in a long exposure (the bracket NAME / NAME_long) and still names no layout when the cues disagree."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from sellip.calibrate import board_spheres, flash_fit, polarization, synthetic, synthetic_set
from sellip.calibrate.intrinsics import CalibrationError
from sellip.capture import reader, writer

W, H = 612, 512
BOARD = (14, 10, 0.01)


def _lines(rng, count=18, noise_m=5e-4):
    """Mirror lines (points, unit directions (N, 3)) through a flash at (0, 50, 0) mm from spheres at 0.4-0.55 m
    over the field, each line moved sideways by ``noise_m`` (1-sigma per axis)."""
    target = np.array([0.0, 0.05, 0.0])
    points = np.column_stack([rng.uniform(-0.15, 0.15, count), rng.uniform(-0.12, 0.12, count),
                              rng.uniform(0.4, 0.55, count)])
    directions = target - points
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for k in range(count):  # sideways, across the line
        points[k] += (np.eye(3) - np.outer(directions[k], directions[k])) @ rng.normal(0, noise_m, 3)
    return target, points, directions


def test_leave_one_out_drops_the_outlier_and_the_refit_lands_on_the_flash():
    """18 lines with 0.5 mm of scatter and one 40 mm off (a sphere a square off): the leave-one-out test drops
    exactly that line (far beyond 5 sigma), and the refit is within 1 mm.
    Clean lines lose none; the test never drops below the minimum number of highlights."""
    rng = np.random.default_rng(3)
    target, points, directions = _lines(rng)
    keep, dropped = flash_fit.drop_outliers(points, directions)
    assert keep.all() and dropped == []
    points[4] += (np.eye(3) - np.outer(directions[4], directions[4])) @ np.array([0.04, 0.0, 0.0])
    keep, dropped = flash_fit.drop_outliers(points, directions)
    assert [d.index for d in dropped] == [4] and dropped[0].ratio > 20
    refit, *_ = flash_fit.nearest_point(points[keep], directions[keep])
    assert np.linalg.norm(refit - target) < 1e-3
    keep, dropped = flash_fit.drop_outliers(points[:6], directions[:6], min_lines=6)
    assert keep.all() and dropped == []


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """The board protocol's 6 pairs at 612x512 (sellip's renderer, seed 0, no other frames) and its truth."""
    out = synthetic_set.synthesize_calibration(tmp_path_factory.mktemp("pairs") / "set", W, H, seed=0, board_frames=0,
                                               sphere_frames=0, raw_format="tiff")
    return out, yaml.safe_load((out / "truth.yaml").read_text())


@pytest.mark.slow
def test_a_sphere_off_its_square_is_dropped_named_and_the_flash_refitted(pairs, monkeypatch):
    """One sphere of spheres_02 set down 3 mm off its square's centre (rendered so): its silhouette still fits
    that square (intersection over union above 0.6), so its centre is taken 3 mm off and its mirror line passes
    some 100 mm from the flash. The step drops it, names frame and sphere, and the refit lands where the clean set's
    does (within 1 mm) and within 3 sigma of the truth; kept in (no outlier test), it pulls the flash by more than
    5 mm."""
    out, truth = pairs
    device = copy.deepcopy(truth["device"])
    sensor, radius = device["sensor"], truth["board_spheres"]["radius_m"]
    frames = {p.name: reader.read_raw_file(p, sensor) for p in sorted((out / "board_spheres").iterdir())}
    clean = board_spheres.calibrate_flash_on_board(frames, device, radius, *BOARD)
    assert clean.dropped == 0 and len(clean.highlights) == 18

    name = "spheres_02.tiff"
    pose = truth["board_spheres"]["poses"][name]
    rotation, translation = np.asarray(pose["rotation"]), np.asarray(pose["translation_m"])
    marks = np.asarray(truth["board_spheres"]["marks_m"][name])
    marks[0] += [0.003, 0.0]
    spheres = [(board_spheres.sphere_centre(rotation, translation, m, radius), radius) for m in marks]
    board = synthetic.render_board(device, synthetic.BoardSpec(), rotation, translation)
    image = synthetic.render_spheres(device, spheres, reflect_panel=False, background=board)
    white = sensor["white_level"] - float(np.max(sensor["black_level"]))
    frames[name] = synthetic.expose(image, device, 0.75 * white, np.random.default_rng(1), reference=float(image.max()))
    logged = []
    result = board_spheres.calibrate_flash_on_board(frames, device, radius, *BOARD, log=logged.append)
    assert result.dropped == 1 and len(result.highlights) == 17
    (label, why), = [(k, v) for k, v in result.left_out.items() if "dropped as an outlier" in v]
    assert label.startswith("spheres_02.tiff#") and "sigma of their residual" in why
    assert any(line.startswith(label) and "dropped as an outlier" in line for line in logged)
    assert any("1 highlight(s) dropped as outliers" in c for c in result.causes())
    error = result.position_m - np.asarray(device["light"]["position_m"])
    assert np.linalg.norm(result.position_m - clean.position_m) < 1e-3
    assert np.all(np.abs(error) <= 3 * result.std_m), (error, result.std_m)

    monkeypatch.setattr(flash_fit, "OUTLIER_SIGMA", np.inf)
    kept = board_spheres.calibrate_flash_on_board(frames, device, radius, *BOARD)
    assert kept.dropped == 0 and np.linalg.norm(kept.position_m - clean.position_m) > 5e-3


DARK_BALL = {**synthetic.SPHERE_PARAMS, "rho_d": (0.01, 0.01, 0.01)}
"""A black ball whose highlight stands 6x higher over its diffuse light than the calibration set's (rho_d 0.06): like
Mitsuba's black ball, a frame exposed for the highlight leaves its diffuse light near 0.5 % of full scale."""


@pytest.fixture(scope="module")
def dark_spheres(tmp_path_factory):
    """3 layouts of 3 dark glossy spheres before the panel at 612x512 (sellip's renderer), each as a bracket:
    NAME.tiff exposed for the highlights (peak at 75 % of full scale, ExposureTime 10 ms), NAME_long.tiff 16x
    brighter (160 ms, the highlights and the panel clipped), NAME_mid.tiff 3x (30 ms, the panel below white),
    NAME_flat.tiff: exposed as NAME, recording 80 ms (a flash whose
    pulse the shutter does not lengthen), and NAME_hot.tiff: 400x brighter, the diffuse light clipped too. Returns
    (folder, device, radius)."""
    folder = tmp_path_factory.mktemp("dark")
    device = synthetic.true_device(W, H)
    sensor = device["sensor"]
    white = sensor["white_level"] - float(np.max(sensor["black_level"]))
    radius = 0.6 * synthetic.SPHERE_RADIUS_M
    rng = np.random.default_rng([7, 20])
    for k, centres in enumerate(synthetic.sphere_layouts(device, 3, rng, radius=radius)):
        image = synthetic.render_spheres(device, [(c, radius) for c in centres], params=DARK_BALL)
        peak = float(image.max())
        for suffix, gain, seconds in (("", 1, 0.01), ("_long", 16, 0.16), ("_mid", 3, 0.03), ("_flat", 1, 0.08),
                                      ("_hot", 400, 4.0)):
            raw = synthetic.expose(image, device, gain * 0.75 * white, np.random.default_rng([7, k, gain, len(suffix)]),
                                   reference=peak)
            writer.write_raw_file(folder / f"spheres_{k:02d}{suffix}.tiff", raw, sensor, exposure_s=seconds)
    return folder, device, radius


def _bracket(folder, sensor, suffixes, stand_in="_long"):
    """({name: raw}, {name: ExposureTime}) of the frames spheres_<suffix>.tiff, ``stand_in`` frames named as the
    long ones."""
    paths = [p for p in sorted(folder.iterdir()) if p.stem[len("spheres_"):] in suffixes]
    names = {p: p.name.replace(stand_in, "_long") for p in paths}
    return ({names[p]: reader.read_raw_file(p, sensor) for p in paths},
            {names[p]: reader.exposure_time(p) for p in paths})


@pytest.mark.slow
def test_dark_spheres_need_the_long_exposure_and_cues_that_disagree_still_fail(dark_spheres):
    """Exposed for the highlights alone, the dark spheres' diffuse light cannot tell the layouts apart and the
    check fails naming none (and saying to shoot NAME_long); with the long exposures it names the right layout by
    more than the margin and measures the flash polarizer on the short frames' highlights. A claim turned by 90 deg
    with the flash polarizer claimed 90 deg off still fails with the cues disagreeing. A "long" frame no brighter
    than its sphere frame is left out, quoting the ExposureTime that says otherwise; so is a long frame of another
    layout."""
    folder, device, radius = dark_spheres
    sensor = device["sensor"]
    short, _ = _bracket(folder, sensor, {"00", "01", "02"})
    assert len(short) == 3
    with pytest.raises(CalibrationError, match="cannot tell the polarizer layouts apart") as failed:
        polarization.check_polarization(short, device, radius)
    assert "(0 long exposures)" in str(failed.value) and "NAME_long" in str(failed.value)

    frames, exposures = _bracket(folder, sensor, {"00", "01", "02", "00_long", "01_long", "02_long"})
    logged = []
    report = polarization.check_polarization(frames, device, radius, log=logged.append, exposures=exposures)
    assert report.ok and report.best_layout == sensor["polarizer_layout"] and report.long_frames == 3
    assert report.best_score - report.second_score > polarization.MIN_SCORE_MARGIN
    assert abs(report.polarizer_error_deg) < 0.5 and report.highlights == 9
    assert 0.02 < report.diffuse_level < 0.5
    assert any("spheres_00_long.tiff: the diffuse light of spheres_00.tiff's spheres" in line for line in logged)

    turned = copy.deepcopy(device)
    turned["sensor"]["polarizer_layout"] = [[0, 135], [45, 90]]
    turned["light"]["polarizer_deg"] = 90.0
    with pytest.raises(CalibrationError, match="the cues disagree"):
        polarization.check_polarization(frames, turned, radius, exposures=exposures)
    frames["spheres_09_long.tiff"] = frames["spheres_00_long.tiff"]
    report = polarization.check_polarization(frames, device, radius, exposures=exposures)
    assert report.ok and report.left_out["spheres_09_long.tiff"].startswith("a long exposure without its sphere frame")
    swapped = dict(frames)
    swapped["spheres_01_long.tiff"] = frames["spheres_02_long.tiff"]
    report = polarization.check_polarization(swapped, device, radius, exposures=exposures)
    assert report.ok and report.long_frames == 2
    assert "not the layout of spheres_01.tiff" in report.left_out["spheres_01_long.tiff"]  # its band clips
    mid, exposures = _bracket(folder, sensor, {"00", "01", "02", "00_mid", "01_mid", "02_mid"}, "_mid")
    assert polarization.check_polarization(mid, device, radius, exposures=exposures).long_frames == 3
    mid["spheres_01_long.tiff"] = mid["spheres_02_long.tiff"]
    with pytest.raises(CalibrationError, match="(2 long exposures)") as failed:  # two 3x brackets cannot decide
        polarization.check_polarization(mid, device, radius, exposures=exposures)
    assert ("spheres_01_long.tiff: not the layout of spheres_01.tiff: around its sphere #0 this frame ranks"
            in str(failed.value))

    flat, exposures = _bracket(folder, sensor, {"00", "01", "02", "00_flat", "01_flat", "02_flat"}, "_flat")
    with pytest.raises(CalibrationError, match="cannot tell the polarizer layouts apart") as failed:
        polarization.check_polarization(flat, device, radius, exposures=exposures)
    assert "(0 long exposures)" in str(failed.value)
    assert "spheres_00_long.tiff: only " in str(failed.value)
    assert ("x as bright on the spheres as spheres_00.tiff (ExposureTime 0.08 s against 0.01 s: 8x): a flash's pulse "
            "is shorter than the shutter") in str(failed.value)
    hot, exposures = _bracket(folder, sensor, {"00", "01", "02", "00_hot", "01_hot", "02_hot"}, "_hot")
    with pytest.raises(CalibrationError, match="cannot tell the polarizer layouts apart") as failed:
        polarization.check_polarization(hot, device, radius, exposures=exposures)
    assert "spheres_01_long.tiff: " in str(failed.value)
    assert "of the spheres' diffuse band saturated" in str(failed.value)
