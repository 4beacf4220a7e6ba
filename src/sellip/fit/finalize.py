"""The final model (rule ``finalize_model``; docs/design.md §4): per-material η and lobes with per-vertex deviations
where a vertex's data demand them, unfitted vertices interpolated from their neighbours, confidence, ``model``:
``final/model.ply`` and ``final/params.zarr`` (:func:`finalize_model`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sellip.jobs import atomic_file
from sellip.settings import setting

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FinalSettings:
    """How the final model takes its materials' values (config section ``final``, beside its ``settings``, the final
    pass's FitSettings; each declared once here, :mod:`sellip.settings`): :func:`finalize_model`."""

    eta_deviation_sigmas: float = setting(3.0, "eta is a material property: each vertex takes its material cluster's "
                                          "eta unless its own differs by more than this many of its std (written per "
                                          "vertex as eta_source; <= 0 keeps every vertex's own)", unit="std")
    lobe_deviation_sigmas: float = setting(3.0, "so is the specular lobe: each vertex takes its cluster's sigma_s and "
                                           "rho_s unless its own sigma_s differs by more than this many of its std "
                                           "(written per vertex as lobe_source; <= 0 keeps every vertex's own)",
                                           unit="std")
    deviation_support: int = setting(3, "either only where at least this many of the vertex's 6 nearest vertices "
                                     "deviate the same way: a deviation the data demand is a spot, not one vertex "
                                     "(docs/augment.md; 0: any vertex)", minimum=0, maximum=6)


def finalize_model(params_path: Path, mesh_path: Path, output_model: Path, output_params: Path,
                   clusters: Path | None = None, model: int = 3, settings: FinalSettings = FinalSettings()) -> dict:
    """Write the final model PLY and parameter store; returns a summary dict. The per-vertex model is
    the store's ``model``; ``model`` is the code of every vertex of a store that has none. ``settings``: the deviation
    rules below (:class:`FinalSettings`). With
    ``clusters``, eta is its material cluster's (the median of the cluster's confident vertices' own eta,
    :func:`sellip.fit.lobes.cluster_medians`; the cluster lobe fit's where it has none) unless a vertex's own differs
    by more than ``eta_deviation_sigmas`` of its std, and so is the specular lobe (the cluster lobe fit's sigma_s
    with its rho_s) unless the vertex's sigma_s differs by more than ``lobe_deviation_sigmas`` of its std (at
    least 0.01, the rule's floor), and either way only where at least ``deviation_support`` of its 6 nearest vertices
    deviate the same way (:func:`sellip.fit.lobes.material_or_own`; <= 0: every vertex's own). An eta pinned at a bound
    (:func:`sellip.fit.parameterization.eta_at_bound`) is no estimate: the vertex takes its material's, and is not in
    its median. With ``clusters``, each vertex also carries its cluster's model-selection margin and runner-up
    (``selection_margin``, ``selection_runner_up``; :func:`sellip.fit.selection.cluster_margins`), and its confidence
    is multiplied by :func:`sellip.fit.selection.margin_confidence` (halved where the lobe choice sat on the rule's
    boundary), and its cluster's support (``cluster_support``, ``cluster_alternative``: how often repeats of the
    clustering on resampled vertices found it again, and what it became otherwise; NaN, -1 where not measured).

    Long: one job's steps in order (read, per-material values, fill, confidence, write), each a call."""
    eta_deviation_sigmas, lobe_deviation_sigmas = settings.eta_deviation_sigmas, settings.lobe_deviation_sigmas
    deviation_support = settings.deviation_support
    from sellip.fit.clusters import AugmentSettings, nearest_vertices
    from sellip.fit.lobe_store import read_lobes
    from sellip.fit.lobes import cluster_medians, material_or_own
    from sellip.fit.observe import read_mesh
    from sellip.fit.parameterization import eta_at_bound
    from sellip.fit.selection import margin_confidence
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
    margin, runner_up = np.full(n, np.nan), np.full(n, -1, np.int64)
    support, alternative = np.full(n, np.nan), np.full(n, -1, np.int64)
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
        margin, runner_up = _selection_margins(Path(clusters), cluster, len(lobes))
        support, alternative = vertex_cluster_support(Path(clusters), cluster, len(lobes))
    if "model" in store:
        models = np.asarray(store["model"], np.uint8)
        if not np.isin(models, sorted(MODEL_NAMES)).all():
            raise ParamsError(f"{params_path}: model codes {sorted(set(np.unique(models)) - set(MODEL_NAMES))} "
                              f"are not in {sorted(MODEL_NAMES)}")
    else:
        models = np.full(n, model, np.uint8)
        log.info("%s has no model array: every vertex gets model %d", params_path, model)
    params = params_from(store, np.float64)._replace(eta=eta, sigma_s=sigma_s, rho_s=rho_s)
    confidence_fit = np.asarray(store.get("confidence", np.zeros(n)), np.float64)
    confidence = (confidence_fit * margin_confidence(margin)).astype(np.float32)
    with atomic_file(output_model) as tmp:
        write_param_mesh(tmp, ParamMesh(vertices, mesh.faces, store["normals"], params),
                         extra={"confidence": confidence, "model": models, "eta_source": eta_source,
                                "lobe_source": lobe_source})
    arrays = {name: store[name] for name in store if name != "attrs"}
    arrays.update(model=models, cluster=cluster, eta=eta.astype(np.float32), eta_source=eta_source,
                  eta_vertex=np.asarray(store["eta"], np.float32), sigma_s=sigma_s.astype(np.float32),
                  rho_s=rho_s.astype(np.float32), lobe_source=lobe_source,
                  sigma_s_vertex=np.asarray(store["sigma_s"], np.float32),
                  rho_s_vertex=np.asarray(store["rho_s"], np.float32), confidence=confidence,
                  confidence_fit=confidence_fit.astype(np.float32),
                  selection_margin=margin.astype(np.float32), selection_runner_up=runner_up,
                  cluster_support=support.astype(np.float32), cluster_alternative=alternative)
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


def _selection_margins(clusters: Path, cluster: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, its cluster's selection margin and runner-up (NaN, -1: none) from ``clusters/clusters.json``
    (:func:`sellip.fit.selection.cluster_margins`); none at all where the file is missing (a directory written
    without it)."""
    import json

    from sellip.fit.selection import MARGIN_FULL_CONFIDENCE, cluster_margins

    path = clusters / "clusters.json"
    if not path.is_file():
        log.warning("%s is missing: no model-selection margins (confidence not lowered by them)", path)
        return np.full(len(cluster), np.nan), np.full(len(cluster), -1, np.int64)
    margins, runner_up = cluster_margins(json.loads(path.read_text()), k)
    log.info("model-selection margin per cluster: %s (runner-up %s; below %s the confidence is lowered)",
             np.round(margins, 2).tolist(), runner_up.tolist(), MARGIN_FULL_CONFIDENCE)
    return margins[cluster], runner_up[cluster]


def vertex_cluster_support(clusters: Path, cluster: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, its cluster's support and the cluster it became otherwise (NaN, -1: not measured) from
    ``clusters/clusters.json``'s ``support`` (:func:`sellip.fit.cluster_support.clustering_support`)."""
    import json

    path = clusters / "clusters.json"
    support, alternative = np.full(k, np.nan), np.full(k, -1, np.int64)
    record = json.loads(path.read_text()).get("support") if path.is_file() else None
    for row in (record or {}).get("clusters", []):
        c = int(row["cluster"])
        if 0 <= c < k and row.get("support") is not None:
            support[c], alternative[c] = float(row["support"]), int(row["alternative"])
    if record:
        log.info("support of each material over %d resamples: %s (otherwise into %s)", record["resamples"],
                 support.tolist(), alternative.tolist())
    return support[cluster], alternative[cluster]
