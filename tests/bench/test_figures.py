"""The documented figures (sellip.bench.figures, ``sellip figures``; issue #49 item 6): the README's accuracy table
read back from the README itself, and compared with a run's metrics.json within the stated tolerances."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sellip.bench import figures
from sellip.jobs import write_text
from sellip.report import eta_per_material

ROOT = Path(__file__).resolve().parents[2]
DEMO = figures.run_named("demo")
# The demo scene's true η per material label (plumage, facial disc, eyes and beak: sellip.capture.scenes).
DEMO_TRUE_ETA = (1.48, 1.36, 1.62)


def _demo_figures() -> dict[str, figures.Figure]:
    return {figure.name: figure for figure in figures.FIGURES if figure.run == "demo"}


def _documented(readme: str) -> dict[str, float]:
    return {name: figures.documented(figure, readme) for name, figure in _demo_figures().items()}


def _write_demo_run(results: Path, values: dict[str, float], ks=(3, 3, 3)) -> Path:
    """A finished demo run's outputs under ``results``: metrics.json with ``values`` (figure name -> measured, in
    the figure's units), η per material computed by the library's own function from vertex arrays, and one
    clusters.json per iteration with ``k``."""
    folder = results / DEMO.results
    labels = np.repeat([0, 1, 2], [400, 300, 100])
    eta_true = np.asarray(DEMO_TRUE_ETA)[labels]
    errors = [values[f"demo: η {m} (%)"] for m in ("plumage", "disc", "eyes")]
    eta = eta_true * (1 + np.asarray(errors)[labels] / 100)
    metrics = {"vertices": {"model": int(values["demo: vertices"]), "confident": len(labels)},
               "eta_per_material": eta_per_material(eta, eta_true, labels),
               "normal_error_deg": {"all": {"median": values["demo: normals median (°)"]}},
               "psnr_held_out": {"views": {}, "mean_db": values["demo: held-out PSNR (dB)"]},
               "geometry": {"chamfer_mm": values["demo: Chamfer (mm)"]}}
    write_text(json.dumps(metrics, indent=2, allow_nan=False), folder / "metrics.json")
    for it, k in enumerate(ks):
        write_text(json.dumps({"k": k, "merges": [], "regions": []}), folder / "iter" / str(it) / "clusters" /
                   "clusters.json")
    return folder


def _near(readme: str, share: float) -> dict[str, float]:
    """Every demo figure moved by ``share`` of its tolerance from the README's value."""
    demo = _demo_figures()
    return {name: value + share * figures.tolerance_of(demo[name], value)
            for name, value in _documented(readme).items()}


def _check(root: Path, results: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sellip.cli", "figures", "check", "--only", "demo", "--root",
                           str(root), "--results", str(results), *extra], capture_output=True, text=True, timeout=120)


def test_every_registered_figure_reads_back_from_the_current_documents():
    assert figures.document_problems(ROOT) == []
    readme = (ROOT / "README.md").read_text()
    for run in figures.RUNS:
        line, row = figures.table_row(readme, run.command)
        # The row parses into the README's own line, cell for cell.
        assert readme.splitlines()[line - 1] == "| " + " | ".join(row.values()) + " |"
    for figure in figures.FIGURES:
        value = figures.documented(figure, readme)
        cell = figures.table_row(readme, figures.run_named(figure.run).command)[1][figure.column]
        assert np.isfinite(value) and value >= 0, figure.name
        assert (f"{value / figure.scale:g}" in cell) or figure.kind == "materials", (figure.name, cell)
    assert _documented(readme)["demo: materials at every iteration"] == 3  # "three materials at every iteration"
    covered = {figure.run for figure in figures.FIGURES}
    assert covered == {run.name for run in figures.RUNS} and len(figures.FIGURES) == 36


def test_a_demo_run_within_tolerance_passes_and_one_outside_fails_with_its_difference(tmp_path):
    readme = (ROOT / "README.md").read_text()
    _write_demo_run(tmp_path, _near(readme, 0.8))
    passed = _check(ROOT, tmp_path, "--record", str(tmp_path / "figures.json"))
    assert passed.returncode == 0, passed.stdout + passed.stderr
    assert passed.stdout.count("PASS") == 8 and "FAIL" not in passed.stdout
    record = json.loads((tmp_path / "figures.json").read_text())
    assert record["runs"]["demo"]["command"] == "make demo" and record["versions"]["jax"]
    assert len(record["commit"]) == 40 and {row["status"] for row in record["figures"]} == {"PASS"}

    values = _near(readme, 0.8)
    chamfer = values["demo: Chamfer (mm)"] = _documented(readme)["demo: Chamfer (mm)"] + 0.007
    _write_demo_run(tmp_path, values)
    failed = _check(ROOT, tmp_path)
    assert failed.returncode == 1
    line = next(text for text in failed.stdout.splitlines() if text.startswith("demo: Chamfer (mm)"))
    assert line.split()[3:] == [f"{_documented(readme)['demo: Chamfer (mm)']:g}", f"{chamfer:.6g}", "±0.005",
                                "+0.007", "FAIL"]
    assert "1 of 8 documented figures were not reproduced" in failed.stderr


def test_one_iteration_with_two_materials_fails_the_materials_figure(tmp_path):
    readme = (ROOT / "README.md").read_text()
    _write_demo_run(tmp_path, _near(readme, 0.0), ks=(3, 2, 3, 3))
    comparisons = {c.figure.name: c for c in figures.check(ROOT, tmp_path, (DEMO,))}
    materials = comparisons.pop("demo: materials at every iteration")
    assert materials.status == "FAIL" and materials.measured == (3, 2, 3, 3) and materials.difference == -1
    assert {c.status for c in comparisons.values()} == {"PASS"}


def test_a_changed_readme_value_makes_the_check_disagree(tmp_path):
    readme = (ROOT / "README.md").read_text()
    _write_demo_run(tmp_path / "results", _near(readme, 0.0))
    docs = tmp_path / "checkout"
    docs.mkdir()
    line, row = figures.table_row(readme, "make demo")
    wrong = f"{float(row['normals (median)'].rstrip('°')) + 0.2:.2f}"  # four times the tolerance off
    changed = row["normals (median)"].replace(row["normals (median)"].rstrip("°"), wrong)
    (docs / "README.md").write_text(readme.replace("| " + row["normals (median)"] + " |", f"| {changed} |", 1))
    assert figures.table_row((docs / "README.md").read_text(), "make demo")[1]["normals (median)"] == f"{wrong}°"
    result = _check(docs, tmp_path / "results")
    assert result.returncode == 1
    failing = [text for text in result.stdout.splitlines() if "FAIL" in text]
    assert len(failing) == 1 and failing[0].startswith("demo: normals median (°)")
    assert _check(ROOT, tmp_path / "results").returncode == 0  # the same run against the README as it is


def test_a_reworded_row_or_a_missing_tolerance_sentence_stops_the_check_naming_what_changed(tmp_path):
    readme = (ROOT / "README.md").read_text()
    line, row = figures.table_row(readme, "make demo")
    eta = row["η per material"]
    reworded = readme.replace(eta, eta.replace(" / ", ", "), 1)
    plumage = _demo_figures()["demo: η plumage (%)"]
    with pytest.raises(figures.FiguresError, match=rf"README.md:{line}: column 'η per material' reads"):
        figures.documented(plumage, reworded)
    with pytest.raises(figures.FiguresError, match="0 table rows have `make demo`"):
        figures.documented(plumage, readme.replace("(`make demo`)", "(make demo)"))
    assert readme.count("held-out PSNR ±0.3 dB") == 1
    (tmp_path / "README.md").write_text(readme.replace("held-out PSNR ±0.3 dB", "held-out PSNR ±0.5 dB"))
    assert any("tolerance sentence" in problem for problem in figures.document_problems(tmp_path))
    result = _check(tmp_path, tmp_path)
    assert result.returncode == 1 and "tolerance sentence is not there" in result.stderr


def test_a_missing_run_says_which_command_makes_it(tmp_path):
    comparisons = figures.check(ROOT, tmp_path, (DEMO,))
    assert {c.status for c in comparisons} == {"MISSING"}
    assert all("run `make demo` first" in c.note for c in comparisons)
    with pytest.raises(figures.FiguresError, match="no registered run 'owl'"):
        figures.select(["owl"])
    assert figures.select(size="small") == (DEMO,)


def test_a_known_and_sfm_row_reads_each_value_from_its_own_rung(tmp_path):
    """The painted cow's row is one accuracy-ladder command with two workflow rungs: "known / SfM" in each cell, the
    first read from the ``hull`` rung's metrics.json, the second from the ``sfm`` rung's; a wrong SfM value fails
    only the SfM figure."""
    readme = (ROOT / "README.md").read_text()
    run = figures.run_named("cow_painted_mitsuba")
    line, row = figures.table_row(readme, run.command)
    assert "--renderer mitsuba" in run.command and "--rungs hull sfm" in run.command
    cow = [figure for figure in figures.FIGURES if figure.run == run.name]
    assert len(cow) == 8 and {figure.folder.split("_")[-4] for figure in cow} == {"hull", "sfm"}

    def write(folder: str, values: dict[str, float]) -> None:
        metrics = {"eta_per_material": {"mean_error_pct": values["η (%)"]},
                   "normal_error_deg": {"all": {"median": values["normals median (°)"]}},
                   "psnr_held_out": {"mean_db": values["held-out PSNR (dB)"]},
                   "geometry": {"chamfer_mm": values["Chamfer (mm)"]}}
        write_text(json.dumps(metrics), tmp_path / run.results / folder / "metrics.json")

    def documented_by_rung(shift: float = 0.0) -> dict[str, dict[str, float]]:
        by = {}
        for figure in cow:
            what = figure.name.split(": ", 1)[1]
            value = figures.documented(figure, readme)
            by.setdefault(figure.folder, {})[what] = value + shift * figures.tolerance_of(figure, value)
        return by

    for folder, values in documented_by_rung(0.8).items():
        write(folder, values)
    comparisons = figures.check(ROOT, tmp_path, (run,))
    assert [c.status for c in comparisons] == ["PASS"] * 8
    known = next(c for c in comparisons if c.figure.name == f"{run.name}, known poses: normals median (°)")
    sfm = next(c for c in comparisons if c.figure.name == f"{run.name}, SfM: normals median (°)")
    assert known.documented == float(row["normals (median)"].split("°")[0]) != sfm.documented

    sfm_folder = sfm.figure.folder
    values = documented_by_rung()[sfm_folder]
    values["normals median (°)"] += 0.2
    write(sfm_folder, values)
    failed = [c.figure.name for c in figures.check(ROOT, tmp_path, (run,)) if c.status != "PASS"]
    assert failed == [f"{run.name}, SfM: normals median (°)"]
