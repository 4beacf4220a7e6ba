"""Convergence of the outer loop (issue #54 item 1): the geometry update's verdict, the jobs that pass their inputs
through once it says converged (hard links, markers, a summary marked passed through), `sellip pass-through` running
the job's own command otherwise, and metrics.json's record of where the loop converged."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from sellip import cli
from sellip.fit.convergence import PASSED_THROUGH, ConvergenceSettings, judge, loop_convergence, pass_through

EDGE = 1e-3  # a 1 mm mean edge


def _verdict(iteration=4, offset_edges=0.005, eta_change=0.0005, poses=None, **settings):
    offsets = np.full(100, offset_edges * EDGE)
    eta_before = np.full(100, 1.5)
    eta = eta_before * (1 + eta_change * np.where(np.arange(100) % 2, 1, -1))
    return judge(iteration, offsets, EDGE, eta, eta_before, None, poses, ConvergenceSettings(**settings))


def test_converged_when_every_measure_is_within_its_limit_from_min_iterations_on():
    verdict = _verdict()
    assert verdict["converged"] and verdict["iteration"] == 4 and verdict["reason"].startswith("converged")
    assert verdict["offset_edges"] == pytest.approx(0.005) and verdict["eta_change"] == pytest.approx(0.0005)
    assert "rotation_deg" not in verdict  # the poses are not refined: not a measure
    assert not _verdict(iteration=1)["converged"]  # iteration 1 < min_iterations 3 - 1
    assert _verdict(iteration=2)["converged"]  # the third iteration may converge
    assert "min_iterations" in _verdict(iteration=1)["reason"]


@pytest.mark.parametrize("change, words", [({"offset_edges": 0.02}, "the surface's median step (edges) 0.02 > 0.01"),
                                           ({"eta_change": 0.003}, "eta's median relative change 0.003 > 0.001")])
def test_a_measure_over_its_limit_keeps_the_loop_running_and_says_which(change, words):
    verdict = _verdict(**change)
    assert not verdict["converged"] and verdict["iteration"] is None and words in verdict["reason"]


def test_a_region_still_moving_keeps_the_loop_running_while_the_median_rests():
    """2 % of the vertices (a hollow being carved) still step by half an edge: the median step is within its limit,
    the 99th percentile is not."""
    offsets = np.where(np.arange(1000) < 20, 0.5, 0.002) * EDGE
    eta = np.full(1000, 1.5)
    verdict = judge(4, offsets, EDGE, eta, eta, None, None)
    assert verdict["offset_edges"] == pytest.approx(0.002) and verdict["offset_p99_edges"] == pytest.approx(0.5)
    assert not verdict["converged"] and "the surface's 99th-percentile step (edges) 0.5 > 0.1" in verdict["reason"]
    assert judge(4, np.minimum(offsets, 0.05 * EDGE), EDGE, eta, eta, None, None)["converged"]


def test_the_poses_count_where_they_are_refined_and_nothing_unmeasured_converges():
    turning = _verdict(poses={"rotation_deg": {"median": 0.05}})
    assert not turning["converged"] and "the poses' median rotation (deg) 0.05 > 0.01" in turning["reason"]
    assert _verdict(poses={"rotation_deg": {"median": 0.004}})["converged"]
    assert not _verdict(poses={"rotation_deg": None})["converged"]  # no view refined: not measured
    first = judge(3, np.zeros(10), EDGE, np.full(10, 1.5), None, None, None)  # no previous fit
    assert not first["converged"] and "eta's median relative change not measured" in first["reason"]
    assert not _verdict(enabled=False)["converged"] and "converge.enabled" in _verdict(enabled=False)["reason"]


def test_only_confident_finite_vertices_count_for_eta():
    eta_before = np.full(10, 1.5)
    eta = eta_before.copy()
    eta[:4] = 3.0  # unconfident vertices that moved a lot
    eta[4] = np.nan
    confident = np.arange(10) >= 4
    verdict = judge(5, np.zeros(10), EDGE, eta, eta_before, confident, None)
    assert verdict["eta_change"] == 0 and verdict["converged"]


def _summary(path, converged_at=None):
    verdict = {"converged": converged_at is not None, "iteration": converged_at, "reason": "test"}
    path.write_text(json.dumps({"vertices": 3, "convergence": verdict}))
    return path


def test_pass_through_links_marks_and_copies_the_summary_once_converged(tmp_path):
    after = _summary(tmp_path / "mesh_3.ply.json", converged_at=3)
    store = tmp_path / "fit_3.zarr"
    (store / "eta").mkdir(parents=True)
    (store / "eta" / "c0").write_bytes(b"12345")
    (store / "zarr.json").write_text("{}")
    (store / ".snakemake_timestamp").write_text("")
    mesh = tmp_path / "mesh_3.ply"
    mesh.write_bytes(b"ply")
    links = [(store, tmp_path / "fit_4.zarr"), (mesh, tmp_path / "mesh_4.ply"), (after, tmp_path / "mesh_4.ply.json")]
    markers = [tmp_path / "shard.npz", tmp_path / "cameras.csv.json"]
    assert pass_through(after, links, markers, [tmp_path / "observations.zarr"]) == 3
    assert os.path.samefile(tmp_path / "fit_4.zarr" / "eta" / "c0", store / "eta" / "c0")  # linked, not copied
    assert not (tmp_path / "fit_4.zarr" / ".snakemake_timestamp").exists()  # Snakemake's own, never shared
    assert (tmp_path / "mesh_4.ply").read_bytes() == b"ply" and not os.path.samefile(tmp_path / "mesh_4.ply", mesh)
    summary = json.loads((tmp_path / "mesh_4.ply.json").read_text())
    assert summary["passed_through"] and summary["convergence"]["iteration"] == 3
    assert "converged at iteration 3" in (tmp_path / "shard.npz").read_text()
    assert json.loads((tmp_path / "cameras.csv.json").read_text()) == {"passed_through": True, "converged_at": 3}
    assert (tmp_path / "observations.zarr" / PASSED_THROUGH).is_file()
    # a summary that has not converged: nothing is touched
    assert pass_through(_summary(tmp_path / "open.json"), [(mesh, tmp_path / "other.ply")], [tmp_path / "m"]) is None
    assert not (tmp_path / "other.ply").exists() and not (tmp_path / "m").exists()


def test_sellip_pass_through_runs_the_command_unless_converged(tmp_path):
    missing = tmp_path / "no-such-schema.yaml"  # the command fails when it runs: it cannot read its schema
    marker = tmp_path / "marker.npz"
    command = ["--", "config-schema", "--schema", str(missing), "--check"]
    with pytest.raises(FileNotFoundError):
        cli.main(["pass-through", "--after", str(_summary(tmp_path / "open.json")), "--marker", str(marker), *command])
    assert not marker.exists()
    converged = _summary(tmp_path / "done.json", converged_at=2)
    assert cli.main(["pass-through", "--after", str(converged), "--marker", str(marker), *command]) == 0
    assert marker.is_file()
    with pytest.raises(SystemExit):  # no command after --
        cli.main(["pass-through", "--after", str(converged), "--marker", str(marker)])


def test_loop_convergence_says_where_the_loop_converged(tmp_path):
    meshes = [tmp_path / "init.ply"] + [tmp_path / f"mesh_{it}.ply" for it in range(5)]
    for it in range(3):
        verdict = {"converged": it == 2, "iteration": 2 if it == 2 else None, "reason": "r"}
        (tmp_path / f"mesh_{it}.ply.json").write_text(json.dumps({"convergence": verdict}))
    for it in (3, 4):
        (tmp_path / f"mesh_{it}.ply.json").write_text(json.dumps({"convergence": {"converged": True, "iteration": 2},
                                                                   "passed_through": True}))
    record = loop_convergence(meshes)
    assert record["converged_at"] == 2 and record["iterations"] == 5 and record["passed_through"] == [3, 4]
    assert sorted(record["verdicts"]) == ["0", "1", "2"]
    assert loop_convergence([tmp_path / "init.ply", tmp_path / "none.ply"]) is None
