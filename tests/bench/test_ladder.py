"""The accuracy ladder's figures (sellip.bench.ladder; the rungs themselves run in benchmarks/accuracy_ladder.py)."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.bench.ladder import WORKFLOW_RUNGS, capture_tag, eta_by_albedo_mode, figures, workflow_run_name
from sellip.capture.scenes import build_scene
from sellip.fit.records import STATUS_FITTED, STATUS_TOO_FEW_VIEWS


def test_figures_of_a_fit_on_the_true_mesh():
    truth = build_scene("tiny").mesh
    n = len(truth.vertices)
    eta = np.asarray(truth.params.eta, np.float64).copy()
    status = np.full(n, STATUS_FITTED)
    status[:10] = STATUS_TOO_FEW_VIEWS
    eta[:10] = 9.0  # unfitted rows do not count
    exact = figures({"status": status, "eta": eta, "normal": truth.normals}, truth)
    assert exact["fitted"] == n - 10 and exact["eta_vertex_median_pct"] == 0 and exact["normal_median_deg"] < 1e-6
    assert exact["eta_per_material"]["max_error_pct"] == 0
    biased = figures({"status": status, "eta": 1.02 * eta, "normal": truth.normals}, truth)
    assert biased["eta_per_material"]["mean_error_pct"] == pytest.approx(2.0)
    assert biased["eta_vertex_p90_pct"] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="no vertex"):
        figures({"status": np.full(n, STATUS_TOO_FEW_VIEWS), "eta": eta, "normal": truth.normals}, truth)



def test_eta_by_albedo_mode_splits_a_checker_material_by_its_true_albedo():
    """tiny's two materials each have a checker of two gains: each gets its two albedos, darkest first, with the
    signed error of their vertices' median eta; a material of many albedos (a photographed texture) gets none."""
    truth = build_scene("tiny").mesh
    material = np.asarray(truth.material)
    rho_d = np.asarray(truth.params.rho_d, np.float64)
    eta_true = np.asarray(truth.params.eta, np.float64)
    total = rho_d.sum(1)
    bright = total > np.array([np.ptp(total[material == m]) / 2 + total[material == m].min() for m in (0, 1)])[material]
    eta = eta_true * np.where(bright, 0.99, 1.02)  # the dark mode reads 2 % high, the bright 1 % low
    modes = eta_by_albedo_mode(eta, eta_true, material, rho_d)
    assert sorted(modes) == ["0", "1"]
    for m, rows in modes.items():
        assert len(rows) == 2 and sum(r["vertices"] for r in rows) == np.sum(material == int(m))
        assert np.sum(rows[0]["rho_d"]) < np.sum(rows[1]["rho_d"])
        assert rows[0]["error_pct"] == pytest.approx(2.0) and rows[1]["error_pct"] == pytest.approx(-1.0)
    speckled = rho_d * np.random.default_rng(0).uniform(0.5, 1.5, (len(rho_d), 1))
    assert eta_by_albedo_mode(eta, eta_true, material, speckled) == {}
    assert eta_by_albedo_mode(eta, eta_true, None, rho_d) == {}


@pytest.mark.slow
def test_psnr_ceiling_falls_when_the_truth_has_fewer_vertices(tmp_path):
    """The truth at its own vertices scores what the sensor and ingest leave; resampled on a coarse mesh, its checker
    texture blurs and the ceiling falls (measured at 320x256: 29.0 dB for the truth, 26.8 dB at 2,000 vertices,
    21.1 dB at 300)."""
    from sellip.bench.ladder import psnr_ceiling, resampled_truth
    from sellip.capture.hdr import merge_capture
    from sellip.capture.linearize import linearize_capture
    from sellip.capture.synthetic import synthesize_capture

    capture = synthesize_capture("tiny", tmp_path / "capture", views=4, width=320, height=256, seed=3, progress=False)
    hdr = merge_capture(linearize_capture(capture, tmp_path / "linear.zarr"), tmp_path / "hdr.zarr")
    truth = build_scene("tiny").mesh
    coarse = resampled_truth(truth, 300)
    assert 250 <= coarse.num_vertices <= 350
    assert set(np.unique(coarse.material)) == {0, 1}
    assert np.allclose(np.sort(np.unique(coarse.params.eta)), np.sort(np.unique(truth.params.eta)))
    full = psnr_ceiling(capture, hdr, ["v001", "v003"])
    reduced = psnr_ceiling(capture, hdr, ["v001", "v003"], vertices=300)
    assert full["vertices"] == truth.num_vertices and set(full["views"]) == {"v001", "v003"}
    assert full["mean_db"] > 26
    assert reduced["mean_db"] < full["mean_db"] - 5


@pytest.mark.slow
def test_render_rung_of_both_renderers_agrees_on_a_mitsuba_capture(tmp_path):
    """render_hdr draws the truth noise-free at the HDR grid with either renderer; on a scene both can draw
    (tiny_plain: no single scattering) the two agree pixel by pixel two pixels in from the silhouettes, which is
    what makes the render rung of a Mitsuba capture comparable with a sellip one. Measured at 4 views of 320x256
    (HDR grid 160x128, 16 samples a pixel): the median analyzer difference 0.04-0.1 % of the view's brightest
    pixel, the 99th percentile 0.6-1.6 % (the checker's edges under different sample patterns)."""
    pytest.importorskip("mitsuba")
    from scipy.ndimage import binary_erosion

    from sellip.bench.ladder import render_hdr
    from sellip.capture.hdr import merge_capture, read_hdr
    from sellip.capture.linearize import linearize_capture
    from sellip.capture.synthetic import synthesize_capture

    capture = synthesize_capture("tiny_plain", tmp_path / "capture", views=4, width=320, height=256, seed=5,
                                 progress=False)
    hdr = merge_capture(linearize_capture(capture, tmp_path / "linear.zarr"), tmp_path / "hdr.zarr")
    ours = read_hdr(render_hdr(capture, hdr, tmp_path / "sellip.zarr", supersample=4))
    theirs = read_hdr(render_hdr(capture, hdr, tmp_path / "mitsuba.zarr", supersample=4, renderer="mitsuba", batch=3))
    assert ours.view_ids == theirs.view_ids and len(ours.view_ids) == 4
    for v in range(4):
        a, b = np.asarray(ours.analyzers[v]), np.asarray(theirs.analyzers[v])
        assert np.asarray(theirs.valid[v]).all()
        inside = binary_erosion(a.sum(axis=(-1, -2)) > 0, iterations=2, border_value=0)
        assert inside.sum() > 800
        difference = np.abs(a - b)[inside].max(axis=(-1, -2)) / a[inside].max()
        assert np.median(difference) < 0.002 and np.percentile(difference, 99) < 0.03, v
    with pytest.raises(ValueError, match="renderer"):
        render_hdr(capture, hdr, tmp_path / "other.zarr", renderer="blender")


def test_a_workflow_rung_with_other_settings_is_a_run_of_its_own():
    """Each setting other than its default names its own results folder, so a rung never reuses a cached run of
    other settings; the README's figures (sellip.bench.figures) find the runs by the same names."""
    tag = capture_tag("cow_painted", 72, 1224, 1024, "mitsuba", 3)
    assert tag == "cow_painted_72v_1224x1024_mitsuba_seed3"
    assert capture_tag("sphere_ior", 72, 1224, 1024) == "sphere_ior_72v_1224x1024"
    names = {workflow_run_name(tag, rung, iterations, vertices, hull)
             for rung in WORKFLOW_RUNGS for iterations in (1, 3) for vertices in (None, 10000) for hull in (None, 128)}
    assert len(names) == 3 * 2 * 2 * 2
    assert workflow_run_name("s", "hull", 3, 30000) == "s_hull_3it_30000v"  # the sphere_ior row's folder
    assert workflow_run_name("s", "sfm", 3, 10000, 128, "_slope0.4") == "s_sfm_3it_10000v_hull128_slope0.4"
    with pytest.raises(ValueError, match="not a workflow rung"):
        workflow_run_name("s", "render", 1)
