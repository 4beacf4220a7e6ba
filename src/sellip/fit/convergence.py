"""Convergence of the outer loop (issue #54, docs/speed.md "Convergence"): iterations after the loop has converged
pass their inputs through at almost no cost, with the DAG kept static.

The geometry update of iteration ``it`` (rule ``refine_geometry``) judges whether the loop has converged
(:func:`judge`) from what it already has: how far it moved the surface (the median and the 99th-percentile vertex
offset, in the mesh's mean edge lengths), how far the confident vertices' η moved from iteration ``it - 1``'s fit
(median relative change), and, where the poses are refined, how far this iteration's pose refinement turned the
views (median rotation, degrees). The verdict goes into ``iter/<it>/mesh.ply.json`` (``convergence``). Every job of
a later iteration before the final pass runs through ``sellip pass-through --after iter/<it-1>/mesh.ply.json ... --
<its command>`` (:func:`pass_through`): when that summary says converged, the job links its predecessor's outputs
to its own (a store's files hard-linked, a mesh or table copied) or writes a marker where nothing reads its output,
and its command does not run; otherwise the command runs as before. The final pass always runs, on the converged
iteration's mesh, parameters, lobes and cameras. A converged summary stays converged when passed through (the
iteration it converged at is kept), so ``metrics.json`` can say where the loop converged (:func:`loop_convergence`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sellip.jobs import atomic_directory, atomic_file, write_text
from sellip.settings import setting

log = logging.getLogger(__name__)

PASSED_THROUGH = "PASSED_THROUGH"
"""The file a passed-through job writes into an output folder that nothing reads (the observations)."""


@dataclass(frozen=True)
class ConvergenceSettings:
    """When the outer loop has converged (config ``converge``; docs/speed.md, "Convergence")."""

    enabled: bool = setting(True, "iterations after the loop has converged pass their inputs through (the final pass "
                                  "always runs)")
    min_iterations: int = setting(3, "iterations that always run (0 .. min_iterations - 1) before the loop may "
                                     "converge (iteration 0 has no previous fit to compare with)", minimum=2)
    max_offset_edges: float = setting(0.01, "converged only if the geometry update moved the vertices by at most "
                                            "this median offset, in mean edge lengths of the mesh", minimum=0)
    max_offset_p99_edges: float = setting(0.1, "converged only if the geometry update moved 99 % of the vertices by "
                                                "at most this offset, in mean edge lengths: a region still moving (a "
                                                "hollow being carved) keeps the loop going while the median rests",
                                          minimum=0)
    max_eta_change: float = setting(0.001, "converged only if the confident vertices' eta moved from the previous "
                                           "iteration's by at most this median relative change", minimum=0)
    max_rotation_deg: float = setting(0.01, "converged only if, where the poses are refined, this iteration's pose "
                                            "refinement turned the views by at most this median rotation",
                                      unit="deg", minimum=0)


def judge(iteration: int, offsets_m: np.ndarray, mean_edge_m: float, eta: np.ndarray | None,
          eta_before: np.ndarray | None, confident: np.ndarray | None, poses: dict | None,
          settings: ConvergenceSettings = ConvergenceSettings()) -> dict:
    """The convergence verdict of iteration ``iteration``'s geometry update: ``offsets_m`` (V,) how far it moved each
    vertex [m], ``mean_edge_m`` the mesh's mean edge length [m]; ``eta`` and ``eta_before`` (V,) the vertices' η of
    this iteration's and the previous iteration's fit (None at iteration 0), ``confident`` (V,) bool the vertices
    whose η counts (None: all); ``poses`` the summary of the pose refinement that made this iteration's cameras
    (``cameras.csv.json``), None where the poses are not refined. Returns a JSON-able dict: ``converged``,
    ``iteration`` (this one where converged, else None), each measure, its limit, and ``reason`` in words."""
    measurable = len(offsets_m) and mean_edge_m > 0
    offset_edges = float(np.median(offsets_m) / mean_edge_m) if measurable else None
    offset_p99_edges = float(np.percentile(offsets_m, 99) / mean_edge_m) if measurable else None
    eta_change = None
    if eta is not None and eta_before is not None:
        use = np.isfinite(eta) & np.isfinite(eta_before) & (eta_before > 0)
        if confident is not None:
            use &= np.asarray(confident, bool)
        if use.any():
            eta_change = float(np.median(np.abs(eta[use] - eta_before[use]) / eta_before[use]))
    rotation = ((poses or {}).get("rotation_deg") or {}).get("median") if poses is not None else None
    measures = [("offset_edges", offset_edges, settings.max_offset_edges, "the surface's median step (edges)"),
                ("offset_p99_edges", offset_p99_edges, settings.max_offset_p99_edges,
                 "the surface's 99th-percentile step (edges)"),
                ("eta_change", eta_change, settings.max_eta_change, "eta's median relative change")]
    if poses is not None:
        measures.append(("rotation_deg", rotation, settings.max_rotation_deg, "the poses' median rotation (deg)"))
    verdict = {name: value for name, value, _, _ in measures}
    verdict["limits"] = {name: limit for name, _, limit, _ in measures}
    open_measures = [f"{words} {'not measured' if value is None else f'{value:.3g} > {limit:g}'}"
                     for _, value, limit, words in measures if value is None or value > limit]
    if not settings.enabled:
        reason = "convergence off (config converge.enabled)"
    elif iteration + 1 < settings.min_iterations:
        reason = f"iteration {iteration} < min_iterations {settings.min_iterations} - 1: the loop runs on"
    elif open_measures:
        reason = "not converged: " + "; ".join(open_measures)
    else:
        reason = "converged: " + "; ".join(f"{words} {value:.3g} <= {limit:g}" for _, value, limit, words in measures)
    converged = reason.startswith("converged")
    verdict.update({"converged": converged, "iteration": iteration if converged else None, "reason": reason})
    return verdict


def converged_at(summary: str | Path) -> int | None:
    """The iteration the loop converged at, as the geometry update's summary ``summary`` (``mesh.ply.json``) records
    it; None where it has not converged (or the summary predates convergence)."""
    block = json.loads(Path(summary).read_text(encoding="utf-8")).get("convergence") or {}
    return block.get("iteration") if block.get("converged") else None


WORKFLOW_STAMP = ".snakemake_timestamp"
"""The file whose time Snakemake takes for a folder's: never linked (touching a link would date the source)."""


def _link_tree(source: Path, output: Path) -> None:
    """``output`` as hard links to every file of the folder ``source`` but Snakemake's time stamp (atomic: renamed
    into place). The files of a store are written once and replaced whole, never changed in place."""
    with atomic_directory(output) as tmp:
        shutil.copytree(source, tmp, copy_function=os.link, ignore=shutil.ignore_patterns(WORKFLOW_STAMP))


def _copy_file(source: Path, output: Path) -> None:
    """A copy, not a link: the output must be newer than its inputs (Snakemake compares modification times)."""
    with atomic_file(output) as tmp:
        shutil.copyfile(source, tmp)


def pass_through(after: str | Path, links: list[tuple[Path, Path]] = (), markers: list[Path] = (),
                 marker_folders: list[Path] = ()) -> int | None:
    """If the summary ``after`` (the previous iteration's ``mesh.ply.json``) says the loop has converged: make each
    ``(source, output)`` of ``links`` (a folder's files hard-linked; a file copied, so that it is newer than its
    inputs; a ``.json`` summary copied with ``passed_through`` set), write each file of ``markers`` and each folder
    of ``marker_folders`` (holding :data:`PASSED_THROUGH`), and return the iteration it converged at; else touch
    nothing and return None (the job then runs)."""
    iteration = converged_at(after)
    if iteration is None:
        return None
    note = f"passed through: the loop converged at iteration {iteration} ({after})\n"
    for source, output in links:
        source, output = Path(source), Path(output)
        if not source.exists():
            raise FileNotFoundError(f"{source}: missing, so {output} cannot pass it through")
        if output.suffix == ".json":
            summary = json.loads(source.read_text(encoding="utf-8"))
            write_text(json.dumps({**summary, "passed_through": True}, indent=1), output)
        elif source.is_dir():
            _link_tree(source, output)
        else:
            _copy_file(source, output)
    for output in markers:
        output = Path(output)
        text = json.dumps({"passed_through": True, "converged_at": iteration}) if output.suffix == ".json" else note
        write_text(text, output)
    for output in marker_folders:
        with atomic_directory(output) as tmp:
            tmp.mkdir()
            (tmp / PASSED_THROUGH).write_text(note, encoding="utf-8")
    log.info("%s", note.strip())
    return iteration


def loop_convergence(iteration_meshes: list[str | Path]) -> dict | None:
    """``metrics.json``'s ``convergence``: from the summaries beside the loop's meshes (the initial one, then each
    iteration's: ``<mesh>.json``), the iteration the loop converged at (None: it ran every iteration), the
    iterations passed through, and each iteration's verdict; None where no summary records one."""
    verdicts, passed = {}, []
    for it, mesh in enumerate(iteration_meshes[1:]):
        path = Path(f"{mesh}.json")
        if not path.is_file():
            continue
        summary = json.loads(path.read_text(encoding="utf-8"))
        if summary.get("passed_through"):
            passed.append(it)
        elif summary.get("convergence") is not None:
            verdicts[it] = summary["convergence"]
    if not verdicts:
        return None
    converged = [it for it, verdict in verdicts.items() if verdict.get("converged")]
    return {"converged_at": converged[0] if converged else None, "iterations": len(iteration_meshes) - 1,
            "passed_through": passed, "verdicts": {str(it): verdict for it, verdict in verdicts.items()}}
