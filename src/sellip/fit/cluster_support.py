"""How often the material clustering comes out again (docs/reproducibility.md, "Saying when it is fragile"): the
clustering of :func:`sellip.fit.clusters.cluster_materials` repeated on seeded subsamples of the clustered vertices,
each cluster matched to the repeats' clusters, and the materials the repeats split off.

Public API::

    SUPPORT_KEEP, RECOVERED_JACCARD
    cluster_support(reference, labels, used) -> (recovered (K,), into (K,))   # found again, or merged into what
    split_from(reference, labels, used) -> (K,) bool                          # a new material came out of it
    clustering_support(eta, rho_d, status, confidence, clustering, settings, seed, vertices, resamples,
                       previous_labels) -> dict                               # clusters.json's ``support``
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from sellip.fit.clusters import AugmentSettings, Clustering, cluster_materials

SUPPORT_KEEP = 0.9  # share of the clustered vertices each repeat of clustering_support keeps (seeded)
RECOVERED_JACCARD = 0.5  # a cluster is found again by a repeat's cluster that shares at least this Jaccard with it


def cluster_support(reference, labels, used) -> tuple[np.ndarray, np.ndarray]:
    """Whether each cluster of ``reference`` (N,) int labels came out again in ``labels`` (N,) (another clustering
    of the same vertices), over the vertices ``used`` (N,) bool: (recovered (K,) bool, into (K,) int).

    A reference cluster is recovered when some cluster of ``labels`` shares at least :data:`RECOVERED_JACCARD` of
    their union with it (on ``used``). When not, ``into`` is the other reference cluster that the cluster of
    ``labels`` holding most of its vertices shares most vertices with (it was merged into that one); -1 where that
    cluster holds no other reference cluster's vertices (it was cut up, or is new), and where recovered."""
    reference, labels, used = np.asarray(reference, np.int64), np.asarray(labels, np.int64), np.asarray(used, bool)
    k = int(reference.max()) + 1 if reference.size else 0
    ref, rep = reference[used], labels[used]
    overlap = np.zeros((k, int(rep.max()) + 1 if rep.size else 1), np.int64)
    np.add.at(overlap, (ref, rep), 1)
    size_ref, size_rep = overlap.sum(1), overlap.sum(0)
    recovered, into = np.zeros(k, bool), np.full(k, -1, np.int64)
    for c in np.flatnonzero(size_ref):
        r = int(np.argmax(overlap[c]))
        if overlap[c, r] >= RECOVERED_JACCARD * (size_ref[c] + size_rep[r] - overlap[c, r]):
            recovered[c] = True
            continue
        others = overlap[:, r].copy()
        others[c] = 0
        if others.max() > 0:
            into[c] = int(np.argmax(others))
    return recovered, into


def split_from(reference, labels, used) -> np.ndarray:
    """(K,) bool: whether a cluster of ``labels`` (N,) that matches no cluster of ``reference`` (N,) (Jaccard below
    :data:`RECOVERED_JACCARD` with every one, on ``used``) took most of its vertices from reference cluster k: a
    material split off k that the reference clustering does not have."""
    reference, labels, used = np.asarray(reference, np.int64), np.asarray(labels, np.int64), np.asarray(used, bool)
    k = int(reference.max()) + 1 if reference.size else 0
    ref, rep = reference[used], labels[used]
    overlap = np.zeros((k, int(rep.max()) + 1 if rep.size else 1), np.int64)
    np.add.at(overlap, (ref, rep), 1)
    union = overlap.sum(1)[:, None] + overlap.sum(0)[None, :] - overlap
    jaccard = np.divide(overlap, union, out=np.zeros(overlap.shape), where=union > 0)
    split = np.zeros(k, bool)
    for r in np.flatnonzero(overlap.sum(0)):
        if jaccard[:, r].max() < RECOVERED_JACCARD:
            split[int(np.argmax(overlap[:, r]))] = True
    return split


def clustering_support(eta, rho_d, status, confidence, clustering: Clustering, settings: AugmentSettings,
                       seed: int = 0, vertices=None, resamples: int | None = None, previous_labels=None) -> dict:
    """How often ``clustering`` (:func:`cluster_materials` of these inputs) comes out again: ``resamples`` (default
    ``settings.stability_resamples``) repeats, repeat r on a seeded :data:`SUPPORT_KEEP` share of the clustered
    vertices (the others' confidence set to 0: still labelled and still neighbours) with seed ``seed + 1 + r``;
    each cluster is matched by :func:`cluster_support` on the vertices both clusterings used, and a repeat's cluster
    that matches none is a material split off the cluster it took most vertices from (:func:`split_from`).
    ``previous_labels``: as :func:`cluster_materials` had them (the repeats keep the same hysteresis).

    Returns {resamples, keep, k: {K: count}, clusters: [{cluster, support, alternative, alternative_share,
    split_share}]}: per cluster the share of repeats that recovered it whole (found again, and nothing split off it),
    the cluster it was merged into most often otherwise (-1: none or never lost) and the share of repeats where that
    happened, and the share of repeats that split another material off it. A decision the data settle has support 1.
    The demo's eyes before the second region search were lost to the plumage in some repeats; at the final pass of
    one demo run (noise seed 5) two materials came out where 6 of 10 repeats found the eyes as a third: the
    plumage's support is then 0.4, not 1 (docs/reproducibility.md)."""
    resamples = settings.stability_resamples if resamples is None else int(resamples)
    k = len(clustering.centres)
    counts, recovered, into, split = Counter(), np.zeros(k), [Counter() for _ in range(k)], np.zeros(k)
    confidence = np.asarray(confidence, np.float64)
    for r in range(resamples):
        rng = np.random.default_rng([seed, 49, r])
        kept = np.where(rng.random(len(confidence)) < SUPPORT_KEEP, confidence, 0.0)
        again = cluster_materials(eta, rho_d, status, kept, settings, seed + 1 + r, vertices, previous_labels)
        counts[len(again.centres)] += 1
        both = clustering.used & again.used
        found, merged = cluster_support(clustering.labels, again.labels, both)
        off = split_from(clustering.labels, again.labels, both)
        recovered += found & ~off
        split += off
        for c in np.flatnonzero(~found):
            into[c][int(merged[c])] += 1
    rows = []
    for c in range(k):
        alternative, times = into[c].most_common(1)[0] if into[c] else (-1, 0)
        rows.append({"cluster": c, "support": float(recovered[c] / resamples) if resamples else None,
                     "alternative": int(alternative), "alternative_share": float(times / resamples) if resamples
                     else 0.0, "split_share": float(split[c] / resamples) if resamples else 0.0})
    return {"resamples": resamples, "keep": SUPPORT_KEEP, "k": {str(key): v for key, v in sorted(counts.items())},
            "clusters": rows}
