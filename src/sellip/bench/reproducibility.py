"""Reproducibility of the material clustering's discrete decisions (issue #49): the clustering of a finished run's
stored per-vertex fit replayed under perturbations that carry no information, and how often each decision came out
the same (``benchmarks/reproducibility.py``; docs/reproducibility.md).

A perturbation (:data:`KINDS`) of the inputs of :func:`sellip.fit.clusters.cluster_materials`:

- ``exact``: none (the run's own clustering, to the bit: the reference);
- ``noise``: eta, rho_d and the vertex positions times (1 + 1e-9 N(0, 1)), seeded per replicate: another CPU's or
  thread count's last bits;
- ``permute``: the vertices in another (seeded) order: another shard layout or gather order;
- ``subsample``: a seeded ``SUBSAMPLE_KEEP`` share of the clustered vertices kept, the others' confidence set to 0
  (they are still labelled, and still neighbours): another photon draw, as far as the clustering can tell. Without
  replacement: a bootstrap's duplicated vertices would sit at one position and fake spatial coherence;
- ``seed``: the clustering's own seed (k-means++ starts, subsamples) another one.

Public API::

    KINDS, NOISE_RELATIVE, SUBSAMPLE_KEEP
    perturbed_inputs(arrays, kind, replicate, seed) -> (arrays, order, seed)
    replay(arrays, settings, seed, kind, replicate, previous_labels=None) -> (labels (N,), Clustering, used (N,))
    merge_rule(reason) -> str                                 # "size", "coherence", "eta_cut" or "other"
    decisions(clustering, labels, eta, material, eta_true) -> dict   # one replay against the truth
    summarise(rows) -> dict                                   # the distribution of each decision over replays
"""

from __future__ import annotations

from collections import Counter

import numpy as np

KINDS = ("exact", "noise", "permute", "subsample", "seed")
NOISE_RELATIVE = 1e-9
SUBSAMPLE_KEEP = 0.9


def perturbed_inputs(arrays: dict, kind: str, replicate: int, seed: int) -> tuple[dict, np.ndarray, int]:
    """The clustering's inputs ``arrays`` (eta (N,), rho_d (N, 3), status (N,), confidence (N,), vertices (N, 3))
    under perturbation ``kind`` (:data:`KINDS`), seeded by ``replicate``. Returns (arrays, order, seed):
    the perturbed arrays are the originals' rows ``order`` (N,) (the identity but for ``permute``), and the seed the
    clustering runs with (the run's ``seed`` but for ``seed``)."""
    if kind not in KINDS:
        raise ValueError(f"perturbation must be one of {KINDS}, got {kind!r}")
    rng = np.random.default_rng([20261127, KINDS.index(kind), replicate])
    n = len(arrays["eta"])
    out = {name: np.array(arrays[name], copy=True) for name in ("eta", "rho_d", "status", "confidence", "vertices")}
    order = np.arange(n)
    if kind == "noise":
        for name in ("eta", "rho_d", "vertices"):
            value = np.asarray(out[name], np.float64)
            out[name] = value * (1 + NOISE_RELATIVE * rng.standard_normal(value.shape))
    elif kind == "permute":
        order = rng.permutation(n)
        out = {name: value[order] for name, value in out.items()}
    elif kind == "subsample":
        drop = rng.random(n) >= SUBSAMPLE_KEEP
        out["confidence"] = np.where(drop, 0.0, np.asarray(out["confidence"], np.float64))
    elif kind == "seed":
        seed = int(seed) + 1 + replicate
    return out, order, seed


def replay(arrays: dict, settings, seed: int, kind: str = "exact", replicate: int = 0, previous_labels=None):
    """The clustering of ``arrays`` (a fit store: :func:`perturbed_inputs`) with ``settings``
    (:class:`sellip.fit.clusters.AugmentSettings`), ``seed`` and the previous pass's ``previous_labels`` (N,) (None:
    none) under ``kind``. Returns (labels (N,) int in the
    store's vertex order, the :class:`sellip.fit.clusters.Clustering` of the perturbed inputs, used (N,) bool in the
    store's order)."""
    from sellip.fit.clusters import cluster_materials

    inputs, order, run_seed = perturbed_inputs(arrays, kind, replicate, seed)
    previous = None if previous_labels is None else np.asarray(previous_labels)[order]
    clustering = cluster_materials(inputs["eta"], inputs["rho_d"], inputs["status"], inputs["confidence"], settings,
                                   run_seed, vertices=inputs["vertices"], previous_labels=previous)
    labels = np.empty(len(order), np.int64)
    labels[order] = clustering.labels
    used = np.empty(len(order), bool)
    used[order] = clustering.used
    return labels, clustering, used


def merge_rule(reason: str) -> str:
    """The rule of a merge's recorded ``reason`` (:func:`sellip.fit.clusters.cluster_materials`): ``size`` (too few
    confident vertices), ``coherence`` (spatially incoherent), ``eta_cut`` (one material cut along its eta) or
    ``other``."""
    if "min_cluster_vertices" in reason:
        return "size"
    if "spatially incoherent" in reason:
        return "coherence"
    if "cut along its eta" in reason:
        return "eta_cut"
    return "other"


def decisions(clustering, labels, used, eta, material, eta_true) -> dict:
    """The discrete decisions and eta per material of one replay, against the truth.

    ``clustering`` the replay's :class:`~sellip.fit.clusters.Clustering`, ``labels`` and ``used`` (N,) its labels
    and clustered vertices in the store's order, ``eta`` (N,) the stored per-vertex eta, ``material`` (N,) and
    ``eta_true`` (N,) the truth at each vertex (nearest ground-truth vertex). Returns {k, k_bic, regions, merges:
    [rule, ...] in order, materials: {label: {own, cluster, eta, error_pct}}}: a true material is ``own`` when
    its vertices' most common cluster has it as its most common material; ``eta`` is that cluster's median own eta
    (the material's eta as ``sellip finalize`` sets it, before per-vertex deviations)."""
    from sellip.fit.lobes import cluster_medians

    eta, material, eta_true = np.asarray(eta, np.float64), np.asarray(material), np.asarray(eta_true, np.float64)
    k = len(clustering.centres)
    medians = cluster_medians(eta, labels, used, np.full(k, np.nan))
    rows = {}
    for m in np.unique(material[used]):
        members = used & (material == m)
        cluster = int(np.bincount(labels[members], minlength=k).argmax())
        in_cluster = used & (labels == cluster)
        major = np.unique(material[in_cluster], return_counts=True)
        own = bool(major[0][np.argmax(major[1])] == m)
        truth = float(np.median(eta_true[members]))
        rows[str(int(m))] = {"own": own, "cluster": cluster, "eta": float(medians[cluster]),
                             "error_pct": float(100 * abs(medians[cluster] - truth) / truth), "eta_true": truth}
    return {"k": k, "k_bic": int(min(clustering.bic, key=clustering.bic.get)) if clustering.bic else k,
            "regions": len(clustering.regions), "merges": [merge_rule(m["reason"]) for m in clustering.merges],
            "materials": rows}


def summarise(rows: list[dict]) -> dict:
    """The distribution over replays ``rows`` (each {kind, decisions: :func:`decisions`}) of every decision, per
    perturbation kind and over all: K, K by BIC, regions and the merge sequence as {value: count}; per true
    material the share of replays where it has its own cluster and its eta error (min, median, max, %)."""
    out = {}
    for kind in sorted({r["kind"] for r in rows}) + ["all"]:
        chosen = [r["decisions"] for r in rows if kind == "all" or r["kind"] == kind]
        if not chosen:
            continue
        count = lambda values: dict(sorted(Counter(values).items()))
        materials = {}
        for label in sorted({m for d in chosen for m in d["materials"]}, key=int):
            per = [d["materials"][label] for d in chosen if label in d["materials"]]
            errors = np.array([p["error_pct"] for p in per])
            materials[label] = {"own_share": float(np.mean([p["own"] for p in per])),
                                "error_pct": [float(errors.min()), float(np.median(errors)), float(errors.max())],
                                "eta_true": per[0]["eta_true"]}
        out[kind] = {"replays": len(chosen), "k": count(d["k"] for d in chosen),
                     "k_bic": count(d["k_bic"] for d in chosen), "regions": count(d["regions"] for d in chosen),
                     "merges": count(" ".join(d["merges"]) or "-" for d in chosen), "materials": materials}
    return out
