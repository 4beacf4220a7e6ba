"""``sellip finalize``: the final model (rule ``finalize_model``, DESIGN §4).

    sellip finalize --params results/NAME/iter/10/params.zarr --mesh results/NAME/iter/9/mesh.ply
                    --output-model results/NAME/final/model.ply --output-params results/NAME/final/params.zarr
                    [--clusters results/NAME/iter/10/clusters] [--model 3]

``--params`` is the last pass of the loop: the pBRDF refitted with the normals of the final
geometry (paper §4.4); its rows are the vertices of ``--mesh``, whose triangles the model keeps.
Written (each atomically): ``model.ply`` with the vertex properties of DESIGN §4 (float32) plus
``confidence`` (float32) and ``model`` (uint8, :data:`sellip.model.params.MODEL_NAMES`), and
``params.zarr`` with the same arrays (plus status, loss, views_used, iterations, cluster).
``model`` is the store's own (the model each vertex was fitted with, DESIGN §7); ``--model``
only fills it for a store without one.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def run_stage(params_path: Path, mesh_path: Path, output_model: Path, output_params: Path,
              clusters: Path | None = None, model: int = 3, eta_deviation_sigmas: float = 3.0,
              lobe_deviation_sigmas: float = 3.0, deviation_support: int = 3) -> dict:
    """Write the final model PLY and parameter store; returns a summary dict. The per-vertex model is
    the store's ``model``; ``model`` is the code of every vertex of a store that has none. With
    ``clusters``, eta is its material cluster's (the median of the cluster's confident vertices' own eta,
    :func:`sellip.fit.lobes.cluster_medians`; the cluster lobe fit's where it has none) unless a vertex's own differs
    by more than ``eta_deviation_sigmas`` of its std, and so is the specular lobe (the cluster lobe fit's sigma_s
    with its rho_s) unless the vertex's sigma_s differs by more than ``lobe_deviation_sigmas`` of its std (at
    least 0.01, the rule's floor), and either way only where at least ``deviation_support`` of its 6 nearest vertices
    deviate the same way (:func:`sellip.fit.lobes.material_or_own`; <= 0: every vertex's own). An eta pinned at a bound
    (:func:`sellip.fit.parameterization.eta_at_bound`) is no estimate: the vertex takes its material's, and is not in its median."""
    from sellip.fit.clusters import AugmentSettings, nearest_vertices
    from sellip.fit.lobes import cluster_medians, material_or_own
    from sellip.fit.observe import read_mesh
    from sellip.fit.parameterization import eta_at_bound
    from sellip.model.params import (
        MODEL_NAMES,
        PARAM_FIELDS,
        ParamsError,
        params_from,
        read_params,
        same_vertices,
        write_params,
    )
    from sellip.model.ply import write_param_mesh
    from sellip.model.render import ParamMesh
    from sellip.stages.cluster_lobes import read_lobes

    if model not in MODEL_NAMES:
        raise ValueError(f"--model must be one of {sorted(MODEL_NAMES)}, got {model}")
    store = read_params(params_path)
    mesh = read_mesh(mesh_path)
    vertices = store["vertices"]
    if not same_vertices(vertices, mesh.vertices):
        raise ParamsError(f"{params_path}: its {len(vertices)} vertices are not those of {mesh_path} "
                          f"({mesh.num_vertices}): the final pass must fit the final mesh")
    n = len(vertices)
    cluster = np.zeros(n, np.int32)
    eta, eta_source = np.asarray(store["eta"], np.float64), np.ones(n, np.uint8)
    sigma_s, rho_s = np.asarray(store["sigma_s"], np.float64), np.asarray(store["rho_s"], np.float64)
    lobe_source = np.ones(n, np.uint8)
    if clusters is not None:
        try:
            labels, lobes = read_lobes(clusters)
        except ValueError as exc:
            raise ParamsError(str(exc)) from None
        cluster = labels.astype(np.int32)
        if cluster.shape != (n,):
            raise ParamsError(f"{Path(clusters) / 'labels.npy'}: {cluster.shape[0]} labels for {n} vertices")
        pinned = eta_at_bound(eta)  # no estimate: neither in its material's eta nor kept as its own
        eta_std = np.where(pinned, np.inf, np.asarray(store.get("eta_std", np.full(n, np.inf)), np.float64))
        confident = np.asarray(store.get("confidence", np.zeros(n)), np.float64) > 0
        material_eta = cluster_medians(eta, cluster, confident & ~pinned, [lobe.eta for lobe in lobes])
        neighbours = AugmentSettings().coherence_neighbours  # the vertices that stand for a 1-ring, as in clustering
        near = nearest_vertices(vertices, neighbours)
        eta, eta_source = material_or_own(eta, eta_std, cluster, material_eta, eta_deviation_sigmas,
                                          neighbours=near, min_support=deviation_support)
        log.info("eta per material: %d of %d vertices keep their own eta (more than %g std from their cluster's %s, "
                 "with %d of their %d neighbours; the cluster lobe fits' %s)", int(eta_source.sum()), n,
                 eta_deviation_sigmas, np.round(material_eta, 3).tolist(), deviation_support, neighbours,
                 np.round([lobe.eta for lobe in lobes], 3).tolist())
        sigma_s_std = np.asarray(store.get("sigma_s_std", np.full(n, np.inf)), np.float64)
        sigma_s, lobe_source = material_or_own(sigma_s, sigma_s_std, cluster, [lobe.sigma_s for lobe in lobes],
                                               lobe_deviation_sigmas, neighbours=near, min_support=deviation_support)
        rho_s = np.where(lobe_source == 1, rho_s, np.asarray([lobe.rho_s for lobe in lobes])[cluster])
        log.info("specular lobe per material: %d of %d vertices keep their own (sigma_s more than %g std from their "
                 "cluster's %s, with %d of their %d neighbours)", int(lobe_source.sum()), n, lobe_deviation_sigmas,
                 np.round([lobe.sigma_s for lobe in lobes], 3).tolist(), deviation_support, neighbours)
    if "model" in store:
        models = np.asarray(store["model"], np.uint8)
        if not np.isin(models, sorted(MODEL_NAMES)).all():
            raise ParamsError(f"{params_path}: model codes {sorted(set(np.unique(models)) - set(MODEL_NAMES))} "
                              f"are not in {sorted(MODEL_NAMES)}")
    else:
        models = np.full(n, model, np.uint8)
        log.info("%s has no model array: every vertex gets model %d", params_path, model)
    params = params_from(store, np.float64)._replace(eta=eta, sigma_s=sigma_s, rho_s=rho_s)
    confidence = np.asarray(store.get("confidence", np.zeros(n)), np.float32)
    output_model = Path(output_model)
    output_model.parent.mkdir(parents=True, exist_ok=True)
    tmp = output_model.with_name(output_model.name + ".tmp.ply")
    write_param_mesh(tmp, ParamMesh(vertices, mesh.faces, store["normals"], params),
                     extra={"confidence": confidence, "model": models, "eta_source": eta_source,
                            "lobe_source": lobe_source})
    tmp.replace(output_model)
    arrays = {name: store[name] for name in store if name != "attrs"}
    arrays.update(model=models, cluster=cluster, eta=eta.astype(np.float32), eta_source=eta_source,
                  eta_vertex=np.asarray(store["eta"], np.float32), sigma_s=sigma_s.astype(np.float32),
                  rho_s=rho_s.astype(np.float32), lobe_source=lobe_source,
                  sigma_s_vertex=np.asarray(store["sigma_s"], np.float32),
                  rho_s_vertex=np.asarray(store["rho_s"], np.float32))
    write_params(output_params, arrays, attrs={**store["attrs"], "model_names": {str(k): v for k, v in
                                                                                  MODEL_NAMES.items()}})
    summary = {"vertices": n, "faces": len(mesh.faces), "confidence_median": float(np.median(confidence)),
               "eta_median": float(np.median(eta)), "eta_own_vertices": int(eta_source.sum()),
               "lobe_own_vertices": int(lobe_source.sum()),
               "fields": list(PARAM_FIELDS),
               "vertices_per_model": {str(m): int(np.sum(models == m)) for m in sorted(MODEL_NAMES)}}
    log.info("wrote %s and %s: %d vertices, %d faces, median confidence %.2f, median eta %.3f, vertices per model %s",
             output_model, output_params, n, len(mesh.faces), summary["confidence_median"], summary["eta_median"],
             summary["vertices_per_model"])
    return summary


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", type=Path, required=True, help="the last pass's params.zarr")
    parser.add_argument("--mesh", type=Path, required=True, help="the final mesh (its triangles)")
    parser.add_argument("--output-model", type=Path, required=True, help="final model PLY")
    parser.add_argument("--output-params", type=Path, required=True, help="final params.zarr")
    parser.add_argument("--clusters", type=Path, default=None, help="cluster_lobes output of the last pass")
    parser.add_argument("--eta-deviation-sigmas", type=float, default=3.0,
                        help="a vertex keeps its own eta (not its material cluster's) when it differs by more than "
                             "this many of its std (<= 0: every vertex its own)")
    parser.add_argument("--lobe-deviation-sigmas", type=float, default=3.0,
                        help="a vertex keeps its own specular lobe (sigma_s and rho_s, not its material cluster's) "
                             "when its sigma_s differs by more than this many of its std (<= 0: every vertex its own)")
    parser.add_argument("--deviation-support", type=int, default=3,
                        help="... and only when at least this many of its 6 nearest vertices deviate the same way "
                             "(a spot, not one vertex; 0: any vertex)")
    parser.add_argument("--model", type=int, default=3,
                        help="model code of every vertex when the store has no model array (sellip.model.params.MODEL_NAMES)")


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        run_stage(args.params, args.mesh, args.output_model, args.output_params, args.clusters, args.model,
                  args.eta_deviation_sigmas, args.lobe_deviation_sigmas, args.deviation_support)
    except (ParamsError, ObserveError, ValueError) as error:
        log.error("%s", error)
        return 1
    return 0
