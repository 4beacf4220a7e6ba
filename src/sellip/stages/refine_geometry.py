"""``sellip refine-geometry``: the geometry update of one iteration (rule ``refine_geometry``, paper §4.4).

    sellip refine-geometry --params results/NAME/iter/3/refit.zarr --mesh results/NAME/iter/2/mesh.ply
                           --output results/NAME/iter/3/mesh.ply [--reference-mesh results/NAME/mesh/init.ply]
                           [--smoothness 0.01] [--anchor 0.001] [--rounds 3]

The mesh's vertices move along its normals until its surface agrees with the iteration's fitted
normals, as far as the fit's normal confidence allows (:func:`sellip.geometry.refine_from_normals`,
docs/geometry_update.md); what normals cannot tell (the mean offset, the shape far from any confident
normal) is held at ``--reference-mesh`` (the loop's initial mesh, so that small biases of the normals
do not add up over the iterations; default: ``--mesh``). The faces stay, so every vertex keeps its
parameters (the next fit's warm start) and the vertex count does not drift. Written atomically as a model PLY
(:func:`sellip.io.write_param_mesh`) with the normals of the new surface and the ``confidence``: the
mesh of the next iteration. Beside it, ``<output>.json`` says how far the surface moved and how far the
fitted normals were from the mesh's before and after (a convergence figure that needs no ground truth).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def run_stage(params_path: Path, mesh_path: Path, output: Path, smoothness: float = 0.01, anchor: float = 1e-3,
              rounds: int = 3, min_confidence: float = 0.5, reference_mesh: Path | None = None) -> dict:
    """Write the next iteration's mesh ``output`` and ``<output>.json``; returns the summary written there.
    ``min_confidence``: the vertices whose normal agreement is reported."""
    from sellip.evaluate import angular_error_deg
    from sellip.fit import confidence_from_uncertainty
    from sellip.geometry import mesh_distances, refine_from_normals, vertex_normals
    from sellip.io import write_param_mesh
    from sellip.observe import read_mesh
    from sellip.params import PARAM_FIELDS, ParamsError, params_from, read_params, same_vertices
    from sellip.render import ParamMesh

    started = time.perf_counter()
    store = read_params(params_path)
    vertices, fitted, confidence = store["vertices"], store["normals"], store.get("confidence")
    if confidence is None:
        confidence = np.ones(len(vertices), np.float32)
    # The normals move the surface as far as they are certain (eta's uncertainty does not matter here).
    normal_confidence = np.asarray(confidence_from_uncertainty(store["normal_std_deg"], 0.0)
                                   if "normal_std_deg" in store else confidence, np.float64)
    mesh = read_mesh(mesh_path)
    if not same_vertices(mesh.vertices, vertices):
        raise ParamsError(f"{params_path}: its {len(vertices)} vertices are not those of {mesh_path} "
                          f"({mesh.num_vertices})")
    reference = None
    if reference_mesh is not None:
        reference = read_mesh(reference_mesh)
        if reference.num_vertices != mesh.num_vertices or not np.array_equal(reference.faces, mesh.faces):
            raise ParamsError(f"{reference_mesh}: not the same mesh as {mesh_path} (vertices {reference.num_vertices} "
                              f"vs {mesh.num_vertices}, or other faces); the loop keeps the initial mesh's faces")
        reference = reference.vertices
    confident = normal_confidence >= min_confidence
    log.info("%s: %d vertices, %d with normal confidence >= %.2f (median %.2f); smoothness %g, anchor %g, "
             "%d rounds", params_path, len(vertices), int(confident.sum()), min_confidence,
             float(np.median(normal_confidence)), smoothness, anchor, rounds)
    new_vertices = refine_from_normals(mesh.vertices, mesh.faces, fitted, normal_confidence, smoothness=smoothness,
                                       anchor=anchor, rounds=rounds, reference=reference)
    new_normals = vertex_normals(new_vertices, mesh.faces)
    params = params_from({name: store[name] for name in PARAM_FIELDS}, np.float64)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(output.name + ".tmp.ply")
    write_param_mesh(tmp, ParamMesh(new_vertices, mesh.faces, new_normals, params),
                     extra={"confidence": np.asarray(confidence, np.float32)})
    moved = mesh_distances(new_vertices, mesh.faces, mesh.vertices, mesh.faces, count=20000)
    offsets = np.linalg.norm(new_vertices - mesh.vertices, axis=1)

    def agreement(normals):
        return float(np.median(angular_error_deg(fitted[confident], normals[confident]))) if confident.any() else None

    summary = {"vertices": len(new_vertices), "confident_vertices": int(confident.sum()),
               "moved_chamfer_mm": 1e3 * moved.chamfer, "moved_hausdorff_mm": 1e3 * moved.hausdorff,
               "offset_median_mm": 1e3 * float(np.median(offsets)), "offset_max_mm": 1e3 * float(offsets.max()),
               "fitted_vs_mesh_before_deg": agreement(vertex_normals(mesh.vertices, mesh.faces)),
               "fitted_vs_mesh_after_deg": agreement(new_normals),
               "seconds": time.perf_counter() - started}
    tmp.replace(output)
    Path(f"{output}.json").write_text(json.dumps(summary, indent=1))
    log.info("wrote %s in %.1f s: the surface moved %.3f mm (Chamfer; Hausdorff %.3f mm, vertex offsets median "
             "%.3f mm); fitted vs mesh normals (median, confident vertices) %.2f -> %.2f deg", output,
             summary["seconds"], summary["moved_chamfer_mm"], summary["moved_hausdorff_mm"],
             summary["offset_median_mm"], *(np.nan if summary[key] is None else summary[key]
                                          for key in ("fitted_vs_mesh_before_deg", "fitted_vs_mesh_after_deg")))
    return summary


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", type=Path, required=True, help="this iteration's params.zarr (fitted normals)")
    parser.add_argument("--mesh", type=Path, required=True, help="this iteration's mesh (its vertices and normals)")
    parser.add_argument("--output", type=Path, required=True, help="the next iteration's mesh (.ply)")
    parser.add_argument("--smoothness", type=float, default=0.01,
                        help="weight of smooth offsets against agreeing with the normals (no units)")
    parser.add_argument("--anchor", type=float, default=1e-3,
                        help="weight that holds the vertices where they are (no units; what normals cannot tell)")
    parser.add_argument("--rounds", type=int, default=3, help="linearisations around the moved surface")
    parser.add_argument("--reference-mesh", type=Path, default=None,
                        help="the mesh (same faces) whose surface the anchor holds (default: --mesh)")


def main(args: argparse.Namespace) -> int:
    from sellip.observe import ObserveError
    from sellip.params import ParamsError

    try:
        run_stage(args.params, args.mesh, args.output, args.smoothness, args.anchor, args.rounds,
                  reference_mesh=args.reference_mesh)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
