"""The renderer comparison's figures (sellip.bench.renderers): the share of vertices given single scattering their
ground truth does not have, overall and per material, from model and ground-truth PLY files."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.bench.renderers import (
    false_single_scattering,
    renderer_markdown,
    single_scattering_shares,
)
from sellip.capture.scenes import build_scene
from sellip.model.ply import write_param_mesh
from sellip.model.render import ParamMesh


def test_false_single_scattering_counts_lobes_the_truth_does_not_have(tmp_path):
    truth = build_scene("pplastic_set").mesh  # four materials, no single scattering anywhere
    write_param_mesh(tmp_path / "truth.ply", truth)
    material = np.asarray(truth.material)
    rho_ss = np.zeros((truth.num_vertices, 3))
    rho_ss[material == 1, 2] = 0.05          # all of material 1 gets a lobe on one channel
    first_of_2 = np.flatnonzero(material == 2)[: (material == 2).sum() // 4]
    rho_ss[first_of_2] = 0.01                 # a quarter of material 2
    model = ParamMesh(truth.vertices * 1.001, truth.faces, truth.normals, truth.params._replace(rho_ss=rho_ss))
    write_param_mesh(tmp_path / "model.ply", model)
    found = false_single_scattering(tmp_path / "model.ply", tmp_path / "truth.ply")
    assert found["vertices"] == truth.num_vertices
    assert found["share"] == pytest.approx(((material == 1).sum() + len(first_of_2)) / truth.num_vertices)
    assert found["per_material"]["0"] == 0 and found["per_material"]["1"] == 1
    assert found["per_material"]["2"] == pytest.approx(len(first_of_2) / (material == 2).sum())
    row = {"case": "c", "scene": "pplastic_set", "renderer": "mitsuba", "eta_per_material": {"0": (1.49, 1.5, 0.67)},
           "normal_median_deg": 1.0, "normal_mean_deg": 2.0, "psnr_held_out_db": None,
           "false_ss_share": found["share"], "false_ss_per_material": found["per_material"]}
    table = renderer_markdown([row]).splitlines()
    assert len(table) == 3 and "1.490 → 1.500 (0.67)" in table[2] and "1: 100.0 %" in table[2]


def test_a_truth_with_single_scattering_has_no_false_positives_there(tmp_path):
    truth = build_scene("tiny").mesh  # its rough half has single scattering
    write_param_mesh(tmp_path / "truth.ply", truth)
    rho_ss = np.full((truth.num_vertices, 3), 0.1)
    write_param_mesh(tmp_path / "model.ply", ParamMesh(truth.vertices, truth.faces, truth.normals,
                                                       truth.params._replace(rho_ss=rho_ss)))
    found = false_single_scattering(tmp_path / "model.ply", tmp_path / "truth.ply")
    has_ss = np.asarray(truth.params.rho_ss).max(axis=1) > 0
    assert found["vertices"] == int((~has_ss).sum()) and found["share"] == 1.0 and list(found["per_material"]) == ["0"]
    assert found["recall"] == 1.0 and found["recall_vertices"] == int(has_ss.sum())
    assert list(found["recall_per_material"]) == ["1"]


def test_single_scattering_shares_count_false_lobes_and_recall_apart():
    truth_ss = np.array([False, False, False, False, True, True, True, True])
    has_ss = np.array([True, False, False, False, True, True, False, False])
    label = np.array([0, 0, 1, 1, 2, 2, 2, 2])
    found = single_scattering_shares(has_ss, truth_ss, label)
    assert found["share"] == 0.25 and found["vertices"] == 4 and found["per_material"] == {"0": 0.5, "1": 0.0}
    assert found["recall"] == 0.5 and found["recall_vertices"] == 4 and found["recall_per_material"] == {"2": 0.5}
    none = single_scattering_shares(has_ss[:4], truth_ss[:4])
    assert none["recall"] is None and none["recall_per_material"] == {} and none["per_material"] == {}
