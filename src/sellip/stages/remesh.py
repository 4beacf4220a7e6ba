"""``sellip remesh``: the geometry update of one iteration (rule ``remesh_poisson``, paper §4.4).

    sellip remesh --params results/NAME/iter/3/refit.zarr --mesh results/NAME/iter/2/mesh.ply
                  --output results/NAME/iter/3/mesh.ply
                  [--depth 9] [--point-weight 4] [--trim-density 2]
                  [--target-vertices N | --reference-mesh results/NAME/mesh/init.ply]

Screened Poisson from the iteration's vertices and fitted normals, blended towards the normals
of the iteration's mesh (``--mesh``, whose vertices the store holds) by the fit confidence
(:func:`sellip.geometry.remesh_from_normals`); low-density surface trimmed, the
largest component kept, remeshed to ``--target-vertices``, or to the vertex count of
``--reference-mesh`` (the initial mesh: no drift over the iterations), or else of ``--mesh``.
The new vertices take the parameters of their nearest old vertex and the normals of the new
surface. Written atomically as a model PLY (:func:`sellip.io.write_param_mesh`) with the
carried ``confidence``: the mesh of the next iteration.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def run_stage(params_path: Path, mesh_path: Path, output: Path, depth: int = 9, point_weight: float = 4.0,
              trim_density: float | None = 2.0, target_vertices: int | None = None,
              reference_mesh: Path | None = None) -> dict:
    """Write the next iteration's mesh ``output``; returns a summary dict."""
    from sellip.fit import confidence_from_uncertainty
    from sellip.geometry import mesh_distances, remesh_from_normals, vertex_normals
    from sellip.io import write_param_mesh
    from sellip.observe import read_mesh
    from sellip.params import (
        PARAM_FIELDS,
        ParamsError,
        params_from,
        read_params,
        same_vertices,
        transfer_nearest,
    )
    from sellip.render import ParamMesh

    started = time.perf_counter()
    store = read_params(params_path)
    vertices, normals, confidence = store["vertices"], store["normals"], store.get("confidence")
    if confidence is None:
        confidence = np.ones(len(vertices), np.float32)
    # The normals move the surface as far as they are certain (eta's uncertainty does not matter here).
    normal_confidence = (confidence_from_uncertainty(store["normal_std_deg"], 0.0) if "normal_std_deg" in store
                         else confidence)
    mesh = read_mesh(mesh_path)
    if not same_vertices(mesh.vertices, vertices):
        raise ParamsError(f"{params_path}: its {len(vertices)} vertices are not those of {mesh_path} "
                          f"({mesh.num_vertices})")
    target = int(target_vertices or (read_mesh(reference_mesh).num_vertices if reference_mesh else len(vertices)))
    log.info("%s: %d vertices (median confidence %.2f, of the normal %.2f); screened Poisson at depth %d, "
             "target %d vertices", params_path, len(vertices), float(np.median(confidence)),
             float(np.median(normal_confidence)), depth, target)
    new_vertices, faces = remesh_from_normals(vertices, normals, np.asarray(normal_confidence), mesh.normals, target,
                                              depth=depth,
                                              point_weight=point_weight, trim_density=trim_density)
    new_normals = vertex_normals(new_vertices, faces)
    nearest = transfer_nearest(vertices, new_vertices)
    params = params_from({name: store[name][nearest] for name in PARAM_FIELDS}, np.float64)
    moved = mesh_distances(new_vertices, faces, mesh.vertices, mesh.faces, count=20000)  # how far the surface moved
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(output.name + ".tmp.ply")
    write_param_mesh(tmp, ParamMesh(new_vertices, faces, new_normals, params),
                     extra={"confidence": np.asarray(confidence[nearest], np.float32)})
    tmp.replace(output)
    summary = {"vertices": len(new_vertices), "faces": len(faces), "seconds": time.perf_counter() - started,
               "moved_chamfer_mm": 1e3 * moved.chamfer, "moved_hausdorff_mm": 1e3 * moved.hausdorff}
    log.info("wrote %s: %d vertices, %d faces in %.1f s; the surface moved %.3f mm (Chamfer; Hausdorff %.3f mm)",
             output, summary["vertices"], summary["faces"], summary["seconds"], summary["moved_chamfer_mm"],
             summary["moved_hausdorff_mm"])
    return summary


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", type=Path, required=True, help="this iteration's params.zarr (fitted normals)")
    parser.add_argument("--mesh", type=Path, required=True, help="this iteration's mesh (its vertices and normals)")
    parser.add_argument("--output", type=Path, required=True, help="the next iteration's mesh (.ply)")
    parser.add_argument("--depth", type=int, default=9, help="screened Poisson octree depth")
    parser.add_argument("--point-weight", type=float, default=4.0, help="screening weight of the sample positions")
    parser.add_argument("--trim-density", type=float, default=2.0,
                        help="remove surface whose Poisson density is this far below the median (negative: keep all)")
    parser.add_argument("--target-vertices", type=int, default=None,
                        help="vertices of the new mesh (default: as many as --reference-mesh, or as --mesh)")
    parser.add_argument("--reference-mesh", type=Path, default=None,
                        help="a mesh whose vertex count the new mesh takes (e.g. the initial mesh)")


def main(args: argparse.Namespace) -> int:
    from sellip.observe import ObserveError
    from sellip.params import ParamsError

    try:
        run_stage(args.params, args.mesh, args.output, args.depth, args.point_weight,
                  None if args.trim_density < 0 else args.trim_density, args.target_vertices, args.reference_mesh)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
