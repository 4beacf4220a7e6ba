"""The reproducibility replays (sellip.bench.reproducibility, issue #49) on tiny synthetic clusterings."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.bench import reproducibility as rep
from sellip.fit.clusters import AugmentSettings


def _two_materials(n_side=24):
    """Two halves of a grid of vertices, two albedos and etas (1.48, 1.62): a clustering that is never in doubt."""
    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.arange(n_side), np.arange(n_side))
    vertices = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]) * 1e-3
    half = x.ravel() >= n_side // 2
    n = len(vertices)
    eta = np.where(half, 1.62, 1.48) + rng.normal(0, 0.02, n)
    rho_d = np.where(half[:, None], [0.42, 0.28, 0.06], [0.22, 0.14, 0.075]) * np.exp(rng.normal(0, 0.05, (n, 1)))
    return {"eta": eta, "rho_d": rho_d, "status": np.zeros(n, np.int8), "confidence": np.ones(n),
            "vertices": vertices}, half.astype(int)


def test_perturbations_change_only_what_they_say():
    arrays, _ = _two_materials()
    same, order, seed = rep.perturbed_inputs(arrays, "exact", 0, 7)
    assert seed == 7 and (order == np.arange(len(order))).all()
    np.testing.assert_array_equal(same["eta"], arrays["eta"])
    noisy = rep.perturbed_inputs(arrays, "noise", 0, 7)[0]
    relative = np.abs(noisy["eta"] / arrays["eta"] - 1)
    assert 0 < relative.max() < 1e-8 and not np.array_equal(noisy["eta"], arrays["eta"])
    moved, order, _ = rep.perturbed_inputs(arrays, "permute", 1, 7)
    np.testing.assert_array_equal(moved["vertices"], arrays["vertices"][order])
    assert sorted(order) == list(range(len(order))) and not (order == np.arange(len(order))).all()
    dropped = rep.perturbed_inputs(arrays, "subsample", 2, 7)[0]["confidence"]
    assert 0.8 < np.mean(dropped > 0) < 0.97
    assert rep.perturbed_inputs(arrays, "seed", 3, 7)[2] == 11
    with pytest.raises(ValueError, match="perturbation"):
        rep.perturbed_inputs(arrays, "nonsense", 0, 0)


def test_replays_of_a_clear_clustering_agree_and_are_summarised():
    """Every perturbation of a clustering that is never in doubt gives the same labels in the store's order (up to
    their numbering), its decisions against the truth and the summary's counts."""
    arrays, material = _two_materials()
    settings = AugmentSettings(min_coherence=0.5, min_cluster_vertices=20)
    reference, _, _ = rep.replay(arrays, settings, 0)
    rows = []
    for kind in rep.KINDS:
        labels, clustering, used = rep.replay(arrays, settings, 0, kind, 1)
        assert len(np.unique(labels)) == 2
        assert np.array_equal(labels == labels[0], reference == reference[0])  # the same partition, store order
        rows.append({"kind": kind, "decisions": rep.decisions(clustering, labels, used, arrays["eta"], material,
                                                              np.where(material == 1, 1.62, 1.48))})
    summary = rep.summarise(rows)
    assert summary["all"]["replays"] == len(rep.KINDS) and summary["all"]["k"] == {2: len(rep.KINDS)}
    for label in ("0", "1"):
        assert summary["all"]["materials"][label]["own_share"] == 1.0
        assert summary["all"]["materials"][label]["error_pct"][2] < 1.0


def test_merge_rules_are_named():
    assert rep.merge_rule("12 confident vertices < min_cluster_vertices 50") == "size"
    assert rep.merge_rule("spatially incoherent: 0.44 of its vertices' neighbours in it < min_coherence 0.5") \
        == "coherence"
    assert rep.merge_rule("one material cut along its eta: mean albedos 1.2 pooled sd apart") == "eta_cut"
    assert rep.merge_rule("something else") == "other"
