"""Degenerate statistics in the clustering and the region search (sellip.fit): each case degrades (one
cluster, no region, a note) and never raises. The Mitsuba captures of a painted figure, a figure with flat black
and white patches and a uniform dark object crashed here (scikit-learn's MinCovDet on identical feature rows)."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.fit import clusters, records
from sellip.fit.clusters import AugmentSettings


def _sphere(n: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return 0.04 * v / np.linalg.norm(v, axis=1, keepdims=True)


def _cluster(eta, rho_d, status=None, confidence=None, vertices=None, **settings):
    n = len(eta)
    status = np.full(n, records.STATUS_FITTED, np.int8) if status is None else status
    confidence = np.ones(n) if confidence is None else confidence
    vertices = _sphere(n) if vertices is None else vertices
    clustering = clusters.cluster_materials(eta, rho_d, status, confidence, AugmentSettings(**settings), 0,
                                           vertices=vertices)
    assert clustering.labels.shape == (n,) and clustering.labels.min() >= 0
    assert clustering.labels.max() < len(clustering.centres) and np.all(np.isfinite(clustering.centres))
    return clustering


def test_flat_two_colour_patches_are_two_clusters_not_a_crash():
    """A cow: one material (one eta) in black and white patches of one albedo each (identical feature rows)."""
    vertices = _sphere(3000)
    white = np.sin(40 * vertices[:, 0]) * np.sin(40 * vertices[:, 1]) > 0  # patches with sharp edges
    rho_d = np.where(white[:, None], [0.8, 0.78, 0.74], [0.03, 0.03, 0.03])
    eta = 1.5 + np.random.default_rng(1).normal(0, 0.01, len(vertices))
    clustering = _cluster(eta, rho_d, vertices=vertices)
    assert len(clustering.centres) == 2 and not clustering.regions
    assert any("no spread" in note for note in clustering.notes)  # said so
    labels = clustering.labels
    assert len(np.unique(labels[white])) == 1 and len(np.unique(labels[~white])) == 1


def test_a_small_flat_region_inside_a_flat_cluster_is_still_found():
    """The region rule still works where the robust Gaussian is degenerate: a coherent spot of a third flat colour
    (2 % of the surface, too small for BIC) inside a flat white cluster becomes a cluster of its own."""
    vertices = _sphere(4000, 2)
    spot = vertices @ np.array([0, 0, 1.0]) > 0.04 * 0.98
    rho_d = np.where(spot[:, None], [0.6, 0.2, 0.1], [0.8, 0.78, 0.74])
    eta = np.where(spot, 1.6, 1.5) + np.random.default_rng(3).normal(0, 0.002, len(vertices))
    clustering = _cluster(eta, rho_d, vertices=vertices, min_cluster_vertices=20)
    assert 20 < spot.sum() < 0.03 * len(vertices)
    assert len(np.unique(clustering.labels[spot])) == 1
    assert clustering.labels[spot][0] != np.bincount(clustering.labels[~spot]).argmax()


@pytest.mark.parametrize("rho_d", [(0.04, 0.04, 0.04), (0.7, 0.7, 0.7), (0.0, 0.0, 0.0)],
                         ids=["uniform_dark", "uniform_bright", "black"])
def test_one_uniform_material_is_one_cluster(rho_d):
    n = 2500
    eta = 1.5 + np.random.default_rng(4).normal(0, 0.005, n)
    clustering = _cluster(eta, np.tile(rho_d, (n, 1)))
    assert len(clustering.centres) == 1 and np.all(clustering.labels == 0)


def test_three_flat_colours_and_an_albedo_without_chroma_spread():
    """Rank-deficient covariances: every albedo grey (no chroma spread) in three flat levels."""
    vertices = _sphere(3000, 5)
    level = np.digitize(vertices[:, 2], [-0.013, 0.013])
    rho_d = np.array([[0.05] * 3, [0.3] * 3, [0.8] * 3])[level]
    clustering = _cluster(np.full(len(vertices), 1.5), rho_d, vertices=vertices)
    assert len(clustering.centres) == 3
    assert all(len(np.unique(clustering.labels[level == k])) == 1 for k in range(3))


def test_no_vertex_to_cluster_gives_one_cluster_and_a_note():
    """All vertices with too few views (or all unconfident, or every eta pinned at a bound)."""
    n = 500
    rho_d = np.random.default_rng(6).uniform(0.1, 0.5, (n, 3))
    for status, confidence, eta in [(np.full(n, records.STATUS_TOO_FEW_VIEWS, np.int8), np.zeros(n), np.full(n, 1.5)),
                                    (np.zeros(n, np.int8), np.zeros(n), np.full(n, 1.5)),
                                    (np.zeros(n, np.int8), np.ones(n), np.full(n, 1.0))]:
        clustering = _cluster(eta, rho_d, status, confidence)
        assert len(clustering.centres) == 1 and not clustering.used.any() and clustering.notes


def test_a_material_smaller_than_the_minimum_is_merged_not_a_crash():
    n = 1000
    rho_d = np.tile([0.5, 0.4, 0.3], (n, 1))
    rho_d[:7] = [0.1, 0.1, 0.6]
    eta = np.full(n, 1.5)
    clustering = _cluster(eta, rho_d)
    assert len(clustering.centres) == 1


@pytest.mark.parametrize("seed", range(12))
def test_random_flat_textures_never_raise(seed):
    """Property-style: random mixtures of 1-4 flat albedos (some dark, some exact duplicates of each other), a few
    etas, random statuses and confidences, on a random surface: the clustering always returns valid labels."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(60, 1500))
    vertices = _sphere(n, seed)
    colours = rng.choice([0.0, 0.03, 0.3, 0.8], size=(int(rng.integers(1, 5)), 3))
    patch = np.floor((vertices[:, 0] + 0.04) / 0.08 * rng.integers(1, 6)).astype(int) % len(colours)
    eta = rng.choice([1.3, 1.5, 1.5, 2.0], size=len(colours))[patch] + rng.normal(0, rng.choice([0, 0.01]), n)
    status = np.where(rng.random(n) < rng.choice([0.0, 0.5, 1.0]), records.STATUS_TOO_FEW_VIEWS, records.STATUS_FITTED)
    confidence = rng.choice([0.0, 1.0], n, p=[0.2, 0.8])
    _cluster(eta, colours[patch], status.astype(np.int8), confidence, vertices, min_cluster_vertices=20)


def test_degenerate_statistics_helpers():
    rng = np.random.default_rng(0)
    flat = np.tile([1.0, 2.0, 3.0], (100, 1))
    distances, note = clusters.robust_mahalanobis(flat, np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 4.0]]), rng)
    assert distances[0] == 0 and distances[1] == pytest.approx(1 / clusters.VARIANCE_FLOOR) and note
    spread = rng.normal(size=(300, 3))
    distances, note = clusters.robust_mahalanobis(spread, spread[:5], rng)
    assert note is None and np.all(np.isfinite(distances))
    assert clusters.albedo_separation(np.array([0.0, 0.0, 1.0]), np.zeros((3, 3))) == pytest.approx(2.0)
    assert clusters.one_mode(np.full(50, 3.0), rng)
    assert not clusters.same_eta_by_albedo(np.tile([1.0, 1, 1, 30], (20, 1)), np.tile([1.0, 1, 1, 31], (20, 1)), rng)
